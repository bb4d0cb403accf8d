"""`r2g judge`, mechanics only. The answers here are synthetic (written in this file, not by a
model), served by the scripted LLM server over real HTTP on loopback in both wire formats; the
evidence is real: the native gate runs, `r2g render` draws the MuJoCo images, and the request the
server receives carries them. What these tests check is the plumbing and the arithmetic — that a
valid answer is recorded and simulation success is computed by us, that a malformed answer and an
out-of-range score are refused with a clear error and the raw answer kept, that the physical-
failure override follows the native verdict, and that an unreachable endpoint is a clear error.
No score here measures a gym.

Blender images are left out (`--no-blender`): tests/python/test_blender*.py cover Blender, and a
Cycles render per instant would make this file slow."""
from __future__ import annotations

import json
import socket
import subprocess
from pathlib import Path

import pytest

from conftest import R2G, ROOT
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
        assert s["content_alignment"] == 84 and "doubled" in s["content_alignment_basis"]
        assert s["viewpoint_alignment"] is None
        assert rec["override"] == {"applied": False, "reasons": []}
        assert rec["native_verdict"]["kind"] == "validate" and rec["native_verdict"]["success"] is True
        # Model, tokens and what was sent.
        assert rec["llm"]["source"] == "scripted" and rec["llm"]["model"] == "scripted-pick_block_plate"
        assert rec["llm"]["usage"]["input"] > 0 and rec["llm"]["usage"]["output"] > 0
        req = rec["request"]
        assert any("not requested (--no-blender)" in m for m in req["missing_evidence"])
        assert any(m.startswith("source frames:") for m in req["missing_evidence"])
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
        assert "pick_block_plate" in (out / "request.md").read_text()


def test_source_frames_are_sent_beside_renders_from_their_cameras(tmp_path: Path) -> None:
    """Synthetic source frames: the gym rendered at rest by `r2g render` in the BOP layout."""
    frames = tmp_path / "frames"
    r = subprocess.run([str(R2G), "render", "pick_block_plate", "--out", str(frames)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    graded = answer(viewpoint_alignment=part(100, "synthetic: the same camera"))
    p, out = judge(tmp_path, graded, "--frames", str(frames))
    assert p.returncode == 0, p.stderr
    rec = json.loads((out / "judge.json").read_text())
    assert rec["source_frames"] == str(frames) and rec["scores"]["viewpoint_alignment"] == 100
    labels = [i["label"] for i in rec["request"]["images"]]
    n = len(json.loads((frames / "scene_camera.json").read_text()))
    assert sum(lb.startswith("Source frame") for lb in labels) == n
    at_rest = json.loads((out / "evidence" / "mujoco-source" / "scene_camera.json").read_text())
    assert sorted(at_rest) == sorted(json.loads((frames / "scene_camera.json").read_text()))  # the same ids
    assert sum(lb.startswith("MuJoCo image") for lb in labels) == n + len(rec["request"]["instants_s"])
    # The fixed camera's frame, rendered again from its BOP pose and intrinsics at rest, shows
    # the same picture (the wrist camera's pose follows the arm, so it is left out here).
    source = json.loads((frames / "scene_camera.json").read_text())
    fixed = next(k for k, v in source.items() if v["r2g_camera"] == "agentview")
    w, h, c, a = decode((out / "evidence" / "mujoco-source" / "rgb" / f"{int(fixed):06d}.png").read_bytes())
    w2, h2, _, b = decode((frames / "rgb" / f"{int(fixed):06d}.png").read_bytes())
    assert (w, h) == (w2, h2)
    assert sum(abs(x - y) for x, y in zip(a, b)) / len(a) < 2.0
    assert rec["request"]["not_gradable"] == ["content_alignment.blender"]


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
