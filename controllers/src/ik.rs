//! Inverse kinematics: the joint configuration that puts a frame of the arm at a full pose
//! (position and orientation), inside the joint limits.
//!
//! Method: Levenberg–Marquardt on the 6-D pose error `[p* − p; log(R*·Rᵀ)]` in the base frame,
//! with the geometric Jacobian. Each step solves the damped 6×6 system `(J·Jᵀ + λ·I)·y = e` by
//! Cholesky and moves `Δq = Jᵀ·y`; the new configuration is clamped into the (optionally
//! shrunk) joint box. A step that does not lower the error is refused and the damping raised;
//! an accepted one lowers it, so the solver behaves like gradient descent far from the target
//! and like Gauss–Newton close to it. Joints pinned at a limit that the step would push further
//! out are taken out of the system for that step, so the others do the work.
//!
//! An attempt ends when both errors are within tolerance, after `max_iterations` evaluations,
//! or when the damping has grown so large that it is stuck in a local minimum. Then the solver
//! restarts from a pseudo-random configuration drawn by a seeded generator, so the same call
//! always gives the same answer. All state lives in fixed-size arrays: nothing allocates after
//! [`IkSolver::new`].

use std::time::{Duration, Instant};

use nalgebra::{Cholesky, Isometry3, SMatrix, SVector, UnitQuaternion, Vector3};

use crate::kinematics::{FrameId, Jacobian, Kinematics};
use crate::robot::RobotModel;
use crate::N;

type Vector6 = SVector<f64, 6>;
type Matrix6 = SMatrix<f64, 6, 6>;

/// Settings of an [`IkSolver`]. [`IkConfig::default`] gives 1e-5 m and 1e-5 rad.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkConfig {
    /// Largest accepted distance between the frame's origin and the target position, m.
    pub position_tolerance_m: f64,
    /// Largest accepted angle of the rotation between the frame and the target, rad.
    pub rotation_tolerance_rad: f64,
    /// Each joint range is shrunk by this much at both ends, rad (0: the full range).
    pub limit_margin_rad: f64,
    /// Evaluations of one attempt (from the seed or one restart) before it gives up.
    pub max_iterations: u32,
    /// Restarts from pseudo-random configurations after the seeded attempt fails.
    pub max_restarts: u32,
    /// Evaluations over all attempts of one solve.
    pub max_total_iterations: u32,
    /// Wall-clock budget of one solve. `None` (the default) keeps the solver deterministic;
    /// with a budget the answer can depend on the machine's speed.
    pub time_budget: Option<Duration>,
    /// Seed of the generator that draws restart configurations (reset on every solve).
    pub restart_seed: u64,
}

impl Default for IkConfig {
    fn default() -> Self {
        Self {
            position_tolerance_m: 1e-5,
            rotation_tolerance_rad: 1e-5,
            limit_margin_rad: 0.0,
            max_iterations: 60,
            max_restarts: 400,
            max_total_iterations: 20000,
            time_budget: None,
            restart_seed: 0x5EED_1C0F_FEE0_0001,
        }
    }
}

/// Inputs the solver refuses; unreachable targets are not errors but `ok == false`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum IkError {
    #[error("target {what} is not finite (NaN or infinity)")]
    NonFiniteTarget { what: &'static str },
    #[error("target orientation is not a unit quaternion (norm {norm})")]
    NotUnitQuaternion { norm: f64 },
    #[error("seed joint {} = {value} is not finite (NaN or infinity)", joint + 1)]
    NonFiniteSeed { joint: usize, value: f64 },
    #[error("frame index {index} does not exist (the model has {count} frames)")]
    NoSuchFrame { index: usize, count: usize },
    #[error("IK settings are not usable: {0}")]
    BadConfig(String),
}

/// Result of one solve. When `ok` is false, `q` is the best configuration found (still within
/// the limits) and the errors say how far it is from the target; both are always finite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    pub ok: bool,
    pub q: [f64; N],
    pub position_error_m: f64,
    pub rotation_error_rad: f64,
    /// Pose evaluations over all attempts.
    pub iterations: u32,
    /// Attempts started from a pseudo-random configuration.
    pub restarts: u32,
}

/// A small seeded generator (SplitMix64): deterministic, allocation-free, good enough to
/// scatter restart configurations and benchmark targets.
#[derive(Debug, Clone, Copy)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// A configuration drawn uniformly from the box `[lo, hi]`.
    pub fn config(&mut self, lo: &[f64; N], hi: &[f64; N]) -> [f64; N] {
        let mut q = [0.0; N];
        for j in 0..N {
            q[j] = lo[j] + (hi[j] - lo[j]) * self.next_f64();
        }
        q
    }
}

/// Rotation vector (axis · angle, angle in [0, π]) of a unit quaternion.
#[inline]
fn log_map(r: &UnitQuaternion<f64>) -> Vector3<f64> {
    let q = r.quaternion();
    // q and −q are the same rotation: take the one with w ≥ 0 for the shorter angle.
    let (w, v) = if q.w >= 0.0 { (q.w, q.vector().into_owned()) } else { (-q.w, -q.vector().into_owned()) };
    let s = v.norm();
    if s < 1e-12 {
        // sin(θ/2) ≈ θ/2: the first-order term is exact to rounding here.
        return v * 2.0;
    }
    v * (2.0 * s.atan2(w) / s)
}

/// Pose error of `pose` against `target`: translation (rows 0–2) and rotation vector (3–5).
#[inline]
fn pose_error(target: &Isometry3<f64>, pose: &Isometry3<f64>) -> Vector6 {
    let dp = target.translation.vector - pose.translation.vector;
    let dr = log_map(&(target.rotation * pose.rotation.inverse()));
    Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
}

#[inline]
fn norms(e: &Vector6) -> (f64, f64) {
    (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm())
}

/// Counts evaluations and watches the clock across the attempts of one solve.
struct Budget {
    used: u32,
    max: u32,
    deadline: Option<Instant>,
}

impl Budget {
    #[inline]
    fn take(&mut self) -> bool {
        if self.used >= self.max {
            return false;
        }
        if let Some(d) = self.deadline {
            if Instant::now() >= d {
                return false;
            }
        }
        self.used += 1;
        true
    }
}

/// Outcome of one attempt.
#[derive(Clone, Copy)]
struct Attempt {
    q: [f64; N],
    position_error_m: f64,
    rotation_error_rad: f64,
    ok: bool,
}

const LAMBDA_START: f64 = 0.1;
/// Damping factors after an accepted and after a refused step.
const LAMBDA_DOWN: f64 = 0.3;
const LAMBDA_UP: f64 = 4.0;
/// Every `PROGRESS_EVERY` evaluations the squared error must have at least halved, or the
/// attempt is abandoned: converging attempts do that easily, ones caught on a limit do not.
const PROGRESS_EVERY: u32 = 5;
const PROGRESS_FACTOR: f64 = 0.5;
const LAMBDA_MIN: f64 = 1e-12;
/// Damping beyond which an attempt counts as stuck.
const LAMBDA_STUCK: f64 = 1e4;

/// Full-pose IK for one arm. Build once (this allocates: it keeps its own copy of the
/// kinematics); every solve after that is allocation-free.
#[derive(Debug, Clone)]
pub struct IkSolver {
    kin: Kinematics,
    lo: [f64; N],
    hi: [f64; N],
    config: IkConfig,
    frame: FrameId,
}

impl IkSolver {
    /// A solver for `robot`'s TCP within its joint limits shrunk by `config.limit_margin_rad`.
    pub fn new(robot: &RobotModel, config: IkConfig) -> Result<Self, IkError> {
        let mut lo = [0.0; N];
        let mut hi = [0.0; N];
        for (j, l) in robot.joints.iter().enumerate() {
            lo[j] = l.q_min_rad;
            hi[j] = l.q_max_rad;
        }
        Self::from_parts(robot.kin.clone(), lo, hi, config)
    }

    /// A solver for any chain: `lo`/`hi` are the joint limits before the margin is applied.
    pub fn from_parts(kin: Kinematics, lo: [f64; N], hi: [f64; N], config: IkConfig) -> Result<Self, IkError> {
        let c = &config;
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !(positive(c.position_tolerance_m) && positive(c.rotation_tolerance_rad)) {
            return Err(IkError::BadConfig("tolerances must be finite and positive".into()));
        }
        if !(c.limit_margin_rad.is_finite() && c.limit_margin_rad >= 0.0) {
            return Err(IkError::BadConfig("limit_margin_rad must be finite and not negative".into()));
        }
        if c.max_iterations == 0 || c.max_total_iterations == 0 {
            return Err(IkError::BadConfig("max_iterations and max_total_iterations must be at least 1".into()));
        }
        let (mut l2, mut h2) = (lo, hi);
        for j in 0..N {
            l2[j] = lo[j] + c.limit_margin_rad;
            h2[j] = hi[j] - c.limit_margin_rad;
            if !(l2[j].is_finite() && h2[j].is_finite() && l2[j] <= h2[j]) {
                return Err(IkError::BadConfig(format!(
                    "joint {} range [{}, {}] is empty after a margin of {} rad",
                    j + 1,
                    lo[j],
                    hi[j],
                    c.limit_margin_rad
                )));
            }
        }
        let frame = kin.tcp;
        Ok(Self { kin, lo: l2, hi: h2, config, frame })
    }

    pub fn config(&self) -> &IkConfig {
        &self.config
    }

    pub fn kinematics(&self) -> &Kinematics {
        &self.kin
    }

    /// The joint box the solver keeps to (limits after the margin).
    pub fn bounds(&self) -> (&[f64; N], &[f64; N]) {
        (&self.lo, &self.hi)
    }

    /// The frame [`Self::solve`] places (the TCP unless changed).
    pub fn frame(&self) -> FrameId {
        self.frame
    }

    /// Makes [`Self::solve`] place `frame` instead of the TCP.
    pub fn set_frame(&mut self, frame: FrameId) -> Result<(), IkError> {
        self.check_frame(frame)?;
        self.frame = frame;
        Ok(())
    }

    fn check_frame(&self, frame: FrameId) -> Result<(), IkError> {
        let count = self.kin.frames().len();
        if frame.0 >= count {
            return Err(IkError::NoSuchFrame { index: frame.0, count });
        }
        Ok(())
    }

    /// Puts the configured frame (TCP by default) at `target`, starting from `seed`.
    pub fn solve(&self, target: &Isometry3<f64>, seed: &[f64; N]) -> Result<IkSolution, IkError> {
        self.solve_frame(target, self.frame, seed)
    }

    /// Puts `frame` at `target` (base frame), starting from `seed` (clamped into the limits).
    pub fn solve_frame(&self, target: &Isometry3<f64>, frame: FrameId, seed: &[f64; N]) -> Result<IkSolution, IkError> {
        self.check_frame(frame)?;
        if !target.translation.vector.iter().all(|v| v.is_finite()) {
            return Err(IkError::NonFiniteTarget { what: "position" });
        }
        let quat = target.rotation.quaternion();
        if !quat.coords.iter().all(|v| v.is_finite()) {
            return Err(IkError::NonFiniteTarget { what: "orientation" });
        }
        let norm = quat.norm();
        if (norm - 1.0).abs() > 1e-6 {
            return Err(IkError::NotUnitQuaternion { norm });
        }
        if let Some((joint, &value)) = seed.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(IkError::NonFiniteSeed { joint, value });
        }
        let mut budget = Budget {
            used: 0,
            max: self.config.max_total_iterations,
            deadline: self.config.time_budget.map(|d| Instant::now() + d),
        };
        let mut start = *seed;
        self.clamp(&mut start);
        let mut best = self.attempt(target, frame, start, &mut budget);
        let mut rng = SplitMix64::new(self.config.restart_seed);
        let mut restarts = 0;
        while !best.ok && restarts < self.config.max_restarts && budget.used < budget.max {
            restarts += 1;
            let q0 = rng.config(&self.lo, &self.hi);
            let a = self.attempt(target, frame, q0, &mut budget);
            if a.ok || Self::score(&a) < Self::score(&best) {
                best = a;
            }
            if let Some(d) = budget.deadline {
                if Instant::now() >= d {
                    break;
                }
            }
        }
        Ok(IkSolution {
            ok: best.ok,
            q: best.q,
            position_error_m: best.position_error_m,
            rotation_error_rad: best.rotation_error_rad,
            iterations: budget.used,
            restarts,
        })
    }

    /// Orders failed attempts: a metre of position counts like a radian of rotation.
    fn score(a: &Attempt) -> f64 {
        a.position_error_m + a.rotation_error_rad
    }

    #[inline]
    fn clamp(&self, q: &mut [f64; N]) {
        for ((qj, lo), hi) in q.iter_mut().zip(&self.lo).zip(&self.hi) {
            *qj = qj.clamp(*lo, *hi);
        }
    }

    fn converged(&self, pos: f64, rot: f64) -> bool {
        pos <= self.config.position_tolerance_m && rot <= self.config.rotation_tolerance_rad
    }

    /// One Levenberg–Marquardt run from `q` (already within the box).
    fn attempt(&self, target: &Isometry3<f64>, frame: FrameId, mut q: [f64; N], budget: &mut Budget) -> Attempt {
        let (pose, mut jac) = self.kin.jacobian(&q, frame);
        let mut e = pose_error(target, &pose);
        let mut cost = e.norm_squared();
        let (mut pos, mut rot) = norms(&e);
        let done = |q: [f64; N], pos: f64, rot: f64, ok: bool| Attempt {
            q,
            position_error_m: pos,
            rotation_error_rad: rot,
            ok,
        };
        if self.converged(pos, rot) {
            return done(q, pos, rot, true);
        }
        let mut lambda = LAMBDA_START;
        let mut used = 0;
        let mut checkpoint = cost;
        while used < self.config.max_iterations && budget.take() {
            used += 1;
            if used % PROGRESS_EVERY == 0 {
                if cost > PROGRESS_FACTOR * checkpoint {
                    break;
                }
                checkpoint = cost;
            }
            let Some(dq) = self.step(&q, &jac, &e, lambda) else {
                lambda *= LAMBDA_UP;
                if lambda > LAMBDA_STUCK {
                    break;
                }
                continue;
            };
            let mut trial = q;
            for j in 0..N {
                trial[j] += dq[j];
            }
            self.clamp(&mut trial);
            let (tpose, tjac) = self.kin.jacobian(&trial, frame);
            let te = pose_error(target, &tpose);
            let tcost = te.norm_squared();
            if tcost < cost {
                q = trial;
                jac = tjac;
                e = te;
                cost = tcost;
                (pos, rot) = norms(&e);
                if self.converged(pos, rot) {
                    return done(q, pos, rot, true);
                }
                lambda = (lambda * LAMBDA_DOWN).max(LAMBDA_MIN);
            } else {
                lambda *= LAMBDA_UP;
                if lambda > LAMBDA_STUCK {
                    break;
                }
            }
        }
        done(q, pos, rot, false)
    }

    /// The damped step from `q`; joints at a limit that the step would push outward are frozen
    /// and the step recomputed without them. `None` when the system cannot be factored.
    #[inline]
    fn step(&self, q: &[f64; N], jac: &Jacobian, e: &Vector6, lambda: f64) -> Option<SVector<f64, N>> {
        let dq = Self::damped(jac, e, lambda)?;
        let mut frozen = false;
        let mut masked = *jac;
        for j in 0..N {
            let at_lo = q[j] <= self.lo[j] && dq[j] < 0.0;
            let at_hi = q[j] >= self.hi[j] && dq[j] > 0.0;
            if at_lo || at_hi {
                masked.column_mut(j).fill(0.0);
                frozen = true;
            }
        }
        if frozen {
            Self::damped(&masked, e, lambda)
        } else {
            Some(dq)
        }
    }

    #[inline]
    fn damped(jac: &Jacobian, e: &Vector6, lambda: f64) -> Option<SVector<f64, N>> {
        let mut a: Matrix6 = jac * jac.transpose();
        for i in 0..6 {
            a[(i, i)] += lambda;
        }
        let chol = Cholesky::new(a)?;
        let y = chol.solve(e);
        let dq = jac.transpose() * y;
        dq.iter().all(|v| v.is_finite()).then_some(dq)
    }
}
