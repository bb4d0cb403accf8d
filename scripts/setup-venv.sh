#!/usr/bin/env bash
# Creates .venv with the pinned Python packages and exposes the wheel's libmujoco as
# .venv/mujoco-lib/libmujoco.so for the Rust binding to link (see .cargo/config.toml).
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.txt
.venv/bin/python -m pip install -q --disable-pip-version-check -r requirements-ray.txt
dir=$(.venv/bin/python -c 'import mujoco, os; print(os.path.dirname(mujoco.__file__))')
lib=$(ls "$dir"/libmujoco.so.* | head -n1)
mkdir -p .venv/mujoco-lib
ln -sfn "$lib" .venv/mujoco-lib/libmujoco.so
ln -sfn "$lib" ".venv/mujoco-lib/$(basename "$lib")"
# The stage-program helpers (robo_perception, robo_services) import anywhere in the venv, as
# robo does; the sandbox finds them on its own path.
site=$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
echo "$PWD/agent-host/py/lib" > "$site/r2g_agent_lib.pth"
# Robot meshes: the DAE reader goes into the venv; the asset wheels of requirements-assets.txt are
# only downloaded and unpacked into robots/packages/ (robots/assets.py; a no-op when up to date).
.venv/bin/python -m pip install -q --disable-pip-version-check -r robots/requirements-tools.txt
.venv/bin/python robots/assets.py install requirements-assets.txt
# franka-sim, the independent FCI peer r2g-fci is tested against, pins a MuJoCo and numpy older
# than ours: it gets its own environment (fci/franka-sim/serve.py runs in it).
[ -x .venv-franka-sim/bin/python ] || python3 -m venv .venv-franka-sim
.venv-franka-sim/bin/python -m pip install -q --disable-pip-version-check -r fci/franka-sim/requirements.txt
