#!/usr/bin/env bash
# The r2g_gym wheel a user installs into a venv of their own (target/wheels/), with the gym pack
# and the robot meshes inside, and a wheelhouse (.wheelhouse/) of its pinned dependencies so the
# test that installs it into a fresh venv runs offline. Idempotent: pip download skips what is
# there, and maturin rebuilds only when cargo says the module is stale.
set -euo pipefail
cd "$(dirname "$0")/.."
py=.venv/bin/python
trap '$py gym-env/bundle.py remove' EXIT
$py gym-env/bundle.py add
rm -f target/wheels/r2g_gym-*.whl
VIRTUAL_ENV=$PWD/.venv PATH=$PWD/.venv/bin:$PATH .venv/bin/maturin build --release --locked -q \
  -m gym-env/Cargo.toml --out target/wheels --compatibility linux --auditwheel skip --strip
$py -m pip download -q --disable-pip-version-check --only-binary=:all: -d .wheelhouse -r gym-env/requirements.txt
