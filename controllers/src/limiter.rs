//! The last stage before a command leaves the runtime: a per-joint tracker whose output never
//! leaves the position range (minus margin) and never exceeds the velocity and acceleration
//! limits, whatever reference it is given. Jerk limiting comes with the Controllers issue.

use crate::chunk::Reference;
use crate::robot::RobotModel;
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
    /// Feedback gain pulling the command onto the reference, 1/s.
    pub gain_per_s: f64,
    pub default_freq_hz: f64,
    /// Slowest waypoint rate accepted; with `max_chunk_duration_s`, bounds how long the runtime
    /// stays busy with one chunk.
    pub min_freq_hz: f64,
    pub max_freq_hz: f64,
    pub max_chunk_duration_s: f64,
    pub max_chunk: usize,
}

impl Default for LimiterConfig {
    fn default() -> Self {
        Self {
            q_margin_rad: 0.01,
            speed_scale: 0.5,
            accel_scale: 0.5,
            gain_per_s: 40.0,
            default_freq_hz: 20.0,
            min_freq_hz: 0.5,
            max_freq_hz: 1000.0,
            max_chunk_duration_s: 120.0,
            max_chunk: 256,
        }
    }
}

/// The largest speed at which, after one more tick of motion, the remaining distance `d` still
/// covers the stopping distance at deceleration `a`: v·dt + v²/(2a) ≤ d. Discrete time keeps
/// the reserve that the continuous √(2ad) bound lacks, so the limits hold tick by tick.
#[inline]
fn stop_speed(d: f64, a: f64, dt: f64) -> f64 {
    let d = d.max(0.0);
    (-a * dt + (a * a * dt * dt + 2.0 * a * d).sqrt()).max(0.0)
}

/// The commanded joint state, advanced one tick at a time.
#[derive(Debug, Clone, Copy)]
pub struct JointTracker {
    pub q_rad: [f64; N],
    pub dq_rad_s: [f64; N],
    pub finger_m: f64,
}

impl JointTracker {
    /// Starts at rest at a measured configuration (clamped into the safe range).
    pub fn at_rest(q_rad: [f64; N], finger_m: f64, robot: &RobotModel, cfg: &LimiterConfig) -> Self {
        let mut q = q_rad;
        for (qj, l) in q.iter_mut().zip(&robot.joints) {
            let v = if qj.is_finite() { *qj } else { 0.5 * (l.q_min_rad + l.q_max_rad) };
            *qj = v.clamp(l.q_min_rad + cfg.q_margin_rad, l.q_max_rad - cfg.q_margin_rad);
        }
        let finger = if finger_m.is_finite() { finger_m.clamp(0.0, robot.finger_max_m) } else { 0.0 };
        Self { q_rad: q, dq_rad_s: [0.0; N], finger_m: finger }
    }

    /// One tick of `dt_s`: follow `reference` within every limit. Allocation-free.
    #[allow(clippy::needless_range_loop)] // joint j indexes limits, reference and state alike
    pub fn step(&mut self, reference: &Reference, dt_s: f64, robot: &RobotModel, cfg: &LimiterConfig) {
        for j in 0..N {
            let l = robot.joints[j];
            let a = cfg.accel_scale * l.ddq_max_rad_s2;
            let (lo, hi) = (l.q_min_rad + cfg.q_margin_rad, l.q_max_rad - cfg.q_margin_rad);
            let p = self.q_rad[j];
            let r = if reference.q_rad[j].is_finite() { reference.q_rad[j].clamp(lo, hi) } else { p };
            let vr = if reference.dq_rad_s[j].is_finite() { reference.dq_rad_s[j] } else { 0.0 };
            let e = r - p;
            let fb = e.signum() * (cfg.gain_per_s * e.abs()).min(stop_speed(e.abs(), a, dt_s));
            let vmax = l.dq_max_rad_s;
            // Never a speed from which a position limit could not be reached at rest.
            let mut v_up = stop_speed(hi - p, a, dt_s).min(vmax);
            let mut v_dn = stop_speed(p - lo, a, dt_s).min(vmax);
            // Nor one that would carry the arm past the chunk's final target.
            let g = reference.goal_q_rad[j];
            if g.is_finite() {
                let g = g.clamp(lo, hi);
                if g >= p {
                    v_up = v_up.min(stop_speed(g - p, a, dt_s));
                } else {
                    v_dn = v_dn.min(stop_speed(p - g, a, dt_s));
                }
            }
            let v_des = (vr + fb).clamp(-v_dn, v_up);
            let dv = (v_des - self.dq_rad_s[j]).clamp(-a * dt_s, a * dt_s);
            let mut v = self.dq_rad_s[j] + dv;
            let mut q = p + v * dt_s;
            // Unreachable by construction (stop_speed keeps a stopping distance in reserve);
            // kept as the last guard should a model or rounding ever disagree.
            if q > hi {
                q = hi;
                v = 0.0;
            } else if q < lo {
                q = lo;
                v = 0.0;
            }
            self.q_rad[j] = q;
            self.dq_rad_s[j] = v;
        }
        let target = robot.finger_from_gripper(if reference.gripper.is_finite() { reference.gripper } else { 0.0 });
        let step = robot.finger_speed_m_s * dt_s;
        self.finger_m += (target - self.finger_m).clamp(-step, step);
        self.finger_m = self.finger_m.clamp(0.0, robot.finger_max_m);
    }

    /// True once the command sits on `reference` and has stopped.
    pub fn settled_on(&self, reference: &Reference, robot: &RobotModel) -> bool {
        let target = robot.finger_from_gripper(reference.gripper);
        (0..N).all(|j| (self.q_rad[j] - reference.q_rad[j]).abs() < 1e-6 && self.dq_rad_s[j].abs() < 1e-4)
            && (self.finger_m - target).abs() < 1e-6
    }
}
