"""prctl: try to clear no_new_privs and check a seccomp filter is in force; contained = NNP stays 1, seccomp mode 2 (exit 1), or killed."""
import ctypes
import sys

PR_GET_SECCOMP, PR_SET_NO_NEW_PRIVS, PR_GET_NO_NEW_PRIVS = 21, 38, 39
libc = ctypes.CDLL(None, use_errno=True)
libc.prctl.restype = ctypes.c_int
r = libc.prctl(PR_SET_NO_NEW_PRIVS, 0, 0, 0, 0)
print(f"INFO: PR_SET_NO_NEW_PRIVS(0) returned {r}, errno {ctypes.get_errno()}")
nnp = libc.prctl(PR_GET_NO_NEW_PRIVS, 0, 0, 0, 0)
mode = libc.prctl(PR_GET_SECCOMP, 0, 0, 0, 0)
print(f"INFO: no_new_privs={nnp} seccomp_mode={mode}")
try:
    with open("/proc/self/status") as f:
        print("INFO: " + " ".join(l.strip() for l in f if l.startswith(("NoNewPrivs", "Seccomp", "Cap"))))
except OSError as e:
    print(f"INFO: /proc/self/status: {e!r}")
if nnp == 0:
    print("ESCAPED: no_new_privs is clear (setuid binaries would gain privileges)")
if mode == 0:
    print("ESCAPED: no seccomp filter is installed")
sys.exit("BLOCKED: no_new_privs cannot be cleared" if nnp == 1 else 1)
