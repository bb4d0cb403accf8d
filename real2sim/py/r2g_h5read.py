"""Reads an HDF5 file with h5py for `r2g import` and prints one JSON object on stdout.

    r2g_h5read.py FILE [PREFIX ...]

Every numeric dataset whose path starts with one of the prefixes (all of them without one)
comes out as {"shape": [...], "data": [flat, row-major]}, with null for NaN and infinities so
the importer can name the frame; text datasets as {"shape": [...], "text": [...]}. The file's
root attributes come out under "attrs". Nothing is converted here: units, frames and
conventions are the importer's business (real2sim/src/droid.rs, egodex.rs).
Exit status 2 with a one-line message on stderr when the file cannot be read.
"""

import json
import math
import sys
from typing import Any, Dict, List

import h5py
import numpy as np


def plain(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray):
        return [plain(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def dataset(obj: "h5py.Dataset") -> Dict[str, Any]:
    arr = np.asarray(obj[()])
    shape: List[int] = list(arr.shape)
    if arr.dtype.kind in "biuf":
        flat = arr.astype(np.float64).ravel()
        data = [float(v) if math.isfinite(v) else None for v in flat.tolist()]
        return {"shape": shape, "data": data}
    if arr.dtype.kind in "SUO":
        return {"shape": shape, "text": [plain(v) for v in arr.ravel().tolist()]}
    return {"shape": shape, "unsupported": str(arr.dtype)}


def main(argv: List[str]) -> int:
    if len(argv) < 2:
        print("usage: r2g_h5read.py FILE [PREFIX ...]", file=sys.stderr)
        return 2
    path, prefixes = argv[1], argv[2:]
    out: Dict[str, Any] = {"datasets": {}, "attrs": {}}
    try:
        with h5py.File(path, "r") as f:
            out["attrs"] = {k: plain(v) for k, v in f.attrs.items()}

            def visit(name: str, obj: Any) -> None:
                if isinstance(obj, h5py.Dataset) and (not prefixes or any(name.startswith(p) for p in prefixes)):
                    out["datasets"][name] = dataset(obj)

            f.visititems(visit)
    except (OSError, ValueError, KeyError) as e:
        print(f"{type(e).__name__}: {e}".replace("\n", " "), file=sys.stderr)
        return 2
    json.dump(out, sys.stdout, allow_nan=False)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
