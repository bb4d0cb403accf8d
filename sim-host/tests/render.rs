//! Depth and intrinsics from a camera looking straight down on the table from 1 m: the table
//! reads 1 m everywhere (planar depth, not ray length), a block's top reads 1 m less its height,
//! and the block's edge lands on the pixel the intrinsics predict. And from a camera looking
//! down at a slant (agentview's pose), where the depth changes across the image: every table
//! pixel's depth is the table's depth along the ray the published intrinsics give that pixel.

mod common;

use sim_host::render::{intrinsics, Cameras};
use sim_host::Sim;

fn scene() -> std::path::PathBuf {
    write_scene("render-test", "[0.6, 0.0, 1.0]", "[0.6, 0.0, 0.0]", "[1.0, 0.0, 0.0]", 45.0)
}

fn write_scene(tag: &str, position: &str, look_at: &str, up: &str, fovy: f64) -> std::path::PathBuf {
    let dir = common::temp_dir(tag);
    let text = format!(
        r#"
name = "render_test"
{}[[cameras]]
name = "down"
position_m = {position}
look_at_m = {look_at}
up = {up}
fovy_deg = {fovy}
[[objects]]
name = "block"
shape = "box"
size_m = [0.05, 0.05, 0.05]
position_m = [0.6, 0.0, 0.05]
free = false
"#,
        common::robot_and_table()
    );
    let p = dir.join("scene.toml");
    std::fs::write(&p, text).expect("write scene");
    p
}

#[test]
fn depth_is_planar_metres_and_intrinsics_match_the_image() {
    let path = scene();
    let sim = Sim::load(&path).unwrap_or_else(|e| panic!("scene loads: {e}"));
    let spec = sim.scene.cameras[0].clone();
    let cam = sim.layout.cameras[0].1;
    let mut cams = Cameras::new(sim.model.clone(), spec.width, spec.height, true).expect("EGL renderer");
    cams.set_state(sim.qpos(), 0.0);
    let (w, h) = (spec.width as usize, spec.height as usize);
    let (_, depth) = cams.render(cam).expect("render");
    let depth = depth.expect("depth enabled").to_vec();
    let at = |row: usize, col: usize| depth[row * w + col] as f64;
    // Centre: the block's top, 0.1 m up.
    assert!((at(h / 2, w / 2) - 0.9).abs() < 2e-3, "block top depth {}", at(h / 2, w / 2));
    // Left and right of the block, far off-axis: still the table plane at 1 m.
    for col in [40, w - 40] {
        assert!((at(h / 2, col) - 1.0).abs() < 2e-3, "table depth at column {col}: {}", at(h / 2, col));
    }
    // The block's half-width 0.05 m at 0.9 m depth lands fx·0.05/0.9 pixels from the centre.
    let (fx, _, cx, _) = intrinsics(&spec);
    let edge = fx * 0.05 / 0.9;
    let row = h / 2;
    let inside = (cx + edge - 2.0) as usize;
    let outside = (cx + edge + 2.0) as usize;
    assert!((at(row, inside) - 0.9).abs() < 5e-3, "just inside the block edge: {}", at(row, inside));
    assert!((at(row, outside) - 1.0).abs() < 5e-3, "just outside the block edge: {}", at(row, outside));
    // The optical frame looks down: its z axis is world −z.
    let (p, q) = cams.optical_pose(cam);
    let z = controllers::math::rotate(q, [0.0, 0.0, 1.0]);
    assert!((p[2] - 1.0).abs() < 1e-9 && (z[2] + 1.0).abs() < 1e-9, "optical pose {p:?} {z:?}");
    let _ = std::fs::remove_dir_all(path.parent().expect("dir"));
}

/// The slanted view is where a half-pixel error shows: the table's depth changes along the image
/// rows, so a ray half a pixel off, or a depth read from another point of the pixel than its
/// centre (a multisampled buffer's sample), puts the back-projected table a millimetre or two
/// above or below its plane. Tolerance 0.05 mm: the 24-bit depth buffer resolves about 0.01 mm
/// at 1.7 m with this near plane, and half a pixel here is 0.4-1.2 mm of depth.
#[test]
fn slanted_depth_is_the_table_at_each_pixel_centre_along_the_published_rays() {
    let path = write_scene("render-slant", "[1.4, 0.0, 0.95]", "[0.3, 0.0, 0.18]", "[0.0, 0.0, 1.0]", 50.0);
    let sim = Sim::load(&path).unwrap_or_else(|e| panic!("scene loads: {e}"));
    let spec = sim.scene.cameras[0].clone();
    let cam = sim.layout.cameras[0].1;
    let mut cams = Cameras::new(sim.model.clone(), spec.width, spec.height, true).expect("EGL renderer");
    cams.set_state(sim.qpos(), 0.0);
    let (w, h) = (spec.width as usize, spec.height as usize);
    let (fx, fy, cx, cy) = intrinsics(&spec);
    assert_eq!(
        (cx, cy),
        ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0),
        "principal point in pixel-index coordinates"
    );
    let depth = cams.render(cam).expect("render").1.expect("depth enabled").to_vec();
    let (p, q) = cams.optical_pose(cam);
    let mut errs = Vec::new();
    // The lower two thirds of the image show the table in front of the robot; the floor beyond the
    // table's edge, the arm and most of the block are off the table's plane by more than 1 cm.
    for v in h / 3..h {
        for u in 0..w {
            let ray = controllers::math::rotate(q, [(u as f64 - cx) / fx, (v as f64 - cy) / fy, 1.0]);
            if ray[2] >= 0.0 {
                continue;
            }
            let expected = -p[2] / ray[2]; // planar depth of the table plane z = 0 along this ray
            let err = depth[v * w + u] as f64 - expected;
            if err.abs() < 0.01 {
                errs.push(err.abs());
            }
        }
    }
    assert!(errs.len() > w * h / 3, "only {} pixels show the table", errs.len());
    // The block's sides close to the table also lie within 1 cm of its plane: a few hundred
    // pixels of the ~130,000; every other one is the table.
    errs.sort_by(f64::total_cmp);
    let (median, p99) = (errs[errs.len() / 2], errs[errs.len() * 99 / 100]);
    println!("table pixels {}: |depth error| median {:.4} mm, p99 {:.4} mm", errs.len(), median * 1e3, p99 * 1e3);
    assert!(p99 < 5e-5, "table depth off the published rays: median {:.3} mm, p99 {:.3} mm", median * 1e3, p99 * 1e3);
    let _ = std::fs::remove_dir_all(path.parent().expect("dir"));
}
