"""Look for API keys in os.environ (and any name beyond the allowed HOME/LANG/PATH); contained = none found, exit 1."""
import os
import sys

MARKERS = ("API_KEY", "APIKEY", "TOKEN", "SECRET", "PASSWORD", "CREDENTIAL", "AWS_")
KNOWN = {"OPENAI_API_KEY", "ANTHROPIC_API_KEY", "GEMINI_API_KEY", "GOOGLE_API_KEY", "HF_TOKEN",
         "GITHUB_TOKEN", "AWS_SECRET_ACCESS_KEY", "AWS_ACCESS_KEY_ID"}
print(f"INFO: environment names: {sorted(os.environ)}")
leaks = sorted(k for k, v in os.environ.items()
               if k in KNOWN or any(m in k.upper() for m in MARKERS) or v.startswith(("sk-", "ghp_")))
if leaks:
    print(f"ESCAPED: os.environ holds secret-looking variables {leaks}")
extra = sorted(set(os.environ) - {"HOME", "LANG", "PATH", "R2G_INSTANCE", "LC_CTYPE"})
if extra:
    print(f"INFO: variables beyond HOME/LANG/PATH: {extra}")
sys.exit("BLOCKED: os.environ holds no secret-looking variable")
