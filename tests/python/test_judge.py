"""`r2g judge`, mechanics only. The answers here are synthetic (written in this file, not by a
model), served by the scripted LLM server over real HTTP on loopback in both wire formats; the
evidence is real: the native gate runs, `r2g render` draws the MuJoCo images, and the request the
server receives carries them. What these tests check is the plumbing and the arithmetic — that a
valid answer is recorded and simulation success is computed by us, that a malformed answer and an
out-of-range score are refused with a clear error and the raw answer kept, that the physical-
failure override follows the native verdict (initial or persistent penetration only), that the viewpoint
evidence is the gym's own cameras paired with the source frames they stand for, and that an
unreachable endpoint is a clear error.
No score here measures a gym.

Blender images are left out (`--no-blender`) but in one test, which renders one gym camera at rest and
one instant with Blender (tests/python/test_blender*.py cover Blender's pictures): a Cycles render
per instant would make this file slow."""
from __future__ import annotations

import json
import socket
import subprocess
from pathlib import Path

import pytest

from conftest import R2G, ROOT, STRICT
from pngdecode import decode

PB = ROOT / "gyms" / "pick_block_plate"


def part(score, why="synthetic justification citing the evidence"):
    return {"score": score, "justification": why}


def answer(**change) -> dict:
    """A well-formed synthetic answer for a run without Blender images and without source frames
    (those two items null); `change` replaces top-level items."""
    a = {
        "content_alignment": {"mujoco": part(42), "blender": part(None, "no Blender images were sent")},
        "viewpoint_alignment": part(None, "no source frames to compare with"),
        "action_fidelity": {
            "goals_objects": part(10), "actions_order": part(20), "contacts_mode": part(20),
            "paths_poses": part(15), "timing": part(8), "initial_final_states": part(10),
            "wrong_goal": False, "non_equivalent": False, "justification": "synthetic",
        },
        "task_completion": {"steps": part(40), "final_state": part(30), "physical_execution": part(15)},
        "physical_failure": {"observed": False, "justification": "synthetic: nothing passes through anything"},
    }
    a.update(change)
    return a


def judge(tmp: Path, reply, *extra: str, gym: str = "pick_block_plate", name: str = "run",
          provider: str = "openai") -> tuple[subprocess.CompletedProcess[str], Path]:
    """`r2g judge` against the scripted server answering `reply` (a dict is sent as JSON)."""
    script = tmp / f"{name}-answer.json"
    text = reply if isinstance(reply, str) else json.dumps(reply)
    script.write_text(json.dumps({"gym": "judge-test", "model": "scripted-judge", "responses": [text]}))
    out = tmp / name
    p = subprocess.run([str(R2G), "judge", gym, "--llm", f"scripted:{script}", "--provider", provider,
                        "--no-blender", "--out", str(out), *extra],
                       capture_output=True, text=True, timeout=300)
    return p, out


def test_a_valid_answer_is_recorded_and_simulation_success_is_ours(tmp_path: Path) -> None:
    for provider in ("openai", "anthropic"):
        p, out = judge(tmp_path, answer(), name=provider, provider=provider)
        assert p.returncode == 0, p.stderr
        line = json.loads(p.stdout.strip().splitlines()[-1])
        rec = json.loads((out / "judge.json").read_text())
        assert line["judge"] == str(out / "judge.json") and line["measurement"] is False
        assert rec["measurement"] is False and rec["label"].startswith("mechanics only")
        s = rec["scores"]
        # Parts added up here: 10+20+20+15+8+10 and 40+30+15; the product over 100 by us.
        assert s["action_fidelity"] == 83 and s["task_completion"] == 85
        assert s["simulation_success"] == pytest.approx(83 * 85 / 100, abs=0.006)
        # One engine's part alone is no total: reported as partial, never scaled up.
        assert s["content_alignment"] is None and s["content_alignment_partial"] is True
        assert s["content_alignment_mujoco"] == 42 and s["content_alignment_blender"] is None
        assert "MuJoCo part (0-50) stands alone" in s["content_alignment_basis"]
        assert line["scores"]["content_alignment"] is None and line["scores"]["content_alignment_mujoco"] == 42
        assert s["viewpoint_alignment"] is None
        assert rec["override"] == {"applied": False, "reasons": []}
        assert rec["native_verdict"]["kind"] == "validate" and rec["native_verdict"]["success"] is True
        # Model, tokens and what was sent.
        assert rec["llm"]["source"] == "scripted" and rec["llm"]["model"] == "scripted-pick_block_plate"
        assert rec["llm"]["usage"]["input"] > 0 and rec["llm"]["usage"]["output"] > 0
        req = rec["request"]
        assert any("not requested (--no-blender)" in m for m in req["missing_evidence"])
        assert any(m.startswith("source frames:") for m in req["missing_evidence"])
        assert req["viewpoints"] is None  # no source frames: no at-rest views to pair
        assert sorted(req["not_gradable"]) == ["content_alignment.blender", "viewpoint_alignment"]
        images = req["images"]
        assert len(images) == len(req["instants_s"]) >= 3, images
        assert all(i["label"].startswith("MuJoCo image") for i in images)
        # The server received those images, in the provider's wire format.
        sent = json.loads((out / "llm-log" / "request-001.json").read_text())
        parts = sent["messages"][-1]["content"]
        kind = "image_url" if provider == "openai" else "image"
        assert sum(1 for x in parts if x["type"] == kind) == len(images)
        assert "physical-failure rule" in json.dumps(sent)  # the rubric went as the system prompt
        assert (out / "answer.raw.txt").read_text() == json.dumps(answer())
        assert p.stderr.startswith("r2g judge: mechanics only"), p.stderr[:200]
        assert "pick_block_plate" in (out / "request.md").read_text()


def render_frames(tmp: Path) -> tuple[Path, dict]:
    """Synthetic source frames: pick_block_plate rendered at rest by `r2g render` (BOP layout)."""
    frames = tmp / "frames"
    r = subprocess.run([str(R2G), "render", "pick_block_plate", "--out", str(frames)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return frames, json.loads((frames / "scene_camera.json").read_text())


def copy_gym(tmp: Path, name: str, cameras: dict[str, str], shift_agentview_m: float = 0.0) -> Path:
    """pick_block_plate under another name, its cameras renamed (`cameras`: old name -> new) and
    the agentview camera moved sideways by `shift_agentview_m` (synthetic)."""
    g = tmp / name
    g.mkdir()
    scene = (PB / "scene.toml").read_text()
    scene = scene.replace('urdf = "../../robots/panda/panda.urdf"', f'urdf = "{ROOT / "robots/panda/panda.urdf"}"')
    assert "position_m = [1.4, 0.0, 0.95]" in scene
    scene = scene.replace("position_m = [1.4, 0.0, 0.95]", f"position_m = [1.4, {shift_agentview_m}, 0.95]")
    for old, new in cameras.items():
        assert f'name = "{old}"' in scene
        scene = scene.replace(f'name = "{old}"', f'name = "{new}"')
    (g / "scene.toml").write_text(scene)
    (g / "demo.csv").write_text((PB / "demo.csv").read_text())
    return g


def changed_share(a: Path, b: Path, step: int = 40) -> float:
    """The share of pixels of two same-sized images where some channel differs by more than `step`."""
    w, h, c, x = decode(a.read_bytes())
    w2, h2, c2, y = decode(b.read_bytes())
    assert (w, h, c) == (w2, h2, c2)
    changed = {i // c for i, (p, q) in enumerate(zip(x, y)) if abs(p - q) > step}
    return len(changed) / (w * h)


def rest_image(out: Path, camera: str) -> Path:
    """The at-rest MuJoCo image of a gym camera in a judge run's evidence."""
    cams = json.loads((out / "evidence" / "mujoco-rest" / "scene_camera.json").read_text())
    im = next(k for k, v in cams.items() if v["r2g_camera"] == camera)
    return out / "evidence" / "mujoco-rest" / "rgb" / f"{int(im):06d}.png"


def test_viewpoints_are_the_gyms_own_cameras_paired_with_the_source_frames(tmp_path: Path) -> None:
    frames, source = render_frames(tmp_path)
    by_camera = {v["r2g_camera"]: int(k) for k, v in source.items()}
    graded = answer(viewpoint_alignment=part(100, "synthetic: the same camera"))
    # 1. The gym the frames came from: its own cameras see what the frames saw, pixel for pixel.
    p, out = judge(tmp_path, graded, "--frames", str(frames))
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    assert rec["source_frames"] == str(frames) and rec["scores"]["viewpoint_alignment"] == 100
    vp = rec["request"]["viewpoints"]
    assert vp["paired"] is True and "r2g_camera" in vp["basis"]
    assert sorted((x["gym_camera"], x["source_id"]) for x in vp["pairs"]) == sorted(by_camera.items())
    labels = [i["label"] for i in rec["request"]["images"]]
    assert sum(lb.startswith("Source frame") for lb in labels) == len(source)
    # Each source frame is followed by the gym camera that stands for it.
    for cam, sid in by_camera.items():
        k = labels.index(next(lb for lb in labels if lb.startswith(f"Source frame {sid} ")))
        assert labels[k + 1] == f"MuJoCo image of the gym's own camera {cam} at rest, the view of source frame {sid}"
    assert sum(lb.startswith("MuJoCo image") for lb in labels) == len(source) + len(rec["request"]["instants_s"])
    assert changed_share(rest_image(out, "agentview"), frames / "rgb" / f"{by_camera['agentview']:06d}.png") < 0.001
    assert rec["request"]["not_gradable"] == ["content_alignment.blender"]

    # 2. A gym reconstructed from those frames (its cameras named cam_<id>, reconstruction.json
    # naming the frames) whose front camera sits 10 cm to the side: it is paired by name, and its
    # image differs from the source frame's, so the model sees the shift.
    ids = {cam: f"cam_{sid}" for cam, sid in by_camera.items()}
    moved = copy_gym(tmp_path, "moved", ids, shift_agentview_m=0.1)
    (moved / "reconstruction.json").write_text(json.dumps({"source": str(frames)}))
    p, out = judge(tmp_path, graded, gym=str(moved), name="moved-run")
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    assert rec["source_frames"] == str(frames)
    vp = rec["request"]["viewpoints"]
    assert vp["paired"] is True and "r2g reconstruct" in vp["basis"]
    assert sorted((x["gym_camera"], x["source_id"]) for x in vp["pairs"]) == sorted(
        (ids[c], sid) for c, sid in by_camera.items())
    front = frames / "rgb" / f"{by_camera['agentview']:06d}.png"
    # (10 cm changes about 6 % of the pixels clearly; the unmoved camera changes none.)
    assert changed_share(rest_image(out, ids["agentview"]), front) > 0.02
    # The wrist camera did not move: the same picture.
    assert changed_share(rest_image(out, ids["wrist"]), frames / "rgb" / f"{by_camera['wrist']:06d}.png") < 0.001

    # 3. Cameras that name no source frame: sent unpaired, and the request says so.
    other = copy_gym(tmp_path, "other", {"agentview": "front", "wrist": "hand_cam"})
    p, out = judge(tmp_path, graded, "--frames", str(frames), gym=str(other), name="other-run")
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    vp = rec["request"]["viewpoints"]
    assert vp["paired"] is False and vp["pairs"] == [] and vp["unpaired_gym_cameras"] == ["front", "hand_cam"]
    text = (out / "request.md").read_text()
    assert "NOT paired with the source frames" in text and "is not known" in text
    assert "MuJoCo image of the gym's own camera front at rest, not paired with a source frame" in text


def test_blender_renders_the_gyms_own_cameras_too(tmp_path: Path) -> None:
    """Synthetic source frames (as above); Blender draws the same gym camera at rest as MuJoCo,
    so no Blender evidence is missing. One frame, one instant."""
    if not (ROOT / ".venv-blender" / "bin" / "python").is_file():
        why = ".venv-blender is missing: run scripts/setup-blender.sh"
        if STRICT:
            pytest.fail(f"{why}; make test installs it", pytrace=False)
        pytest.skip(why)
    frames, _ = render_frames(tmp_path)
    graded = answer(viewpoint_alignment=part(100, "synthetic: the same camera"),
                    content_alignment={"mujoco": part(42), "blender": part(40)})
    script = tmp_path / "answer.json"
    script.write_text(json.dumps({"gym": "judge-test", "model": "scripted-judge", "responses": [json.dumps(graded)]}))
    out = tmp_path / "run"
    p = subprocess.run([str(R2G), "judge", "pick_block_plate", "--llm", f"scripted:{script}", "--frames", str(frames),
                        "--max-frames", "1", "--at", "0", "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    req = rec["request"]
    assert not any("Blender" in m for m in req["missing_evidence"]), req["missing_evidence"]
    assert req["not_gradable"] == []
    s = rec["scores"]
    assert s["content_alignment"] == 82 and s["content_alignment_partial"] is False
    mj = json.loads((out / "evidence" / "mujoco-rest" / "scene_camera.json").read_text())
    bl = json.loads((out / "evidence" / "blender-rest" / "scene_camera.json").read_text())
    # The same gym camera, the one paired with the source frame, in both renderers.
    assert len(mj) == len(bl) == 1
    assert [c["r2g_camera"] for c in bl.values()] == [c["r2g_camera"] for c in mj.values()] == ["agentview"]
    labels = [i["label"] for i in req["images"]]
    assert sum(lb.startswith("Blender image") for lb in labels) == 2  # the gym camera at rest, the instant


def test_a_replay_verdict_is_taken_as_given(tmp_path: Path) -> None:
    rep = tmp_path / "replay"
    r = subprocess.run([str(R2G), "replay", "pick_block_plate", "--out", str(rep)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    verdict = tmp_path / "replay.json"
    verdict.write_text(r.stdout)  # the evaluator's JSON line, as printed
    trace = rep / "pick_block_plate-seed0.trace.json"
    p, out = judge(tmp_path, answer(), "--verdict", str(verdict), "--trace", str(trace), "--at", "0,12")
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    assert rec["native_verdict"]["kind"] == "replay" and rec["native_verdict"]["success"] is True
    assert rec["request"]["instants_s"] == [0, 12] and len(rec["request"]["images"]) == 2
    assert not (out / "native").exists()  # the gate did not run again
    # Something else given as a verdict is refused by name.
    p, out = judge(tmp_path, answer(), "--verdict", str(PB / "keyframes.toml"), name="not-a-verdict")
    assert p.returncode != 0 and "keyframes.toml is not JSON" in p.stderr, p.stderr
    p, out = judge(tmp_path, answer(), "--verdict", str(rep / "pick_block_plate-seed0.trace.json"), name="trace")
    assert p.returncode != 0 and "is neither r2g validate's evidence.json nor r2g replay's evaluation" in p.stderr


def test_a_malformed_answer_is_refused_and_kept(tmp_path: Path) -> None:
    text = "The reconstruction looks faithful; I would give it 85/100 overall."
    p, out = judge(tmp_path, text)
    assert p.returncode != 0
    assert "the judge's answer is not valid: the answer is not one JSON object" in p.stderr, p.stderr
    assert str(out / "answer.raw.txt") in p.stderr
    assert (out / "answer.raw.txt").read_text() == text
    assert not (out / "judge.json").exists()


def test_an_out_of_range_score_and_a_missing_justification_are_named(tmp_path: Path) -> None:
    bad = answer(content_alignment={"mujoco": part(70), "blender": part(None, "none sent")})
    bad["task_completion"]["steps"] = {"score": 40, "justification": ""}
    p, out = judge(tmp_path, bad)
    assert p.returncode != 0
    assert "content_alignment.mujoco.score = 70 is outside [0, 50]" in p.stderr, p.stderr
    assert "task_completion.steps.justification is empty" in p.stderr, p.stderr
    assert not (out / "judge.json").exists()
    # A score where the evidence was absent is refused as well: it cannot have been seen.
    made_up = answer(viewpoint_alignment=part(90))
    p, out = judge(tmp_path, made_up, name="made-up")
    assert p.returncode != 0
    assert "viewpoint_alignment.score is 90, but its evidence is absent: it must be null" in p.stderr, p.stderr


def sunk_gym(tmp: Path) -> Path:
    """pick_block_plate with the block started 8 mm into the table (synthetic fault)."""
    g = tmp / "pick_block_plate_sunk"
    g.mkdir()
    scene = (PB / "scene.toml").read_text()
    scene = scene.replace('urdf = "../../robots/panda/panda.urdf"', f'urdf = "{ROOT / "robots/panda/panda.urdf"}"')
    assert "position_m = [0.5, -0.12, 0.02]" in scene
    scene = scene.replace("position_m = [0.5, -0.12, 0.02]", "position_m = [0.5, -0.12, 0.012]")
    (g / "scene.toml").write_text(scene)
    (g / "demo.csv").write_text((PB / "demo.csv").read_text())
    return g


def test_the_override_follows_the_native_verdict(tmp_path: Path) -> None:
    p, out = judge(tmp_path, answer(), gym=str(sunk_gym(tmp_path)))
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    assert rec["native_verdict"]["physical_failures"], rec["native_verdict"]
    assert any("initial_penetration failed" in r for r in rec["native_verdict"]["physical_failures"])
    # The sunk block also fails worst_penetration and settles_at_rest; those alone are not the
    # paper's confirmed failure, so they fail the gate but are not reasons for the override.
    assert {"worst_penetration", "settles_at_rest"} <= set(rec["native_verdict"]["failed_checks"])
    assert not any(r.startswith(("worst_penetration", "settles_at_rest"))
                   for r in rec["native_verdict"]["physical_failures"])
    assert rec["override"]["applied"] is True
    assert all(r["from"] == "native verdict" for r in rec["override"]["reasons"])
    s = rec["scores"]
    assert s["simulation_success"] == 0 and s["simulation_success_before_override"] > 0
    # The request told the model that it was measured.
    assert "measured a physical failure" in (out / "request.md").read_text()
    # The judge's own report of a physical failure overrides too (the native verdict is clean here).
    flagged = answer(physical_failure={"observed": True, "justification": "synthetic: the block sinks into the plate"})
    p, out = judge(tmp_path, flagged, name="flagged")
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    assert rec["override"]["applied"] is True and rec["override"]["reasons"][0]["from"] == "judge"
    assert rec["scores"]["simulation_success"] == 0


def test_an_unreachable_endpoint_is_a_clear_error(tmp_path: Path) -> None:
    with socket.socket() as s:  # a port nothing listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = tmp_path / "down.toml"
    endpoint.write_text(f'provider = "openai"\nbase_url = "http://127.0.0.1:{port}"\nmodel = "m"\n'
                        "retries = 0\ntimeout_s = 10\n")
    out = tmp_path / "down"
    p = subprocess.run([str(R2G), "judge", "pick_block_plate", "--llm", str(endpoint), "--no-blender",
                        "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode != 0
    assert "the judge's call to the LLM endpoint failed" in p.stderr, p.stderr
    assert f"127.0.0.1:{port}" in p.stderr, p.stderr
    assert not (out / "judge.json").exists()
    # A folder already used is refused before anything runs.
    p = subprocess.run([str(R2G), "judge", "pick_block_plate", "--llm", str(endpoint), "--no-blender",
                        "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert p.returncode != 0 and "exists and is not empty" in p.stderr, p.stderr
