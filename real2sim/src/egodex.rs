//! EgoDex episodes: one HDF5 file per episode (the video beside it is not needed here).
//!
//! Conventions of the source, converted here once ([`CONVENTIONS`]):
//! - `transforms/<joint>` (N, 4, 4): world-from-joint poses in ARKit's world: metres, right
//!   handed, **y up** (gravity along −y), origin and heading wherever the session started.
//! - `transforms/camera` (N, 4, 4): world-from-camera in ARKit's camera convention (x right,
//!   y up, looking along −z); our optical frame (x right, y down, z forward) is that turned half
//!   a turn about x.
//! - `camera/intrinsic` (3, 3): pinhole K in pixels of the 1920×1080 video; the image size is
//!   taken as twice the principal point.
//! - `confidences/<joint>` (N,): ARKit's tracking confidence, 0 … 1 (absent: 1).
//! - Root attribute `llm_description` (or `llm_description2` when `which_llm_description` is 2):
//!   the task.
//! - 30 Hz, no timestamps: frame k is at k / 30 s.
//! - There are no object poses and the ARKit origin is arbitrary: the world → robot-base
//!   registration is given by the user or estimated ([`crate::retarget::estimate_registration`]).

use std::path::Path;

use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion};

use crate::h5::H5;
use crate::record::{CameraTrack, Intrinsics, Pose};
use crate::{Error, Result};

pub const RATE_HZ: f64 = 30.0;

pub const CONVENTIONS: [&str; 6] = [
    "transforms/<joint>: world_from_joint 4x4 in ARKit's world (m, y up, arbitrary origin and heading) -> points in the robot base through the registration",
    "transforms/camera: world_from_camera in ARKit's camera convention (x right, y up, looking along -z) -> optical frame (x right, y down, z forward) = camera * Rx(pi)",
    "camera/intrinsic: 3x3 K in pixels -> fx, fy, cx, cy; image size 2*cx x 2*cy",
    "confidences/<joint>: 0..1 -> frames whose pinch points fall below the threshold are dropped",
    "llm_description (or llm_description2 when which_llm_description == 2) -> task",
    "rate: 30 Hz, frame k at k/30 s -> resampled to the scene's demonstration rate without blending across gripper switches",
];

/// The three joints the pinch frame is built from, by hand.
pub fn pinch_joints(side: &str) -> [String; 3] {
    [format!("{side}ThumbTip"), format!("{side}IndexFingerTip"), format!("{side}IndexFingerKnuckle")]
}

/// What an EgoDex file holds for one hand, still in ARKit's world.
#[derive(Debug, Clone)]
pub struct HandInWorld {
    pub file: String,
    pub side: String,
    pub task: String,
    /// Thumb tip, index tip, index knuckle per frame (NaN where the file has none).
    pub points: Vec<[[f64; 3]; 3]>,
    /// Least confidence of the three points per frame.
    pub confidence: Vec<f64>,
    /// Which joint was least confident, per frame (for messages).
    pub weakest: Vec<usize>,
    pub intrinsics: Intrinsics,
    /// World-from-optical per frame.
    pub world_from_optical: Vec<Isometry3<f64>>,
}

fn iso_rows(rows: &[f64]) -> Option<Isometry3<f64>> {
    let m: [[f64; 4]; 4] = std::array::from_fn(|r| std::array::from_fn(|c| rows[4 * r + c]));
    crate::record::iso_of(&m).ok()
}

/// Reads the hands of an EgoDex file: `side` is `left`, `right`, or `auto` (the hand with the
/// most confident frames among those whose pinch opens and closes by at least 1 cm; the right
/// one on a tie).
pub fn read(path: &Path, side: &str, min_confidence: f64) -> Result<HandInWorld> {
    let h5 = H5::read(path, &["transforms/", "confidences/", "camera/"])?;
    let file = h5.file.clone();
    let k = h5.rows("camera/intrinsic", &[3], Some(3))?;
    let (fx, fy, cx, cy) = (k[0][0], k[1][1], k[0][2], k[1][2]);
    if !(fx > 0.0 && fy > 0.0 && cx > 0.0 && cy > 0.0) {
        return Err(Error::input(
            &file,
            "camera/intrinsic",
            None,
            "focal lengths and principal point must be positive",
        ));
    }
    let intrinsics = Intrinsics { fx, fy, cx, cy, width: (2.0 * cx).round() as u32, height: (2.0 * cy).round() as u32 };
    let cam = h5.rows("transforms/camera", &[4, 4], None)?;
    let n = cam.len();
    let mut world_from_optical = Vec::with_capacity(n);
    let flip = UnitQuaternion::from_axis_angle(&nalgebra::Vector3::x_axis(), std::f64::consts::PI);
    for (f, rows) in cam.iter().enumerate() {
        let m = iso_rows(rows).ok_or_else(|| {
            Error::input(&file, "transforms/camera", Some(f), "not a rigid transform (rotation block not orthonormal)")
        })?;
        world_from_optical.push(m * flip);
    }
    let sides: Vec<&str> = match side {
        "auto" => vec!["right", "left"],
        "left" | "right" => vec![side],
        other => {
            return Err(Error::input(&file, "--hand", None, format!("'{other}': accepted are left, right or auto")))
        }
    };
    let mut best: Option<HandInWorld> = None;
    let mut best_score = -1.0;
    let mut first_unseen = None;
    for s in sides {
        match read_side(&h5, s, n, min_confidence) {
            // A hand out of view: try the other one. Anything else is the file's fault.
            Err(Side::Unseen(e)) => {
                first_unseen.get_or_insert(e);
            }
            Err(Side::Bad(e)) => return Err(e),
            Ok(hand) => {
                let seen = hand.confidence.iter().filter(|c| **c >= min_confidence).count() as f64;
                let apertures: Vec<f64> = hand
                    .points
                    .iter()
                    .zip(&hand.confidence)
                    .filter(|(_, c)| **c >= min_confidence)
                    .map(|(p, _)| dist(p[0], p[1]))
                    .collect();
                let lo = apertures.iter().cloned().fold(f64::INFINITY, f64::min);
                let hi = apertures.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let score = seen * if hi - lo >= 0.01 { 1.0 } else { 0.1 };
                if score > best_score {
                    best_score = score;
                    best = Some(HandInWorld { intrinsics, world_from_optical: world_from_optical.clone(), ..hand });
                }
            }
        }
    }
    let mut hand = match (best, first_unseen) {
        (Some(h), _) => h,
        (None, Some(e)) => return Err(e),
        (None, None) => return Err(Error::input(&file, "transforms", None, "no hand found")),
    };
    hand.task = match h5.attrs.get("which_llm_description").and_then(|v| v.as_f64()) {
        Some(w) if w == 2.0 => h5.attr_text("llm_description2"),
        _ => h5.attr_text("llm_description"),
    }
    .unwrap_or_default();
    Ok(hand)
}

/// Why a hand could not be read: out of view, or a fault of the file.
enum Side {
    Unseen(Error),
    Bad(Error),
}

impl From<Error> for Side {
    fn from(e: Error) -> Self {
        Side::Bad(e)
    }
}

fn read_side(h5: &H5, side: &str, n: usize, min_confidence: f64) -> std::result::Result<HandInWorld, Side> {
    let file = &h5.file;
    let joints = pinch_joints(side);
    let mut points = vec![[[f64::NAN; 3]; 3]; n];
    let mut confidence = vec![1.0f64; n];
    let mut weakest = vec![0usize; n];
    for (j, name) in joints.iter().enumerate() {
        let tf_field = format!("transforms/{name}");
        let conf_field = format!("confidences/{name}");
        let conf = if h5.has(&conf_field) { h5.rows_lenient(&conf_field, &[], Some(n))? } else { vec![vec![1.0]; n] };
        let tf = h5.rows_lenient(&tf_field, &[4, 4], Some(n))?;
        for f in 0..n {
            let c = if conf[f][0].is_finite() { conf[f][0] } else { 0.0 };
            if c < confidence[f] {
                confidence[f] = c;
                weakest[f] = j;
            }
            let rows = &tf[f];
            if rows.iter().all(|v| v.is_finite()) {
                points[f][j] = [rows[3], rows[7], rows[11]];
            } else if c >= min_confidence {
                return Err(Side::Bad(Error::input(
                    file,
                    &tf_field,
                    Some(f),
                    format!("NaN or infinite pose with confidence {c:.2}"),
                )));
            } else {
                // Untracked: the frame is dropped below.
                confidence[f] = 0.0;
                weakest[f] = j;
            }
        }
    }
    let seen = confidence.iter().filter(|c| **c >= min_confidence).count();
    if seen < 5.max(n / 20) {
        let field = format!("confidences/{}", joints[weakest.iter().copied().max().unwrap_or(0)]);
        return Err(Side::Unseen(Error::input(
            file,
            &field,
            None,
            format!(
                "the {side} hand is never seen: {seen} of {n} frames have all of {} at confidence >= {min_confidence}",
                joints.join(", ")
            ),
        )));
    }
    Ok(HandInWorld {
        file: file.clone(),
        side: side.into(),
        task: String::new(),
        points,
        confidence,
        weakest,
        intrinsics: Intrinsics { fx: 1.0, fy: 1.0, cx: 1.0, cy: 1.0, width: 2, height: 2 },
        world_from_optical: Vec::new(),
    })
}

pub fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    (Point3::from(a) - Point3::from(b)).norm()
}

/// The rotation that takes ARKit's y-up world to a z-up one (x kept, y → z, z → −y).
pub fn z_up_from_arkit() -> UnitQuaternion<f64> {
    UnitQuaternion::from_matrix(&Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0))
}

/// Camera track in the robot base for the frames kept.
pub fn camera_track(hand: &HandInWorld, base_from_world: &Isometry3<f64>, frames: &[usize]) -> CameraTrack {
    CameraTrack {
        name: "egocentric".into(),
        intrinsics: Some(hand.intrinsics),
        base_from_optical: frames
            .iter()
            .map(|&f| Pose::from_iso(&(base_from_world * hand.world_from_optical[f])))
            .collect(),
    }
}

/// An isometry from a translation and a rotation.
pub fn iso(t: [f64; 3], r: UnitQuaternion<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), r)
}
