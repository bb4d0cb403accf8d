//! The last stage before a command leaves the runtime: a per-joint, jerk-limited tracker whose
//! output never leaves the position range (minus margin) and never exceeds the velocity,
//! acceleration or jerk limits, whatever reference it is given.
//!
//! Each tick proposes the acceleration that best follows the reference, then asks whether the
//! arm could still come to rest inside every limit from the state that proposal leads to, by
//! running the braking policy forward (a handful of ticks, the constant-deceleration stretch in
//! closed form). If it could not, the tick takes the braking policy's own step instead. The
//! braking policy depends on the state alone, so from a state that passed the check its step
//! stays on the checked path: the invariant holds tick after tick, in discrete time.

use crate::reference::Reference;
use crate::robot::{JointLimits, RobotModel};
use crate::N;

/// Settings of the limiter and of chunk timing. Defaults suit a Panda in simulation.
#[derive(Debug, Clone, Copy)]
pub struct LimiterConfig {
    /// Kept inside each joint's position limits, rad.
    pub q_margin_rad: f64,
    /// Fraction of each joint's velocity limit that chunk timing plans for.
    pub speed_scale: f64,
    /// Fraction of each joint's acceleration limit the tracker uses.
    pub accel_scale: f64,
    /// Fraction of each joint's jerk limit the tracker uses.
    pub jerk_scale: f64,
    /// Fraction of the published TCP speed limits the tracker aims for.
    pub tcp_speed_scale: f64,
    /// Feedback gain pulling the command onto the reference, 1/s.
    pub gain_per_s: f64,
    /// Gain of the inner velocity loop, 1/s.
    pub velocity_gain_per_s: f64,
    pub default_freq_hz: f64,
    /// Slowest waypoint rate accepted; with `max_chunk_duration_s`, bounds how long the runtime
    /// stays busy with one chunk.
    pub min_freq_hz: f64,
    pub max_freq_hz: f64,
    pub max_chunk_duration_s: f64,
    pub max_chunk: usize,
    /// Step caps between consecutive waypoints, the first counted from the measured position:
    /// any joint (joint chunks), TCP translation and rotation (ee_pose chunks). Infinite: none.
    pub max_joint_step_rad: f64,
    pub max_tcp_step_m: f64,
    pub max_tcp_step_rad: f64,
}

impl Default for LimiterConfig {
    fn default() -> Self {
        Self {
            q_margin_rad: 0.01,
            speed_scale: 0.5,
            accel_scale: 0.5,
            jerk_scale: 0.5,
            tcp_speed_scale: 0.5,
            gain_per_s: 40.0,
            velocity_gain_per_s: 200.0,
            default_freq_hz: 20.0,
            min_freq_hz: 0.5,
            max_freq_hz: 1000.0,
            max_chunk_duration_s: 120.0,
            max_chunk: 256,
            max_joint_step_rad: f64::INFINITY,
            max_tcp_step_m: f64::INFINITY,
            max_tcp_step_rad: f64::INFINITY,
        }
    }
}

/// The largest speed at which, after one more tick of motion, the remaining distance `d` still
/// covers the stopping distance at deceleration `a`: v·dt + v²/(2a) ≤ d. Used to shape the
/// desired motion; safety itself comes from [`can_stop`].
#[inline]
fn stop_speed(d: f64, a: f64, dt: f64) -> f64 {
    let d = d.max(0.0);
    (-a * dt + (a * a * dt * dt + 2.0 * a * d).sqrt()).max(0.0)
}

/// What the limiter needs to know about one joint during one tick.
#[derive(Debug, Clone, Copy)]
struct Axis {
    lim: JointLimits,
    lo: f64,
    hi: f64,
    acc: f64,
    jerk: f64,
    dt: f64,
}

/// Slack kept inside the position range for rounding and the last creep to rest, rad.
const REST_SLACK_RAD: f64 = 1e-7;
/// Velocity loop of the braking policy near rest: a = −v/(2·dt) when that is within limits.
const BRAKE_GAIN_TICKS: f64 = 2.0;
/// The TCP speed (share of the published limits) past which a step is replaced by braking.
const CARTESIAN_GUARD: f64 = 0.9;
/// Ticks the check may simulate one by one (the constant-deceleration stretch is one step).
const MAX_CHECK_TICKS: usize = 400;

impl Axis {
    fn new(lim: JointLimits, cfg: &LimiterConfig, dt: f64) -> Self {
        Self {
            lim,
            lo: lim.q_min_rad + cfg.q_margin_rad,
            hi: lim.q_max_rad - cfg.q_margin_rad,
            acc: cfg.accel_scale * lim.ddq_max_rad_s2,
            jerk: cfg.jerk_scale * lim.jerk_max_rad_s3,
            dt,
        }
    }

    /// The acceleration one jerk-limited tick can reach from `a` toward `target`.
    #[inline]
    fn toward(&self, a: f64, target: f64) -> f64 {
        let step = self.jerk * self.dt;
        let next = if (target - a).abs() <= step { target } else { a + step.copysign(target - a) };
        next.clamp(-self.acc, self.acc)
    }

    /// The braking policy: drive the velocity to zero as fast as the limits allow, easing in
    /// near rest. A function of (v, a) only, which is what makes the safety check exact.
    #[inline]
    fn brake(&self, v: f64, a: f64) -> f64 {
        // The velocity reached if the acceleration were ramped to zero right away.
        let v_end = v + a * a.abs() / (2.0 * self.jerk);
        let target = (-v_end / (BRAKE_GAIN_TICKS * self.dt)).clamp(-self.acc, self.acc);
        self.toward(a, target)
    }

    #[inline]
    fn velocity_ok(&self, p: f64, v: f64) -> bool {
        let (lo, hi) = self.lim.velocity_bounds(p);
        v >= lo * (1.0 + 1e-12) - 1e-12 && v <= hi * (1.0 + 1e-12) + 1e-12
    }

    /// Where the braking policy, started at (p, v, a), comes to rest; `None` if it would leave
    /// the position range or exceed the velocity bounds on the way.
    fn can_stop(&self, mut p: f64, mut v: f64, mut a: f64) -> Option<f64> {
        let (lo, hi, dt) = (self.lo + REST_SLACK_RAD, self.hi - REST_SLACK_RAD, self.dt);
        for _ in 0..MAX_CHECK_TICKS {
            if !(p >= lo && p <= hi && self.velocity_ok(p, v)) {
                return None;
            }
            if v.abs() < 1e-8 && a.abs() < 1e-5 {
                return Some(p);
            }
            // A stretch at full deceleration, done in closed form: k ticks of a = ∓acc.
            let s = v.signum();
            if a == -s * self.acc {
                let v_end = v.abs() - self.acc * self.acc / (2.0 * self.jerk);
                let free = (v_end - BRAKE_GAIN_TICKS * dt * self.acc) / (self.acc * dt);
                let k = free.floor() - 1.0;
                if k >= 1.0 {
                    let dv = self.acc * dt;
                    let p_end = p + s * dt * (k * v.abs() - dv * k * (k + 1.0) / 2.0);
                    let v_end = v - s * k * dv;
                    if !(p_end >= lo && p_end <= hi && self.stretch_within_velocity(p, v, p_end)) {
                        return None;
                    }
                    p = p_end;
                    v = v_end;
                    continue;
                }
            }
            a = self.brake(v, a);
            v += a * dt;
            p += v * dt;
        }
        None
    }

    /// Position-dependent velocity bounds (FR3) along a constant-deceleration stretch from
    /// (p0, v0) to p1; |v| only falls along it, so constant bounds need no look.
    fn stretch_within_velocity(&self, p0: f64, v0: f64, p1: f64) -> bool {
        if self.lim.ddq_dec_rad_s2 <= 0.0 {
            return true;
        }
        (1..=8).all(|i| {
            let p = p0 + (p1 - p0) * f64::from(i) / 8.0;
            let v = v0.signum() * (v0 * v0 - 2.0 * self.acc * (p - p0).abs()).max(0.0).sqrt();
            self.velocity_ok(p, v)
        })
    }
}

/// The commanded joint state, advanced one tick at a time.
#[derive(Debug, Clone, Copy)]
pub struct JointTracker {
    pub q_rad: [f64; N],
    pub dq_rad_s: [f64; N],
    pub ddq_rad_s2: [f64; N],
    pub finger_m: f64,
    /// Where each joint comes to rest if braking starts now: the configuration the runtime
    /// checks for collisions along with the command itself.
    pub stop_q_rad: [f64; N],
    /// Ticks on which the braking policy overrode the tracking step of some joint.
    pub braking_ticks: u64,
    /// Ticks on which the TCP speed guard replaced the whole step by braking.
    pub tcp_guard_ticks: u64,
}

impl JointTracker {
    /// Starts at rest at a measured configuration (clamped into the safe range).
    pub fn at_rest(q_rad: [f64; N], finger_m: f64, robot: &RobotModel, cfg: &LimiterConfig) -> Self {
        let mut q = q_rad;
        for (qj, l) in q.iter_mut().zip(&robot.joints) {
            let v = if qj.is_finite() { *qj } else { 0.5 * (l.q_min_rad + l.q_max_rad) };
            *qj = v.clamp(l.q_min_rad + cfg.q_margin_rad + 1e-6, l.q_max_rad - cfg.q_margin_rad - 1e-6);
        }
        let finger = if finger_m.is_finite() { finger_m.clamp(0.0, robot.finger_max_m) } else { 0.0 };
        Self {
            q_rad: q,
            dq_rad_s: [0.0; N],
            ddq_rad_s2: [0.0; N],
            finger_m: finger,
            stop_q_rad: q,
            braking_ticks: 0,
            tcp_guard_ticks: 0,
        }
    }

    /// One tick of `dt_s`: follow `reference` within every limit. Allocation-free.
    #[allow(clippy::needless_range_loop)] // joint j indexes limits, reference and state alike
    pub fn step(&mut self, reference: &Reference, dt_s: f64, robot: &RobotModel, cfg: &LimiterConfig) {
        let before = *self;
        let mut braked = false;
        let mut v_des = [0.0; N];
        for j in 0..N {
            let x = Axis::new(robot.joints[j], cfg, dt_s);
            let track = 0.8 * x.acc;
            let p = self.q_rad[j];
            let r = if reference.q_rad[j].is_finite() { reference.q_rad[j].clamp(x.lo, x.hi) } else { p };
            let vr = if reference.dq_rad_s[j].is_finite() { reference.dq_rad_s[j] } else { 0.0 };
            let e = r - p;
            let fb = e.signum() * (cfg.gain_per_s * e.abs()).min(stop_speed(e.abs(), track, dt_s));
            let (vlo, vhi) = x.lim.velocity_bounds(p);
            // Aim below the bounds and stop short of the position limits with room to spare.
            let mut v_up = (0.95 * vhi).min(stop_speed(x.hi - p, track, dt_s));
            let mut v_dn = (-0.95 * vlo).min(stop_speed(p - x.lo, track, dt_s));
            // Nor past the point where the reference turns back or ends.
            let g = reference.goal_q_rad[j];
            if g.is_finite() {
                let g = g.clamp(x.lo, x.hi);
                if g >= p {
                    v_up = v_up.min(stop_speed(g - p, track, dt_s));
                } else {
                    v_dn = v_dn.min(stop_speed(p - g, track, dt_s));
                }
            }
            v_des[j] = (vr + fb).clamp(-v_dn, v_up);
        }
        self.limit_tcp_speed(&mut v_des, robot, cfg);
        for j in 0..N {
            let x = Axis::new(robot.joints[j], cfg, dt_s);
            let (p, v, a) = (self.q_rad[j], self.dq_rad_s[j], self.ddq_rad_s2[j]);
            // Inner loop: the acceleration toward the desired velocity, eased so that
            // ramping it back to zero lands on that velocity instead of past it.
            let dv = v_des[j] - v;
            let a_des = dv.signum() * (cfg.velocity_gain_per_s * dv.abs()).min(stop_speed(dv.abs(), x.jerk, dt_s));
            let mut a1 = x.toward(a, a_des);
            // The check also keeps the arm from passing the point where the reference turns
            // back or ends (braking lands short of it; tracking then closes the rest).
            let mut bounded = x;
            let g = reference.goal_q_rad[j];
            if g.is_finite() {
                if g >= p {
                    bounded.hi = bounded.hi.min(g);
                } else {
                    bounded.lo = bounded.lo.max(g);
                }
            }
            match bounded.can_stop(p + (v + a1 * dt_s) * dt_s, v + a1 * dt_s, a1) {
                Some(rest) => self.stop_q_rad[j] = rest,
                // The braking step continues the path checked last tick: its rest point stays.
                None => {
                    a1 = x.brake(v, a);
                    braked = true;
                }
            }
            let v1 = v + a1 * dt_s;
            self.ddq_rad_s2[j] = a1;
            self.dq_rad_s[j] = v1;
            self.q_rad[j] = p + v1 * dt_s;
        }
        // A step that would carry the TCP faster than CARTESIAN_GUARD of its published limits
        // is replaced by braking every joint from where the tick began.
        if !self.tcp_speed_within(robot, CARTESIAN_GUARD) {
            *self = before;
            self.brake(dt_s, robot, cfg);
            self.tcp_guard_ticks += 1;
        } else if braked {
            self.braking_ticks += 1;
        }
        self.step_finger(reference.gripper, dt_s, robot);
    }

    /// Whether the commanded TCP twist stays within `fraction` of the Cartesian limits.
    fn tcp_speed_within(&self, robot: &RobotModel, fraction: f64) -> bool {
        let (_, jac) = robot.kin.jacobian(&self.q_rad, robot.kin.tcp);
        let twist = jac * nalgebra::SVector::<f64, N>::from_column_slice(&self.dq_rad_s);
        twist.fixed_rows::<3>(0).norm() <= fraction * robot.cartesian.v_m_s
            && twist.fixed_rows::<3>(3).norm() <= fraction * robot.cartesian.w_rad_s
    }

    /// One tick of braking on every joint, toward the rest configuration `stop_q_rad`.
    pub fn brake(&mut self, dt_s: f64, robot: &RobotModel, cfg: &LimiterConfig) {
        for j in 0..N {
            let x = Axis::new(robot.joints[j], cfg, dt_s);
            let a1 = x.brake(self.dq_rad_s[j], self.ddq_rad_s2[j]);
            self.ddq_rad_s2[j] = a1;
            self.dq_rad_s[j] += a1 * dt_s;
            self.q_rad[j] += self.dq_rad_s[j] * dt_s;
        }
        self.braking_ticks += 1;
    }

    /// True once every joint has stopped.
    pub fn stopped(&self) -> bool {
        self.dq_rad_s.iter().all(|v| v.abs() < 1e-9) && self.ddq_rad_s2.iter().all(|a| a.abs() < 1e-6)
    }

    fn step_finger(&mut self, gripper: f64, dt_s: f64, robot: &RobotModel) {
        let target = robot.finger_from_gripper(if gripper.is_finite() { gripper } else { 0.0 });
        let step = robot.finger_speed_m_s * dt_s;
        self.finger_m += (target - self.finger_m).clamp(-step, step);
        self.finger_m = self.finger_m.clamp(0.0, robot.finger_max_m);
    }

    /// Scales the desired joint velocity so that the TCP stays under its speed limits.
    fn limit_tcp_speed(&self, v_des: &mut [f64; N], robot: &RobotModel, cfg: &LimiterConfig) {
        let (_, jac) = robot.kin.jacobian(&self.q_rad, robot.kin.tcp);
        let v = nalgebra::SVector::<f64, N>::from_column_slice(v_des);
        let twist = jac * v;
        let lin = twist.fixed_rows::<3>(0).norm();
        let ang = twist.fixed_rows::<3>(3).norm();
        let cap_lin = cfg.tcp_speed_scale * robot.cartesian.v_m_s;
        let cap_ang = cfg.tcp_speed_scale * robot.cartesian.w_rad_s;
        let scale = (cap_lin / lin).min(cap_ang / ang).min(1.0);
        if scale < 1.0 {
            v_des.iter_mut().for_each(|v| *v *= scale);
        }
    }

    /// True once the command sits on `reference` and has stopped.
    pub fn settled_on(&self, reference: &Reference, robot: &RobotModel) -> bool {
        let target = robot.finger_from_gripper(reference.gripper);
        (0..N).all(|j| {
            (self.q_rad[j] - reference.q_rad[j]).abs() < 1e-6
                && self.dq_rad_s[j].abs() < 1e-4
                && self.ddq_rad_s2[j].abs() < 1e-2
        }) && (self.finger_m - target).abs() < 1e-6
    }
}
