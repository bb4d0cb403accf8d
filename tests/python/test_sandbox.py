"""The hostile-program suite (tests/hostile/): every attack runs through `r2g exec` in the sandbox
against a live gym, and must be contained and reported while the gym keeps running.

Outer net: each `r2g exec` runs with its own address-space and file-size limits and a timeout,
so a sandbox bug cannot take the machine down; only processes this test started are signalled.
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
from pathlib import Path
from typing import Iterator

import pytest

import robo
from conftest import R2G, ROOT, Instance, _instance

HOSTILE = ROOT / "tests" / "hostile"
MANIFEST = json.loads((HOSTILE / "manifest.json").read_text())


@pytest.fixture(scope="module")
def gym() -> Iterator[Instance]:
    yield from _instance("lockstep", "sx")


def outer_net() -> None:
    # Above what the sandbox grants (4 GiB address space, 64 MiB files), below harm.
    resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))
    resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 30, 1 << 30))


def run(gym: Instance, program: Path, tmp: Path) -> dict:
    out = subprocess.run(
        [str(R2G), "exec", str(program), "--instance", gym.name, "--wall-s", "10", "--cpu-s", "5", "--scratch", str(tmp / "scratch")],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=outer_net,
        env={"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "OPENAI_API_KEY": "sk-test-secret-never-seen",
             "R2G_IPC_CONFIG": os.environ["R2G_IPC_CONFIG"]},
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def nonzero(r: dict) -> bool:
    return r["exit"] in ("exception", "killed") or (r["exit"] == "exit" and r.get("exit_code") not in (0, None))


@pytest.mark.parametrize("case", MANIFEST, ids=[c["file"] for c in MANIFEST])
def test_hostile_program_is_contained(gym, case, tmp_path: Path) -> None:
    canary = case.get("canary")
    if canary and os.path.lexists(canary):
        os.remove(canary)
    r = run(gym, HOSTILE / case["file"], tmp_path)
    text = r["stdout"] + r.get("raw_output", "")
    assert not [l for l in text.splitlines() if l.startswith("ESCAPED:")], (case, r)
    assert r["sandbox"]["landlock"] == "full" and r["sandbox"]["seccomp"], r["sandbox"]
    expect = case["expect"]
    if expect == "violation":
        assert r["violation"], (case, r)
    elif expect == "error":
        assert nonzero(r), (case, r)
    elif expect == "limit":
        assert nonzero(r) or r["violation"], (case, r)
    elif expect == "allowed":
        assert not nonzero(r) and r["violation"] is None, (case, r)
    elif expect == "rejected":
        assert r["exit"] == "ok" and r["violation"] is None, (case, r)
        assert "BLOCKED:" in r["stdout"], (case, r)
    else:
        raise AssertionError(f"unknown expectation {expect}")
    if canary:
        assert not os.path.lexists(canary), f"{case['file']} created {canary}"
    # The gym survived: the test's own robo connection still gets fresh state.
    assert len(robo.get_state([])["joint"]) == 7


def test_the_sandbox_reports_what_it_enforced_and_passes_no_secrets(gym, tmp_path: Path) -> None:
    prog = tmp_path / "probe.py"
    prog.write_text("import os\nfrom robo import get_state\nprint(sorted(os.environ))\nprint(len(get_state([])['joint']))\n")
    r = run(gym, prog, tmp_path)
    assert r["exit"] == "ok" and r["violation"] is None, r
    assert "OPENAI_API_KEY" not in r["stdout"] and "7" in r["stdout"].split()[-1]
    s = r["sandbox"]
    assert (s["landlock"], s["landlock_abi"], s["seccomp"], s["no_new_privs"], s["capabilities_dropped"]) == ("full", 7, True, True, True)


def test_relative_scratch_paths_work(gym, tmp_path: Path) -> None:
    (tmp_path / "p.py").write_text("open('note.txt', 'w').write('kept')\nprint('ok')\n")
    out = subprocess.run(
        [str(R2G), "exec", "p.py", "--instance", gym.name, "--scratch", "rel/scratch"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["exit"] == "ok" and r["violation"] is None, r
    assert (tmp_path / "rel" / "scratch" / "note.txt").read_text() == "kept"


def test_exec_keeps_memory_only_when_asked(gym, tmp_path: Path) -> None:
    """`r2g exec --memory DIR` copies DIR's records into the scratch folder's memory/ and appends
    the program's new records to DIR, never touching an old one; without --memory the program
    gets no memory/ and nothing is appended anywhere (robot-skill/memory/README.md)."""
    memory = tmp_path / "memory"
    memory.mkdir()
    old = memory / "20250101T000000Z-00000000-0000-4000-8000-000000000000.json"
    old.write_text('{"kind": "observation", "content": "old"}')
    (memory / "README.md").write_text("the folder's own documentation, not a record")
    prog = tmp_path / "mem.py"
    prog.write_text(
        "import os, pathlib\n"
        "m = pathlib.Path('memory')\n"
        "print('present', m.is_dir(), sorted(os.listdir(m)) if m.is_dir() else [])\n"
        "m.mkdir(exist_ok=True)\n"
        "(m / '20250101T000000Z-00000000-0000-4000-8000-000000000000.json').write_text('overwritten')\n"
        "(m / '20250102T000000Z-11111111-1111-4111-8111-111111111111.json').write_text('{\"kind\": \"warmup\"}')\n"
    )
    base = [str(R2G), "exec", str(prog), "--instance", gym.name, "--wall-s", "20"]
    out = subprocess.run([*base, "--scratch", str(tmp_path / "s1"), "--memory", str(memory)],
                         capture_output=True, text=True, timeout=120)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["exit"] == "ok", r
    assert f"present True ['{old.name}']" in r["stdout"], r["stdout"]
    assert r["memory_added"] == ["20250102T000000Z-11111111-1111-4111-8111-111111111111.json"], r
    assert old.read_text() == '{"kind": "observation", "content": "old"}'  # append-only
    assert sorted(p.name for p in memory.iterdir()) == [old.name, r["memory_added"][0], "README.md"]
    # Without --memory: no memory/ in the scratch folder, nothing collected.
    out = subprocess.run([*base, "--scratch", str(tmp_path / "s2")], capture_output=True, text=True, timeout=120)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["exit"] == "ok" and "present False []" in r["stdout"] and "memory_added" not in r, r
    assert len(list(memory.iterdir())) == 3


def test_exec_memory_ignores_a_link_planted_in_a_reused_scratch(gym, tmp_path: Path) -> None:
    """A program plants `memory -> elsewhere` in its scratch folder; the next `r2g exec --memory`
    on that scratch must not copy records through the link (nor truncate them)."""
    memory, elsewhere = tmp_path / "memory", tmp_path / "elsewhere"
    memory.mkdir()
    elsewhere.mkdir()
    old = memory / "20250101T000000Z-00000000-0000-4000-8000-000000000000.json"
    old.write_text('{"kind": "observation"}')
    plant = tmp_path / "plant.py"
    plant.write_text(f"import os\nos.symlink({str(elsewhere)!r}, 'memory')\nprint('planted', os.path.islink('memory'))\n")
    look = tmp_path / "look.py"
    look.write_text("import os\nprint('link', os.path.islink('memory'), sorted(os.listdir('memory')))\n")
    base = [str(R2G), "exec", "--instance", gym.name, "--wall-s", "20", "--scratch", str(tmp_path / "s")]
    r = json.loads(subprocess.run([*base[:2], str(plant), *base[2:]], capture_output=True, text=True,
                                  timeout=120).stdout.strip().splitlines()[-1])
    assert "planted True" in r["stdout"], r
    r = json.loads(subprocess.run([*base[:2], str(look), *base[2:], "--memory", str(memory)], capture_output=True,
                                  text=True, timeout=120).stdout.strip().splitlines()[-1])
    assert f"link False ['{old.name}']" in r["stdout"], r
    assert list(elsewhere.iterdir()) == [] and old.read_text() == '{"kind": "observation"}'


def test_exec_programs_of_one_scratch_share_object_identities(gym, tmp_path: Path) -> None:
    """The host names a tracker file in the scratch folder ($R2G_PERCEPTION_TRACKS), so a second
    stage program sees the objects under the numbers and names the first one gave them
    (api/PERCEPTION.md, "Identity across observations")."""
    prog = tmp_path / "look.py"
    prog.write_text(
        "import os\n"
        "from robo import get_state\n"
        "import robo_perception as rp\n"
        "s = get_state(['agentview', 'wrist'], raw=True)\n"
        "sc = rp.segment_scene(s)\n"
        "print('file', os.path.basename(os.environ.get('R2G_PERCEPTION_TRACKS', '')))\n"
        "print('ids', sorted((o.track_id, o.color_name, o.shape_name) for o in sc.objects))\n"
        "from robo_perception.tracking import default_tracker\n"
        "print('seen', sorted({t.seen for t in default_tracker().tracks}))\n"
    )
    base = [str(R2G), "exec", str(prog), "--instance", gym.name, "--wall-s", "30", "--scratch", str(tmp_path / "s")]
    runs = [json.loads(subprocess.run(base, capture_output=True, text=True, timeout=120).stdout.strip().splitlines()[-1])
            for _ in range(2)]
    for r in runs:
        assert r["exit"] == "ok", r
        assert "file .perception-tracks.json" in r["stdout"], r["stdout"]
    ids = [next(line for line in r["stdout"].splitlines() if line.startswith("ids")) for r in runs]
    assert ids[0] == ids[1] and "None" not in ids[0] and "(0," in ids[0], ids
    # the second program continued the first one's tracks (a fresh tracker would say seen [1])
    assert "seen [1]" in runs[0]["stdout"] and "seen [2]" in runs[1]["stdout"], [r["stdout"] for r in runs]
    assert (tmp_path / "s" / ".perception-tracks.json").is_file()


def test_exec_program_draws_markers_and_saves_png_crops(gym, tmp_path: Path) -> None:
    """The documented way to mark points and save an enlarged crop (api/PERCEPTION.md, "Images")
    works inside the sandbox: no image library, no chmod, files land in the scratch folder."""
    prog = tmp_path / "png.py"
    prog.write_text(
        "from robo import get_state\n"
        "import robo_perception as rp\n"
        "s = get_state(['agentview', 'wrist'], raw=True)\n"
        "tips = rp.fingertip_points(s['ee_pose'], s['gripper'])\n"
        "for cam in ('agentview', 'wrist'):\n"
        "    img, drawn = rp.draw_markers(s['image'][cam], tips, s, cam, color=['red', 'blue'], shape='circle')\n"
        "    (u, v), = rp.project(tips.mean(axis=0), s, cam)[0]\n"
        "    print(cam, rp.save_png(f'{cam}_tips.png', img, crop=(u - 80, v - 60, u + 80, v + 60), scale=3))\n"
    )
    scratch = tmp_path / "s"
    r = json.loads(subprocess.run([str(R2G), "exec", str(prog), "--instance", gym.name, "--wall-s", "30",
                                   "--scratch", str(scratch)], capture_output=True, text=True,
                                  timeout=120).stdout.strip().splitlines()[-1])
    assert r["exit"] == "ok" and not r.get("violation"), r
    for cam in ("agentview", "wrist"):
        data = (scratch / f"{cam}_tips.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
        # 160 x 120 crop, 3x: the IHDR chunk says 480 x 360
        assert int.from_bytes(data[16:20], "big") == 480 and int.from_bytes(data[20:24], "big") == 360
