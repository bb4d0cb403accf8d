"""The agent loop offline, end to end: the scripted endpoint (real HTTP on loopback, both wire
formats) -> stage programs -> sandbox -> live gym -> native evaluator; the run folder it leaves,
its viewer in headless Chromium, and a run killed with SIGKILL."""
from __future__ import annotations

import json
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from conftest import R2G


def episode(tmp: Path, *extra: str) -> tuple[dict, Path]:
    run = tmp / "run"
    out = subprocess.run(
        [str(R2G), "episode", "pick_block_plate", "--llm", "scripted", "--out", str(run), *extra],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.stdout.strip(), out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1]), run


@pytest.mark.parametrize("provider", ["openai", "anthropic"])
def test_the_scripted_conversation_solves_the_gym_through_the_sandbox(provider: str, tmp_path: Path) -> None:
    r, run = episode(tmp_path, "--provider", provider)
    assert r["success"] is True, r
    assert r["evaluation"]["success"] is True
    assert r["responses"] >= 4 and r["executions"] >= 3
    assert r["violations"] == 0
    assert r["tokens_in"] > r["tokens_cached"] > 0 and r["tokens_out"] > 0  # cached counted once, in both formats
    assert r["wall_s"] >= r["model_s"] + r["exec_s"] - 1e-6 and r["overhead_s"] >= 0
    assert r["run_dir"] == str(run)
    # The run folder: config, prompts, every response, code, feedback, images, verdict.
    rounds = [json.loads(l) for l in (run / "transcript.jsonl").read_text().splitlines()]
    assert len(rounds) == r["responses"]
    assert rounds[0]["observe_only"] and not rounds[1]["observe_only"]
    assert (run / "system_prompt.md").read_text().count("robot-skill/") >= 4
    assert (run / "rounds/002/stage.py").is_file() and (run / "rounds/002/feedback.txt").is_file()
    assert (run / "rounds/002/agentview.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((run / "result.json").read_text())["success"] is True
    # The model never saw the verdict: no prompt mentions it.
    log = run / "llm-log"
    requests = sorted(log.glob("request-*.json"))
    assert requests and not any("eval.json" in p.read_text() or "trace_sha256" in p.read_text() for p in requests)


def chromium_dom(html: Path) -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    assert exe, "chromium is installed by scripts/install-deps.sh"
    out = subprocess.run(
        [exe, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files", "--dump-dom", html.as_uri()],
        capture_output=True,
        text=True,
        timeout=120,
    )
    return out.stdout


def test_the_viewer_renders_the_run_in_headless_chromium(tmp_path: Path) -> None:
    r, run = episode(tmp_path)
    dom = chromium_dom(run / "index.html")
    assert "Native verdict: success" in dom
    assert dom.count('class="round"') == r["responses"]
    assert dom.count("<img") >= 2 * r["executions"]
    assert 'class="code"' in dom and "from robo import" in dom


def test_a_run_killed_with_sigkill_leaves_a_readable_record(tmp_path: Path) -> None:
    run = tmp_path / "run"
    proc = subprocess.Popen(
        [str(R2G), "episode", "pick_block_plate", "--llm", "scripted", "--out", str(run), "--wall"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        transcript = run / "transcript.jsonl"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if transcript.exists() and len(transcript.read_text().splitlines()) >= 2:
                break
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = transcript.read_text().splitlines()
    assert len(lines) >= 2
    assert all(json.loads(l)["round"] == i + 1 for i, l in enumerate(lines))
    assert not (run / "result.json").exists()
    # Files are whole or absent: a kill between a write and its rename may leave the temporary
    # `*.partial` (the file it was for is then absent), never a half-written file.
    for p in run.rglob("*.json"):
        json.loads(p.read_text())
    view = subprocess.run([str(R2G), "view", str(run)], capture_output=True, text=True, timeout=60)
    assert view.returncode == 0, view.stderr
    dom = chromium_dom(run / "index.html")
    assert "not judged" in dom and dom.count('class="round"') == len(lines)


def one_stage_episode(tmp: Path, stage: str, stop: str, memory: Path) -> tuple[dict, Path]:
    """An episode whose scripted model observes, runs `stage` once, then stops with `stop`."""
    conv = tmp / "conversation.json"
    conv.write_text(json.dumps({"gym": "pick_block_plate", "responses": [
        "<observation>start</observation>",
        f"<observation>x</observation><plan>one stage</plan><code>\n{stage}\n</code><expected>-</expected>",
        f"<observation>done</observation><stop>{stop}</stop>",
    ]}))
    run = tmp / "run"
    out = subprocess.run(
        [str(R2G), "episode", "pick_block_plate", "--llm", f"scripted:{conv}", "--out", str(run), "--memory", str(memory)],
        capture_output=True, text=True, timeout=300,
    )
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["responses"] == 3 and r["stop_reason"] == stop, r
    return r, run


def test_memory_records_are_append_only_and_readable_next_episode(tmp_path: Path) -> None:
    memory = tmp_path / "memory"
    memory.mkdir()
    old = memory / "20260101T000000Z-00000000-0000-4000-8000-000000000000.json"
    old.write_text('{"kind": "warmup", "content": "original"}')
    stage = (
        "import json, os, uuid, datetime\n"
        "names = sorted(os.listdir('memory'))\n"
        "print('seen', names)\n"
        "stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%dT%H%M%SZ')\n"
        "json.dump({'kind': 'observation', 'content': 'new'}, open(f'memory/{stamp}-{uuid.uuid4()}.json', 'w'))\n"
        "open('memory/' + names[0], 'w').write('overwritten')\n"
    )
    _, run = one_stage_episode(tmp_path, stage, "memory written", memory)
    rounds = [json.loads(l) for l in (run / "transcript.jsonl").read_text().splitlines()]
    assert old.name in rounds[1]["exec"]["stdout"]  # earlier records are readable
    assert len(rounds[1]["memory_added"]) == 1
    records = sorted(p.name for p in memory.iterdir())
    assert len(records) == 2 and old.name in records
    assert old.read_text() == '{"kind": "warmup", "content": "original"}'  # never overwritten


def test_a_batch_reports_success_rate_tokens_and_the_time_split(tmp_path: Path) -> None:
    out = subprocess.run(
        [str(R2G), "batch", "pick_block_plate", "--episodes", "2", "--out", str(tmp_path / "b"), "--memory", str(tmp_path / "m")],
        capture_output=True, text=True, timeout=600,
    )
    b = json.loads(out.stdout.strip().splitlines()[-1])
    assert b["episodes"] == 2 and b["success_rate"] == 1.0, b
    assert b["tokens_in"] > b["tokens_cached"] > 0 and b["tokens_out"] > 0
    assert b["wall_s"] >= b["model_s"] + b["exec_s"] - 1e-6
    assert json.loads((tmp_path / "b" / "batch.json").read_text())["success_rate"] == 1.0
    assert all((tmp_path / "b" / f"episode-{i:03}" / "index.html").is_file() for i in range(2))


def test_a_batch_that_cannot_run_any_episode_fails(tmp_path: Path) -> None:
    """An unreachable endpoint (a closed loopback port): every episode errors, the batch exits 1."""
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again when the block ends: nothing listens there
    endpoint = tmp_path / "down.toml"
    endpoint.write_text(f'provider = "openai"\nbase_url = "http://127.0.0.1:{port}"\nmodel = "m"\n'
                        'temperature = 0.0\nmax_tokens = 64\ntimeout_s = 5\nretries = 0\n')
    out = subprocess.run(
        [str(R2G), "batch", "pick_block_plate", "--episodes", "1", "--llm", str(endpoint), "--out", str(tmp_path / "b")],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 1, out
    b = json.loads(out.stdout.strip().splitlines()[-1])
    assert b["episodes"] == 1 and b["errors"] == 1 and b["success_rate"] == 0.0, b


def test_memory_collection_follows_no_links_planted_by_a_program(tmp_path: Path) -> None:
    memory = tmp_path / "memory"
    stage = (
        "import os\n"
        "os.rename('memory', 'old-memory') if os.path.exists('memory') else None\n"
        "os.symlink('robot-skill/config', 'memory')  # the host must not copy robot.json out\n"
        "print('planted')\n"
    )
    _, run = one_stage_episode(tmp_path, stage, "planted", memory)
    rounds = [json.loads(l) for l in (run / "transcript.jsonl").read_text().splitlines()]
    assert "planted" in rounds[1]["exec"]["stdout"]  # the link really was planted
    assert not memory.exists() or not list(memory.iterdir())
