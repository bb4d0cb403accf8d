//! The one demonstration record every source is imported into. Conventions are ours, fixed
//! here once: SI units, times in seconds from the first kept frame, poses in the robot base
//! frame (x forward, y left, z up), quaternions (x, y, z, w), camera poses of the optical frame
//! (x right, y down, z forward), the gripper as the fraction closed (0 open … 1 closed). Each
//! importer converts its source's conventions into these in one function and writes which ones
//! it converted into [`Source::conventions`].

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::Error;

/// A rigid pose: position (m) and orientation quaternion (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position_m: [f64; 3],
    pub quat_xyzw: [f64; 4],
}

impl Pose {
    pub fn iso(&self) -> Isometry3<f64> {
        let [x, y, z, w] = self.quat_xyzw;
        Isometry3::from_parts(
            Translation3::new(self.position_m[0], self.position_m[1], self.position_m[2]),
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)),
        )
    }

    pub fn from_iso(t: &Isometry3<f64>) -> Self {
        let q = t.rotation.quaternion();
        let v = t.translation.vector;
        Self { position_m: [v.x, v.y, v.z], quat_xyzw: [q.i, q.j, q.k, q.w] }
    }
}

/// Pinhole intrinsics, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

/// One camera of the source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraTrack {
    pub name: String,
    /// Absent when the source does not record them (DROID keeps them in its video files).
    pub intrinsics: Option<Intrinsics>,
    /// Pose of the optical frame in the robot base frame: one per frame, or one for a fixed camera.
    pub base_from_optical: Vec<Pose>,
}

impl CameraTrack {
    /// Pixel (u right, v down) of a point given in the robot base frame at `frame`, or None when
    /// the point is behind the camera or the intrinsics are unknown.
    pub fn project(&self, frame: usize, point_in_base: [f64; 3]) -> Option<[f64; 2]> {
        let k = self.intrinsics?;
        let pose = self.base_from_optical.get(frame).or(self.base_from_optical.first())?;
        let p = pose.iso().inverse() * Point3::from(point_in_base);
        if p.z <= 1e-9 {
            return None;
        }
        Some([k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy])
    }
}

/// A robot's recorded state per frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotTrack {
    pub joints_rad: Vec<[f64; 7]>,
    /// The flange (link8) pose in the base frame as the source recorded it; empty when absent.
    pub base_from_flange: Vec<Pose>,
    /// 0 open … 1 closed, per frame.
    pub gripper_closed: Vec<f64>,
    /// Where `gripper_closed` came from (the command, or the measured opening).
    pub gripper_source: String,
}

/// A tracked human hand per frame: the three points the pinch frame is built from, in the
/// robot base frame (after registration), and the least confidence of the three.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HandTrack {
    /// `left` or `right`.
    pub side: String,
    pub thumb_tip_m: Vec<[f64; 3]>,
    pub index_tip_m: Vec<[f64; 3]>,
    pub index_knuckle_m: Vec<[f64; 3]>,
    /// 0 … 1; frames below the importer's threshold are dropped before retargeting.
    pub confidence: Vec<f64>,
}

/// How the source's world frame was tied to the robot base.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Registration {
    /// Row-major 4×4.
    pub base_from_world: [[f64; 4]; 4],
    /// `given` (a file from the user) or `estimated` (see `how`).
    pub kind: String,
    pub how: String,
    /// Least-squares residual of the estimate, m (0 when given).
    pub residual_m: f64,
}

/// Where the record came from and what was converted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Source {
    /// `droid` or `egodex`.
    pub kind: String,
    pub files: Vec<String>,
    /// The task as the source states it.
    pub task: String,
    /// The source's nominal frame rate, Hz.
    pub rate_hz: f64,
    /// Every convention of the source and what it was converted to, one sentence each.
    pub conventions: Vec<String>,
    pub registration: Option<Registration>,
    /// Source frames kept, by index into the source's arrays (low-confidence frames dropped).
    pub frames: Vec<usize>,
}

/// The demonstration record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub source: Source,
    /// Seconds from the first kept frame, strictly increasing.
    pub t_s: Vec<f64>,
    pub cameras: Vec<CameraTrack>,
    pub robot: Option<RobotTrack>,
    pub hand: Option<HandTrack>,
}

impl Record {
    /// Checks the shapes every consumer relies on: one entry per frame in every track.
    pub fn check(&self) -> Result<(), Error> {
        let n = self.t_s.len();
        let bad = |field: &str, got: usize| Error::Input {
            file: self.source.files.first().cloned().unwrap_or_default(),
            field: field.into(),
            frame: None,
            why: format!("{got} entries, the time base has {n}"),
        };
        if let Some(r) = &self.robot {
            for (f, len) in [("joints", r.joints_rad.len()), ("gripper", r.gripper_closed.len())] {
                if len != n {
                    return Err(bad(f, len));
                }
            }
            if !r.base_from_flange.is_empty() && r.base_from_flange.len() != n {
                return Err(bad("cartesian pose", r.base_from_flange.len()));
            }
        }
        if let Some(h) = &self.hand {
            for (f, len) in [
                ("thumb tip", h.thumb_tip_m.len()),
                ("index tip", h.index_tip_m.len()),
                ("index knuckle", h.index_knuckle_m.len()),
                ("confidence", h.confidence.len()),
            ] {
                if len != n {
                    return Err(bad(f, len));
                }
            }
        }
        for c in &self.cameras {
            if c.base_from_optical.len() != n && c.base_from_optical.len() != 1 {
                return Err(bad(&format!("camera {}", c.name), c.base_from_optical.len()));
            }
        }
        Ok(())
    }
}

/// Rotation of `angle_rad` about the unit `axis`.
pub fn axis_angle(axis: Vector3<f64>, angle_rad: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle_rad)
}

/// Row-major 4×4 of an isometry.
pub fn matrix_of(t: &Isometry3<f64>) -> [[f64; 4]; 4] {
    let m = t.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// The isometry of a row-major 4×4 (its rotation block re-orthonormalised), or why not.
pub fn iso_of(m: &[[f64; 4]; 4]) -> Result<Isometry3<f64>, String> {
    if !m.iter().flatten().all(|v| v.is_finite()) {
        return Err("not finite (NaN or infinity)".into());
    }
    if (m[3][0].abs() + m[3][1].abs() + m[3][2].abs() + (m[3][3] - 1.0).abs()) > 1e-6 {
        return Err(format!("last row is {:?}, not [0, 0, 0, 1]", m[3]));
    }
    let r = nalgebra::Matrix3::from_fn(|i, j| m[i][j]);
    let det = r.determinant();
    if (det - 1.0).abs() > 1e-3 {
        return Err(format!("rotation block has determinant {det:.4}, not 1 (not a rigid transform)"));
    }
    let rot = UnitQuaternion::from_matrix(&r);
    Ok(Isometry3::from_parts(Translation3::new(m[0][3], m[1][3], m[2][3]), rot))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_in_front_of_a_camera_projects_to_its_centre_and_behind_it_to_nothing() {
        // Optical z along base x: a camera at the origin looking forward, image x along -y.
        let base_from_optical = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_matrix(&nalgebra::Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0)),
        );
        let cam = CameraTrack {
            name: "c".into(),
            intrinsics: Some(Intrinsics { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }),
            base_from_optical: vec![Pose::from_iso(&base_from_optical)],
        };
        let uv = cam.project(0, [2.0, 0.0, 0.0]).expect("in front");
        assert!((uv[0] - 320.0).abs() < 1e-9 && (uv[1] - 240.0).abs() < 1e-9);
        // Left of the camera (base +y) is image left (u smaller); up (base +z) is image up.
        let left = cam.project(0, [2.0, 0.1, 0.0]).expect("in front");
        let up = cam.project(0, [2.0, 0.0, 0.1]).expect("in front");
        assert!(left[0] < 320.0 && up[1] < 240.0, "{left:?} {up:?}");
        assert!(cam.project(0, [-1.0, 0.0, 0.0]).is_none());
    }

    #[test]
    fn matrices_must_be_rigid() {
        let t = Isometry3::from_parts(Translation3::new(0.1, 0.2, 0.3), axis_angle(Vector3::z(), 0.7));
        let back = iso_of(&matrix_of(&t)).expect("rigid");
        assert!((back.translation.vector - t.translation.vector).norm() < 1e-12);
        let mut m = matrix_of(&t);
        m[0][0] *= 2.0;
        assert!(iso_of(&m).expect_err("scaled").contains("determinant"));
        m[0][0] = f64::NAN;
        assert!(iso_of(&m).expect_err("nan").contains("not finite"));
    }
}
