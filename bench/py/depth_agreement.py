"""How far the two cameras' back-projected depth is from the truth, and from each other.

For each gym: `r2g up <gym> --mode lockstep`, reset, observe both cameras raw (RGB-D) at the
reset pose and with the hand lowered over the first free object (TCP 0.25 m above the table,
pointing down), back-project every pixel the documented way (robot-skill/api/README.md, "Raw
images and depth") and compare it with what MuJoCo's ray caster hits through the centre of the
same pixel in the very MJCF the sim-host runs (tests/python/depth_truth.py): the table's top
and every upward flat face (a block's top, a plate, a bowl's floor), per camera; median and
spread of the height error, a 3 x 3 grid of the table's median error over the image, each face's
height as each camera reads it, and the 3-D error at edge pixels.

Usage: depth_agreement.py [--gyms pick_block_plate,stack_bowls] [--no-lower]
(R2G_BIN: the r2g binary, e.g. an older build's, to measure it; R2G_GYMS: the gym pack.)
Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT / "tests" / "python")]
import depth_truth as dt  # noqa: E402
import render_truth as rt  # noqa: E402


def run_gym(gym: str, lower: bool) -> list[dict]:
    out = []
    with tempfile.TemporaryDirectory() as td:
        g = rt.LiveGym(rt.R2G, rt.GYMS_DIR, gym, trace_dir=Path(td), tag="depth")
        try:
            if not g.ready.wait(120):
                raise RuntimeError(f"{gym}: r2g up did not get ready")
            import robo
            g.use()
            robo.reset()
            observations = [("reset", g.observe())]
            target = dt.first_free_object(g.scene)
            if lower and target is not None:
                if rt.move_tcp([target[0], target[1], 0.25], 0.0):
                    observations.append(("lowered", g.observe()))
                else:
                    print(f"{gym}: could not lower the hand", file=sys.stderr)
            trace = g.end_episode()
            xml = rt.compiled_mjcf(rt.R2G.parent / "r2g-sim", g.scene_path)
        finally:
            g.stop()
        truth = dt.Truth(xml)
        for pose, obs in observations:
            objects, fixtures = rt.trace_state(g.scene, trace, t=obs["timestamp"])
            dt.posed_truth(truth, obs, objects, fixtures)
            for cam in ("agentview", "wrist"):
                r = dt.measure(obs, truth, cam)
                out.append({"gym": gym, "pose": pose, "camera": cam, "intrinsics": r.intrinsics,
                            "extrinsics_error_m": r.extrinsics_error_m, "depth_error": r.depth_error,
                            "table": r.table, "table_regions_mm": r.table_regions, "top": r.top,
                            "top_faces": r.top_faces, "edge_3d": r.edge})
    return out


def fmt(s: dict) -> str:
    if not s.get("n"):
        return "—"
    return f"{s['median_mm']:+6.2f} [{s['p5_mm']:+6.2f}, {s['p95_mm']:+6.2f}] max {s['max_abs_mm']:5.2f} (n={s['n']})"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gyms", default="pick_block_plate,stack_bowls")
    ap.add_argument("--no-lower", action="store_true", help="only the reset pose")
    a = ap.parse_args()
    rows = []
    for gym in a.gyms.split(","):
        rows += run_gym(gym, not a.no_lower)
    print(f"r2g: {rt.R2G}")
    print("height error, back-projected minus true, mm: median [p5, p95] max |err| (n pixels); edge pixels excluded")
    for r in rows:
        k = r["intrinsics"]
        print(f"\n{r['gym']} / {r['pose']} / {r['camera']}: fx {k['fx']:.2f} cx {k['cx']} cy {k['cy']}; "
              f"published pose vs MuJoCo's camera {r['extrinsics_error_m']:.1e} m")
        print(f"  depth - truth depth  {fmt(r['depth_error'])}")
        print(f"  table                {fmt(r['table'])}")
        print(f"  flat top faces       {fmt(r['top'])}")
        print(f"  edge pixels, 3-D     median {r['edge_3d'].get('median_mm', float('nan')):.2f} mm, "
              f"p95 {r['edge_3d'].get('p95_mm', float('nan')):.2f} mm (n={r['edge_3d'].get('n', 0)})")
        grid = " | ".join(" ".join("  —  " if x is None else f"{x:+5.2f}" for x in row) for row in r["table_regions_mm"])
        print(f"  table by image third (rows top→bottom | …): {grid}")
        for face, f in r["top_faces"].items():
            print(f"  face {face:<24} reads {f['height_m']:.4f} m (true {f['truth_m']:.4f}, {f['median_mm']:+.2f} mm, n={f['n']})")
    # the two cameras on the same faces
    print("\nagentview - wrist, same gym and pose, mm:")
    by = {(r["gym"], r["pose"], r["camera"]): r for r in rows}
    for (gym, pose, cam), r in by.items():
        if cam != "agentview" or (gym, pose, "wrist") not in by:
            continue
        w = by[(gym, pose, "wrist")]
        parts = []
        if r["table"].get("n") and w["table"].get("n"):
            parts.append(f"table {r['table']['median_mm'] - w['table']['median_mm']:+.2f}")
        for face in sorted(set(r["top_faces"]) & set(w["top_faces"])):
            parts.append(f"{face} {(r['top_faces'][face]['height_m'] - w['top_faces'][face]['height_m']) * 1e3:+.2f}")
        print(f"  {gym} / {pose}: " + ", ".join(parts))
    print(json.dumps({"r2g": str(rt.R2G), "rows": rows}))


if __name__ == "__main__":
    main()
