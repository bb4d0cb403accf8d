//! Mesh objects: an OBJ file (relative to the scene) is compiled, collides through its convex
//! hull and comes to rest on the table under native physics; a fixture's hinge holds its range.

mod common;

use ipc_schema::JointCommand;
use sim_host::Sim;

#[test]
fn an_obj_mesh_falls_onto_the_table_and_rests_there() {
    let dir = common::temp_dir("mesh-test");
    // A 4 cm cube as a triangle mesh.
    let mut obj = String::new();
    for v in 0..8 {
        let c = |bit: i32| if v & bit != 0 { 0.02 } else { -0.02 };
        obj.push_str(&format!("v {} {} {}\n", c(1), c(2), c(4)));
    }
    for f in [[1, 3, 4, 2], [5, 6, 8, 7], [1, 2, 6, 5], [3, 7, 8, 4], [1, 5, 7, 3], [2, 4, 8, 6]] {
        obj.push_str(&format!("f {} {} {}\nf {} {} {}\n", f[0], f[1], f[2], f[0], f[2], f[3]));
    }
    std::fs::write(dir.join("cube.obj"), obj).expect("write obj");
    let scene = format!(
        r#"
name = "mesh_test"
cameras = []
{}[[objects]]
name = "cube"
shape = "mesh"
mesh = "cube.obj"
position_m = [0.5, 0.2, 0.1]
mass_kg = 0.1
[[fixtures]]
name = "door"
position_m = [0.6, -0.3, 0.0]
parts = [{{ shape = "box", size_m = [0.01, 0.01, 0.1], position_m = [0.0, 0.0, 0.1] }}]
[fixtures.joint]
kind = "hinge"
axis = [0.0, 0.0, 1.0]
range_deg = [0.0, 90.0]
initial = 45.0
mass_kg = 0.3
parts = [{{ shape = "box", size_m = [0.005, 0.1, 0.1], position_m = [0.0, 0.1, 0.1] }}]
"#,
        common::robot_and_table()
    );
    std::fs::write(dir.join("scene.toml"), scene).expect("write scene");
    let mut sim = Sim::load(&dir.join("scene.toml")).unwrap_or_else(|e| panic!("mesh scene: {e}"));
    let cmd = JointCommand {
        q_rad: sim.scene.robot.initial_joints_rad,
        finger_m: 0.04,
        state_seq: u64::MAX,
        ..Default::default()
    };
    let mut trace = sim.new_trace();
    for _ in 0..1500 {
        sim.step(&cmd);
        sim.record(&mut trace);
    }
    let last = trace.samples.last().expect("samples");
    let z = last.objects[0][2];
    assert!((z - 0.02).abs() < 1.5e-3, "the cube's centre should rest 2 cm above the table, is at {z}");
    let table = trace.owners.iter().position(|o| o == "table").expect("table") as u16;
    assert!(last.contacts.contains(&[0, table]), "cube and table touch: {:?}", last.contacts);
    assert!((last.joints[0] - 45.0).abs() < 1.0, "the door stays where it started: {}", last.joints[0]);
    let _ = std::fs::remove_dir_all(&dir);
}
