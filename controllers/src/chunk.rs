//! Turns an accepted chunk of waypoints into a time-parameterised joint reference.
//!
//! Each segment lasts at least one period of the requested rate and long enough that no joint
//! needs more than `speed_scale` of its velocity limit: a faster `freq` never buys speed past
//! the limits. Storage is fixed-size so that sampling in the tick allocates nothing.

use crate::error::Rejection;
use crate::limiter::LimiterConfig;
use crate::robot::RobotModel;
use crate::N;

/// Largest chunk the plan holds.
pub const MAX_WAYPOINTS: usize = 256;

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
}

/// A reference sample: where the arm should be, how fast it should move, and the gripper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reference {
    pub q_rad: [f64; N],
    pub dq_rad_s: [f64; N],
    pub gripper: f64,
    /// Per joint, where the current one-directional stretch of the reference ends: the next
    /// waypoint at which it turns back, or the last one. The limiter never passes it.
    pub goal_q_rad: [f64; N],
    /// Waypoints whose segment has ended.
    pub reached: usize,
    pub finished: bool,
}

impl ChunkPlan {
    /// Checks every value of a joint chunk and times it from `start_q`. Rejects, never clips.
    pub fn joint(
        actions: &[[f64; 8]],
        freq_hz: f64,
        start_q: [f64; N],
        robot: &RobotModel,
        cfg: &LimiterConfig,
    ) -> Result<Self, Rejection> {
        if actions.is_empty() {
            return Err(Rejection::Empty);
        }
        if actions.len() > MAX_WAYPOINTS.min(cfg.max_chunk) {
            return Err(Rejection::TooLong { len: actions.len(), max: MAX_WAYPOINTS.min(cfg.max_chunk) });
        }
        let freq = if freq_hz == 0.0 { cfg.default_freq_hz } else { freq_hz };
        if !(freq.is_finite() && freq >= cfg.min_freq_hz && freq <= cfg.max_freq_hz) {
            return Err(Rejection::BadFrequency { freq_hz, min_hz: cfg.min_freq_hz, max_hz: cfg.max_freq_hz });
        }
        let mut plan = Self {
            start_q,
            waypoints: [Waypoint { q_rad: [0.0; N], gripper: 0.0 }; MAX_WAYPOINTS],
            ends_s: [0.0; MAX_WAYPOINTS],
            turns: [[0.0; N]; MAX_WAYPOINTS],
            len: actions.len(),
        };
        let mut prev = start_q;
        let mut t = 0.0;
        for (w, a) in actions.iter().enumerate() {
            for (i, v) in a.iter().enumerate() {
                if !v.is_finite() {
                    return Err(Rejection::NotFinite { waypoint: w, index: i });
                }
            }
            let mut q = [0.0; N];
            let mut seg_s = 1.0 / freq;
            for j in 0..N {
                let lim = robot.joints[j];
                let (lo, hi) = (lim.q_min_rad + cfg.q_margin_rad, lim.q_max_rad - cfg.q_margin_rad);
                if a[j] < lo || a[j] > hi {
                    return Err(Rejection::JointOutOfRange { waypoint: w, joint: j, value: a[j], min: lo, max: hi });
                }
                q[j] = a[j];
                let v = cfg.speed_scale * lim.dq_max_rad_s;
                // Trapezoid with the limiter's acceleration: the time it needs to cover the step.
                let acc = cfg.accel_scale * lim.ddq_max_rad_s2;
                let d = (q[j] - prev[j]).abs();
                let need = if d * acc > v * v { d / v + v / acc } else { 2.0 * (d / acc).sqrt() };
                seg_s = seg_s.max(need.max(d / v));
            }
            let g = a[N];
            if !(-1.0..=1.0).contains(&g) {
                return Err(Rejection::GripperOutOfRange { waypoint: w, value: g });
            }
            t += seg_s;
            if t > cfg.max_chunk_duration_s {
                return Err(Rejection::TooSlow { waypoint: w, duration_s: t, max_s: cfg.max_chunk_duration_s });
            }
            plan.waypoints[w] = Waypoint { q_rad: q, gripper: g };
            plan.ends_s[w] = t;
            prev = q;
        }
        plan.find_turns();
        Ok(plan)
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
        Self { start_q: q_rad, waypoints, ends_s: [0.0; MAX_WAYPOINTS], turns: [q_rad; MAX_WAYPOINTS], len: 1 }
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
