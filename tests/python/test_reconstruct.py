"""`r2g reconstruct` on synthetic frames: shipped gyms rendered by `r2g render` (real MuJoCo, EGL)
from their agentview and four extra viewpoints, reconstructed, compared with the gym's own
scene.toml, and validated with the gym's demonstration (`r2g validate`). Bad input: precise
errors and no half-written gym. The geometry service is a real HTTP server on loopback that
answers with the wire format (depth taken from the synthetic frames)."""
from __future__ import annotations

import base64
import json
import shutil
import subprocess
import sys
import threading
import tomllib
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "real2sim" / "py"))
import r2g_reconstruct_eval as ev  # noqa: E402
import r2g_reconstruct_io as rio  # noqa: E402

R2G = ROOT / "target" / "release" / "r2g"


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    """pick_block_plate rendered from three viewpoints (synthetic; the error cases need no more)."""
    if not R2G.is_file():
        pytest.fail(f"{R2G} missing: run `make build` first")
    return ev.render_frames("pick_block_plate", tmp_path_factory.mktemp("rec") / "frames", 2)


@pytest.mark.parametrize("gym", ["pick_block_plate", "push_to_line", "stack_bowls"])
def test_shipped_gym_reconstructs_and_validates(gym, tmp_path):
    """Synthetic: every object found once, within 1 cm and 0.5 cm of size, IoU >= 0.9 (gate IoU
    and true-mask IoU), and the
    reconstructed gym passes the validation gate with the gym's demonstration."""
    res = ev.evaluate(gym, tmp_path / gym, rounds=1)
    assert "error" not in res, res
    assert res["missed"] == [] and res["spurious"] == [], res
    assert res["matched"] == res["truth_objects"], res
    assert res["position_error_cm_max"] <= 1.0, res
    assert res["size_error_cm_mean"] <= 0.5, res
    assert res["iou_min"] >= 0.9, res
    # Against the truth too: the render of the reconstruction vs the frames' own mask_visib.
    assert res["true_iou_error"] is None and len(res["true_iou_per_object"]) == res["truth_objects"], res
    assert res["true_iou_min"] >= 0.9, res
    assert res["validate"]["success"], res
    rep = json.loads((tmp_path / gym / "gym" / "reconstruction.json").read_text())
    assert rep["rounds"] and all("per_view" in o for o in rep["rounds"][0]["objects"])
    assert len(rep["rounds"][0]["objects"][0]["per_view"]) == 1 + len(ev.EXTRA_VIEWS)
    # Five source images: the scene names the first four cameras (the runtime's image slots)
    # and says so; the gate above used all five.
    cams = tomllib.loads((tmp_path / gym / "gym" / "scene.toml").read_text())["cameras"]
    assert [c["name"] for c in cams] == ["cam_0", "cam_1", "cam_2", "cam_3"], cams
    assert any("the scene keeps the first 4" in w for w in rep["warnings"]), rep["warnings"]


def run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([str(R2G), "reconstruct", *map(str, args)], capture_output=True, text=True, timeout=300)


def test_empty_task_is_said(frames, tmp_path):
    out = tmp_path / "gym"
    p = run(frames, "--joints", frames / "joints.json", "--out", out, "--rounds", "0")
    assert p.returncode == 0, p.stderr
    assert "task: empty" in p.stdout
    line = json.loads(p.stdout.strip().splitlines()[-1])
    assert line["task_empty"] is True and sorted(line["kinds"]) == ["box", "cylinder"]
    scene = (out / "scene.toml").read_text()
    assert "success" not in scene and "fx = " in scene
    # The gym is usable as it stands: the sim-host compiles it and renders it.
    r = subprocess.run([str(R2G), "render", str(out), "--out", str(tmp_path / "r")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def copy_frames(frames: Path, to: Path) -> Path:
    shutil.copytree(frames, to)
    return to


def expect_error(tmp_path: Path, frames: Path, needle: str, *extra) -> None:
    out = tmp_path / "gym"
    p = run(frames, "--joints", extra[0] if extra else frames / "joints.json", "--out", out, "--rounds", "0",
            *extra[1:])
    assert p.returncode != 0, p.stdout
    assert needle in p.stderr, p.stderr
    assert "Traceback" not in p.stderr, p.stderr
    assert not out.exists(), "a half-written gym was left"
    assert not any(x.name.startswith(".gym.partial") for x in tmp_path.iterdir())


def test_missing_intrinsics(frames, tmp_path):
    f = copy_frames(frames, tmp_path / "f")
    doc = json.loads((f / "scene_camera.json").read_text())
    del doc["1"]["cam_K"]
    (f / "scene_camera.json").write_text(json.dumps(doc))
    expect_error(tmp_path, f, "image '1': no \"cam_K\"")


def test_nan_in_pose(frames, tmp_path):
    f = copy_frames(frames, tmp_path / "f")
    text = (f / "scene_camera.json").read_text()
    doc = json.loads(text)
    doc["0"]["cam_t_w2c"][1] = "NAN_HERE"
    (f / "scene_camera.json").write_text(json.dumps(doc).replace('"NAN_HERE"', "NaN"))
    expect_error(tmp_path, f, "\"cam_t_w2c\" holds NaN")


def test_depth_of_another_size(frames, tmp_path):
    f = copy_frames(frames, tmp_path / "f")
    d = rio.read_png(f / "depth" / "000002.png")
    rio.write_png(f / "depth" / "000002.png", np.ascontiguousarray(d[::2, ::2]))
    expect_error(tmp_path, f, "depth/000002.png is 320x240 but its colour image 000002.png is 640x480")


def test_depth_without_values(frames, tmp_path):
    f = copy_frames(frames, tmp_path / "f")
    rio.write_png(f / "depth" / "000000.png", np.zeros((480, 640), np.uint16))
    expect_error(tmp_path, f, "holds no valid depth (every pixel is 0)")


def test_no_objects(frames, tmp_path):
    """The objects' pixels emptied (their masks from the render): empty masks are an error."""
    f = copy_frames(frames, tmp_path / "f")
    for k in ("000000", "000001", "000002"):
        d = rio.read_png(f / "depth" / f"{k}.png")
        for m in sorted((f / "mask_visib").glob(f"{k}_*.png")):
            d[rio.read_png(m) > 0] = 0
        rio.write_png(f / "depth" / f"{k}.png", d)
    expect_error(tmp_path, f, "no object found on the support plane")


def test_bad_joints(frames, tmp_path):
    expect_error(tmp_path, frames, "--joints: 3 values given", "0,1,2")
    expect_error(tmp_path, frames, "joint 4 = 0.5000 rad is outside", "0,0,0,0.5,0,1.57,0.78")


def test_task_naming_an_unknown_object(frames, tmp_path):
    task = tmp_path / "task.toml"
    task.write_text('[task]\ninstruction = "x"\nsuccess = [{ kind = "on", object = "cup", support = "table" }]\n')
    expect_error(tmp_path, frames, "names object 'cup', which the reconstruction does not have",
                 frames / "joints.json", "--task", task)


def test_task_name_that_is_a_path_refused(frames, tmp_path):
    """A [names] key names files under meshes/ too: one with a slash is refused, nothing written."""
    task = tmp_path / "task.toml"
    task.write_text('[task]\ninstruction = "x"\n[names]\n"../x" = [0.5, 0.0]\n')
    expect_error(tmp_path, frames, "[names] '../x': a name is letters, digits", frames / "joints.json", "--task", task)


def test_demonstration_reanchored_to_moved_block(tmp_path):
    """Synthetic: frames of pick_block_plate with the block 3 cm further from the robot than in
    the scene its demonstration was recorded in. Re-anchored (the task file names that scene),
    the demonstration follows the block and the gym validates; copied, it closes on nothing."""
    moved = ev.moved_copy("pick_block_plate", tmp_path / "moved", "block", (0.03, 0.0))
    f = ev.render_frames("pick_block_plate", tmp_path / "frames", 2, gym_dir=moved)
    src = ROOT / "gyms" / "pick_block_plate"
    verdicts = {}
    for tag, reanchor in (("re", True), ("copy", False)):
        task = ev.task_file(src, tmp_path / f"task_{tag}.toml", reanchor=reanchor, names_from=moved)
        p = run(f, "--joints", f / "joints.json", "--out", tmp_path / tag, "--rounds", "0", "--task", task)
        assert p.returncode == 0, p.stderr
        rep = json.loads((tmp_path / tag / "reconstruction.json").read_text())
        v = subprocess.run([str(R2G), "validate", str(tmp_path / tag), "--out", str(tmp_path / f"v_{tag}")],
                           capture_output=True, text=True, timeout=300)
        verdicts[tag] = json.loads((tmp_path / f"v_{tag}" / "evidence.json").read_text())
        if reanchor:
            assert "demonstration: re-anchored from" in p.stdout, p.stdout
            d = rep["demonstration"]
            assert d["status"] == "re-anchored" and [m["entity"] for m in d["moves"]] == ["block"], d
            assert abs(d["moves"][0]["translation_m"][0] - 0.03) < 0.003, d
            assert [m["entity"] for m in d["unchanged"]] == ["plate"] and d["rows_re_solved"] > 0, d
            assert v.returncode == 0, v.stdout[-600:]
        else:
            assert "demonstration: copied unchanged" in p.stdout, p.stdout
            assert rep["demonstration"]["status"] == "copied"
    assert verdicts["re"]["success"] is True, verdicts["re"]["checks"]
    assert verdicts["copy"]["success"] is False
    assert not verdicts["copy"]["checks"]["task_success"]["pass"]


def test_demonstration_scene_with_another_demonstration(frames, tmp_path):
    """The scene named as the demonstration's must hold that demonstration."""
    other = tmp_path / "demo.csv"
    other.write_text((ROOT / "gyms" / "pick_block_plate" / "demo.csv").read_text() + "\n")
    task = tmp_path / "task.toml"
    task.write_text(f'[task]\ninstruction = "x"\ndemonstration = "{other}"\n'
                    f'demonstration_scene = "{ROOT / "gyms" / "pick_block_plate"}"\n')
    expect_error(tmp_path, frames, "does not hold the same demonstration", frames / "joints.json", "--task", task)


def model_run(tmp_path: Path, frames: Path, answer, name: str = "gym") -> subprocess.CompletedProcess:
    """`r2g reconstruct --llm scripted:<file>`: the scripted server on loopback (real HTTP, the
    OpenAI wire format) answering `answer`. Mechanics only: the answer is written here."""
    script = tmp_path / f"{name}.answers.json"
    text = answer if isinstance(answer, str) else json.dumps(answer)
    script.write_text(json.dumps({"gym": "reconstruct", "model": "scripted-reconstruct", "responses": [text]}))
    return run(frames, "--joints", frames / "joints.json", "--out", tmp_path / name, "--rounds", "0",
               "--llm", f"scripted:{script}", "--provider", "openai")


def test_model_names_and_primitives_applied(frames, tmp_path):
    """Mechanics only (scripted answer): the model's names and primitive choice are applied, the
    raw answer is kept in reconstruction.json, objects it does not mention keep their fit."""
    ans = {"objects": [{"id": "o1", "name": "thing_one", "primitive": "mesh"}, {"id": "o2", "name": "thing_two"}]}
    p = model_run(tmp_path, frames, ans)
    assert p.returncode == 0, p.stderr
    assert "mechanics only" in p.stderr
    line = json.loads(p.stdout.strip().splitlines()[-1])
    assert sorted(line["objects"]) == ["thing_one", "thing_two"], line
    rep = json.loads((tmp_path / "gym" / "reconstruction.json").read_text())
    assert rep["model"]["raw_answer"] == json.dumps(ans) and rep["model"]["mechanics_only"] is True
    by = {o["name"]: o for o in rep["objects"]}
    assert by["thing_one"]["kind"] == "mesh" and by["thing_one"]["fit"]["chosen_by"] == "model"
    assert by["thing_one"]["fit"]["evidence_chose"] in ("box", "cylinder")
    assert "chosen_by" not in by["thing_two"]["fit"]
    assert (tmp_path / "gym" / "meshes" / "thing_one.obj").is_file()


def test_model_materials_and_kept_shapes(frames, tmp_path):
    """Mechanics only (scripted answer): a material sets the object's mass (its density times the
    fitted volume) and friction in scene.toml; a fitted shape the model asks to keep that the
    frames did not give is a warning, and the fit stands."""
    ans = {"objects": [{"id": "o1", "name": "thing_one", "material": "metal"},
                       {"id": "o2", "name": "thing_two", "primitive": "parts", "material": "foam"}]}
    p = model_run(tmp_path, frames, ans)
    assert p.returncode == 0, p.stderr
    rep = json.loads((tmp_path / "gym" / "reconstruction.json").read_text())
    scene = tomllib.loads((tmp_path / "gym" / "scene.toml").read_text())
    by = {o["name"]: o for o in scene["objects"]}
    fits = {o["name"]: o["fit"] for o in rep["objects"]}
    for name, (density, friction) in (("thing_one", (7800.0, 0.4)), ("thing_two", (60.0, 0.8))):
        fit = fits[name]
        assert fit["material"]["chosen_by"] == "model" and by[name]["friction"] == friction
        want = min(2.0, max(0.02, density * fit["volume_m3"]))
        assert by[name]["mass_kg"] == pytest.approx(want, rel=1e-3), (name, by[name]["mass_kg"], want)
    assert fits["thing_two"]["chosen"] != "parts" and fits["thing_two"]["model_asked"] == "parts"
    assert any("asked to keep a parts fit" in w for w in rep["warnings"]), rep["warnings"]


@pytest.mark.parametrize("answer,needle", [
    ({"objects": [{"id": "o7", "name": "ghost", "primitive": "box"}]}, "names object id 'o7', which the reconstruction"),
    ({"objects": [{"id": "o1", "primitive": "cone"}]}, "primitive 'cone' is not one of box, cylinder, sphere, bowl"),
    ({"objects": [{"id": "o1", "material": "unobtainium"}]}, "material 'unobtainium' is not one of wood, ceramic"),
    ({"objects": [{"id": "o1", "material": ["wood"]}]}, "material ['wood'] is not one of wood, ceramic"),
    ("The block is red.", "the model's answer is not JSON"),
    ({"objects": [{"id": "o1", "name": "Big Block"}]}, "name 'Big Block' is not a lower-case identifier"),
])
def test_model_answer_refused(frames, tmp_path, answer, needle):
    """Mechanics only: an answer that is not a valid labelling is a clear error, no gym."""
    p = model_run(tmp_path, frames, answer)
    assert p.returncode != 0 and needle in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    assert not (tmp_path / "gym").exists()
    assert not any(x.name.startswith(".gym.partial") for x in tmp_path.iterdir())


class Geometry(BaseHTTPRequestHandler):
    """A geometry service on loopback: answers the depth of the synthetic frame whose RGB it
    receives (looked up by the PNG's pixels), or NaN in `nan` mode."""
    depths: dict = {}
    mode = "ok"

    def do_POST(self):  # noqa: N802 - http.server's name
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        png = base64.b64decode(body["image"]["png"])
        tmp = Path(self.server.tmp) / "q.png"  # type: ignore[attr-defined]
        tmp.write_bytes(png)
        rgb = rio.read_png(tmp)
        key = rgb.tobytes()[:: 997][:4096]
        d = self.depths[key].astype("<f4").copy()
        if self.mode == "nan":
            d[10, 10] = np.nan
        ans = {"depth": {"dtype": "float32", "shape": list(d.shape), "data": base64.b64encode(d.tobytes()).decode()}}
        data = json.dumps(ans).encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, *a):
        pass


@pytest.fixture()
def rgb_only(frames, tmp_path):
    f = tmp_path / "rgb_only"
    shutil.copytree(frames, f)
    sc = json.loads((f / "scene_camera.json").read_text())
    Geometry.depths = {}
    for im in sc:
        rgb = rio.read_png(f / "rgb" / f"{int(im):06d}.png")[..., :3]
        d = rio.read_png(f / "depth" / f"{int(im):06d}.png").astype(np.float32) * 0.1 / 1000
        Geometry.depths[np.ascontiguousarray(rgb).tobytes()[:: 997][:4096]] = d
    shutil.rmtree(f / "depth")
    srv = ThreadingHTTPServer(("127.0.0.1", 0), Geometry)
    srv.tmp = str(tmp_path)  # type: ignore[attr-defined]
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield f, f"http://127.0.0.1:{srv.server_address[1]}/depth"
    srv.shutdown()
    srv.server_close()


def test_rgb_only_with_geometry_service(rgb_only, tmp_path):
    f, url = rgb_only
    Geometry.mode = "ok"
    p = run(f, "--joints", f / "joints.json", "--out", tmp_path / "gym", "--rounds", "0", "--geometry-url", url)
    assert p.returncode == 0, p.stderr
    rep = json.loads((tmp_path / "gym" / "reconstruction.json").read_text())
    assert rep["images"][0]["depth"].startswith("geometry service")
    assert sorted(json.loads(p.stdout.strip().splitlines()[-1])["kinds"]) == ["box", "cylinder"]


def test_geometry_service_nan_and_down(rgb_only, tmp_path):
    f, url = rgb_only
    Geometry.mode = "nan"
    expect_error(tmp_path, f, "holds 1 NaN or infinite values", f / "joints.json", "--geometry-url", url)
    Geometry.mode = "ok"
    expect_error(tmp_path, f, "has no depth/ folder: give depth PNGs or a geometry service", f / "joints.json")
    expect_error(tmp_path, f, "is not reachable: connection refused", f / "joints.json",
                 "--geometry-url", "http://127.0.0.1:9/depth")


def test_depth_png_of_8_bits_refused(frames, tmp_path):
    """The layout's depth is uint16: an 8-bit grey PNG would be read as depth 256 times too coarse."""
    f = copy_frames(frames, tmp_path / "f")
    d = rio.read_png(f / "depth" / "000001.png")
    rio.write_png(f / "depth" / "000001.png", np.clip(d // 40, 0, 255).astype(np.uint8))
    expect_error(tmp_path, f, "depth/000001.png: a depth image must be 16-bit grey")


def test_principal_point_off_the_image(frames, tmp_path):
    f = copy_frames(frames, tmp_path / "f")
    doc = json.loads((f / "scene_camera.json").read_text())
    doc["1"]["cam_K"][2] = -50.0
    (f / "scene_camera.json").write_text(json.dumps(doc))
    expect_error(tmp_path, f, "scene_camera.json image '1': cam_K principal point (cx -50.0")


def test_unknown_tcp_link_lists_the_links(frames, tmp_path):
    expect_error(tmp_path, frames, "URDF has no link named 'no_such_link' (links: link0,", frames / "joints.json",
                 "--tcp-link", "no_such_link")


def test_unexpected_failure_is_one_line_naming_the_stage(frames, tmp_path):
    """A fault that is not an input check (here a NaN that a task rule carries into scene.toml,
    refused by the TOML writer with a ValueError) is one error line naming the step and stage."""
    task = tmp_path / "task.toml"
    task.write_text('[task]\ninstruction = "x"\n'
                    'success = [{ kind = "on", object = "table", support = "table", margin_m = nan }]\n')
    expect_error(tmp_path, frames, "fit step failed while writing scene.toml: ValueError: non-finite number",
                 frames / "joints.json", "--task", task)


def test_unexpected_failure_keeps_the_traceback_only_when_asked(tmp_path, monkeypatch, capsys):
    import argparse
    import r2g_reconstruct as rc

    def broken(a):
        rc.set_stage("fitting the objects")
        raise KeyError("radius")

    a = argparse.Namespace(cmd="fit", work=str(tmp_path / "w"))
    monkeypatch.delenv("R2G_RECONSTRUCT_KEEP_WORK", raising=False)
    monkeypatch.delenv("R2G_DEBUG", raising=False)
    with pytest.raises(SystemExit) as e:
        rc.run_step(broken, a)
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("error: the reconstruction's fit step failed while fitting the objects: KeyError"), err
    assert not (tmp_path / "w" / "traceback-fit.txt").exists()
    monkeypatch.setenv("R2G_RECONSTRUCT_KEEP_WORK", "1")
    with pytest.raises(SystemExit):
        rc.run_step(broken, a)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "traceback-fit.txt" in err, err
    assert "raise KeyError" in (tmp_path / "w" / "traceback-fit.txt").read_text()
