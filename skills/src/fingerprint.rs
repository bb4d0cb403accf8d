//! What a skill depends on, hashed: the arm's kinematics (TCP poses at fixed joint
//! configurations, rounded to 0.1 mm / 1e-4, and the joint position limits), the gripper and the
//! profile. Changing an unrelated key of config/robot.json (a chunk cap, a camera) leaves it
//! alone; a different arm, TCP or gripper changes it.

use std::path::Path;

use anyhow::Context;
use sha2::{Digest, Sha256};

use crate::format::Fingerprint;

/// Joint configurations the kinematics are sampled at (inside both Panda and FR3 limits).
const CONFIGS: [[f64; 7]; 4] = [
    [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785],
    [0.5, -0.3, 0.4, -1.8, 0.3, 1.9, -0.4],
    [-0.7, 0.2, -0.5, -2.6, -0.6, 2.4, 1.2],
    [1.2, -1.0, 0.9, -1.2, 1.0, 1.2, 0.0],
];

fn gripper_name(urdf_hand: &str, config: &runtime::robot_config::RobotConfig) -> String {
    use runtime::robot_config::Gripper;
    match &config.gripper {
        Gripper::Robotiq2f85(_) => "robotiq_2f85".into(),
        Gripper::FrankaHand => "franka_hand".into(),
        // The robot side's own fingers: the description says which hand they are.
        Gripper::Sim => urdf_hand.into(),
    }
}

/// The fingerprint of the robot `scene` describes under `robot_config`.
pub fn of(scene: &Path, robot_config: &Path) -> anyhow::Result<Fingerprint> {
    let (model, _) = runtime::scene_robot(scene)?;
    let config = runtime::robot_config::RobotConfig::load(robot_config)
        .with_context(|| format!("reading the robot config {}", robot_config.display()))?;
    let mut h = Sha256::new();
    // Tenths of a millimetre / 1e-4, with -0 written as 0.
    let r4 = |v: f64| format!("{}", (v * 1e4).round() as i64);
    for q in CONFIGS {
        let t = model.kin.fk(&q, model.kin.tcp);
        for v in t.translation.vector.iter().chain(t.rotation.coords.iter().map(|c| c.abs()).collect::<Vec<_>>().iter())
        {
            h.update(r4(*v).as_bytes());
        }
    }
    for j in &model.joints {
        h.update(format!("{}:{}", r4(j.q_min_rad), r4(j.q_max_rad)).as_bytes());
    }
    let hand = if model.name.to_lowercase().contains("robotiq") || scene_mentions(scene, "robotiq") {
        "robotiq_2f85"
    } else {
        "franka_hand"
    };
    Ok(Fingerprint {
        kinematics: format!("{:x}", h.finalize()),
        gripper: gripper_name(hand, &config),
        profile: format!("{:?}", config.profile).to_lowercase(),
    })
}

fn scene_mentions(scene: &Path, word: &str) -> bool {
    std::fs::read_to_string(scene).map(|t| t.to_lowercase().contains(word)).unwrap_or(false)
}
