"""What a policy relies on in robo_perception: prompts that refuse unknown words and say when
they are ambiguous, fixture-part shapes, object fields, held-from-evidence, identities that
survive a pick and a place, steerable grasps, and the placing helper - judged natively.

Offline tests use synthetic clusters we build here. Live tests run gyms in lockstep
(`r2g up ... --mode lockstep --trace-dir`), check identities and the held flag against MuJoCo's
own segmentation (tests/python/render_truth.py, ground truth the library never sees), and run
robot-skill/examples/place_object.py on three gyms; the verdict is the sim-host's own
evaluator (episode-N.eval.json), never the program's claim.

Run:  .venv/bin/python -m pytest tests/python/test_perception_policy.py -q
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import render_truth as rt  # also puts agent-host/py/lib on the path
import robo_perception as rp
from robo_perception.segmentation import _make_cluster

ROOT, R2G, GYMS_DIR = rt.ROOT, rt.R2G, rt.GYMS_DIR
PLACE = ROOT / "robot-skill" / "examples" / "place_object.py"
PICK = ROOT / "robot-skill" / "examples" / "pick_object.py"
CAMS = ["agentview", "wrist"]


# ------------------------------------------------------------------------------------------
# Offline (synthetic clusters)
# ------------------------------------------------------------------------------------------

def test_unknown_prompt_words_are_errors_that_list_the_known_words():
    with pytest.raises(rp.PromptError) as e:
        rp.parse_prompt("the rack")
    msg = str(e.value)
    assert "'rack'" in msg and "Colours:" in msg and "handle" in msg and "left" in msg
    with pytest.raises(ValueError):            # PromptError is a ValueError
        rp.parse_prompt("blue gizmo on the left")
    q = rp.parse_prompt("the handle of the drawer")
    assert q["shapes"] == ["bar"] and q["context"] == ["drawer"]       # the head noun, not the drawer
    assert rp.parse_prompt("drawer handle")["shapes"] == ["bar"]         # compound: the last noun
    q = rp.parse_prompt("the red block on the left")
    assert q["colors"] == ["red"] and q["shapes"] == ["box"] and q["spatial"] == ["left"] and not q["context"]
    q = rp.parse_prompt("the block on the blue plate")
    assert q["colors"] == [] and q["shapes"] == ["box"] and q["context"] == ["blue", "plate"]
    assert rp.parse_prompt("the red object")["shapes"] == []   # "object" means any shape
    with pytest.raises(TypeError):
        rp.parse_prompt(None)


@pytest.mark.parametrize("extents, fill, expect", [
    ((0.138, 0.046, 0.014), 0.9, "bar"),       # a drawer's bar handle lying along the front
    ((0.022, 0.012, 0.099), 0.9, "bar"),       # an upright door handle
    ((0.300, 0.019, 0.301), 0.95, "panel"),    # a cabinet door
    ((0.040, 0.040, 0.041), 1.0, "box"),       # a block stays a box
    ((0.179, 0.179, 0.014), 0.79, "plate"),    # a plate lying flat stays a plate
])
def test_fixture_parts_have_shape_words(extents, fill, expect):
    assert rp.shape_name(extents, fill, False, 0.95) == expect


def _plane() -> rp.Plane:
    return rp.fit_plane_ransac(np.c_[np.random.default_rng(0).uniform(-1, 1, (500, 2)), np.zeros(500)])[0]


def _cluster(center, size, color=(200, 30, 30), n=2000, seed=0):
    """A solid box of points (synthetic), as segment_scene would report it."""
    rng = np.random.default_rng(seed)
    P = np.asarray(center) + (rng.uniform(-0.5, 0.5, (n, 3)) * np.asarray(size))
    C = np.tile(np.asarray(color, dtype=np.uint8), (n, 1))
    plane = _plane()
    h = plane.distance(P)
    view = rp.CameraView("cam", np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32),
                         {"fx": 1, "fy": 1, "cx": 2, "cy": 2, "width": 4, "height": 4}, np.eye(4))
    o = _make_cluster(0, P, C, h, np.arange(n), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int32),
                      [view], plane)
    return o, plane


def _scene(objs, plane):
    return rp.SceneSegmentation(plane=plane, objects=objs, views=[], timings_ms={}, plane_masks={})


def test_implausible_support_planes_are_warned_about():
    from robo_perception.segmentation import _plane_warnings
    flat = _plane()
    assert _plane_warnings(flat, np.ones(100, dtype=bool)) == []
    # a wall-like plane seen by a camera facing sideways: 60 deg from horizontal
    P = np.random.default_rng(1).uniform(-0.2, 0.2, (400, 2))
    tilted, _ = rp.fit_plane_ransac(np.c_[P[:, 0], P[:, 1], 0.33 + math.tan(math.radians(60)) * P[:, 0]],
                                    up=None)
    w = _plane_warnings(tilted, np.ones(100, dtype=bool))
    assert len(w) == 1 and "tilted 60 deg" in w[0], w
    assert "only 1.0 %" in _plane_warnings(flat, np.r_[np.ones(1, bool), np.zeros(99, bool)])[0]


def test_fields_top_bottom_height_size():
    o, _ = _cluster([0.5, 0.0, 0.13], [0.04, 0.04, 0.04])          # lifted: 11-15 cm above the plane
    assert abs(o.top - 0.15) < 0.003 and abs(o.bottom - 0.11) < 0.003
    assert abs(o.height - 0.04) < 0.004                              # its own size, not its top
    r, _ = _cluster([0.5, 0.0, 0.025], [0.04, 0.04, 0.04])         # resting: box reaches the plane
    assert abs(r.height - r.top) < 0.004 and np.allclose(sorted(r.dims)[:2], [0.04, 0.04], atol=0.004)


def test_ambiguous_selection_says_so_and_a_unique_one_does_not():
    a, plane = _cluster([0.5, 0.1, 0.03], [0.05, 0.05, 0.06], color=(200, 30, 30), seed=1)
    b, _ = _cluster([0.5, -0.1, 0.03], [0.05, 0.05, 0.06], color=(30, 30, 200), seed=2)
    a.id, b.id = 0, 1
    scene = _scene([a, b], plane)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert rp.select(scene, "red block on the blue plate") is a
        assert any("'blue plate' was not used" in str(x.message) for x in w), [str(x.message) for x in w]
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert rp.select(scene, "red") is a
        assert not w
        rp.select(scene, "box")
        assert any(issubclass(x.category, rp.PerceptionWarning) and "ambiguous" in str(x.message) for x in w)
    assert any("ambiguous" in s for s in scene.warnings)
    with warnings.catch_warnings():
        warnings.simplefilter("error", rp.PerceptionWarning)
        with pytest.raises(rp.PerceptionWarning):
            rp.select(scene, "box")
        assert rp.select(scene, "box on the left") is a          # +y is left


def test_tracker_keeps_ids_and_names_and_follows_a_held_object(tmp_path):
    path = tmp_path / "tracks.json"
    a, plane = _cluster([0.5, 0.1, 0.03], [0.05, 0.05, 0.06], seed=1)
    t = rp.Tracker(str(path))
    s1 = _scene([a], plane)
    t.update(s1, 1.0, [0.5, 0.1, 0.2])
    assert a.track_id == 0 and path.exists()
    # a later program (a new Tracker from the file): the object now seen lifted with the TCP,
    # 12 cm up and 8 cm aside, partly hidden (named differently by this observation alone)
    b, _ = _cluster([0.58, 0.1, 0.15], [0.05, 0.02, 0.05], seed=3)
    b.shape_name = "flat"
    b.held_evidence = {"gripper_closed_on_something": True, "grasp_status": "holding"}
    b.in_contact = True                      # beside the fingers, which closed on something
    t2 = rp.Tracker(str(path))
    s2 = _scene([b], plane)
    t2.update(s2, 2.0, [0.58, 0.1, 0.32])
    assert b.track_id == 0 and b.shape_name == a.shape_name and b.seen_as.endswith("flat")
    assert b.held_evidence["moves_with_tcp"] is True and b.held and not b.pushed
    # time going backwards = reset(): a new episode, new tracks
    c, _ = _cluster([0.5, 0.1, 0.03], [0.05, 0.05, 0.06], seed=4)
    t2.update(_scene([c], plane), 0.1, [0.3, 0.0, 0.5])
    assert c.track_id == 0 and len(t2.tracks) == 1
    # a damaged file costs the names, never the observation
    path.write_text("{not json")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        t3 = rp.Tracker(str(path))
    assert t3.tracks == [] and any("could not be read" in str(x.message) for x in w)


def test_place_poses_on_a_support_and_into_a_container():
    held, plane = _cluster([0.45, -0.1, 0.15], [0.04, 0.04, 0.04], seed=5)
    held.held = True
    tcp = [0.45, -0.1, 0.16, math.pi, 0.0, 0.0]
    slab, _ = _cluster([0.5, 0.15, 0.01], [0.18, 0.18, 0.02], color=(30, 30, 200), seed=6)
    scene = _scene([held, slab], plane)
    pl = rp.place_poses(held, slab, scene, tcp, clearance=0.01)
    # bottom (0.13) is 3 cm under the TCP: the TCP goes to surface (0.02) + clearance + 0.03
    assert abs(pl.pose[2] - (0.02 + 0.01 + 0.03)) < 0.004
    assert np.allclose(pl.pose[:2], slab.center[:2], atol=0.004) and pl.pose[3:] == tcp[3:]
    assert abs(pl.preplace[2] - pl.pose[2] - 0.10) < 1e-9
    with pytest.raises(ValueError):
        rp.place_poses(held, None, scene, tcp)
    # on the plane at a point, with the object's centre 2 cm beside the TCP
    pl2 = rp.place_poses(held, None, scene, tcp, at=(0.6, 0.0), center_offset=(0.02, 0.0, 0.0))
    assert np.allclose(pl2.pose[:3], [0.58, 0.0, 0.01 + 0.03], atol=0.004)


# ------------------------------------------------------------------------------------------
# Live gyms
# ------------------------------------------------------------------------------------------

def _truth_label(o, truth) -> str:
    """The scene element owning most of the object's pixels (MuJoCo's segmentation)."""
    votes: dict = {}
    for cam in CAMS:
        for name, m in truth.masks(cam).items():
            k = int((m & o.masks[cam]).sum())
            if k:
                votes[name] = votes.get(name, 0) + k
    return max(votes, key=votes.get) if votes else "none"


def _last_eval(trace_dir: Path) -> dict:
    evals = sorted(trace_dir.glob("episode-*.eval.json"), key=lambda p: int(p.name.split("-")[1].split(".")[0]))
    return json.loads(evals[-1].read_text())


def _move(goal, gripper, step=0.02):
    import robo
    path = rp.interpolate_poses(robo.get_state([])["ee_pose"], goal, max_step_m=step, max_step_rad=0.3)
    assert robo.post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints(path, gripper)}) == 1, \
        robo.get_state([])["control_feedback"]


def test_identity_and_held_through_a_pick_and_a_place_against_mujoco_segmentation(tmp_path):
    """stack_bowls: names and track ids at the start (labelled by MuJoCo's segmentation), while
    the orange bowl is held (picked by the example program in another process), and after it is
    put into the blue bowl with `place_poses` and released: every object keeps its id and name,
    and only the bowl in the hand is `held`."""
    g = rt.LiveGym(R2G, GYMS_DIR, "stack_bowls", trace_dir=tmp_path / "trace", tag="ppol")
    truth = None
    try:
        assert g.ready.wait(90), "r2g up did not print READY"
        truth = rt.TruthRenderer(rt.compiled_mjcf(R2G.parent / "r2g-sim", g.scene_path))
        fixtures = rt.initial_fixtures(g.scene)
        tracker = rp.Tracker()          # in memory
        obs = g.observe()
        truth.set_state(obs["joint"], rp.gripper_to_width(obs["gripper"][0]) / 2, fixtures=fixtures)
        scene = rp.segment_scene(obs, tracker=tracker)
        ids: dict = {}
        for o in scene.objects:
            ids[_truth_label(o, truth)] = (o.track_id, o.color_name, o.shape_name, o.height)
            assert not o.held, f"{o.describe()} held with the gripper open"
        assert {"small_bowl", "big_bowl"} <= set(ids), scene.summary()
        # pick the orange bowl with the example (another process), then look while it is held
        env = dict(os.environ, R2G_INSTANCE=g.instance)
        out = subprocess.run([sys.executable, str(PICK), "orange bowl"], env=env, capture_output=True, text=True,
                             timeout=240)
        assert "RESULT lifted=True" in out.stdout, out.stdout[-2000:]
        held_obs = g.observe()
        held_scene = rp.segment_scene(held_obs, tracker=tracker)
        small = next(o for o in held_scene.objects if o.track_id == ids["small_bowl"][0])
        big = next(o for o in held_scene.objects if o.track_id == ids["big_bowl"][0])
        # put it into the blue bowl: pre-place, down, open, straight up
        pl = rp.place_poses(small, big, held_scene, held_obs["ee_pose"], object_height=ids["small_bowl"][3])
        _move(pl.preplace, 1.0)
        _move(pl.pose, 1.0, step=0.01)
        _move(pl.pose, -1.0)
        _move(pl.retreat, -1.0)
        placed_obs = g.observe()
        placed_scene = rp.segment_scene(placed_obs, tracker=tracker)
        # the truth of both states, from the episode's native trace
        trace = g.end_episode()
        for obs, scene, holding in ((held_obs, held_scene, True), (placed_obs, placed_scene, False)):
            truth.set_state(obs["joint"], rp.gripper_to_width(obs["gripper"][0]) / 2, fixtures=fixtures,
                            objects=rt.trace_state(g.scene, trace, obs["timestamp"])[0])
            for o in scene.objects:
                label = _truth_label(o, truth)
                assert label in ids, f"{o.describe()} is {label}, which was not an object at the start"
                assert o.track_id == ids[label][0], f"{label} changed identity: {o.describe()}"
                assert (o.color_name, o.shape_name) == ids[label][1:3], f"{label} changed name: {o.describe()}"
                assert o.held == (holding and label == "small_bowl"), (label, o.held, o.held_evidence)
            assert {ids["small_bowl"][0], ids["big_bowl"][0]} <= {o.track_id for o in scene.objects}, scene.summary()
        verdict = _last_eval(tmp_path / "trace")
        assert verdict["checks"]["inside:small_bowl:big_bowl"]["pass"], verdict["checks"]
    finally:
        if truth is not None:
            truth.close()
        g.stop()


@pytest.mark.parametrize("gym, args", [
    ("pick_block_plate", ["red block", "blue plate"]),
    ("stack_bowls", ["orange bowl", "blue bowl"]),
    ("push_to_line", ["green block", "--past", "yellow"]),
])
def test_place_example_is_judged_successful_natively(tmp_path, gym, args):
    g = rt.LiveGym(R2G, GYMS_DIR, gym, trace_dir=tmp_path / "trace", tag="pplace")
    try:
        assert g.ready.wait(90), "r2g up did not print READY"
        g.end_episode()
        env = dict(os.environ, R2G_INSTANCE=g.instance, R2G_PERCEPTION_TRACKS=str(tmp_path / "tracks.json"))
        out = subprocess.run([sys.executable, str(PLACE), *args], env=env, capture_output=True, text=True, timeout=300)
        g.end_episode()
        verdict = _last_eval(tmp_path / "trace")
        assert verdict["success"], (verdict["checks"], out.stdout[-2500:], out.stderr[-1500:])
        assert "RESULT placed=True" in out.stdout
    finally:
        g.stop()


def test_grasps_can_be_steered_by_region_and_closing_direction():
    bar, plane = _cluster([0.5, 0.0, 0.02], [0.16, 0.03, 0.04], seed=7, n=4000)   # a 16 cm bar along x
    scene = _scene([bar], plane)
    free = rp.propose_grasps(bar, scene)
    assert free and all(abs(g.closing[1]) > 0.9 for g in free[:3])   # across the bar, as expected
    end = rp.propose_grasps(bar, scene, near=(0.56, 0.0, 0.02), near_radius=0.02)
    assert end and all(abs(g.position[0] - 0.56) <= 0.02 + 1e-6 for g in end)
    along = rp.propose_grasps(bar, scene, near=(0.5, 0.0, 0.02), closing=(0.0, 1.0, 0.0), closing_tolerance_deg=10)
    assert along and all(abs(g.closing[1]) >= math.cos(math.radians(10)) - 1e-9 for g in along)
    # the bar is 16 cm long: closing along it cannot fit the 8 cm stroke, so nothing is offered
    assert rp.propose_grasps(bar, scene, closing=(1.0, 0.0, 0.0), closing_tolerance_deg=10) == []
    with pytest.raises(ValueError):
        rp.propose_grasps(bar, scene, closing=(0.0, 0.0, 0.0))


@pytest.mark.parametrize("gym, part, panel, check", [
    # the drawer's bar handle: 14 cm long, its top flush with the drawer front's top (0.2 m).
    # Known limitation: since the hand is drawn as the real one (no guard in the way), the wrist
    # camera sees the drawer front and the cabinet's top together; both are the same colour and
    # touch, so they come out as one box and select('drawer') is ambiguous (no split of a cluster
    # into faces yet). Strict: the day it passes, this mark must go.
    pytest.param("open_drawer", "drawer handle", "drawer",
                 lambda o: 0.12 <= o.dims[0] <= 0.16 and abs(o.top - 0.2) < 0.015,
                 marks=pytest.mark.xfail(strict=True, raises=rp.PerceptionWarning,
                                         reason="drawer front and cabinet top fuse into one box")),
    # the cabinet door's upright handle: about 10 cm tall
    ("close_cabinet", "door handle", "door", lambda o: 0.08 <= o.height <= 0.12),
])
def test_fixture_parts_can_be_asked_for_on_live_gyms(gym, part, panel, check):
    g = rt.LiveGym(R2G, GYMS_DIR, gym, tag="pfix")
    try:
        assert g.ready.wait(90), "r2g up did not print READY"
        scene = rp.segment_scene(g.observe(), tracker=None)
        with warnings.catch_warnings():
            warnings.simplefilter("error", rp.PerceptionWarning)     # neither may be ambiguous
            handle = rp.select(scene, part)
        assert handle is not None and handle.shape_name == "bar" and check(handle), scene.summary()
        with warnings.catch_warnings():
            warnings.simplefilter("error", rp.PerceptionWarning)
            front = rp.select(scene, panel)
        assert front is not None and front.shape_name == "panel" and front is not handle, scene.summary()
    finally:
        g.stop()
