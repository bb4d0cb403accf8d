//! The measured contact force on the robot (`SimState::external_force_n`, `get_state()`'s
//! `external_force_n` once the runtime has filtered it): every robot geom counts, the arm's, the
//! hand's and the fingers', also when the URDF mounts `link0` on a root link of its own (a
//! `world` or `base` link, as many descriptions do). Before, the robot's geoms were found by
//! the body the first joint moves from; under such a root they belonged to no one, the force
//! read [0, 0, 0] whatever pressed on the hand, and the native trace lost the robot's contacts.

use std::path::{Path, PathBuf};

use ipc_schema::JointCommand;
use sim_host::Sim;

/// The shipped Panda, or the same with `link0` mounted on a root link `mount` (meshes by
/// absolute path, so that the copy can live in a temporary folder).
fn urdf(dir: &Path, mounted: bool) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").canonicalize().expect("checkout");
    let shipped = root.join("robots/panda/panda.urdf");
    if !mounted {
        return shipped;
    }
    let text = std::fs::read_to_string(&shipped).expect("urdf");
    let packages = format!("file://{}/", root.join("robots/packages").display());
    let at = text.find("<link name=\"link0\"").expect("link0");
    let text = format!(
        "{}<link name=\"mount\"/>\n  <joint name=\"mount_joint\" type=\"fixed\"><parent link=\"mount\"/><child link=\"link0\"/><origin xyz=\"0 0 0\" rpy=\"0 0 0\"/></joint>\n  {}",
        &text[..at],
        &text[at..]
    )
    .replace("package://", &packages);
    let p = dir.join("panda_mounted.urdf");
    std::fs::write(&p, text).expect("write urdf");
    p
}

/// The Panda at its ready pose (fingertips about 0.478 m up, under the TCP at (0.307, 0, 0.487))
/// with a fixed slab whose top is 7 mm above the fingertips: it presses them up.
fn scene(tag: &str, mounted: bool) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("r2g-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    let text = format!(
        r#"
name = "contact_force_test"
[robot]
urdf = "{}"
initial_joints_rad = [0.0, -0.7853982, 0.0, -2.3561945, 0.0, 1.5707963, 0.7853982]
initial_gripper = 1.0
[table]
top_center_m = [0.45, 0.0, 0.0]
size_m = [1.3, 1.2]
[[objects]]
name = "slab"
shape = "box"
size_m = [0.05, 0.05, 0.01]
position_m = [0.307, 0.0, 0.475]
free = false
"#,
        urdf(&dir, mounted).display()
    );
    let p = dir.join("scene.toml");
    std::fs::write(&p, text).expect("write scene");
    p
}

/// Net force on the robot after holding the ready pose for 0.3 s against the slab.
fn pressed(tag: &str, mounted: bool) -> (Sim, [f64; 3]) {
    let path = scene(tag, mounted);
    let mut sim = Sim::load(&path).unwrap_or_else(|e| panic!("scene loads: {e}"));
    sim.reset();
    let hold = JointCommand { q_rad: sim.scene.robot.initial_joints_rad, finger_m: 0.0, ..Default::default() };
    for _ in 0..300 {
        sim.step(&hold);
    }
    let f = sim.external_force_world();
    let _ = std::fs::remove_dir_all(path.parent().expect("dir"));
    (sim, f)
}

#[test]
fn every_robot_geom_counts_also_under_a_mounting_root_link() {
    let (plain, f_plain) = pressed("force-plain", false);
    let (mounted, f_mounted) = pressed("force-mounted", true);
    for sim in [&plain, &mounted] {
        let robot: Vec<_> =
            sim.layout.geom_owner.iter().enumerate().filter(|(_, o)| **o == sim.layout.robot_owner).collect();
        // link0 … link7, the hand and two fingers: each has a drawn mesh and a collision shape
        assert!(robot.len() >= 22, "only {} geoms are the robot's", robot.len());
        assert!(
            !sim.layout.geom_owner.contains(&u16::MAX),
            "geoms owned by nothing: {:?}",
            sim.layout
                .geom_owner
                .iter()
                .enumerate()
                .filter(|(_, o)| **o == u16::MAX)
                .map(|(g, _)| g)
                .collect::<Vec<_>>()
        );
    }
    // The slab pushes the fingertips up: the force on the robot points up, some newtons.
    assert!(f_plain[2] > 1.0, "force on the robot pressed from below: {f_plain:?}");
    // The mount changes nothing physical: the same force.
    let d = (0..3).map(|k| (f_plain[k] - f_mounted[k]).abs()).fold(0.0, f64::max);
    assert!(d < 1e-6 * f_plain[2].abs().max(1.0), "plain {f_plain:?}, mounted {f_mounted:?}");
}
