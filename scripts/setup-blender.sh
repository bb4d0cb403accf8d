#!/usr/bin/env bash
# Creates .venv-blender with Blender as a Python module (requirements-blender.txt), for
# `r2g blender` and `r2g compare`. Idempotent: a stamp in the venv holds the SHA-256 of the
# requirements it was installed from, and nothing is done while it matches. `make test` and
# `make demo` run this; `r2g blender` runs it on first use when the stamp is missing or stale.
# The download is about 374 MB (the bpy wheel) and the venv about 1 GB.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=.venv-blender
stamp="$venv/r2g-requirements.sha256"
# One installer at a time: two `r2g blender`/`compare`/`judge` started together both find the
# stamp missing; the second waits here, then finds it written.
exec 9>"$venv.lock"
flock 9
want=$(sha256sum requirements-blender.txt | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$venv/bin/python" ]; then
  exit 0
fi
py=python3.11
command -v "$py" >/dev/null || py=python3
"$py" -c 'import sys; assert sys.version_info[:2] == (3, 11), "bpy 5.0.1 needs CPython 3.11, found " + sys.version' \
  || { echo "setup-blender: bpy 5.0.1 has wheels for CPython 3.11 only" >&2; exit 1; }
start=$(date +%s)
echo "setup-blender: installing bpy 5.0.1 into $venv (about 374 MB to download)" >&2
rm -f "$stamp"
# A venv left by another Python is made again (its packages would not load).
if [ -x "$venv/bin/python" ] && ! "$venv/bin/python" -c 'import sys; assert sys.version_info[:2] == (3, 11)' 2>/dev/null; then
  rm -rf "$venv"
fi
[ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
"$venv/bin/python" -m pip install -q --disable-pip-version-check -r requirements-blender.txt
# The import is the check that counts: the wheel loads its own libraries, and a machine that
# lacks one they need fails here, not in the middle of a render.
"$venv/bin/python" -c 'import bpy; assert bpy.app.version_string == "5.0.1", bpy.app.version_string'
echo "$want" > "$stamp.tmp" && mv "$stamp.tmp" "$stamp"
echo "setup-blender: done in $(( $(date +%s) - start )) s" >&2
