"""What the model is told is true and complete, checked on real runs of `r2g episode`:

- the two real-model runs (tests/data/real-model: a real multimodal model wrote every answer),
  served turn by turn: their programs run again for real against today's prompts, sandbox and
  runtime; native success, no violation, and every feedback text true of its program;
- a short conversation we wrote (synthetic) whose programs read every document the prompt names,
  import every module it names, and hand images over, flood the hand-over, and send a chunk that
  is refused after one that executed.
"""
from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import R2G, ROOT

REAL = ROOT / "tests" / "data" / "real-model"
REAL_RUNS = {  # gym -> the seed and placement the real model saw
    "stack_bowls": ("101", "xy=0.04,yaw=20"),
    "open_drawer": ("201", "xy=0.03,yaw=10"),
}


def run_episode(gym: str, llm: str, run: Path, *extra: str) -> dict:
    out = subprocess.run(
        [str(R2G), "episode", gym, "--llm", llm, "--out", str(run), "--memory", str(run.parent / "memory"), *extra],
        capture_output=True, text=True, timeout=900,
    )
    assert out.stdout.strip(), out.stderr[-3000:]  # exit status 1: a failed task
    return json.loads(out.stdout.strip().splitlines()[-1])


def rounds(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "transcript.jsonl").read_text().splitlines()]


def check_feedback_is_true(run: Path) -> None:
    """Each feedback text names the program's own last robot call (from its calls.json), counts its
    chunks as calls.json has them, and reports simulated time that is never negative."""
    for r in rounds(run):
        if "exec" not in r:
            continue
        text = r["feedback"]
        calls = json.loads((run / r["calls"]).read_text())
        chunks = [c for c in calls if c["fn"] == "post_actions"]
        executed = sum(c["feedback"]["status"] == "executed" for c in chunks)
        rejected = sum(c["feedback"]["status"] == "rejected" for c in chunks)
        failed = len(chunks) - executed - rejected
        assert f"Its chunks: {executed} executed, {failed} failed, {rejected} rejected" in text, (r["round"], text[:400])
        resets = sum(c["fn"] == "reset" for c in calls)
        assert f"resets: {resets} done" in text, text[:400]
        if calls:
            last = calls[-1]
            status = last["feedback"]["status"] if last["fn"] == "post_actions" else "executed"
            assert f'Its last robot call: {last["fn"]}() → "{status}"' in text, (r["round"], text[:400])
        else:
            assert "Its last robot call: none" in text, text[:400]
        took = re.search(r"; (-?[0-9.]+) s of simulated time;", text)
        assert took and float(took.group(1)) >= 0, text[:300]
        assert "Last control_feedback" not in text
        # the program's own output, verbatim (feedback.txt is what tools read)
        assert r["exec"]["stdout"].strip() in text
        assert (run / f"rounds/{r['round']:03d}/feedback.txt").read_text() == text
        # The images the host shows (and extraction reads) show the state after the program, not
        # a frame the renderer had made earlier in its motion (lockstep: nothing moves meanwhile).
        with np.load(run / r["obs_after"]) as obs:
            numbers = json.loads(str(obs["state_json"]))
        for cam, t in numbers["image_timestamp"].items():
            assert t >= numbers["timestamp"] - 1e-9, (r["round"], cam, t, numbers["timestamp"])


@pytest.mark.parametrize("gym", sorted(REAL_RUNS))
def test_a_real_models_run_replays_with_honest_feedback_and_its_answer_yields_a_skill(gym: str, tmp_path: Path) -> None:
    seed, perturb = REAL_RUNS[gym]
    run = tmp_path / "run"
    r = run_episode(gym, f"scripted:{REAL / gym / 'episode.cassette.jsonl'}", run, "--seed", seed, "--perturb", perturb,
                    "--learn", "--learn-llm", f"scripted:{REAL / gym / 'extraction.cassette.jsonl'}",
                    "--library", str(tmp_path / "library"), "--admit-runs", "0")
    assert r["success"] is True, r["stop_reason"][:500]
    # The model's own extraction answer, on today's record of its own programs: written, not dropped.
    ex = json.loads((run / "extraction.json").read_text())
    assert ex["answer_dropped"] is None and ex["merge"]["dropped"] == [], ex["merge"]
    written = [w for w in ex["merge"]["written"] if w[0] == "add"]
    assert written, ex["merge"]
    skill = json.loads((tmp_path / "library" / written[0][1] / "v0001.json").read_text())
    assert len(skill["procedure"]) >= 4 and skill["rules"], skill["procedure"]
    assert all(len(r["id"]) <= 64 for r in skill["rules"])
    assert all(st.get("description") for st in skill["procedure"])  # the model's stage texts, whole
    assert r["violations"] == 0, [x["exec"]["violation"] for x in rounds(run) if x.get("exec")]
    check_feedback_is_true(run)
    # The first message gives the run's facts before the model needs them.
    first = (run / "rounds/000/prompt.txt").read_text()
    for fact in ("backend simulation", "mode lockstep", "effective_safety", "decisions in this episode",
                 "at most 600 waypoints", "120 s of wall-clock time", f'"gym":"{gym}"'):
        assert fact in first, fact
    assert "instance" not in first.split("Memory:")[1].split("\n")[0]  # the fingerprint names no episode
    # The layout tools read: system_prompt.md and the estimates of every request.
    system = (run / "system_prompt.md").read_text()
    assert "===== robot-skill/api/PERCEPTION.md =====" in system and "===== robot-skill/memory/README.md =====" in system
    assert r["tokens_in_estimated"] > r["tokens_cached_estimated"] > 0


SYNTHETIC_OBSERVE = r'''
import json, os, re
import robo, robo_memory
found = []
for top, dirs, files in os.walk("robot-skill", followlinks=True):
    for f in files:
        p = os.path.join(top, f)
        with open(p, "rb") as fh:
            fh.read(1)
        found.append(p)
print("READABLE", json.dumps(sorted(found)))
ok = []
for m in ["robo", "robo_perception", "robo_skills", "robo_services", "robo_memory", "numpy", "json", "zlib"]:
    __import__(m)
    ok.append(m)
import sys
sys.path.insert(0, "robot-skill/examples")
import pick_object
ok.append(pick_object.__name__)
print("IMPORTED", json.dumps(ok))
try:
    import mujoco
    print("UNSUPPORTED IMPORTED")
except ImportError as e:
    print("REFUSED", e)
print("SCHEMA", robo.SCHEMA_VERSION)
print("FINGERPRINT", json.dumps(robo_memory.fingerprint(), sort_keys=True))
print("MEMORY", json.dumps(sorted(os.listdir("robot-skill/memory"))))
'''

SYNTHETIC_TASK = r'''
import os
import numpy as np
from robo import get_state, post_actions
import robo_perception as rp
s = get_state(["agentview"], raw=True)
for k in range(3):
    print("shown", rp.show(s["image"]["agentview"], f"view {k}", crop=(0, 0, 64 + 16 * k, 48), scale=2))
rp.save_png("show/04-" + "a" * 200 + ".png", s["image"]["agentview"][:48, :64])  # a legal, long name
try:
    rp.show(s["image"]["agentview"], "fifth")
except ValueError as e:
    print("REFUSED FIFTH", e)
rp.save_png("show/90-extra.png", s["image"]["agentview"][:8, :8])
with open("show/00-not-a-png.png", "wb") as f:
    f.write(b"not a png at all")
q = get_state([])["joint"]
ok = post_actions({"actions": [q[:6] + [q[6] + 0.01 * k] + [-1.0] for k in range(1, 6)], "type": "joint", "freq": ""})
bad = post_actions({"actions": [q[:3] + [0.5] + q[4:] + [-1.0]], "type": "joint", "freq": ""})
print("RESULTS", ok, bad, get_state([])["control_feedback"]["status"])
'''


def decision(code: str | None, stop: str | None = None) -> str:
    body = f"<code>\n{code}\n</code>\n<expected>printed facts</expected>" if code else f"<stop>{stop}</stop>"
    return f"<observation>synthetic test conversation</observation>\n<plan>check the contract</plan>\n{body}"


def test_every_document_module_and_hand_over_the_prompt_names_works(tmp_path: Path) -> None:
    conv = tmp_path / "conversation.json"  # synthetic: written by this test, not by a model
    conv.write_text(json.dumps({"gym": "pick_block_plate", "model": "synthetic-contract",
                                "responses": [decision(SYNTHETIC_OBSERVE), decision(SYNTHETIC_TASK),
                                              decision(None, "done")]}))
    memory = tmp_path / "memory"
    memory.mkdir()
    record = memory / "20250101T000000Z-00000000-0000-4000-8000-000000000000.json"
    record.write_text(json.dumps({"kind": "observation", "fingerprint": {}, "task": "", "stage": "x", "content": {}}))
    run = tmp_path / "run"
    r = run_episode("pick_block_plate", f"scripted:{conv}", run)
    assert r["violations"] == 0
    rs = rounds(run)
    out = rs[0]["exec"]["stdout"]
    readable = set(json.loads(re.search(r"READABLE (.*)", out).group(1)))
    system = (run / "system_prompt.md").read_text()
    # Every robot-skill path the prompt names is readable from a program (a folder: something in it).
    named = set(re.findall(r"robot-skill/([A-Za-z0-9_./-]+[A-Za-z0-9_/])", system))
    assert named, system[:500]
    for path in named:
        hits = [p for p in readable if p == f"robot-skill/{path}" or p.startswith(f"robot-skill/{path.rstrip('/')}/")]
        assert hits, f"the prompt names robot-skill/{path}, which no program can read"
    # Every relative link in every document resolves to something a program can read.
    for doc in sorted((ROOT / "robot-skill").rglob("*.md")):
        rel = doc.relative_to(ROOT / "robot-skill")
        for target in re.findall(r"\]\(([^)#:]+)\)", doc.read_text()):
            p = (Path("robot-skill") / rel.parent / target).as_posix()
            p = re.sub(r"[^/]+/\.\./", "", p).rstrip("/")
            assert any(x == p or x.startswith(p + "/") for x in readable), f"{rel} links {target}: not readable"
    # Every module the answer format names imports; others are refused with the list.
    imported = json.loads(re.search(r"IMPORTED (.*)", out).group(1))
    assert "robo_memory" in imported and "robo_perception" in imported and "pick_object" in imported
    assert "UNSUPPORTED IMPORTED" not in out and "REFUSED No module named 'mujoco'" in out
    modules = re.search(r"A program may import (.*?); any other", system.replace("\n", " ")).group(1)
    for m in ("robo", "robo_perception", "robo_skills", "robo_services", "robo_memory", "numpy"):
        assert m in modules and m in imported
    import robo
    assert f"SCHEMA {robo.SCHEMA_VERSION}" in out
    # robot-skill/memory shows the episode's memory folder, listable; the fingerprint is the host's.
    assert json.loads(re.search(r"MEMORY (.*)", out).group(1)) == sorted(["README.md", record.name])
    fp = json.loads(re.search(r"FINGERPRINT (.*)", out).group(1))
    assert fp["gym"] == "pick_block_plate" and fp["backend"] == "simulation" and len(fp["robot_config_sha256"]) == 64
    assert json.dumps(fp, sort_keys=True, separators=(",", ":")) in (run / "rounds/000/prompt.txt").read_text()
    # The hand-over: four shown in order, the rest named with the reason, all recorded.
    task = rs[1]
    text = task["feedback"]
    assert "REFUSED FIFTH show: at most 4 images" in task["exec"]["stdout"]
    assert len(task["shown"]) == 4 and all((run / p["file"]).read_bytes()[:4] == b"\x89PNG" for p in task["shown"])
    assert [p["name"] for p in task["shown"]] == [f"show/0{k}-view-{k - 1}.png" for k in range(1, 4)] + [
        "show/04-" + "a" * 200 + ".png"]
    assert [p["file"] for p in task["shown"]] == [f"rounds/002/shown/{k}.png" for k in range(1, 5)]
    assert "then the images it showed: show/01-view-0.png (128x96)" in text, text
    assert "Not shown: show/90-extra.png: at most 4 images are shown per program" in text
    assert "Not shown: show/00-not-a-png.png: not a PNG image" in text
    assert not (run / "scratch" / "show").exists()
    request = json.loads(sorted((run / "llm-log").glob("request-*.json"))[2].read_text())
    last_user = request["messages"][-1]["content"]
    assert sum(p["type"] == "image_url" for p in last_user) == 2 + 4
    # The feedback names the program's own calls: one executed chunk, then one refused.
    assert "RESULTS 1 0 rejected" in task["exec"]["stdout"]
    assert "Its chunks: 1 executed, 0 failed, 1 rejected" in text
    assert 'Its last robot call: post_actions() → "rejected"' in text
    check_feedback_is_true(run)


def test_the_scripted_server_caches_anthropic_prompts_only_up_to_cache_marks(tmp_path: Path) -> None:
    """Anthropic caches nothing unmarked; OpenAI-compatible servers cache a repeated prefix by
    themselves. The scripted server (our stand-in for both) must count it the same way, or the
    cache figures of offline runs would flatter requests that carry no marks."""
    import urllib.request

    script = tmp_path / "s.json"
    script.write_text(json.dumps({"gym": "x", "model": "m", "responses": ["<stop>a</stop>"] * 4}))
    srv = subprocess.Popen([str(ROOT / ".venv/bin/python"), str(ROOT / "agent-host/py/scripted_llm.py"),
                            "--script", str(script), "--port", "0"], stdout=subprocess.PIPE, text=True)
    try:
        port = int(srv.stdout.readline().split()[1])

        def ask(body: dict) -> dict:
            req = urllib.request.Request(f"http://127.0.0.1:{port}/v1/messages", json.dumps(body).encode(),
                                         {"x-api-key": "k", "anthropic-version": "2023-06-01",
                                          "content-type": "application/json"})
            return json.loads(urllib.request.urlopen(req, timeout=30).read())["usage"]

        def body(turns: int, marks: bool) -> dict:
            block = lambda t: {"type": "text", "text": t * 400}  # noqa: E731
            msgs = [{"role": "user", "content": [block("u")]}]
            for _ in range(turns):
                msgs += [{"role": "assistant", "content": [block("a")]}, {"role": "user", "content": [block("v")]}]
            system = [block("s")]
            if marks:
                system[0]["cache_control"] = {"type": "ephemeral"}
                msgs[-1]["content"][-1]["cache_control"] = {"type": "ephemeral"}
            return {"model": "m", "max_tokens": 10, "system": system, "messages": msgs}

        ask(body(0, False))
        assert ask(body(1, False))["cache_read_input_tokens"] == 0
        ask(body(0, True))
        assert ask(body(1, True))["cache_read_input_tokens"] == 200  # the marked system + first message
    finally:
        srv.terminate()
        srv.wait(timeout=10)
