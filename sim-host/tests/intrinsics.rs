//! Cameras given with pinhole intrinsics (`fx, fy, cx, cy`, the principal point off the image
//! centre and fx ≠ fy): MuJoCo renders exactly that projection. A small sphere's centre lands on
//! the pixel the intrinsics predict (within 1 px), and the table, back-projected from the depth
//! image through the intrinsics, lies on its plane (within 1 mm). The sign of MuJoCo's principal
//! offset matters here: flipped, the sphere lands 2·(offset) pixels away and the slanted table
//! tilts by centimetres. Bad intrinsics in a scene are refused with a precise message.

mod common;

use sim_host::render::{intrinsics, Cameras};
use sim_host::{Scene, Sim};

const POSITION: [f64; 3] = [0.95, 0.35, 0.7];
const LOOK_AT: [f64; 3] = [0.45, 0.0, 0.0];
const SPHERE: [f64; 3] = [0.5, 0.08, 0.12];
const K: (f64, f64, f64, f64) = (300.0, 270.0, 141.25, 97.5);

fn scene(camera: &str) -> String {
    format!(
        r#"
name = "intrinsics_test"
{}[[cameras]]
name = "side"
position_m = {POSITION:?}
look_at_m = {LOOK_AT:?}
width = 320
height = 240
{camera}
[[objects]]
name = "ball"
shape = "sphere"
size_m = [0.012]
position_m = {SPHERE:?}
free = false
"#,
        common::robot_and_table()
    )
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// The optical axes (x right, y down, z forward) a camera at POSITION looking at LOOK_AT with
/// world z up has, by the definition of look_at and up in SCENES.md.
fn optical_axes() -> [[f64; 3]; 3] {
    let z = unit(sub(LOOK_AT, POSITION));
    let x = unit(cross(z, [0.0, 0.0, 1.0]));
    let y = cross(z, x);
    [x, y, z]
}

#[test]
fn an_off_centre_principal_point_projects_and_back_projects_as_the_intrinsics_say() {
    let (fx, fy, cx, cy) = K;
    let dir = common::temp_dir("intrinsics");
    let path = dir.join("scene.toml");
    std::fs::write(&path, scene(&format!("fx = {fx}\nfy = {fy}\ncx = {cx}\ncy = {cy}"))).expect("write scene");
    let sim = Sim::load(&path).unwrap_or_else(|e| panic!("scene loads: {e}"));
    let spec = sim.scene.cameras[0].clone();
    assert_eq!(intrinsics(&spec), K, "the intrinsics reported are the ones given");
    assert!(sim.mjcf.contains("focalpixel=\"300 270\""), "the MJCF carries the focal length:\n{}", sim.mjcf);
    let cam = sim.layout.cameras[0].1;
    let mut cams = Cameras::new(sim.model.clone(), spec.width, spec.height, true).expect("EGL renderer");
    cams.set_state(sim.qpos(), 0.0);
    let (w, h) = (spec.width as usize, spec.height as usize);
    let depth = cams.render(cam).expect("render").1.expect("depth").to_vec();
    let geoms = cams.segment(cam).expect("segmentation");
    let [ax, ay, az] = optical_axes();
    // The optical frame the renderer reports is the one the spec defines.
    let (p, q) = cams.optical_pose(cam);
    for (axis, want) in [([1.0, 0.0, 0.0], ax), ([0.0, 1.0, 0.0], ay), ([0.0, 0.0, 1.0], az)] {
        let got = controllers::math::rotate(q, axis);
        assert!(dot(got, want) > 1.0 - 1e-9, "optical axis {got:?}, expected {want:?}");
    }
    assert!(dot(sub(p, POSITION), sub(p, POSITION)) < 1e-18, "camera at {p:?}");

    // The sphere: the centroid of its pixels against the projection of its centre.
    // Owners: the objects first (the ball is 0), then fixtures, table, robot, floor.
    let ball = 0u16;
    let table = sim.owners.iter().position(|o| o == "table").expect("table owner") as u16;
    let (mut su, mut sv, mut n) = (0.0, 0.0, 0.0);
    let mut table_err = Vec::new();
    for row in 0..h {
        for col in 0..w {
            let g = geoms[row * w + col];
            if g < 0 {
                continue;
            }
            let owner = sim.layout.geom_owner[g as usize];
            let z = depth[row * w + col] as f64;
            if owner == ball {
                su += col as f64;
                sv += row as f64;
                n += 1.0;
            } else if owner == table {
                // Back-project through the intrinsics into the world: the table top is z = 0.
                let (x, y) = ((col as f64 - cx) / fx * z, (row as f64 - cy) / fy * z);
                let world_z = POSITION[2] + x * ax[2] + y * ay[2] + z * az[2];
                table_err.push(world_z.abs());
            }
        }
    }
    assert!(n > 20.0, "the sphere is seen ({n} pixels)");
    let d = sub(SPHERE, POSITION);
    let (x, y, z) = (dot(d, ax), dot(d, ay), dot(d, az));
    let (u, v) = (cx + fx * x / z, cy + fy * y / z);
    let (mu, mv) = (su / n, sv / n);
    println!("sphere centre: predicted ({u:.2}, {v:.2}), centroid of its pixels ({mu:.2}, {mv:.2})");
    assert!((mu - u).abs() < 1.0 && (mv - v).abs() < 1.0, "sphere at ({mu}, {mv}), predicted ({u}, {v})");
    table_err.sort_by(f64::total_cmp);
    let worst = *table_err.last().expect("table seen");
    println!("table: {} pixels back-projected, worst height error {:.3} mm", table_err.len(), worst * 1e3);
    assert!(table_err.len() > w * h / 4, "the table fills much of the image");
    assert!(worst < 1e-3, "back-projected table off its plane by up to {worst} m");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_camera_without_intrinsics_keeps_its_field_of_view_and_centred_principal_point() {
    let dir = common::temp_dir("intrinsics-fovy");
    let path = dir.join("scene.toml");
    std::fs::write(&path, scene("fovy_deg = 50.0")).expect("write scene");
    let sim = Sim::load(&path).unwrap_or_else(|e| panic!("scene loads: {e}"));
    assert!(sim.mjcf.contains("fovy=\"50\"/>") && !sim.mjcf.contains("focalpixel"), "{}", sim.mjcf);
    let (fx, fy, cx, cy) = intrinsics(&sim.scene.cameras[0]);
    let f = 120.0 / (25f64.to_radians()).tan();
    assert!((fx - f).abs() < 1e-9 && fx == fy && cx == 159.5 && cy == 119.5);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_intrinsics_are_refused_with_what_is_wrong() {
    let dir = common::temp_dir("intrinsics-errors");
    let path = dir.join("scene.toml");
    let cases: [(&str, &[&str]); 6] = [
        ("fx = 300.0\nfy = 300.0", &["cameras[0] 'side'", "all four of fx, fy, cx, cy", "missing cx, cy"]),
        ("fovy_deg = 50.0\nfx = 300.0\nfy = 300.0\ncx = 100.0\ncy = 100.0", &["fovy_deg and fx, fy, cx, cy"]),
        ("fx = -300.0\nfy = 300.0\ncx = 100.0\ncy = 100.0", &["fx = -300", "positive"]),
        ("fx = 300.0\nfy = 0.0\ncx = 100.0\ncy = 100.0", &["fy = 0", "positive"]),
        ("fx = 300.0\nfy = 300.0\ncx = 319.5\ncy = 100.0", &["cx = 319.5", "[0, 319]"]),
        ("fx = 300.0\nfy = 300.0\ncx = 100.0\ncy = -1.0", &["cy = -1", "[0, 239]"]),
    ];
    for (camera, want) in cases {
        std::fs::write(&path, scene(camera)).expect("write scene");
        let err = Scene::load(&path).err().map(|e| e.to_string()).unwrap_or_else(|| panic!("accepted:\n{camera}"));
        for w in want {
            assert!(err.contains(w), "error for\n{camera}\nlacks '{w}': {err}");
        }
        assert!(!err.contains('\n'), "one line: {err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
