//! The BOP scene layout `r2g render` writes (synthetic frames of a shipped gym): the files are
//! there, the block's mask back-projected through its depth, `cam_K` and the `w2c` pose lies on
//! the block's true box from `scene_gt.json`, a `scene_camera.json` read back renders the same
//! images, and trace samples pose the scene exactly.

use std::path::{Path, PathBuf};

use serde_json::Value;
use sim_host::bop::{self, Shooter};
use sim_host::Sim;

fn gym() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../gyms/pick_block_plate/scene.toml")
}

fn temp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("r2g-bop-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// (width, height, samples) of a grayscale PNG, 8 or 16 bits.
fn gray(path: &Path) -> (usize, usize, Vec<u32>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).expect("open png")));
    let mut reader = dec.read_info().expect("png header");
    let mut buf = vec![0; reader.output_buffer_size().expect("size")];
    let info = reader.next_frame(&mut buf).expect("png data");
    assert_eq!(info.color_type, png::ColorType::Grayscale, "{}", path.display());
    let px = match info.bit_depth {
        png::BitDepth::Eight => buf[..info.buffer_size()].iter().map(|&b| b as u32).collect(),
        png::BitDepth::Sixteen => {
            buf[..info.buffer_size()].chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]]) as u32).collect()
        }
        d => panic!("{}: bit depth {d:?}", path.display()),
    };
    (info.width as usize, info.height as usize, px)
}

fn nums(v: &Value) -> Vec<f64> {
    v.as_array().expect("list").iter().map(|x| x.as_f64().expect("number")).collect()
}

fn read_json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).expect("read json")).expect("json")
}

/// R·x + t for a row-major R.
fn apply(r: &[f64], t: &[f64], x: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| r[3 * i] * x[0] + r[3 * i + 1] * x[1] + r[3 * i + 2] * x[2] + t[i])
}

/// Rᵀ·(x − t): the inverse of `apply`.
fn unapply(r: &[f64], t: &[f64], x: [f64; 3]) -> [f64; 3] {
    let d = [x[0] - t[0], x[1] - t[1], x[2] - t[2]];
    [0, 1, 2].map(|i| r[i] * d[0] + r[3 + i] * d[1] + r[6 + i] * d[2])
}

/// Distance of a point (object frame) from the surface of a box of half-extents `h`.
fn box_surface_distance(p: [f64; 3], h: [f64; 3]) -> f64 {
    let q = [0, 1, 2].map(|i| p[i].abs() - h[i]);
    let outside = q.iter().map(|v| v.max(0.0).powi(2)).sum::<f64>().sqrt();
    let inside = q[0].max(q[1]).max(q[2]).min(0.0);
    (outside + inside).abs()
}

#[test]
fn pick_block_plate_renders_into_the_bop_layout_and_the_block_mask_back_projects_onto_the_block() {
    let mut sim = Sim::load(&gym()).unwrap_or_else(|e| panic!("gym loads: {e}"));
    sim.reset();
    let cams: Vec<usize> = (0..sim.scene.cameras.len()).collect();
    let images = Shooter::new(&sim).shoot(&sim, &cams, None).expect("render");
    let names: Vec<String> = sim.scene.objects.iter().map(|o| o.name.clone()).collect();
    let out = temp("layout").join("frames");
    bop::write(&out, &names, &images).expect("write");

    let cameras = read_json(&out.join("scene_camera.json"));
    let gt = read_json(&out.join("scene_gt.json"));
    let joints = read_json(&out.join("joints.json"));
    assert_eq!(cameras.as_object().expect("object").len(), 2, "one image per camera");
    let block_half = [0.02, 0.02, 0.02];
    let block_body = sim.layout.objects[0].0;
    for id in ["0", "1"] {
        let cam = &cameras[id];
        let k = nums(&cam["cam_K"]);
        let (r_w2c, t_w2c) = (nums(&cam["cam_R_w2c"]), nums(&cam["cam_t_w2c"]));
        assert_eq!(cam["depth_scale"].as_f64(), Some(0.1));
        assert_eq!((cam["width"].as_u64(), cam["height"].as_u64()), (Some(640), Some(480)));
        let name = cam["r2g_camera"].as_str().expect("camera name");
        assert_eq!(name, ["agentview", "wrist"][id.parse::<usize>().expect("id")]);
        let q = nums(&joints[id]["joints_rad"]);
        assert_eq!(q, sim.scene.robot.initial_joints_rad.to_vec(), "the arm's pose at capture");
        let n = id.parse::<usize>().expect("id");
        for f in [format!("rgb/{n:06}.png"), format!("mask_visib/{n:06}_000001.png")] {
            assert!(out.join(&f).is_file(), "{f} written");
        }
        let objs = gt[id].as_array().expect("gt list");
        assert_eq!(objs.len(), 2);
        assert_eq!((objs[0]["obj_id"].as_u64(), objs[0]["r2g_name"].as_str()), (Some(1), Some("block")));
        let (r_m2c, t_m2c) = (nums(&objs[0]["cam_R_m2c"]), nums(&objs[0]["cam_t_m2c"]));
        // The block's pose in the world (robot base = world here) from scene_gt and w2c, against
        // the simulator's.
        let centre_w = unapply(&r_w2c, &t_w2c, apply(&r_m2c, &t_m2c, [0.0; 3]));
        let truth = sim.data.xpos()[block_body];
        for i in 0..3 {
            assert!((centre_w[i] / 1000.0 - truth[i]).abs() < 1e-6, "block centre {centre_w:?} mm vs {truth:?} m");
        }
        let (w, h, depth) = gray(&out.join(format!("depth/{n:06}.png")));
        let (mw, mh, mask) = gray(&out.join(format!("mask_visib/{n:06}_000000.png")));
        assert_eq!((w, h, mw, mh), (640, 480, 640, 480));
        assert!(mask.iter().all(|&m| m == 0 || m == 255), "masks are 0/255");
        let mut errs = Vec::new();
        for v in 0..h {
            for u in 0..w {
                let d = depth[v * w + u];
                if mask[v * w + u] == 0 {
                    continue;
                }
                assert!(d > 0, "a mask pixel without depth at ({u}, {v})");
                let z = d as f64 * 0.1; // mm
                let xc = [(u as f64 - k[2]) / k[0] * z, (v as f64 - k[5]) / k[4] * z, z];
                let xw = unapply(&r_w2c, &t_w2c, xc);
                // Into the block's frame: world → camera (w2c) → block (m2c inverted).
                let xo = unapply(&r_m2c, &t_m2c, apply(&r_w2c, &t_w2c, xw));
                errs.push(box_surface_distance(xo.map(|v| v / 1000.0), block_half));
            }
        }
        errs.sort_by(f64::total_cmp);
        let worst = *errs.last().expect("the block is seen");
        let mean = errs.iter().sum::<f64>() / errs.len() as f64;
        println!(
            "{name}: {} block pixels, off its box by {:.3} mm mean, {:.3} mm worst",
            errs.len(),
            mean * 1e3,
            worst * 1e3
        );
        assert!(errs.len() > 100, "{name}: the block covers {} pixels", errs.len());
        assert!(worst < 3e-3 && mean < 1e-3, "{name}: back-projected block off its box by up to {worst} m");
    }

    // Read back, scene_camera.json renders the same images from fixed cameras (the wrist camera
    // included, which the scene mounts on the hand).
    let bop_cams = bop::read_scene_camera(&out.join("scene_camera.json")).expect("read back");
    let mut scene = sim.scene.clone();
    scene.cameras =
        bop_cams.iter().map(|c| bop::camera_spec(c, sim.world_from_base())).collect::<Result<_, _>>().expect("spec");
    let mut again = Sim::from_scene(scene).expect("compiles with the file's cameras");
    again.reset();
    let images2 = Shooter::new(&again).shoot(&again, &[0, 1], None).expect("render again");
    for (a, b) in images.iter().zip(&images2) {
        assert_eq!(a.k, b.k);
        let n = a.depth_m.len();
        let same_object = a.object.iter().zip(&b.object).filter(|(x, y)| x == y).count();
        let close = a.depth_m.iter().zip(&b.depth_m).filter(|(x, y)| (**x - **y).abs() < 5e-4).count();
        println!("{}: {same_object}/{n} pixels see the same object, {close}/{n} depths within 0.5 mm", a.camera);
        assert!(same_object as f64 > 0.999 * n as f64 && close as f64 > 0.999 * n as f64, "{}", a.camera);
    }
    let _ = std::fs::remove_dir_all(out.parent().expect("parent"));
}

#[test]
fn a_trace_sample_poses_the_scene_and_a_sample_without_arm_angles_is_refused() {
    let mut sim = Sim::load(&gym()).unwrap_or_else(|e| panic!("gym loads: {e}"));
    let mut s = sim.sample();
    let tcp0 = s.tcp_m;
    assert_eq!(s.arm_rad, sim.scene.robot.initial_joints_rad.to_vec(), "samples carry the arm's angles");
    s.t_s = 1.25;
    s.arm_rad[0] += 0.3;
    s.arm_rad[3] += 0.2;
    s.objects[0][0] += 0.05;
    s.objects[0][2] += 0.1;
    s.finger_m = 0.01;
    sim.set_state_from_sample(&s).expect("poses");
    let back = sim.sample();
    assert_eq!(back.t_s, 1.25);
    for (a, b) in back.arm_rad.iter().zip(&s.arm_rad) {
        assert!((a - b).abs() < 1e-12);
    }
    for (a, b) in back.objects[0].iter().zip(&s.objects[0]) {
        assert!((a - b).abs() < 1e-9, "{:?} vs {:?}", back.objects[0], s.objects[0]);
    }
    assert!((back.finger_m - 0.01).abs() < 1e-12);
    // The TCP moved with the arm.
    let moved = (0..3).map(|i| (back.tcp_m[i] - tcp0[i]).powi(2)).sum::<f64>().sqrt();
    assert!(moved > 0.05, "the TCP moved {moved} m with the arm");
    s.arm_rad.clear();
    let err = sim.set_state_from_sample(&s).expect_err("no arm angles");
    assert!(err.contains("arm_rad") && err.contains("record it again"), "{err}");
    // An old trace (no arm_rad key) still reads, and its hash ignores the field either way.
    let mut t = sim.new_trace();
    t.samples.push(back.clone());
    let h = t.sha256();
    t.samples[0].arm_rad.clear();
    assert_eq!(t.sha256(), h, "arm_rad is not hashed");
    let json = serde_json::to_string(&t).expect("json");
    assert!(!json.contains("arm_rad"), "an empty arm_rad is not written");
    let read: sim_host::trace::Trace = serde_json::from_str(&json).expect("an old-format trace reads");
    assert!(read.samples[0].arm_rad.is_empty());
}

#[test]
fn bad_scene_camera_files_are_refused_naming_the_image_and_the_key() {
    let dir = temp("bad-cameras");
    std::fs::create_dir_all(&dir).expect("dir");
    let good = r#""cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "cam_R_w2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_w2c": [0, 0, 1000]"#;
    let cases = [
        (format!(r#"{{"3": {{{good}, "width": 640}}}}"#), vec!["image '3'", "no \"height\"", "image size"]),
        (
            format!(r#"{{"0": {{{}, "width": 640, "height": 480}}}}"#, good.replace("0, 0, 1],", "0, 1],")),
            vec!["image '0'", "cam_K", "8 entries", "3x3"],
        ),
        (
            format!(r#"{{"0": {{{}, "width": 640, "height": 480}}}}"#, good.replace("[500, 0, 320", "[500, 2, 320")),
            vec!["cam_K", "no skew"],
        ),
        (
            format!(
                r#"{{"0": {{{}, "width": 640, "height": 480}}}}"#,
                good.replace("[1, 0, 0, 0, 1", "[2, 0, 0, 0, 1")
            ),
            vec!["cam_R_w2c", "not a rotation"],
        ),
        (
            format!(r#"{{"0": {{{}, "width": 600, "height": 480}}}}"#, good.replace("320, 0", "700, 0")),
            vec!["cx = 700", "[0, 599]"],
        ),
        ("[1, 2]".to_string(), vec!["keyed by image id"]),
    ];
    for (text, want) in cases {
        let p = dir.join("scene_camera.json");
        std::fs::write(&p, &text).expect("write");
        let err = bop::read_scene_camera(&p).expect_err(&text);
        for w in want {
            assert!(err.contains(w), "error for {text} lacks '{w}': {err}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
