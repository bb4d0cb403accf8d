//! DROID raw episodes: a folder with `trajectory.h5` and `metadata_<uuid>.json` (the camera
//! recordings are not needed when the scene is given).
//!
//! Conventions of the source, converted here once ([`CONVENTIONS`]):
//! - `observation/robot_state/cartesian_position` (N, 6): x, y, z (m) and Euler angles "xyz"
//!   (extrinsic, scipy's lowercase: R = Rz(c)·Ry(b)·Rx(a)) of the **flange, `panda_link8`**, in
//!   the robot base `panda_link0`: DROID logs Polymetis' forward kinematics, whose end-effector
//!   link is `panda_link8` (no gripper offset). Our `link8`/`flange` frame is the same frame.
//! - `observation/robot_state/gripper_position` (N,): 1 − width / max width of the Robotiq
//!   2F-85 (0 open … 1 closed), measured; `action/gripper_position`, when present, is the
//!   commanded value on the same scale and is preferred (a held object stops the measured one;
//!   without a command, the import shuts the gripper over the measured opening's closed intervals).
//! - `observation/robot_state/joint_positions` (N, 7), rad, Franka joint order.
//! - `observation/timestamp/robot_state/robot_timestamp_{seconds,nanos}` (N,): the time base.
//! - `observation/camera_extrinsics/<serial>_left` (N, 6): the left image's optical frame
//!   (x right, y down, z forward), position and Euler "xyz" in the robot base.
//! - 15 Hz nominal.

use std::path::{Path, PathBuf};

use controllers::kinematics::to_arrays;
use controllers::RobotModel;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use crate::h5::H5;
use crate::record::{CameraTrack, Pose, Record, RobotTrack, Source};
use crate::{Error, Result};

pub const CONVENTIONS: [&str; 6] = [
    "cartesian_position: xyz (m) + Euler 'xyz' extrinsic (R = Rz·Ry·Rx, rad) of panda_link8 (the flange) in panda_link0 -> flange pose quaternion xyzw in the base frame",
    "gripper_position: 1 - width/max_width of the Robotiq 2F-85, 0 open .. 1 closed (action/gripper_position preferred: commanded) -> gripper_closed 0..1 as is; demo gripper = 2*closed - 1 from a command; from the measured opening +1 (shut) over its hysteresis-closed intervals (above 0.3, open below 0.15), 2*closed - 1 elsewhere",
    "joint_positions: rad, Franka joint order -> as is",
    "timestamp/robot_state: robot_timestamp_seconds + 1e-9*robot_timestamp_nanos -> seconds from the first frame",
    "camera_extrinsics/<serial>_left: xyz + Euler 'xyz' of the left optical frame (x right, y down, z forward) in panda_link0 -> base_from_optical quaternion xyzw",
    "rate: 15 Hz nominal -> resampled to the scene's demonstration rate without blending across gripper switches",
];

/// Largest accepted gap between our FK of the recorded joints and the recorded flange pose.
#[derive(Debug, Clone, Copy)]
pub struct FkGate {
    pub position_m: f64,
    pub rotation_rad: f64,
}

impl Default for FkGate {
    fn default() -> Self {
        Self { position_m: 0.01, rotation_rad: 0.05 }
    }
}

/// Our FK of the recorded joints against the recorded flange pose.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FkCheck {
    pub max_position_error_m: f64,
    pub mean_position_error_m: f64,
    pub max_rotation_error_rad: f64,
    pub mean_rotation_error_rad: f64,
    pub worst_frame: usize,
}

/// Euler "xyz" (extrinsic, as scipy's lowercase `as_euler("xyz")`) to a rotation.
pub fn euler_xyz(a: f64, b: f64, c: f64) -> UnitQuaternion<f64> {
    // nalgebra's roll-pitch-yaw is Rz(yaw)·Ry(pitch)·Rx(roll): the same composition.
    UnitQuaternion::from_euler_angles(a, b, c)
}

fn pose6(v: &[f64]) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), euler_xyz(v[3], v[4], v[5]))
}

/// The episode folder and its two files.
fn locate(episode: &Path) -> Result<(PathBuf, PathBuf)> {
    let dir = if episode.is_file() { episode.parent().unwrap_or(Path::new(".")).to_path_buf() } else { episode.into() };
    let traj = dir.join("trajectory.h5");
    if !traj.is_file() {
        return Err(Error::input(&dir.display().to_string(), "trajectory.h5", None, "missing from the episode folder"));
    }
    let mut metas: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map_err(Error::io(&dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("metadata_") && n.ends_with(".json"))
        })
        .collect();
    metas.sort();
    let meta = metas.into_iter().next().ok_or_else(|| {
        Error::input(&dir.display().to_string(), "metadata_*.json", None, "missing from the episode folder")
    })?;
    Ok((traj, meta))
}

/// Reads a DROID episode into the record, checking it against the robot: our FK of every
/// frame's joints against its recorded flange pose (`gate`), the joint limits and the
/// collision and workspace checks of the scene.
pub fn read(
    episode: &Path,
    robot: &RobotModel,
    safety: &controllers::safety::SafetyChecks,
    gate: FkGate,
) -> Result<(Record, FkCheck)> {
    let (traj, meta_path) = locate(episode)?;
    let meta_file = meta_path.display().to_string();
    let meta_text = std::fs::read_to_string(&meta_path).map_err(Error::io(&meta_path))?;
    let meta: serde_json::Value = serde_json::from_str(&meta_text)
        .map_err(|e| Error::input(&meta_file, "(file)", None, format!("not JSON: {e}")))?;
    let h5 = H5::read(&traj, &["observation/", "action/gripper_position"])?;
    let file = h5.file.clone();
    const JOINTS: &str = "observation/robot_state/joint_positions";
    const CART: &str = "observation/robot_state/cartesian_position";
    const GRIP: &str = "observation/robot_state/gripper_position";
    const GRIP_CMD: &str = "action/gripper_position";
    const SECS: &str = "observation/timestamp/robot_state/robot_timestamp_seconds";
    const NANOS: &str = "observation/timestamp/robot_state/robot_timestamp_nanos";
    let joints = h5.rows(JOINTS, &[7], None)?;
    let n = joints.len();
    if n < 2 {
        return Err(Error::input(&file, JOINTS, None, format!("{n} frames; a demonstration needs at least 2")));
    }
    if let Some(len) = meta.get("trajectory_length").and_then(|v| v.as_u64()) {
        if len as usize != n {
            return Err(Error::input(
                &meta_file,
                "trajectory_length",
                None,
                format!("{len}, but {file} holds {n} frames in {JOINTS}"),
            ));
        }
    }
    let cart = h5.rows(CART, &[6], Some(n))?;
    let (grip_field, grip) =
        if h5.has(GRIP_CMD) { (GRIP_CMD, h5.column(GRIP_CMD, Some(n))?) } else { (GRIP, h5.column(GRIP, Some(n))?) };
    let secs = h5.column(SECS, Some(n))?;
    let nanos = h5.column(NANOS, Some(n))?;
    // Seconds since the first frame, differenced before adding so no precision is lost.
    let stamps: Vec<f64> = secs.iter().zip(&nanos).map(|(s, ns)| (s - secs[0]) + 1e-9 * (ns - nanos[0])).collect();
    let mut t_s = Vec::with_capacity(n);
    for (k, &s) in stamps.iter().enumerate() {
        if k > 0 && s <= stamps[k - 1] {
            return Err(Error::input(
                &file,
                SECS,
                Some(k),
                format!(
                    "time does not increase: {:.6} s after {:.6} s at frame {} (timestamps must be strictly increasing)",
                    s,
                    stamps[k - 1],
                    k - 1
                ),
            ));
        }
        t_s.push(s);
    }
    for (k, g) in grip.iter().enumerate() {
        if !(-0.05..=1.05).contains(g) {
            return Err(Error::input(&file, grip_field, Some(k), format!("{g} is outside 0 (open) .. 1 (closed)")));
        }
    }
    // Limits, collisions, workspace: name the first frame the robot cannot take.
    let mut joints_rad = Vec::with_capacity(n);
    for (k, row) in joints.iter().enumerate() {
        let q: [f64; 7] = std::array::from_fn(|j| row[j]);
        for (j, lim) in robot.joints.iter().enumerate() {
            if !(lim.q_min_rad..=lim.q_max_rad).contains(&q[j]) {
                return Err(Error::input(
                    &file,
                    JOINTS,
                    Some(k),
                    format!(
                        "joint {} = {:.4} rad is outside the {} limits [{:.4}, {:.4}]: unreachable for this robot",
                        j + 1,
                        q[j],
                        robot.profile.name(),
                        lim.q_min_rad,
                        lim.q_max_rad
                    ),
                ));
            }
        }
        if let Err(v) = safety.check(&q) {
            return Err(Error::input(
                &file,
                JOINTS,
                Some(k),
                format!("the scene's checks refuse this configuration: {v}"),
            ));
        }
        joints_rad.push(q);
    }
    // The FK gate: is the recorded pose the flange of this arm at these joints?
    let flange = robot.kin.flange;
    let (mut max_p, mut sum_p, mut max_r, mut sum_r, mut worst, mut worst_past) = (0.0f64, 0.0, 0.0f64, 0.0, 0, -1.0);
    let mut base_from_flange = Vec::with_capacity(n);
    for (k, (q, c)) in joints_rad.iter().zip(&cart).enumerate() {
        let recorded = pose6(c);
        let ours = robot.kin.fk(q, flange);
        let dp = (ours.translation.vector - recorded.translation.vector).norm();
        let dr = ours.rotation.angle_to(&recorded.rotation);
        // The worst frame is the one furthest past the gate, in position or rotation.
        let past = (dp / gate.position_m).max(dr / gate.rotation_rad);
        if past > worst_past {
            (worst, worst_past) = (k, past);
        }
        max_p = max_p.max(dp);
        max_r = max_r.max(dr);
        sum_p += dp;
        sum_r += dr;
        base_from_flange.push(Pose::from_iso(&recorded));
    }
    let fk = FkCheck {
        max_position_error_m: max_p,
        mean_position_error_m: sum_p / n as f64,
        max_rotation_error_rad: max_r,
        mean_rotation_error_rad: sum_r / n as f64,
        worst_frame: worst,
    };
    if max_p > gate.position_m || max_r > gate.rotation_rad {
        let (p, _) = to_arrays(&robot.kin.fk(&joints_rad[worst], flange));
        return Err(Error::input(
            &file,
            CART,
            Some(worst),
            format!(
                "our FK of {JOINTS} puts the flange at {p:.4?}, {:.1} mm / {:.2} deg from the recorded pose (gate {:.0} mm / {:.2} deg): \
                 the episode's arm is not the scene's, or the pose is not panda_link8's",
                max_p * 1e3,
                max_r.to_degrees(),
                gate.position_m * 1e3,
                gate.rotation_rad.to_degrees()
            ),
        ));
    }
    // Cameras: per-frame extrinsics, named by the metadata's serial roles when it has them.
    let mut cameras = Vec::new();
    for field in h5.names_under("observation/camera_extrinsics/") {
        let Some(leaf) = field.rsplit('/').next() else { continue };
        let Some(serial) = leaf.strip_suffix("_left") else { continue };
        let role = ["ext1_cam_serial", "ext2_cam_serial", "wrist_cam_serial"]
            .iter()
            .find(|k| {
                meta.get(**k).map(|v| v.as_str().map(String::from).unwrap_or(v.to_string())) == Some(serial.into())
            })
            .map(|k| k.trim_end_matches("_cam_serial").to_string())
            .unwrap_or_else(|| serial.to_string());
        let rows = h5.rows(&field, &[6], Some(n))?;
        cameras.push(CameraTrack {
            name: role,
            intrinsics: None,
            base_from_optical: rows.iter().map(|r| Pose::from_iso(&pose6(r))).collect(),
        });
    }
    let task = meta
        .get("current_task")
        .and_then(|v| v.as_str())
        .map(String::from)
        .or_else(|| h5.attr_text("current_task"))
        .unwrap_or_default();
    let record = Record {
        source: Source {
            kind: "droid".into(),
            files: vec![file, meta_file],
            task,
            rate_hz: 15.0,
            conventions: CONVENTIONS.iter().map(|s| s.to_string()).collect(),
            registration: None,
            frames: (0..n).collect(),
        },
        t_s,
        cameras,
        robot: Some(RobotTrack {
            joints_rad,
            base_from_flange,
            gripper_closed: grip.iter().map(|g| g.clamp(0.0, 1.0)).collect(),
            gripper_source: grip_field.into(),
        }),
        hand: None,
    };
    record.check()?;
    Ok((record, fk))
}
