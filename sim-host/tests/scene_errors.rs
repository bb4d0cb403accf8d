//! Malformed scene files: each gives a one-line error naming the file, the field and what is
//! accepted, and never a panic.

mod common;

use std::path::PathBuf;

use sim_host::Scene;

fn base() -> String {
    format!(
        r#"
name = "broken"
{}[[cameras]]
name = "agentview"
position_m = [1.4, 0.0, 0.95]
look_at_m = [0.3, 0.0, 0.18]
fovy_deg = 50.0
[[objects]]
name = "block"
shape = "box"
size_m = [0.02, 0.02, 0.02]
position_m = [0.5, -0.12, 0.02]
mass_kg = 0.05
[[fixtures]]
name = "drawer"
position_m = [0.6, 0.3, 0.0]
parts = [{{ shape = "box", size_m = [0.1, 0.1, 0.1] }}]
[fixtures.joint]
kind = "slide"
axis = [-1.0, 0.0, 0.0]
range_m = [0.0, 0.3]
parts = [{{ shape = "box", size_m = [0.05, 0.05, 0.01] }}]
[task]
instruction = "Open the drawer."
success = [{{ kind = "joint", fixture = "drawer", min = 0.1 }}]
"#,
        common::robot_and_table()
    )
}

fn write(name: &str, text: &str) -> PathBuf {
    let p = common::temp_dir(&format!("scene-errors-{name}")).join("scene.toml");
    std::fs::write(&p, text).expect("write");
    p
}

/// Loads `text` and checks the error: one line, naming the file and every `needles` entry.
fn refused(name: &str, text: &str, needles: &[&str]) {
    let p = write(name, text);
    let err = match Scene::load(&p) {
        Ok(_) => panic!("{name}: the scene was accepted"),
        Err(e) => e.to_string(),
    };
    eprintln!("{name}: {err}");
    assert!(!err.contains('\n'), "{name}: error spans lines: {err}");
    assert!(err.contains(&p.display().to_string()), "{name}: error does not name the file: {err}");
    for n in needles {
        assert!(err.contains(n), "{name}: error lacks '{n}': {err}");
    }
    let _ = std::fs::remove_dir_all(p.parent().expect("dir"));
}

#[test]
fn the_base_scene_is_valid() {
    let p = write("valid", &base());
    Scene::load(&p).unwrap_or_else(|e| panic!("base scene refused: {e}"));
    let _ = std::fs::remove_dir_all(p.parent().expect("dir"));
}

#[test]
fn a_missing_field_is_named() {
    let text =
        base().replace("initial_joints_rad = [0.0, -0.7853982, 0.0, -2.3561945, 0.0, 1.5707963, 0.7853982]\n", "");
    refused("missing", &text, &["initial_joints_rad", "line"]);
}

#[test]
fn an_unknown_key_lists_the_accepted_ones() {
    let text = base().replace("mass_kg = 0.05", "mass_kg = 0.05\ncolour = \"red\"");
    refused("unknown", &text, &["colour", "expected one of", "rgba"]);
}

#[test]
fn negative_and_zero_masses_are_refused() {
    refused(
        "negative-mass",
        &base().replace("mass_kg = 0.05", "mass_kg = -0.05"),
        &["objects[0] 'block'", "mass_kg", "positive"],
    );
    refused("zero-mass", &base().replace("mass_kg = 0.05", "mass_kg = 0.0"), &["mass_kg", "positive"]);
}

#[test]
fn nan_poses_are_refused() {
    let text = base().replace("position_m = [0.5, -0.12, 0.02]", "position_m = [nan, -0.12, 0.02]");
    refused("nan-position", &text, &["objects[0] 'block'", "position_m", "finite"]);
    let text = base().replace("mass_kg = 0.05", "mass_kg = 0.05\nquat_wxyz = [0.0, 0.0, 0.0, 0.0]");
    refused("zero-quat", &text, &["quat_wxyz", "non-zero quaternion"]);
    let text = base().replace("initial_joints_rad = [0.0,", "initial_joints_rad = [inf,");
    refused("inf-joint", &text, &["robot.initial_joints_rad", "finite"]);
}

#[test]
fn a_missing_mesh_file_is_named() {
    let text =
        base().replace("shape = \"box\"\nsize_m = [0.02, 0.02, 0.02]", "shape = \"mesh\"\nmesh = \"no_such_mug.obj\"");
    refused("mesh", &text, &["objects[0] 'block'", "no_such_mug.obj", "does not exist"]);
}

#[test]
fn inverted_joint_limits_are_refused() {
    refused(
        "inverted",
        &base().replace("range_m = [0.0, 0.3]", "range_m = [0.3, 0.0]"),
        &["fixtures[0] 'drawer'.joint.range_m", "lower < upper"],
    );
    let text = base().replace("range_m = [0.0, 0.3]", "range_deg = [0.0, 90.0]");
    refused("wrong-unit", &text, &["fixtures[0] 'drawer'.joint", "range_m"]);
}

#[test]
fn a_camera_with_zero_fovy_is_refused() {
    refused(
        "fovy",
        &base().replace("fovy_deg = 50.0", "fovy_deg = 0.0"),
        &["cameras[0] 'agentview'", "fovy_deg", "(1, 170)"],
    );
}

#[test]
fn two_objects_with_one_name_are_refused() {
    let text = base().replace("[[fixtures]]\nname = \"drawer\"", "[[objects]]\nname = \"block\"\nshape = \"sphere\"\nsize_m = [0.02]\nposition_m = [0.4, 0.0, 0.02]\n[[fixtures]]\nname = \"drawer\"");
    refused("duplicate", &text, &["objects[1] 'block'", "already used"]);
}

#[test]
fn shapes_sizes_and_names_are_checked() {
    refused("cone", &base().replace("shape = \"box\"", "shape = \"cone\""), &["cone", "expected one of", "cylinder"]);
    refused(
        "sizes",
        &base().replace("size_m = [0.02, 0.02, 0.02]", "size_m = [0.02, 0.02]"),
        &["objects[0] 'block'", "size_m", "3 positive numbers"],
    );
    refused("name", &base().replace("name = \"block\"", "name = \"my block!\""), &["objects[0].name", "a-z A-Z 0-9 _"]);
}

#[test]
fn task_rules_must_name_real_things() {
    let text = base().replace("fixture = \"drawer\", min = 0.1", "fixture = \"oven\", min = 0.1");
    refused("criterion", &text, &["task.success[0].fixture = 'oven'", "accepted is a fixture with a joint"]);
    let text = base().replace("[task]\n", "[task]\ndemonstration = \"missing.csv\"\n");
    refused("demo", &text, &["task.demonstration", "missing.csv", "does not exist"]);
    let text = base().replace("kind = \"joint\"", "kind = \"levitates\"");
    refused("kind", &text, &["levitates", "expected one of"]);
}

#[test]
fn bad_physics_settings_are_refused() {
    refused("timestep", &format!("timestep_s = 0.0\n{}", base()), &["timestep_s", "(0, 0.01]"]);
    let text = base().replace("kind = \"slide\"", "kind = \"slide\"\ndamping = -1.0");
    refused("damping", &text, &["fixtures[0] 'drawer'.joint.damping", ">= 0"]);
}

#[test]
fn not_toml_at_all_is_one_line() {
    refused("garbage", "name = \"x\"\n[robot\nurdf = 3\n", &["line 2"]);
}
