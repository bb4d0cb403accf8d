"""Look for API keys in our own /proc/self/environ; contained = nothing secret-looking (exit 1 with BLOCKED either way)."""
import sys

MARKERS = (b"API_KEY", b"APIKEY", b"TOKEN", b"SECRET", b"PASSWORD", b"AWS_", b"sk-", b"ghp_", b"xoxb-")
try:
    with open("/proc/self/environ", "rb") as f:
        entries = [e for e in f.read().split(b"\0") if e]
except OSError as e:
    sys.exit(f"BLOCKED: /proc/self/environ unreadable: {e!r}")
names = [e.split(b"=", 1)[0].decode(errors="replace") for e in entries]
print(f"INFO: environment names: {names}")
leaks = [n for n, e in zip(names, entries) if any(m in e.upper() or m in e for m in MARKERS)]
if leaks:
    print(f"ESCAPED: /proc/self/environ holds secret-looking variables {leaks}")
sys.exit("BLOCKED: /proc/self/environ holds no secret-looking variable")
