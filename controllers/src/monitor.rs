//! An independent referee for the emitted command stream: it sees only the commands, derives
//! velocity, acceleration and jerk by finite differences, and counts every limit broken. The
//! tests, the property tests and `r2g bench limiter-fuzz` all judge the limiter with it.

use crate::limiter::LimiterConfig;
use crate::robot::RobotModel;
use crate::N;

/// Relative slack for floating-point rounding in finite differences.
const REL_TOL: f64 = 1e-9;

/// Counts of broken limits, by kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Violations {
    pub not_finite: u64,
    pub position: u64,
    pub velocity: u64,
    pub acceleration: u64,
    pub jerk: u64,
    pub tcp_speed: u64,
    pub finger: u64,
}

impl Violations {
    pub fn total(&self) -> u64 {
        self.not_finite + self.position + self.velocity + self.acceleration + self.jerk + self.tcp_speed + self.finger
    }
}

/// Watches one command stream at a fixed period.
#[derive(Debug, Clone)]
pub struct Monitor {
    dt_s: f64,
    /// The last four commands, newest first, and how many of them are valid.
    hist: [[f64; N]; 4],
    tcp: [f64; 3],
    finger: f64,
    seen: usize,
    pub commands: u64,
    pub violations: Violations,
    /// The first violation, described, for test messages.
    pub first: Option<String>,
}

impl Monitor {
    pub fn new(dt_s: f64) -> Self {
        Self {
            dt_s,
            hist: [[0.0; N]; 4],
            tcp: [0.0; 3],
            finger: 0.0,
            seen: 0,
            commands: 0,
            violations: Violations::default(),
            first: None,
        }
    }

    /// Starts a new stream from rest at `q` (the limiter's state before its first command).
    pub fn start_at(&mut self, q: &[f64; N], finger_m: f64, robot: &RobotModel) {
        self.hist = [*q; 4];
        self.finger = finger_m;
        self.tcp = tcp_position(q, robot);
        self.seen = 1;
    }

    fn flag(&mut self, kind: fn(&mut Violations) -> &mut u64, what: std::fmt::Arguments<'_>) {
        *kind(&mut self.violations) += 1;
        if self.first.is_none() {
            self.first = Some(format!("command {}: {what}", self.commands));
        }
    }

    /// Judges one command against the robot's configured limits.
    pub fn observe(&mut self, q: &[f64; N], finger_m: f64, robot: &RobotModel, cfg: &LimiterConfig) {
        self.commands += 1;
        if !(q.iter().all(|v| v.is_finite()) && finger_m.is_finite()) {
            self.flag(|v| &mut v.not_finite, format_args!("non-finite command {q:?}"));
            return;
        }
        self.hist.copy_within(0..3, 1);
        self.hist[0] = *q;
        // Without a known start, the stream starts at rest at its first command.
        if self.seen == 0 {
            self.hist = [*q; 4];
            self.finger = finger_m;
            self.tcp = tcp_position(q, robot);
            self.seen = 1;
        }
        let dt = self.dt_s;
        for j in 0..N {
            let l = robot.joints[j];
            let (lo, hi) = (l.q_min_rad + cfg.q_margin_rad, l.q_max_rad - cfg.q_margin_rad);
            let hist = self.hist;
            let h = |k: usize| hist[k][j];
            let p = h(0);
            if p < lo - 1e-12 || p > hi + 1e-12 {
                self.flag(|v| &mut v.position, format_args!("joint {} at {p} outside [{lo}, {hi}]", j + 1));
            }
            let v = (h(0) - h(1)) / dt;
            let (vlo, vhi) = l.velocity_bounds(h(1));
            let (vlo2, vhi2) = l.velocity_bounds(h(0));
            // The bound may be read at either end of the tick: take the looser one.
            let (vlo, vhi) = (vlo.min(vlo2), vhi.max(vhi2));
            if v > vhi * (1.0 + REL_TOL) + 1e-9 || v < vlo * (1.0 + REL_TOL) - 1e-9 {
                self.flag(|v| &mut v.velocity, format_args!("joint {} velocity {v} outside [{vlo}, {vhi}]", j + 1));
            }
            let acc_lim = cfg.accel_scale * l.ddq_max_rad_s2;
            let a = (h(0) - 2.0 * h(1) + h(2)) / (dt * dt);
            if a.abs() > acc_lim * (1.0 + 1e-6) + 1e-6 {
                self.flag(|v| &mut v.acceleration, format_args!("joint {} acceleration {a} > {acc_lim}", j + 1));
            }
            let jerk_lim = cfg.jerk_scale * l.jerk_max_rad_s3;
            let jk = (h(0) - 3.0 * h(1) + 3.0 * h(2) - h(3)) / (dt * dt * dt);
            if jk.abs() > jerk_lim * (1.0 + 1e-6) + 1e-3 {
                self.flag(|v| &mut v.jerk, format_args!("joint {} jerk {jk} > {jerk_lim}", j + 1));
            }
        }
        let tcp = tcp_position(q, robot);
        let speed = ((tcp[0] - self.tcp[0]).powi(2) + (tcp[1] - self.tcp[1]).powi(2) + (tcp[2] - self.tcp[2]).powi(2))
            .sqrt()
            / dt;
        if speed > robot.cartesian.v_m_s {
            self.flag(|v| &mut v.tcp_speed, format_args!("TCP speed {speed} m/s > {}", robot.cartesian.v_m_s));
        }
        self.tcp = tcp;
        let df = (finger_m - self.finger).abs() / dt;
        if !(0.0..=robot.finger_max_m).contains(&finger_m) || df > robot.finger_speed_m_s * (1.0 + 1e-9) + 1e-12 {
            self.flag(|v| &mut v.finger, format_args!("finger {finger_m} m moving {df} m/s"));
        }
        self.finger = finger_m;
    }
}

fn tcp_position(q: &[f64; N], robot: &RobotModel) -> [f64; 3] {
    let t = robot.kin.fk(q, robot.kin.tcp).translation.vector;
    [t.x, t.y, t.z]
}
