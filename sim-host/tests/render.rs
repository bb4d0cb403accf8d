//! Depth and intrinsics from a camera looking straight down on the table from 1 m: the table
//! reads 1 m everywhere (planar depth, not ray length), a block's top reads 1 m less its height,
//! and the block's edge lands on the pixel the intrinsics predict.

mod common;

use sim_host::render::{intrinsics, Cameras};
use sim_host::Sim;

fn scene() -> std::path::PathBuf {
    let dir = common::temp_dir("render-test");
    let text = format!(
        r#"
name = "render_test"
{}[[cameras]]
name = "down"
position_m = [0.6, 0.0, 1.0]
look_at_m = [0.6, 0.0, 0.0]
up = [1.0, 0.0, 0.0]
fovy_deg = 45.0
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
