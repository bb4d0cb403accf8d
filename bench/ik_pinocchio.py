"""Pinocchio baseline of `r2g bench ik` (run by it; not a project dependency).

Reads IK targets as JSON lines ({"position", "quaternion" [x, y, z, w], "seed"}), solves each
with the damped least-squares loop of Pinocchio's own inverse-kinematics example (frame
Jacobian in the local frame, Jlog6 correction, joint limits clipped after every step), and
prints, as its last line, one JSON object: {"solved": n, "times_us": [one per target]}.
Each time covers only the solve, measured inside Python with perf_counter.
Tolerances match the Rust solver: 1e-5 m and 1e-5 rad, checked on the true pose.
"""

import argparse
import json
import time

import numpy as np
import pinocchio as pin

TOL = 1e-5
IT_MAX = 1000
DT = 1.0
DAMP = 1e-6


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--urdf", required=True)
    ap.add_argument("--tcp", default="hand_tcp")
    ap.add_argument("--targets", required=True)
    a = ap.parse_args()

    full = pin.buildModelFromUrdf(a.urdf)
    # Lock every joint that is not revolute (the fingers) at its neutral value: 7 DoF remain.
    lock = [
        j
        for j in range(1, full.njoints)
        if not full.joints[j].shortname().startswith("JointModelR")
    ]
    model = pin.buildReducedModel(full, lock, pin.neutral(full)) if lock else full
    data = model.createData()
    fid = model.getFrameId(a.tcp)
    lo, hi = model.lowerPositionLimit, model.upperPositionLimit
    if model.nq != 7:
        raise SystemExit(f"expected 7 arm joints after locking the fingers, got nq={model.nq}")

    targets = []
    with open(a.targets) as f:
        for line in f:
            if line.strip():
                t = json.loads(line)
                x, y, z, w = t["quaternion"]
                rot = pin.Quaternion(w, x, y, z).normalized().toRotationMatrix()
                targets.append((pin.SE3(rot, np.array(t["position"], dtype=float)), np.array(t["seed"], dtype=float)))

    solved = 0
    times_us = []
    eye6 = np.eye(6)
    for goal, seed in targets:
        t0 = time.perf_counter()
        q = np.clip(seed, lo, hi)
        ok = False
        for _ in range(IT_MAX):
            pin.forwardKinematics(model, data, q)
            pin.updateFramePlacement(model, data, fid)
            cur = data.oMf[fid]
            if (
                np.linalg.norm(goal.translation - cur.translation) <= TOL
                and np.linalg.norm(pin.log3(cur.rotation.T @ goal.rotation)) <= TOL
            ):
                ok = True
                break
            i_m_d = cur.actInv(goal)
            err = pin.log6(i_m_d).vector
            jac = pin.computeFrameJacobian(model, data, q, fid)  # local frame
            jac = -pin.Jlog6(i_m_d.inverse()) @ jac
            v = -jac.T @ np.linalg.solve(jac @ jac.T + DAMP * eye6, err)
            q = np.clip(pin.integrate(model, q, v * DT), lo, hi)
        times_us.append((time.perf_counter() - t0) * 1e6)
        solved += ok
    print(json.dumps({"solved": solved, "times_us": times_us}))


if __name__ == "__main__":
    main()
