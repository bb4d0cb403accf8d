"""Runs franka-sim (PyPI, an independent implementation of the Franka network protocol) on
127.0.0.1 with a robot model this project supplies, for tests and benchmarks of r2g-fci.

Runs in franka-sim's own virtual environment (.venv-franka-sim, made by scripts/setup-venv.sh:
franka-sim pins a MuJoCo and numpy older than ours). Nothing is downloaded: the arm is the
MJCF our sim-host compiles for a gym (`r2g-sim SCENE --dump-mjcf F --exit-after-dump`), whose
names (joint1..7, link0..link8) are the ones franka-sim looks for.

One change to that model, for franka-sim only: its arm servo is explicit (stiffness up to
4500 Nm/rad, damping up to 450 Nm s/rad, applied once per 1 ms step), and with our model's
rotor inertia (armature 0.1 kg m^2) joints 1 and 3 chatter in the null space of the
straight-elbow pose. Raising the arm joints' armature to ARMATURE keeps that servo stable;
kinematics, link inertias and limits are unchanged.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile

import mujoco

ARMATURE = 0.5


def peer_model(src: str, dst: str) -> None:
    spec = mujoco.MjSpec.from_file(src)
    arm = [j for j in spec.joints if j.name in {f"joint{i}" for i in range(1, 8)}]
    if len(arm) != 7:
        sys.exit(f"serve.py: {src} has {len(arm)} of the joints joint1..joint7; is it an r2g-sim dump of a Panda/FR3 gym?")
    for j in arm:
        j.armature = ARMATURE
    spec.compile()
    with open(dst + ".tmp", "w") as f:
        f.write(spec.to_xml())
    os.replace(dst + ".tmp", dst)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="MJCF dumped by r2g-sim --dump-mjcf")
    ap.add_argument("--port", type=int, required=True, help="FCI command port on 127.0.0.1")
    ap.add_argument("--protocol-version", type=int, default=10, help="FCI version the server announces")
    ap.add_argument("--gripper", action="store_true", help="also serve the Franka Hand (port 1338)")
    a = ap.parse_args()
    work = tempfile.mkdtemp(prefix="r2g-franka-sim-")
    model = os.path.join(work, "arm.xml")
    # Meshes (if any) are referenced by absolute path in the dump, so the copy may live anywhere.
    peer_model(a.model, model)
    os.environ["FR3_MJCF"] = model
    from franka_sim import FrankaSimServer

    server = FrankaSimServer(
        host="127.0.0.1",
        port=a.port,
        enable_gripper=a.gripper,
        protocol_version=a.protocol_version,
    )
    def interrupted(*_):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupted)
    print(f"franka-sim on 127.0.0.1:{a.port}, FCI version {a.protocol_version}", flush=True)
    try:
        server.start()
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()


if __name__ == "__main__":
    main()
