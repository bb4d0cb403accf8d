#!/usr/bin/env python3
"""How a resized depth image back-projects: the table's height (true height 0 in the base frame)
as both cameras of pick_block_plate read it at the native size and resized, with the intrinsics
get_state reports for the size asked. Prints a table, then one JSON line.

    .venv/bin/python bench/py/depth_resized.py [--sizes 480x360,320x240]

A resized depth image is picked nearest-neighbour from the native one (never an invented depth),
so a resized pixel reads a native pixel up to half a native pixel from its centre: what is left
after the intrinsics are scaled about the pixel centres.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="480x360,320x240")
    a = ap.parse_args()
    sizes = [None] + [tuple(int(v) for v in s.split("x")) for s in a.sizes.split(",") if s]
    name = f"dres{os.getpid()}"
    p = subprocess.Popen([str(ROOT / "target/release/r2g"), "up", "pick_block_plate", "--instance", name,
                          "--mode", "lockstep"], stdout=subprocess.PIPE, text=True)
    rows = []
    try:
        assert p.stdout is not None and p.stdout.readline().strip() == f"READY {name}"
        os.environ["R2G_INSTANCE"] = name
        import robo

        robo.reset()
        for size in sizes:
            for cam in ("agentview", "wrist"):
                s = robo.get_state({cam: size} if size else [cam], raw=True)
                d, k = s["depth"][cam], s["camera_intrinsics"][cam]
                v, u = np.mgrid[0:d.shape[0], 0:d.shape[1]]
                cam_pts = np.stack([(u - k["cx"]) * d / k["fx"], (v - k["cy"]) * d / k["fy"], d, np.ones_like(d)])
                z = (np.array(s["camera_extrinsics"][cam]) @ cam_pts.reshape(4, -1))[2]
                table = z[np.abs(z) < 0.004]  # the table's pixels (objects stand higher)
                rows.append({"size": "native" if size is None else f"{size[0]}x{size[1]}", "camera": cam,
                             "table_median_mm": round(1000 * float(np.median(table)), 2), "pixels": int(table.size)})
    finally:
        p.send_signal(signal.SIGTERM)
        p.wait(30)
    print(f"{'size':<8} {'camera':<10} {'table height, median mm':>24} {'pixels':>8}")
    for r in rows:
        print(f"{r['size']:<8} {r['camera']:<10} {r['table_median_mm']:>24.2f} {r['pixels']:>8}")
    print(json.dumps({"gym": "pick_block_plate", "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
