"""Cassettes end to end: an episode recorded from a live endpoint (the scripted server, real HTTP
on loopback, Anthropic wire format) with `--llm record:`, then replayed with `--llm replay:` after
that server is gone; a replay whose requests changed, a truncated cassette, and the same cassette
served turn by turn by the scripted server. The answers are synthetic (a conversation written
here), so these runs test the mechanism, not a model.

The conversation observes and does not move the arm: a replay needs every request to repeat, the
camera images included, and in lockstep under CPU load an image taken right after a motion may
show the renderer's previous frame (robo accepts a lagging frame after its wait), which would
end the replay with a miss."""
from __future__ import annotations

import json
import os
import re
import subprocess
import urllib.request
from pathlib import Path
from typing import Iterator

import pytest

from conftest import R2G, ROOT

SERVER = ROOT / "agent-host" / "py" / "scripted_llm.py"
PYTHON = ROOT / ".venv" / "bin" / "python"
NO_PROXY = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback only


class Server:
    """The scripted LLM server on a free loopback port, stopped by pid."""

    def __init__(self, script: Path) -> None:
        self.proc = subprocess.Popen([str(PYTHON), str(SERVER), "--script", str(script), "--port", "0"],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        assert line.startswith("LISTENING "), (line, self.proc.stderr.read() if self.proc.stderr else "")
        self.port = int(line.split()[1])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=30)


def episode(run: Path, llm: str, *extra: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(R2G), "episode", "pick_block_plate", "--llm", llm, "--out", str(run),
         "--memory", str(run.parent / (run.name + "-memory")), *extra],
        capture_output=True, text=True, timeout=600, env={**os.environ, **(env or {})},
    )


# Reads the robot and both cameras, prints what it measured; no motion.
OBSERVE = """
from robo import get_state
s = get_state()
print("joint", [round(q, 4) for q in s["joint"]], "gripper", s["gripper"])
print("images", sorted((k, len(v) > 1000) for k, v in s["image"].items()))
"""
CONVERSATION = {"gym": "pick_block_plate", "responses": [
    f"<observation>first look</observation><plan>read the state</plan><code>{OBSERVE}</code><expected>-</expected>",
    f"<observation>the task</observation><plan>look again</plan><code>{OBSERVE}</code><expected>-</expected>",
    "<observation>seen twice</observation><stop>a synthetic conversation that only observes</stop>",
]}


def rounds(run: Path) -> list[dict]:
    return [json.loads(l) for l in (run / "transcript.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[dict, Path]]:
    tmp = tmp_path_factory.mktemp("cassette")
    script = tmp / "conversation.json"
    script.write_text(json.dumps(CONVERSATION))
    server = Server(script)
    try:
        endpoint = tmp / "endpoint.toml"
        endpoint.write_text(f'provider = "anthropic"\nbase_url = "http://127.0.0.1:{server.port}"\n'
                            'model = "a-live-model"\napi_key_env = "R2G_CASSETTE_TEST_KEY"\ntimeout_s = 60\nretries = 0\n')
        out = episode(tmp / "record", f"record:{endpoint}", env={"R2G_CASSETTE_TEST_KEY": "k"})
    finally:
        server.stop()  # nothing answers on that port from here on
    assert out.stdout.strip(), out.stderr[-3000:]
    yield json.loads(out.stdout.strip().splitlines()[-1]), tmp / "record"


def test_a_recorded_episode_replays_without_its_endpoint(recorded: tuple[dict, Path], tmp_path: Path) -> None:
    live, run = recorded
    assert live["llm_source"] == "live" and live["responses"] == 3 and live["executions"] == 2, live
    assert live["stop_reason"] == "a synthetic conversation that only observes", live
    cassette = run / "cassette.jsonl"
    lines = cassette.read_text().splitlines()
    assert len(lines) == 1 + live["responses"]  # the header, then one line per answer
    config = json.loads((run / "config.json").read_text())
    assert config["endpoint"]["cassette"] == {"mode": "record", "path": str(cassette)}

    out = episode(tmp_path / "replay", f"replay:{cassette}")
    assert out.stdout.strip(), out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["llm_source"] == "replayed", r
    assert r["tokens_in"] > r["tokens_cached"] > 0 and r["tokens_out"] > 0
    for k in ("success", "responses", "executions", "tokens_in", "tokens_cached", "tokens_out", "tokens_reasoning",
              "stop_reason"):
        assert r[k] == live[k], k
    assert json.loads((tmp_path / "replay" / "result.json").read_text())["llm_source"] == "replayed"
    endpoint = json.loads((tmp_path / "replay" / "config.json").read_text())["endpoint"]
    assert endpoint["model"] == "replayed:a-live-model" and endpoint["cassette"]["mode"] == "replay"
    before, after = rounds(run), rounds(tmp_path / "replay")
    assert [x["decision"] for x in after] == [x["decision"] for x in before]
    assert [x["usage"] for x in after] == [x["usage"] for x in before]
    assert all(x["attempts"] == 0 for x in after)  # no HTTP
    assert [x.get("feedback") for x in after] == [x.get("feedback") for x in before]  # the same requests, hence the same keys
    assert "joint [" in after[1]["exec"]["stdout"] and "('agentview', True)" in after[1]["exec"]["stdout"]
    assert len(list((tmp_path / "replay" / "rounds").glob("*/agentview.png"))) == 3  # images in the requests


def test_a_replay_whose_requests_changed_fails_naming_the_key_and_the_difference(
        recorded: tuple[dict, Path], tmp_path: Path) -> None:
    _, run = recorded
    # One decision fewer changes the budget the first message states.
    out = episode(tmp_path / "changed", f"replay:{run / 'cassette.jsonl'}", "--max-decisions", "49")
    assert out.returncode != 0 and not out.stdout.strip(), out.stdout
    err = out.stderr
    assert re.search(r"request [0-9a-f]{64} is not in the cassette", err), err[-2000:]
    assert "messages[0].parts[0] differs" in err and "Budgets: 50 decisions" in err and "Budgets: 49 decisions" in err, err[-2000:]
    assert not (tmp_path / "changed" / "result.json").exists()  # not reported as a result
    assert "not in the cassette" in rounds(tmp_path / "changed")[-1]["error"]


def test_a_truncated_cassette_is_refused_before_the_gym_starts(recorded: tuple[dict, Path], tmp_path: Path) -> None:
    _, run = recorded
    text = (run / "cassette.jsonl").read_text()
    cut = tmp_path / "cut.jsonl"
    cut.write_text(text[: len(text) - 100])  # as if killed in the middle of the last line
    out = episode(tmp_path / "cut", f"replay:{cut}")
    assert out.returncode != 0
    n = len(text.splitlines())
    assert f"line {n}: the last line is incomplete" in out.stderr, out.stderr[-2000:]
    assert not (tmp_path / "cut" / "episodes").exists()  # no gym was started
    bad = tmp_path / "bad.jsonl"
    bad.write_text(text.replace('"r2g_cassette":1', '"r2g_cassette":7', 1))
    out = episode(tmp_path / "bad", f"replay:{bad}")
    assert out.returncode != 0 and "line 1: not a cassette of format 1" in out.stderr, out.stderr[-2000:]


def test_the_scripted_server_serves_a_cassette_turn_by_turn_in_either_wire_format(recorded: tuple[dict, Path]) -> None:
    """The same file as a script: the answer to the request with k assistant messages, whatever
    else the request holds (here another wire format and no images)."""
    _, run = recorded
    answers = [json.loads(l)["response"]["text"] for l in (run / "cassette.jsonl").read_text().splitlines()[1:]]
    server = Server(run / "cassette.jsonl")
    try:
        for k in (0, 2):
            msgs = [{"role": "system", "content": "s"}, {"role": "user", "content": "u"}]
            for _ in range(k):
                msgs += [{"role": "assistant", "content": "a"}, {"role": "user", "content": "u"}]
            req = urllib.request.Request(
                f"http://127.0.0.1:{server.port}/v1/chat/completions",
                data=json.dumps({"model": "m", "messages": msgs}).encode(),
                headers={"content-type": "application/json", "authorization": "Bearer k"},
            )
            with NO_PROXY.open(req, timeout=30) as resp:
                body = json.loads(resp.read())
            assert body["choices"][0]["message"]["content"] == answers[k]
    finally:
        server.stop()
