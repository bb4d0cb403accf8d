//! A skill's fingerprint follows what its motions depend on — the arm's kinematics, the gripper,
//! the profile — and nothing else: changing an unrelated key of config/robot.json keeps it.

use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn config(dir: &Path, name: &str, json: serde_json::Value) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, serde_json::to_string_pretty(&json).expect("json")).expect("write");
    p
}

#[test]
fn unrelated_config_keys_keep_the_fingerprint_and_the_robot_changes_it() {
    let dir = std::env::temp_dir().join(format!("r2g-fingerprint-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let scene = root().join("gyms/pick_block_plate/scene.toml");
    let base = serde_json::json!({"profile": "simulation", "control": {"default_freq_hz": 20, "max_chunk_waypoints": 256,
        "max_joint_step_rad": 0.35, "max_tcp_step_m": 0.05, "max_tcp_step_rad": 0.35}, "franka": {"reflex_force_n": 30, "operator_force_n": 80}});
    let a = skills::fingerprint::of(&scene, &config(&dir, "a.json", base.clone())).expect("fingerprint");
    let mut other = base.clone();
    other["control"]["max_chunk_waypoints"] = 128.into();
    other["control"]["default_freq_hz"] = 10.into();
    other["franka"]["reflex_force_n"] = 25.into();
    let b = skills::fingerprint::of(&scene, &config(&dir, "b.json", other)).expect("fingerprint");
    assert_eq!(a, b, "unrelated keys changed the fingerprint");
    let mut franka = base.clone();
    franka["profile"] = "franka".into();
    let c = skills::fingerprint::of(&scene, &config(&dir, "c.json", franka)).expect("fingerprint");
    assert_eq!(a.kinematics, c.kinematics);
    assert_ne!(a.profile, c.profile);
    // Another arm description (the Robotiq hand moves the TCP): other kinematics and gripper.
    let robotiq = root().join("gyms/pick_block_plate/scene.toml");
    let text = std::fs::read_to_string(&robotiq).expect("scene").replace("panda.urdf", "panda_robotiq.urdf");
    let gym = dir.join("robotiq_gym");
    std::fs::create_dir_all(&gym).expect("dir");
    let scene2 = gym.join("scene.toml");
    std::fs::write(&scene2, text.replace("../../robots", &root().join("robots").display().to_string())).expect("write");
    let d = skills::fingerprint::of(&scene2, &config(&dir, "d.json", base)).expect("fingerprint");
    assert_ne!(a.kinematics, d.kinematics, "a different hand must change the kinematics");
    assert_eq!(d.gripper, "robotiq_2f85");
    let _ = std::fs::remove_dir_all(&dir);
}
