"""Every shipped gym reconstructed from its own frames (synthetic: rendered by `r2g render` from
the gym's agentview and four extra viewpoints, two beside the table and two looking down),
compared with its scene.toml and validated with its demonstration. Prints a table and, as the
last line, one JSON object.

    .venv/bin/python bench/py/reconstruct_all.py [--gyms a,b] [--extra-views 4] [--rounds 2]
        [--depth-noise-mm 0 --depth-noise-rel 0]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "real2sim" / "py"))
import r2g_reconstruct_eval as ev  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gyms", default="")
    ap.add_argument("--extra-views", type=int, default=len(ev.EXTRA_VIEWS))
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--depth-noise-mm", type=float, default=0.0,
                    help="synthetic Gaussian depth noise: standard deviation in mm, plus --depth-noise-rel x depth")
    ap.add_argument("--depth-noise-rel", type=float, default=0.0)
    a = ap.parse_args()
    gyms = [g for g in a.gyms.split(",") if g] or sorted(p.parent.name for p in (ROOT / "gyms").glob("*/scene.toml"))
    rows = []
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="r2g-reconstruct-bench-") as tmp:
        for g in gyms:
            rows.append(ev.evaluate(g, Path(tmp) / g, extra=a.extra_views, rounds=a.rounds,
                                    noise_mm=a.depth_noise_mm, noise_rel=a.depth_noise_rel))
    # IoU columns: "gate IoU" compares the render with the reconstruction's own segmentation of
    # the source (last kept round; "gate IoU0" the first round); "true IoU" compares it with the
    # true masks (mask_visib) of the synthetic frames, objects only.
    fmt = "{:<17} {:>5} {:>9} {:>9} {:>8} {:>6} {:>6} {:>6} {:>7} {:>6}  {}"
    print(fmt.format("gym", "found", "pos mean", "pos max", "size", "gate", "gate", "true", "valid", "s", "verdict"))
    print(fmt.format("", "/true", "cm", "cm", "cm", "IoU", "IoU0", "IoU", "", "", ""))
    for r in rows:
        v = r.get("validate")
        print(fmt.format(r["gym"], f"{r.get('found', '-')}/{r.get('truth_objects', 0) + r.get('truth_fixtures', 0)}",
                         str(r.get("position_error_cm_mean")), str(r.get("position_error_cm_max")),
                         str(r.get("size_error_cm_mean")), str(r.get("iou_mean")), str(r.get("iou_first_round")),
                         str(r.get("true_iou_mean")),
                         "-" if v is None else ("pass" if v["success"] else "FAIL"), r["seconds"],
                         r.get("error") or r["verdict"]))
    summary = {"bench": "reconstruct_all", "synthetic": True, "views": 1 + a.extra_views,
               "depth_noise": {"sigma_mm": a.depth_noise_mm, "relative": a.depth_noise_rel}, "gyms": rows,
               "validated": sum(1 for r in rows if (r.get("validate") or {}).get("success")),
               "ok": sum(1 for r in rows if r["verdict"] == "ok"), "seconds": round(time.monotonic() - t0, 1)}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
