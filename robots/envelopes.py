"""Capsules that enclose the drawn (visual) meshes of the Panda and the Franka Hand, link by link,
for `robo_perception.robot.PANDA`: the self-filter must remove every pixel the cameras see of the
robot, and a stage program cannot read mesh files. Prints the capsules as Python lines to paste;
tests/python/test_self_filter.py checks that every vertex of every drawn mesh lies inside them.

    .venv/bin/python robots/envelopes.py     # after robots/assets.py install (make venv)

Per link: one capsule, or two when two enclose the mesh in much less volume (the mesh's points
split along a principal axis). A capsule's axis starts at a principal axis of its points and is
improved by a small search minimising volume; its radius is the smallest that holds every point
for that axis, rounded up to the millimetre, plus 1 mm.
"""
from __future__ import annotations

import itertools
import math
import sys
from pathlib import Path

import numpy as np

MESHES = Path(__file__).resolve().parent / "packages/example-robot-data/robots/panda_description/meshes/visual"
LINKS = ["link0", "link1", "link2", "link3", "link4", "link5", "link6", "link7", "hand"]


def vertices(name: str) -> np.ndarray:
    """Every vertex of a drawn mesh (its converted OBJ parts), in the link frame, metres."""
    out = []
    for f in sorted((MESHES / f"{name}.dae.parts").glob("*.obj")):
        out += [[float(x) for x in line.split()[1:4]] for line in f.read_text().splitlines() if line.startswith("v ")]
    if not out:
        sys.exit(f"envelopes.py: no vertices for {name} under {MESHES} (run robots/assets.py install)")
    return np.array(out)


def segment_d(P: np.ndarray, a: np.ndarray, u: np.ndarray, length: float) -> np.ndarray:
    t = np.clip((P - a) @ u, 0.0, length)
    return np.linalg.norm(P - a - t[:, None] * u, axis=1)


def _circle(Q: np.ndarray) -> tuple[np.ndarray, float]:
    c = Q.mean(axis=0)  # an approximately smallest enclosing circle (Badoiu-Clarkson)
    for i in range(1, 150):
        j = np.argmax(((Q - c) ** 2).sum(axis=1))
        c = c + (Q[j] - c) / (i + 1)
    return c, float(np.sqrt(((Q - c) ** 2).sum(axis=1).max()))


def capsule_along(P: np.ndarray, u: np.ndarray):
    u = u / np.linalg.norm(u)
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    Q = np.stack([P @ e1, P @ e2], axis=1)
    c, r = _circle(Q)
    t = P @ u
    s = np.sqrt(np.maximum(r * r - ((Q - c) ** 2).sum(axis=1), 0.0))
    lo, hi = (t - s).max(), (t + s).min()  # the segment must reach within r of every point
    lo, hi = min(lo, hi), max(lo, hi)
    a = c[0] * e1 + c[1] * e2 + lo * u
    length = hi - lo
    return math.pi * r * r * length + 4.0 / 3.0 * math.pi * r**3, a, u, length, r


def support(P: np.ndarray) -> np.ndarray:
    """The points of ``P`` that are farthest along some direction: the vertices of its convex
    hull, nearly all. A convex shape that holds them holds ``P``."""
    dirs = np.random.default_rng(0).normal(size=(4000, 3))
    return P[np.unique((P @ dirs.T).argmax(axis=0))]


def best_capsule(P: np.ndarray):
    P = support(P)
    C = P - P.mean(axis=0)
    best = None
    for ax in np.linalg.eigh(C.T @ C)[1].T:
        cand = capsule_along(P, ax)
        best = cand if best is None or cand[0] < best[0] else best
    for step in (0.3, 0.1, 0.03, 0.01):
        u0 = best[2]
        e = np.linalg.svd(u0[None, :])[2][1:]
        for da, db in itertools.product(np.linspace(-step, step, 5), repeat=2):
            cand = capsule_along(P, u0 + da * e[0] + db * e[1])
            best = cand if cand[0] < best[0] else best
    return best


def fit(P: np.ndarray, parts: int):
    if parts == 1:
        return [best_capsule(P)]
    C = P - P.mean(axis=0)
    best = None
    for ax in np.linalg.eigh(C.T @ C)[1].T:
        t = P @ ax  # two capsules are not convex together: each holds its own part of all points
        for q in np.linspace(0.2, 0.8, 7):
            cut = np.quantile(t, q)
            caps = [best_capsule(P[t < cut]), best_capsule(P[t >= cut])]
            if best is None or sum(c[0] for c in caps) < sum(c[0] for c in best):
                best = caps
    return best


def rpy_of_z(u: np.ndarray) -> tuple[float, float, float]:
    """Fixed-axis roll-pitch-yaw of a rotation whose z axis is ``u`` (roll 0)."""
    pitch = math.acos(max(-1.0, min(1.0, float(u[2]))))
    yaw = math.atan2(float(u[1]), float(u[0])) if math.sin(pitch) > 1e-9 else 0.0
    return 0.0, pitch, yaw


def main() -> None:
    for link in LINKS:
        V = vertices(link)
        one, two = fit(V, 1), fit(V, 2)
        caps = two if sum(c[0] for c in two) < 0.85 * one[0][0] else one
        # each vertex belongs to the capsule whose surface it is nearest inside (or least outside)
        gap = np.stack([segment_d(V, a, u, length) - r for _, a, u, length, r in caps])
        owner = gap.argmin(axis=0)
        for k, (_, a, u, length, _) in enumerate(caps):
            rpy = tuple(round(v, 4) for v in rpy_of_z(u))
            # the rounded axis and centre, then the radius that holds every vertex it owns
            cz = np.array([math.sin(rpy[1]) * math.cos(rpy[2]), math.sin(rpy[1]) * math.sin(rpy[2]), math.cos(rpy[1])])
            centre = np.round(a + 0.5 * length * u, 4)
            length = math.ceil(length * 1000) / 1000
            r = math.ceil(segment_d(V[owner == k], centre - 0.5 * length * cz, cz, length).max() * 1000) / 1000 + 0.001
            xyz = tuple(float(x) + 0.0 for x in centre)
            print(f'        RobotCapsule("{link}", {xyz}, {rpy}, {r:.3f}, {length:.3f}, drawn=True),')


if __name__ == "__main__":
    main()
