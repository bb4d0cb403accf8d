//! Turns an accepted chunk of waypoints into a time-parameterised joint reference.
//!
//! Each segment lasts at least one period of the requested rate and long enough that no joint
//! needs more than `speed_scale` of its velocity limit: a faster `freq` never buys speed past
//! the limits. Storage is fixed-size so that sampling in the tick allocates nothing.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3, Vector6};

use crate::error::{Rejection, StepQuantity, Text};
use crate::ik::IkSolver;
use crate::limiter::LimiterConfig;
use crate::reference::Reference;
use crate::robot::RobotModel;
use crate::safety::SafetyChecks;
use crate::N;

/// Largest chunk the plan holds.
pub const MAX_WAYPOINTS: usize = 256;
/// A joint of an IK solution counts as at its limit within this distance of its bound, rad.
const AT_LIMIT_RAD: f64 = 0.01;
/// Spacing of the IK and safety samples along an ee_pose chunk's TCP path, m.
pub const PATH_SPACING_M: f64 = 0.01;
/// Rotation counts as this many metres per radian of path length.
const PATH_ROT_M_PER_RAD: f64 = 0.1;
/// At most this many samples per chunk (the spacing grows for long chunks).
pub const MAX_PATH_SAMPLES: usize = 256;

/// One joint-space target: arm joints and the gripper value (−1 open … +1 closed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Waypoint {
    pub q_rad: [f64; N],
    pub gripper: f64,
}

/// A validated, timed chunk.
#[derive(Debug, Clone)]
pub struct ChunkPlan {
    start_q: [f64; N],
    waypoints: [Waypoint; MAX_WAYPOINTS],
    /// End time of each segment, s from the start of the chunk.
    ends_s: [f64; MAX_WAYPOINTS],
    /// Per segment and joint: where that joint's motion in one direction ends (it turns back
    /// there, or the chunk ends). The limiter never carries a joint past it.
    turns: [[f64; N]; MAX_WAYPOINTS],
    len: usize,
    /// ee_pose chunks: the TCP poses (base frame) the straight segments join, start first.
    /// Inline rather than boxed: accepting a chunk in the tick must not allocate.
    poses: [Isometry3<f64>; MAX_WAYPOINTS + 1],
    cartesian: bool,
}

/// A Cartesian reference sample: where the TCP should be and its twist (linear, angular).
#[derive(Debug, Clone, Copy)]
pub struct PoseReference {
    pub pose: Isometry3<f64>,
    pub twist: Vector6<f64>,
    pub gripper: f64,
    pub reached: usize,
    pub finished: bool,
}

/// Time for a rest-to-rest move over `d` at speed `v` and acceleration `a` (trapezoid).
fn trapezoid_s(d: f64, v: f64, a: f64) -> f64 {
    if d * a > v * v {
        d / v + v / a
    } else {
        2.0 * (d / a).sqrt()
    }
}

/// Checks what every chunk shares: length and rate. Returns the rate to use.
fn check_shape(n: usize, freq_hz: f64, cfg: &LimiterConfig) -> Result<f64, Rejection> {
    if n == 0 {
        return Err(Rejection::Empty);
    }
    let max = MAX_WAYPOINTS.min(cfg.max_chunk);
    if n > max {
        return Err(Rejection::TooLong { len: n, max });
    }
    let freq = if freq_hz == 0.0 { cfg.default_freq_hz } else { freq_hz };
    if !(freq.is_finite() && freq >= cfg.min_freq_hz && freq <= cfg.max_freq_hz) {
        return Err(Rejection::BadFrequency { freq_hz, min_hz: cfg.min_freq_hz, max_hz: cfg.max_freq_hz });
    }
    Ok(freq)
}

/// Over a step cap by more than rounding: a step computed as exactly the cap passes.
fn exceeds(value: f64, cap: f64) -> bool {
    value > cap + 1e-9 * cap.abs().max(1.0)
}

fn check_values(w: usize, a: &[f64; 8]) -> Result<(), Rejection> {
    if let Some(i) = a.iter().position(|v| !v.is_finite()) {
        return Err(Rejection::NotFinite { waypoint: w, index: i });
    }
    if !(-1.0..=1.0).contains(&a[N]) {
        return Err(Rejection::GripperOutOfRange { waypoint: w, value: a[N] });
    }
    Ok(())
}

fn unsafe_at(w: usize, v: crate::collision::Violation<'_>) -> Rejection {
    Rejection::Unsafe { waypoint: w, detail: Text::of(format_args!("{v}")) }
}

impl ChunkPlan {
    /// Checks every value of a joint chunk and times it from `start_q`. Rejects, never clips.
    /// With `safety`, each waypoint and the straight joint path to it must also be free of
    /// collisions and inside the workspace.
    pub fn joint(
        actions: &[[f64; 8]],
        freq_hz: f64,
        start_q: [f64; N],
        robot: &RobotModel,
        cfg: &LimiterConfig,
        safety: Option<&SafetyChecks>,
    ) -> Result<Self, Rejection> {
        let freq = check_shape(actions.len(), freq_hz, cfg)?;
        let mut plan = Self::hold(start_q, 0.0);
        plan.len = actions.len();
        // Path-check spacing: 0.02 rad, coarser when the chunk travels far (bounded work).
        let mut travel = 0.0;
        let mut last = start_q;
        for a in actions {
            let q: [f64; N] = std::array::from_fn(|j| a[j]);
            if q.iter().all(|v| v.is_finite()) {
                travel += (0..N).map(|j| (q[j] - last[j]).abs()).fold(0.0, f64::max);
                last = q;
            }
        }
        let spacing = travel / crate::safety::MAX_PATH_CHECKS as f64;
        let mut prev = start_q;
        let mut t = 0.0;
        for (w, a) in actions.iter().enumerate() {
            check_values(w, a)?;
            let mut q = [0.0; N];
            for j in 0..N {
                let lim = robot.joints[j];
                let (lo, hi) = (lim.q_min_rad + cfg.q_margin_rad, lim.q_max_rad - cfg.q_margin_rad);
                if a[j] < lo || a[j] > hi {
                    return Err(Rejection::JointOutOfRange { waypoint: w, joint: j, value: a[j], min: lo, max: hi });
                }
                q[j] = a[j];
            }
            for j in 0..N {
                let step = (q[j] - prev[j]).abs();
                if exceeds(step, cfg.max_joint_step_rad) {
                    let quantity = StepQuantity::Joint(j);
                    return Err(Rejection::StepTooLarge {
                        waypoint: w,
                        quantity,
                        value: step,
                        max: cfg.max_joint_step_rad,
                    });
                }
            }
            // Timing first: an overlong chunk is refused before any path is checked.
            let seg = plan.segment_s(w, &prev, &q, freq, robot, cfg)?;
            if let Some(s) = safety {
                s.check_path(&prev, &q, spacing).map_err(|v| unsafe_at(w, v))?;
            }
            t += seg;
            plan.waypoints[w] = Waypoint { q_rad: q, gripper: a[N] };
            plan.ends_s[w] = t;
            prev = q;
        }
        plan.find_turns();
        Ok(plan)
    }

    /// Checks an ee_pose chunk: `[x, y, z, ax, ay, az, _, g]` TCP targets in the base frame
    /// (axis-angle rotation). The straight TCP path through them is sampled every
    /// [`PATH_SPACING_M`] (coarser for long chunks): every sample must have an IK solution
    /// within the joint limits, seeded with the previous one, and with `safety` that solution
    /// must be collision-free and inside the workspace. Segments are timed for the TCP's speed
    /// limits and the joints'.
    pub fn ee_pose(
        actions: &[[f64; 8]],
        freq_hz: f64,
        start_q: [f64; N],
        robot: &RobotModel,
        cfg: &LimiterConfig,
        ik: &IkSolver,
        safety: Option<&SafetyChecks>,
    ) -> Result<Self, Rejection> {
        let freq = check_shape(actions.len(), freq_hz, cfg)?;
        let mut plan = Self::hold(start_q, 0.0);
        plan.len = actions.len();
        plan.poses[0] = robot.kin.fk(&start_q, robot.kin.tcp);
        // Sample spacing along the TCP path: 1 cm, coarser for long chunks so that one chunk
        // never costs more than MAX_PATH_SAMPLES IK solves in all.
        let mut length = 0.0;
        let mut turn = 0.0;
        let mut last = plan.poses[0];
        let (mut widest, mut widest_at) = (0.0, 0);
        for (w, a) in actions.iter().enumerate() {
            if a[..6].iter().all(|v| v.is_finite()) {
                let p = Isometry3::from_parts(
                    Translation3::new(a[0], a[1], a[2]),
                    UnitQuaternion::from_scaled_axis(Vector3::new(a[3], a[4], a[5])),
                );
                let step = p.rotation.angle_to(&last.rotation);
                if step > widest {
                    (widest, widest_at) = (step, w);
                }
                turn += step;
                length += (p.translation.vector - last.translation.vector).norm() + PATH_ROT_M_PER_RAD * step;
                last = p;
            }
        }
        // Rotation vectors interpolated component by component across the ±π wrap turn the hand
        // the long way round: a full turn less the direct angle, more than half a turn further
        // than the direct way. Refused however finely it is stepped (a deliberate turn of more
        // than three quarters of a turn looks the same: it takes two chunks; the reason says
        // "probably").
        let direct = plan.poses[0].rotation.angle_to(&last.rotation);
        let pi = std::f64::consts::PI;
        let long_way = turn > direct + pi && (turn + direct - 2.0 * pi).abs() < 0.5;
        if long_way {
            return Err(Rejection::LongWayRound {
                waypoint: widest_at,
                value: widest,
                max: cfg.max_tcp_step_rad,
                turn_rad: turn,
                direct_rad: direct,
            });
        }
        let spacing = (length / MAX_PATH_SAMPLES as f64).max(PATH_SPACING_M);
        let mut prev = start_q;
        let mut t = 0.0;
        let cart = robot.cartesian;
        for (w, a) in actions.iter().enumerate() {
            check_values(w, a)?;
            let pose = Isometry3::from_parts(
                Translation3::new(a[0], a[1], a[2]),
                UnitQuaternion::from_scaled_axis(Vector3::new(a[3], a[4], a[5])),
            );
            // The straight TCP segment to this waypoint, sampled: every sample must have an IK
            // solution near the previous one, and with `safety` pass the checks.
            let from = plan.poses[w];
            let (moved, turned) =
                ((pose.translation.vector - from.translation.vector).norm(), pose.rotation.angle_to(&from.rotation));
            for (value, max, quantity) in [
                (moved, cfg.max_tcp_step_m, StepQuantity::TcpTranslation),
                (turned, cfg.max_tcp_step_rad, StepQuantity::TcpRotation),
            ] {
                if exceeds(value, max) {
                    return Err(Rejection::StepTooLarge { waypoint: w, quantity, value, max });
                }
            }
            let n = (((pose.translation.vector - from.translation.vector).norm()
                + PATH_ROT_M_PER_RAD * pose.rotation.angle_to(&from.rotation))
                / spacing)
                .ceil()
                .clamp(1.0, MAX_PATH_SAMPLES as f64) as usize;
            let mut q = prev;
            for k in 1..=n {
                let s = k as f64 / n as f64;
                let sample = Isometry3::from_parts(
                    Translation3::from(from.translation.vector.lerp(&pose.translation.vector, s)),
                    from.rotation.slerp(&pose.rotation, s),
                );
                let sol = match ik.solve(&sample, &q) {
                    Ok(sol) if sol.ok => sol,
                    Ok(sol) => {
                        let (lo, hi) = ik.bounds();
                        let at_limits = (0..N)
                            .filter(|&j| sol.q[j] - lo[j] < AT_LIMIT_RAD || hi[j] - sol.q[j] < AT_LIMIT_RAD)
                            .fold(0u8, |m, j| m | (1 << j));
                        return Err(Rejection::Unreachable {
                            waypoint: w,
                            position_error_m: sol.position_error_m,
                            rotation_error_rad: sol.rotation_error_rad,
                            at_limits,
                        });
                    }
                    Err(_) => return Err(Rejection::NotFinite { waypoint: w, index: 0 }),
                };
                if let Some(checks) = safety {
                    checks.check(&sol.q).map_err(|v| unsafe_at(w, v))?;
                }
                q = sol.q;
            }
            let from = plan.poses[w];
            let d = (pose.translation.vector - from.translation.vector).norm();
            let ang = pose.rotation.angle_to(&from.rotation);
            let tcp_s = trapezoid_s(d, cfg.tcp_speed_scale * cart.v_m_s, cfg.accel_scale * cart.a_m_s2)
                .max(trapezoid_s(ang, cfg.tcp_speed_scale * cart.w_rad_s, cfg.accel_scale * cart.dw_rad_s2));
            t += plan.segment_s(w, &prev, &q, freq, robot, cfg)?.max(tcp_s);
            if t > cfg.max_chunk_duration_s {
                return Err(Rejection::TooSlow { waypoint: w, duration_s: t, max_s: cfg.max_chunk_duration_s });
            }
            plan.waypoints[w] = Waypoint { q_rad: q, gripper: a[N] };
            plan.ends_s[w] = t;
            plan.poses[w + 1] = pose;
            prev = q;
        }
        plan.find_turns();
        plan.cartesian = true;
        Ok(plan)
    }

    /// Duration of segment `w` from `from` to `to`: one period of the rate at least, and long
    /// enough that no joint needs more than `speed_scale` of its velocity limit.
    fn segment_s(
        &self,
        w: usize,
        from: &[f64; N],
        to: &[f64; N],
        freq: f64,
        robot: &RobotModel,
        cfg: &LimiterConfig,
    ) -> Result<f64, Rejection> {
        let mut seg_s = 1.0 / freq;
        for j in 0..N {
            let lim = robot.joints[j];
            let v = cfg.speed_scale * lim.dq_max_rad_s;
            let d = (to[j] - from[j]).abs();
            seg_s = seg_s.max(trapezoid_s(d, v, cfg.accel_scale * lim.ddq_max_rad_s2));
        }
        let t = if w == 0 { 0.0 } else { self.ends_s[w - 1] } + seg_s;
        if t > cfg.max_chunk_duration_s {
            return Err(Rejection::TooSlow { waypoint: w, duration_s: t, max_s: cfg.max_chunk_duration_s });
        }
        Ok(seg_s)
    }

    /// Whether this is an ee_pose chunk (sample it with [`Self::sample_pose`]).
    pub fn is_cartesian(&self) -> bool {
        self.cartesian
    }

    /// The TCP reference of an ee_pose chunk at `t_s`: straight segments between the poses,
    /// translation interpolated linearly and rotation along the shortest arc.
    pub fn sample_pose(&self, t_s: f64) -> Option<PoseReference> {
        if !self.cartesian {
            return None;
        }
        let poses = &self.poses;
        let mut seg = 0;
        while seg < self.len && self.ends_s[seg] <= t_s {
            seg += 1;
        }
        if seg >= self.len {
            return Some(PoseReference {
                pose: poses[self.len],
                twist: Vector6::zeros(),
                gripper: self.last().gripper,
                reached: self.len,
                finished: true,
            });
        }
        let t0 = if seg == 0 { 0.0 } else { self.ends_s[seg - 1] };
        let dur = self.ends_s[seg] - t0;
        let s = ((t_s - t0) / dur).clamp(0.0, 1.0);
        let (a, b) = (poses[seg], poses[seg + 1]);
        let rot = a.rotation.slerp(&b.rotation, s);
        let pos = a.translation.vector.lerp(&b.translation.vector, s);
        let v = (b.translation.vector - a.translation.vector) / dur;
        let w = (b.rotation * a.rotation.inverse()).scaled_axis() / dur;
        Some(PoseReference {
            pose: Isometry3::from_parts(Translation3::from(pos), rot),
            twist: Vector6::new(v.x, v.y, v.z, w.x, w.y, w.z),
            gripper: self.waypoints[seg].gripper,
            reached: seg,
            finished: false,
        })
    }

    /// Fills `turns` backwards: a segment inherits the next one's turn point while the joint
    /// keeps moving the same way, and ends at its own waypoint otherwise (a turn or a pause).
    #[allow(clippy::needless_range_loop)] // joint j indexes three arrays
    fn find_turns(&mut self) {
        let n = self.len;
        self.turns[n - 1] = self.waypoints[n - 1].q_rad;
        for w in (0..n - 1).rev() {
            let from = if w == 0 { self.start_q } else { self.waypoints[w - 1].q_rad };
            for j in 0..N {
                let here = self.waypoints[w].q_rad[j] - from[j];
                let next = self.waypoints[w + 1].q_rad[j] - self.waypoints[w].q_rad[j];
                self.turns[w][j] = if here * next > 0.0 { self.turns[w + 1][j] } else { self.waypoints[w].q_rad[j] };
            }
        }
    }

    /// A plan that holds one configuration; used as the idle placeholder.
    pub fn hold(q_rad: [f64; N], gripper: f64) -> Self {
        let waypoints = [Waypoint { q_rad, gripper }; MAX_WAYPOINTS];
        Self {
            start_q: q_rad,
            waypoints,
            ends_s: [0.0; MAX_WAYPOINTS],
            turns: [q_rad; MAX_WAYPOINTS],
            len: 1,
            poses: [Isometry3::identity(); MAX_WAYPOINTS + 1],
            cartesian: false,
        }
    }

    /// The configuration the chunk started from.
    pub fn start_q(&self) -> [f64; N] {
        self.start_q
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn duration_s(&self) -> f64 {
        self.ends_s[self.len - 1]
    }

    pub fn last(&self) -> Waypoint {
        self.waypoints[self.len - 1]
    }

    /// ee_pose chunks: the last waypoint's TCP pose (base frame); `None` for joint chunks.
    pub fn last_pose(&self) -> Option<Isometry3<f64>> {
        (self.cartesian && self.len > 0).then(|| self.poses[self.len])
    }

    /// The reference at `t_s` seconds after the chunk started: linear between waypoints.
    pub fn sample(&self, t_s: f64) -> Reference {
        let mut seg = 0;
        while seg < self.len && self.ends_s[seg] <= t_s {
            seg += 1;
        }
        if seg >= self.len {
            let w = self.last();
            return Reference {
                q_rad: w.q_rad,
                dq_rad_s: [0.0; N],
                gripper: w.gripper,
                goal_q_rad: w.q_rad,
                reached: self.len,
                finished: true,
            };
        }
        let (from, t0) =
            if seg == 0 { (self.start_q, 0.0) } else { (self.waypoints[seg - 1].q_rad, self.ends_s[seg - 1]) };
        let to = self.waypoints[seg];
        let dur = self.ends_s[seg] - t0;
        let s = ((t_s - t0) / dur).clamp(0.0, 1.0);
        let mut q = [0.0; N];
        let mut dq = [0.0; N];
        for j in 0..N {
            q[j] = from[j] + s * (to.q_rad[j] - from[j]);
            dq[j] = (to.q_rad[j] - from[j]) / dur;
        }
        Reference {
            q_rad: q,
            dq_rad_s: dq,
            gripper: to.gripper,
            goal_q_rad: self.turns[seg],
            reached: seg,
            finished: false,
        }
    }
}
