"""The two cameras' depth, back-projected the documented way, lands on the true surfaces and on
each other (robot-skill/api/README.md, "Raw images and depth").

stack_bowls in lockstep, observed at the reset pose and with the hand lowered over the small
bowl: every pixel of agentview and wrist is back-projected with the published intrinsics and
`camera_extrinsics`, and compared with what MuJoCo's ray caster hits through the centre of the
same pixel in the very MJCF the sim-host runs (depth_truth.py): the table's top, and the bowls'
floors and rims (upward flat faces; the rim of the big bowl is the "box top at 0.050 m" a model
measured at 0.0515 m from agentview and 0.0492 m from the wrist).

Tolerances: the depth buffer (24 bits, near plane 2.2 cm) resolves about 0.01 mm at agentview's
1.7 m, and the measured medians are 0.00 mm with 5-95 % within 0.005 mm. A principal point half
a pixel off, or depth read from one sample of a multisampled pixel instead of its centre (both
were so before), moved the table and faces by +1.4…+2.4 mm in agentview and -0.3…-0.9 mm in the
wrist image. A median within 0.2 mm and 99 % of pixels within 0.5 mm keep a margin of 20x over
the noise and stay below the smallest of those errors. Pixels next to a change of geom or depth
are left out (`edge`); of the rest about 0.2 % (next to the robot's base, where MuJoCo's rays and
its rasteriser disagree on the base's mesh) may be off by more, hence a percentile, not a maximum.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from conftest import need_module

need_module("mujoco", "MuJoCo's Python bindings give the ground truth")

import depth_truth as dt  # noqa: E402
import render_truth as rt  # noqa: E402

MEDIAN_M = 2e-4
P99_M = 5e-4
CAMERAS = ("agentview", "wrist")


@pytest.fixture(scope="module")
def measured():
    """{pose: {camera: (CameraReport, back-projected z errors on the table and on flat faces)}}."""
    with tempfile.TemporaryDirectory() as td:
        g = rt.LiveGym(rt.R2G, rt.GYMS_DIR, "stack_bowls", trace_dir=Path(td), tag="dp")
        try:
            assert g.ready.wait(120), "r2g up did not get ready"
            import robo
            g.use()
            assert robo.reset() == 1
            observations = {"reset": g.observe(list(CAMERAS))}
            x, y, _ = next(o["position_m"] for o in g.scene["objects"] if o["name"] == "small_bowl")
            assert rt.move_tcp([x, y, 0.25], 0.0), robo.get_state([])["control_feedback"]
            observations["lowered"] = g.observe(list(CAMERAS))
            trace = g.end_episode()
            xml = rt.compiled_mjcf(rt.R2G.parent / "r2g-sim", g.scene_path)
        finally:
            g.stop()
    truth = dt.Truth(xml)
    out = {}
    for pose, obs in observations.items():
        objects, fixtures = rt.trace_state(g.scene, trace, t=obs["timestamp"])
        dt.posed_truth(truth, obs, objects, fixtures)
        out[pose] = {}
        for cam in CAMERAS:
            r = dt.measure(obs, truth, cam)
            c = truth.cast(cam, *obs["depth"][cam].shape[::-1])
            dz = r.points[..., 2] - c.point[..., 2]
            interior = ~c.edge & (c.geom >= 0)
            out[pose][cam] = (r, dz[interior & (c.geom == truth.table)], dz[interior & c.top])
    return out


@pytest.mark.parametrize("pose", ["reset", "lowered"])
@pytest.mark.parametrize("camera", CAMERAS)
def test_published_pose_is_the_camera_mujoco_renders_from(measured, pose, camera):
    r = measured[pose][camera][0]
    assert r.extrinsics_error_m < 1e-9, f"base_from_camera differs from MuJoCo's camera by {r.extrinsics_error_m} m"


@pytest.mark.parametrize("pose", ["reset", "lowered"])
@pytest.mark.parametrize("camera", CAMERAS)
@pytest.mark.parametrize("surface", ["table", "flat faces"])
def test_back_projected_surfaces_are_at_their_true_height(measured, pose, camera, surface):
    r, table, faces = measured[pose][camera]
    dz = table if surface == "table" else faces
    assert dz.size > 500, f"{camera} sees only {dz.size} pixels of the {surface}"
    med, p99 = float(np.median(dz)), float(np.percentile(np.abs(dz), 99))
    assert abs(med) < MEDIAN_M and p99 < P99_M, (
        f"{camera} {pose}: the {surface} reads {med * 1e3:+.2f} mm (median) from its true height, "
        f"99 % within {p99 * 1e3:.2f} mm; intrinsics {r.intrinsics}")


@pytest.mark.parametrize("pose", ["reset", "lowered"])
def test_the_two_cameras_agree_on_the_table_and_each_face(measured, pose):
    a, w = measured[pose]["agentview"][0], measured[pose]["wrist"][0]
    diffs = {"table": (a.table["median_mm"] - w.table["median_mm"]) * 1e-3}
    for face in sorted(set(a.top_faces) & set(w.top_faces)):
        diffs[face] = a.top_faces[face]["height_m"] - w.top_faces[face]["height_m"]
    # the big bowl's rim and floor, the small bowl's floor at least
    assert len(diffs) >= 4, f"faces seen by both cameras: {sorted(diffs)}"
    bad = {k: f"{v * 1e3:+.2f} mm" for k, v in diffs.items() if abs(v) > MEDIAN_M}
    assert not bad, f"agentview minus wrist heights ({pose}): {bad}"
