//! A human hand retargeted to a parallel gripper, and TCP paths solved into joint rows.
//!
//! - **Pinch frame** from the thumb tip T, the index tip I and the index knuckle K: origin at
//!   the middle of T and I; y (the fingers' closing axis) from T to I; z (the approach) from K
//!   towards the origin, made perpendicular to y; x = y × z. Our TCP has the same axes (z out of
//!   the hand, fingers moving along y), so the TCP is put at the pinch frame. The two signs of y
//!   grip alike: the one nearer the previous frame is taken (the first frame: the one whose IK
//!   solution is nearer the scene's start joints).
//! - **Aperture** |I − T| with hysteresis: closed below `close_fraction` of the way from the
//!   episode's small (2nd percentile of the smoothed aperture) to its large (98th) aperture,
//!   open again above `open_fraction`; a state lasting less than `min_state_s` is ignored;
//!   each switch then moves back to where the (smoothed) aperture began to fall or rise. Under 1 cm between the two:
//!   the hand never grasps. Closed is +1; open, the gripper follows the smoothed aperture's
//!   place between the two (−1 wide open … 0 half way; the widest of the next 0.3 s, so a
//!   release opens at once), so a part-open hand stays part open.
//! - Frames whose three points are not all at `min_confidence` are dropped, never interpolated
//!   from; the resampling interpolates between the kept frames around them.
//! - **Registration** (ARKit world → robot base): given (`--registration`, a 4×4), or estimated:
//!   gravity from ARKit's y-up world; heading and position by fitting the pinch point at the
//!   first grasp onset to the centre of the task's object (`gym::roles`; at 1.5 cm below its
//!   top, or its middle when lower) and the pinch point at
//!   the following release to the centre of its target (cavity centre when it has one), in the
//!   horizontal plane; height from the grasp point. It needs a grasp and a release; a residual
//!   over 5 cm means the demonstration does not fit the scene and is refused.
//! - **Object-relative**: the motion is kept relative to what it acts on: the anchors (the
//!   object up to its grasp, the target from the release) are written into `events.json`, and
//!   augmentation re-solves the motion against moved anchors with the same IK.
//! - **IK** row by row with the project's solver (joint limits shrunk by 0.05 rad, 0.5 mm and
//!   0.005 rad tolerances), seeded by the previous row; every row must pass the scene's
//!   collision and workspace checks (a pose that would bring the gripper within the margin + 3 mm of
//!   the table is raised by up to 1 cm first: a human hand may rest on it) and move no joint more than
//!   0.25 rad from the row before.

use controllers::safety::SafetyChecks;
use controllers::{IkConfig, IkSolver, RobotModel, Violation};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::egodex::{self, HandInWorld};
use crate::record::{HandTrack, Record, Registration, Source};
use crate::resample;
use crate::{Error, Result};

#[derive(Debug, Clone, Copy)]
pub struct HandParams {
    pub min_confidence: f64,
    pub min_state_s: f64,
    pub close_fraction: f64,
    pub open_fraction: f64,
    /// Pinch poses are averaged over this much time either side (within one gripper state).
    pub smooth_half_window_s: f64,
}

impl Default for HandParams {
    fn default() -> Self {
        Self {
            min_confidence: 0.5,
            min_state_s: 0.15,
            close_fraction: 0.35,
            open_fraction: 0.65,
            smooth_half_window_s: 0.1,
        }
    }
}

/// The pinch frame and the aperture of three points, or None when they are degenerate.
pub fn pinch_frame(thumb: [f64; 3], index: [f64; 3], knuckle: [f64; 3]) -> Option<(Isometry3<f64>, f64)> {
    let (t, i, k) = (Point3::from(thumb), Point3::from(index), Point3::from(knuckle));
    let origin = Point3::from(0.5 * (t.coords + i.coords));
    let across = i - t;
    let aperture = across.norm();
    if aperture < 1e-4 {
        return None;
    }
    let y = across / aperture;
    let toward = origin - k;
    let z = toward - toward.dot(&y) * y;
    if z.norm() < 1e-4 {
        return None;
    }
    let z = z.normalize();
    let x = y.cross(&z);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Some((Isometry3::from_parts(Translation3::from(origin.coords), UnitQuaternion::from_rotation_matrix(&r)), aperture))
}

/// The kept frames of a hand: pinch frames in the source world, apertures, gripper states.
#[derive(Debug, Clone)]
pub struct Pinches {
    /// Source frame indices kept.
    pub frames: Vec<usize>,
    /// Source time of each kept frame (k / rate).
    pub t_s: Vec<f64>,
    pub world_from_pinch: Vec<Isometry3<f64>>,
    pub aperture_m: Vec<f64>,
    pub closed: Vec<bool>,
    /// The gripper per kept frame: +1 closed; open, the smoothed aperture's place between the
    /// episode's small and large aperture (−1 wide open … 0 half way), so a part-open hand
    /// stays part open.
    pub gripper: Vec<f64>,
    pub close_below_m: f64,
    pub open_above_m: f64,
}

impl Pinches {
    /// (index into the kept frames at which the gripper closes, index at which it opens again).
    pub fn grasps(&self) -> Vec<(usize, Option<usize>)> {
        let mut out = Vec::new();
        let mut start = None;
        for k in 0..self.closed.len() {
            match (start, self.closed[k]) {
                (None, true) => start = Some(k),
                (Some(s), false) => {
                    out.push((s, Some(k)));
                    start = None;
                }
                _ => {}
            }
        }
        if let Some(s) = start {
            out.push((s, None));
        }
        out
    }
}

pub fn pinches(hand: &HandInWorld, p: HandParams, rate_hz: f64) -> Result<Pinches> {
    let mut frames = Vec::new();
    let mut t_s = Vec::new();
    let mut world_from_pinch = Vec::new();
    let mut aperture_m = Vec::new();
    for (f, (pts, c)) in hand.points.iter().zip(&hand.confidence).enumerate() {
        if *c < p.min_confidence {
            continue;
        }
        if let Some((pose, a)) = pinch_frame(pts[0], pts[1], pts[2]) {
            frames.push(f);
            t_s.push(f as f64 / rate_hz);
            world_from_pinch.push(pose);
            aperture_m.push(a);
        }
    }
    let joints = egodex::pinch_joints(&hand.side);
    if frames.len() < 5 {
        return Err(Error::input(
            &hand.file,
            &format!("transforms/{}", joints.join("+")),
            None,
            format!("only {} frames give a pinch frame; the hand is never seen well enough", frames.len()),
        ));
    }
    let smooth = smoothed(&aperture_m, &t_s, p.smooth_half_window_s);
    // The hand's own small and large aperture: near the extremes of the smoothed aperture, so a
    // hand closed (or open) nearly all the time still shows both.
    let mut sorted = smooth.clone();
    sorted.sort_by(f64::total_cmp);
    let pct = |q: f64| sorted[((sorted.len() - 1) as f64 * q).round() as usize];
    let (small, large) = (pct(0.02), pct(0.98));
    let (close_below_m, open_above_m, closed) = if large - small < 0.01 {
        (f64::NAN, f64::NAN, vec![false; aperture_m.len()])
    } else {
        let close = small + p.close_fraction * (large - small);
        let open = small + p.open_fraction * (large - small);
        // Closedness rises as the aperture falls: hysteresis on the negated aperture.
        let neg: Vec<f64> = aperture_m.iter().map(|a| -a).collect();
        let raw = resample::hysteresis(&neg, -close, -open);
        let mut closed = resample::debounce(&raw, &t_s, p.min_state_s);
        onsets(&mut closed, &smooth);
        (close, open, closed)
    };
    // Open: where the hand is opening to (the widest smoothed aperture of the next 0.3 s of the
    // same state), so a release opens the gripper at once rather than along the hand's ramp.
    let gripper = (0..closed.len())
        .map(|k| {
            if closed[k] {
                return 1.0;
            }
            if large - small < 0.01 {
                return -1.0;
            }
            let a = (k..closed.len())
                .take_while(|&j| !closed[j] && t_s[j] - t_s[k] <= 0.3)
                .map(|j| smooth[j])
                .fold(smooth[k], f64::max);
            (1.0 - 2.0 * (a - small) / (large - small)).clamp(-1.0, 0.0)
        })
        .collect();
    Ok(Pinches { frames, t_s, world_from_pinch, aperture_m, closed, gripper, close_below_m, open_above_m })
}

/// Moves each switch back to where the hand began to close (or open): the start of the run
/// over which the smoothed aperture kept falling (rising) by more than 1 mm a frame. The
/// thresholds say that the hand closed; this says when it started to.
fn onsets(closed: &mut [bool], smooth: &[f64]) {
    let n = closed.len();
    let mut last = 0;
    for k in 1..n {
        if closed[k] == closed[k - 1] {
            continue;
        }
        let sign = if closed[k] { 1.0 } else { -1.0 };
        let mut j = k;
        while j > last + 1 && sign * (smooth[j - 1] - smooth[j]) > 1e-3 {
            j -= 1;
        }
        let state = closed[k];
        closed[j..k].iter_mut().for_each(|c| *c = state);
        last = k;
    }
}

/// Each value averaged with those within `half_window_s` of it.
fn smoothed(v: &[f64], t_s: &[f64], half_window_s: f64) -> Vec<f64> {
    (0..v.len())
        .map(|k| {
            let near: Vec<f64> =
                (0..v.len()).filter(|&j| (t_s[j] - t_s[k]).abs() <= half_window_s).map(|j| v[j]).collect();
            near.iter().sum::<f64>() / near.len() as f64
        })
        .collect()
}

/// Estimates base-from-world (see the module notes) from the first grasp and release.
pub fn estimate_registration(
    file: &str,
    scene: &sim_host::Scene,
    pinches: &Pinches,
) -> Result<(Isometry3<f64>, Registration)> {
    let roles = crate::gym::roles(scene);
    let why_not = |why: String| Error::input(file, "transforms (registration)", None, why);
    let (Some(object), Some(target)) = (roles.object.clone(), roles.target.clone()) else {
        let what = match &roles.object {
            Some(o) => format!("no target for '{o}'"),
            None => "no free object to hold".into(),
        };
        return Err(why_not(format!(
            "cannot estimate the world-to-base registration: the scene's success rules name {what} (nothing to fit the \
             grasp and release to); pass --registration FILE"
        )));
    };
    let grasps = pinches.grasps();
    let Some(&(on, Some(off))) = grasps.first() else {
        return Err(why_not(
            "cannot estimate the world-to-base registration: the hand never grasps and releases \
             (its aperture never closes and opens again); pass --registration FILE"
                .into(),
        ));
    };
    // Fingertips close 1.5 cm below the object's top, or at its middle when it is lower.
    let mut q_grasp = crate::gym::entity_centre(scene, &object).unwrap_or_default();
    if let Some(top) = crate::gym::entity_top(scene, &object) {
        q_grasp[2] = q_grasp[2].max(top - 0.015);
    }
    let q_release = crate::gym::entity_centre(scene, &target).unwrap_or_default();
    let g = egodex::z_up_from_arkit();
    let p_grasp = g * Point3::from(pinches.world_from_pinch[on].translation.vector);
    let p_release = g * Point3::from(pinches.world_from_pinch[off].translation.vector);
    let dp = Vector3::new(p_release.x - p_grasp.x, p_release.y - p_grasp.y, 0.0);
    let dq = Vector3::new(q_release[0] - q_grasp[0], q_release[1] - q_grasp[1], 0.0);
    if dp.norm() < 0.05 || dq.norm() < 0.05 {
        return Err(why_not(format!(
            "cannot estimate the heading: grasp and release are {:.3} m apart in the demonstration and {:.3} m in the scene \
             (at least 0.05 m needed); pass --registration FILE",
            dp.norm(),
            dq.norm()
        )));
    }
    let yaw = dp.cross(&dq).z.atan2(dp.dot(&dq));
    let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    let (pg, pr) = (rz * p_grasp, rz * p_release);
    let tx = 0.5 * ((q_grasp[0] - pg.x) + (q_release[0] - pr.x));
    let ty = 0.5 * ((q_grasp[1] - pg.y) + (q_release[1] - pr.y));
    let tz = q_grasp[2] - pg.z;
    let residual = 0.5
        * ((q_grasp[0] - pg.x - tx).hypot(q_grasp[1] - pg.y - ty)
            + (q_release[0] - pr.x - tx).hypot(q_release[1] - pr.y - ty));
    if residual > 0.05 {
        return Err(why_not(format!(
            "the demonstration does not fit the scene: grasp-to-release is {:.3} m, '{object}'-to-'{target}' {:.3} m \
             (residual {residual:.3} m over 0.05 m); pass --registration FILE",
            dp.norm(),
            dq.norm()
        )));
    }
    let base_from_world = Isometry3::from_parts(Translation3::new(tx, ty, tz), rz * g);
    let reg = Registration {
        base_from_world: crate::record::matrix_of(&base_from_world),
        kind: "estimated".into(),
        how: format!(
            "gravity from ARKit's y-up world; heading and position fitted in the horizontal plane to the pinch at the first grasp \
             onset (source frame {}) = centre of '{object}' and at the release (frame {}) = centre of '{target}'; height from \
             the grasp point",
            pinches.frames[on], pinches.frames[off]
        ),
        residual_m: residual,
    };
    Ok((base_from_world, reg))
}

/// Averages each pose with those within `half_window_s` of it that share its gripper state
/// (tracking noise would otherwise become joint jitter, which the runtime can only follow by
/// slowing down); positions by their mean, orientations by the normalised sum of quaternions
/// turned into one hemisphere.
pub fn smooth(poses: &[Isometry3<f64>], t_s: &[f64], state: &[bool], half_window_s: f64) -> Vec<Isometry3<f64>> {
    (0..poses.len())
        .map(|k| {
            let near = (0..poses.len()).filter(|&j| (t_s[j] - t_s[k]).abs() <= half_window_s && state[j] == state[k]);
            let (mut p, mut q, mut n) = (Vector3::zeros(), nalgebra::Vector4::zeros(), 0.0);
            let qk = poses[k].rotation.coords;
            for j in near {
                p += poses[j].translation.vector;
                let c = poses[j].rotation.coords;
                q += if c.dot(&qk) < 0.0 { -c } else { c };
                n += 1.0;
            }
            let rot = UnitQuaternion::from_quaternion(nalgebra::Quaternion::from(q / n));
            Isometry3::from_parts(Translation3::from(p / n), rot)
        })
        .collect()
}

/// IK for retargeted and adapted paths: joint ranges shrunk by 0.05 rad, 0.5 mm and 0.005 rad
/// (tracked hands are noisier than that; the solver's default 10 µm would refuse poses a hair
/// from the shrunk limits).
fn path_ik() -> IkConfig {
    IkConfig { limit_margin_rad: 0.05, position_tolerance_m: 5e-4, rotation_tolerance_rad: 5e-3, ..IkConfig::default() }
}

/// Solves TCP poses (robot base frame) into joint rows, each seeded with the one before; the
/// first with `seed`. A pose whose solution comes too near the table is raised, 2 mm at a time,
/// by at most `lift_max_m` (a human hand may rest on the table; the gripper must not): the rows
/// raised are counted. On failure: the row and why.
pub fn solve_path(
    robot: &RobotModel,
    safety: &SafetyChecks,
    tcp: &[Isometry3<f64>],
    seed: [f64; 7],
    lift_max_m: f64,
) -> std::result::Result<(Vec<[f64; 7]>, usize), (usize, String)> {
    let ik = IkSolver::new(robot, path_ik()).map_err(|e| (0, format!("IK: {e}")))?;
    let mut roomy = safety.clone();
    roomy.margin_m += 0.003;
    let mut q = seed;
    let mut out = Vec::with_capacity(tcp.len());
    let mut lifted = 0;
    for (row, target) in tcp.iter().enumerate() {
        let mut lift = 0.0;
        let sol = loop {
            let raised = Isometry3::translation(0.0, 0.0, lift) * target;
            let sol = ik.solve(&raised, &q).map_err(|e| (row, format!("IK: {e}")))?;
            if !sol.ok {
                let p = raised.translation.vector;
                return Err((
                    row,
                    format!(
                        "unreachable: no IK solution within the joint limits for the TCP at [{:.3}, {:.3}, {:.3}] m \
                         (best {:.1} mm, {:.1} deg away)",
                        p.x,
                        p.y,
                        p.z,
                        sol.position_error_m * 1e3,
                        sol.rotation_error_rad.to_degrees()
                    ),
                ));
            }
            // Lifted rows keep 3 mm more than the margin, so the path between rows clears too.
            let near_table =
                lift_max_m > 0.0 && matches!(roomy.check(&sol.q), Err(Violation::Obstacle { obstacle: "table", .. }));
            match safety.check(&sol.q) {
                Ok(()) if !near_table => break sol,
                Ok(()) | Err(Violation::Obstacle { obstacle: "table", .. }) if lift + 0.002 <= lift_max_m + 1e-12 => {
                    lift += 0.002
                }
                Ok(()) => break sol,
                Err(v) => return Err((row, format!("the scene's checks refuse the solution: {v}"))),
            }
        };
        if lift > 0.0 {
            lifted += 1;
        }
        let jump = (0..7).map(|j| (sol.q[j] - q[j]).abs()).fold(0.0, f64::max);
        if row > 0 && jump > 0.25 {
            return Err((row, format!("the IK solution jumps {jump:.2} rad from the row before (limit 0.25)")));
        }
        q = sol.q;
        out.push(q);
    }
    Ok((out, lifted))
}

/// A joint-space move from `a` to `b` at `hz` with a quintic time law, its duration set so no
/// joint moves faster than 0.5 rad/s on average (at least 1 s); both ends included.
pub fn lead_in(a: [f64; 7], b: [f64; 7], hz: f64) -> Vec<[f64; 7]> {
    let span = (0..7).map(|j| (b[j] - a[j]).abs()).fold(0.0, f64::max);
    let n = ((span / 0.5).max(1.0) * hz).round().max(1.0) as usize;
    (0..=n)
        .map(|k| {
            let t = k as f64 / n as f64;
            let s = t * t * t * (10.0 - 15.0 * t + 6.0 * t * t);
            std::array::from_fn(|j| a[j] + s * (b[j] - a[j]))
        })
        .collect()
}

/// What retargeting produced besides the rows.
#[derive(Debug, Clone, Serialize)]
pub struct HandReport {
    pub side: String,
    pub frames: usize,
    pub kept: usize,
    pub dropped_low_confidence: usize,
    /// Confident frames dropped because thumb and index (or the knuckle) coincide: no pinch frame.
    pub dropped_degenerate: usize,
    pub longest_gap_s: f64,
    pub close_below_m: f64,
    pub open_above_m: f64,
    pub lead_in_rows: usize,
    /// Rows raised (by up to 1 cm) to keep the gripper off the table.
    pub lifted_rows: usize,
    /// Gripper switches in demonstration time (s from row 0): (time, closed).
    pub switches_s: Vec<(f64, bool)>,
}

pub struct Retargeted {
    pub record: Record,
    /// Joint + gripper rows at the demonstration rate, starting at the scene's start joints.
    pub rows: Vec<[f64; 8]>,
    /// Demonstration time of the record's first kept frame.
    pub offset_s: f64,
    pub report: HandReport,
}

/// Retargets a hand onto the scene's robot: registration, pinch frames in the base frame,
/// resampled to `hz` (never blending across a gripper switch), solved row by row, led in from
/// the scene's start joints.
pub fn retarget(
    hand: &HandInWorld,
    scene: &sim_host::Scene,
    robot: &RobotModel,
    safety: &SafetyChecks,
    given: Option<Isometry3<f64>>,
    p: HandParams,
    hz: f64,
) -> Result<Retargeted> {
    let pin = pinches(hand, p, egodex::RATE_HZ)?;
    let (base_from_world, registration) = match given {
        Some(t) => (
            t,
            Registration {
                base_from_world: crate::record::matrix_of(&t),
                kind: "given".into(),
                how: "--registration file".into(),
                residual_m: 0.0,
            },
        ),
        None => estimate_registration(&hand.file, scene, &pin)?,
    };
    let t0 = pin.t_s[0];
    let t_s: Vec<f64> = pin.t_s.iter().map(|t| t - t0).collect();
    // Pinch frames in the base; y kept continuous from frame to frame.
    let mut tcp: Vec<Isometry3<f64>> = pin.world_from_pinch.iter().map(|w| base_from_world * w).collect();
    let flip = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI);
    let start_q = scene.robot.initial_joints_rad;
    // The first frame: the sign of y whose solution is nearer the start joints.
    let first_alt = [tcp[0], tcp[0] * Isometry3::from_parts(Translation3::identity(), flip)];
    let ik = IkSolver::new(robot, path_ik()).map_err(|e| Error::Episode(anyhow::anyhow!("IK: {e}")))?;
    let cost = |t: &Isometry3<f64>| match ik.solve(t, &start_q) {
        Ok(s) if s.ok => (0..7).map(|j| (s.q[j] - start_q[j]).abs()).sum::<f64>(),
        _ => f64::INFINITY,
    };
    if cost(&first_alt[1]) < cost(&first_alt[0]) {
        tcp[0] = first_alt[1];
    }
    for k in 1..tcp.len() {
        let (yp, y) = (tcp[k - 1].rotation * Vector3::y(), tcp[k].rotation * Vector3::y());
        if yp.dot(&y) < 0.0 {
            tcp[k] = tcp[k] * Isometry3::from_parts(Translation3::identity(), flip);
        }
    }
    let tcp = smooth(&tcp, &t_s, &pin.closed, p.smooth_half_window_s);
    // Resample onto the demonstration rate.
    let plan = resample::plan(&t_s, &pin.closed, hz);
    let poses: Vec<Isometry3<f64>> = plan
        .iter()
        .map(|b| {
            let (a, c) = (tcp[b.a], tcp[b.b]);
            let pos = a.translation.vector.lerp(&c.translation.vector, b.w);
            Isometry3::from_parts(Translation3::from(pos), a.rotation.slerp(&c.rotation, b.w))
        })
        .collect();
    let grip: Vec<f64> = plan.iter().map(|b| (1.0 - b.w) * pin.gripper[b.a] + b.w * pin.gripper[b.b]).collect();
    let joints = egodex::pinch_joints(&hand.side);
    let field = format!("transforms/{} (pinch frame)", joints.join("+"));
    let (solved, lifted_rows) = solve_path(robot, safety, &poses, start_q, 0.01).map_err(|(row, why)| {
        let b = plan[row];
        Error::input(&hand.file, &field, Some(pin.frames[if b.w < 0.5 { b.a } else { b.b }]), why)
    })?;
    let lead = lead_in(start_q, solved[0], hz);
    if let Err(v) = safety.check_path(&start_q, &solved[0], 0.02) {
        return Err(Error::input(
            &hand.file,
            &field,
            Some(pin.frames[0]),
            format!("the move from the scene's start joints to the first pose is refused: {v}"),
        ));
    }
    let mut rows: Vec<[f64; 8]> =
        lead[..lead.len() - 1].iter().map(|q| [q[0], q[1], q[2], q[3], q[4], q[5], q[6], grip[0]]).collect();
    let lead_in_rows = rows.len();
    for (q, g) in solved.iter().zip(&grip) {
        rows.push([q[0], q[1], q[2], q[3], q[4], q[5], q[6], *g]);
    }
    let offset_s = lead_in_rows as f64 / hz;
    let longest_gap_s = t_s.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
    let kept = pin.frames.len();
    let low_confidence = hand.confidence.iter().filter(|c| **c < p.min_confidence).count();
    let base_pts = |j: usize| -> Vec<[f64; 3]> {
        pin.frames
            .iter()
            .map(|&f| {
                let p = base_from_world * Point3::from(hand.points[f][j]);
                [p.x, p.y, p.z]
            })
            .collect()
    };
    let record = Record {
        source: Source {
            kind: "egodex".into(),
            files: vec![hand.file.clone()],
            task: hand.task.clone(),
            rate_hz: egodex::RATE_HZ,
            conventions: egodex::CONVENTIONS.iter().map(|s| s.to_string()).collect(),
            registration: Some(registration),
            frames: pin.frames.clone(),
        },
        t_s: t_s.clone(),
        cameras: vec![egodex::camera_track(hand, &base_from_world, &pin.frames)],
        robot: None,
        hand: Some(HandTrack {
            side: hand.side.clone(),
            thumb_tip_m: base_pts(0),
            index_tip_m: base_pts(1),
            index_knuckle_m: base_pts(2),
            confidence: pin.frames.iter().map(|&f| hand.confidence[f]).collect(),
        }),
    };
    record.check()?;
    let report = HandReport {
        side: hand.side.clone(),
        frames: hand.points.len(),
        kept,
        dropped_low_confidence: low_confidence,
        dropped_degenerate: hand.points.len() - kept - low_confidence,
        longest_gap_s,
        close_below_m: pin.close_below_m,
        open_above_m: pin.open_above_m,
        lead_in_rows,
        lifted_rows,
        switches_s: resample::switches(&pin.closed, &t_s).into_iter().map(|(t, s)| (t + offset_s, s)).collect(),
    };
    Ok(Retargeted { record, rows, offset_s, report })
}
