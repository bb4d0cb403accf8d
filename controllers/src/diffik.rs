//! Differential IK for the 1 kHz tick, posed as a small QP over joint velocities:
//!
//!   minimise ½‖J·q̇ − ξ‖²_W + ½λ‖q̇‖² + ½μ‖q̇ − k·(q_rest − q)‖²
//!   subject to  max(−q̇_max, (q_min − q)/τ) ≤ q̇ ≤ min(q̇_max, (q_max − q)/τ)
//!
//! where ξ is the desired TCP twist (feed-forward plus feedback on the pose error). The joint
//! position and velocity limits are box constraints on q̇, so the QP is solved exactly by a
//! primal active-set method on fixed-size matrices: no allocation, a few microseconds. The
//! test suite checks every solution against the Clarabel interior-point solver.

use nalgebra::{Cholesky, Isometry3, SMatrix, SVector, Vector3, Vector6};

use crate::limiter::LimiterConfig;
use crate::robot::RobotModel;
use crate::N;

pub type Mat7 = SMatrix<f64, N, N>;
pub type Vec7 = SVector<f64, N>;

/// Result of [`solve_box_qp`].
#[derive(Debug, Clone, Copy)]
pub struct BoxQpSolution {
    pub x: Vec7,
    pub iterations: usize,
    pub converged: bool,
}

/// Minimises ½xᵀHx + gᵀx subject to lb ≤ x ≤ ub (H symmetric positive definite, lb ≤ ub).
pub fn solve_box_qp(h: &Mat7, g: &Vec7, lb: &Vec7, ub: &Vec7) -> BoxQpSolution {
    // 0 free, −1 at the lower bound, +1 at the upper bound.
    let mut state = [0i8; N];
    let mut x = Vec7::from_fn(|i, _| 0.0f64.clamp(lb[i], ub[i]));
    for (i, s) in state.iter_mut().enumerate() {
        if lb[i] == ub[i] {
            *s = -1;
        }
    }
    for it in 0..(4 * N + 8) {
        // Minimiser over the free variables with the others held at their bounds.
        let mut hr = *h;
        let mut rhs = -g;
        for i in 0..N {
            if state[i] != 0 {
                let b = if state[i] < 0 { lb[i] } else { ub[i] };
                for k in 0..N {
                    if state[k] == 0 {
                        rhs[k] -= h[(k, i)] * b;
                    }
                    hr[(i, k)] = 0.0;
                    hr[(k, i)] = 0.0;
                }
                hr[(i, i)] = 1.0;
                rhs[i] = b;
            }
        }
        let Some(chol) = Cholesky::new(hr) else {
            return BoxQpSolution { x, iterations: it, converged: false };
        };
        let cand = chol.solve(&rhs);
        // Walk from x toward the candidate until the first free variable meets a bound.
        let mut alpha = 1.0f64;
        let mut blocking = None;
        for i in 0..N {
            if state[i] != 0 {
                continue;
            }
            let d = cand[i] - x[i];
            if d > 0.0 && cand[i] > ub[i] {
                let a = (ub[i] - x[i]) / d;
                if a < alpha {
                    alpha = a;
                    blocking = Some((i, 1i8));
                }
            } else if d < 0.0 && cand[i] < lb[i] {
                let a = (lb[i] - x[i]) / d;
                if a < alpha {
                    alpha = a;
                    blocking = Some((i, -1i8));
                }
            }
        }
        x += alpha.max(0.0) * (cand - x);
        if let Some((i, side)) = blocking {
            state[i] = side;
            x[i] = if side < 0 { lb[i] } else { ub[i] };
            continue;
        }
        // At the minimiser of this face: a bound whose multiplier has the wrong sign is released.
        let grad = h * x + g;
        let mut worst = (0.0, None);
        for i in 0..N {
            let wrong = match state[i] {
                -1 if lb[i] < ub[i] => -grad[i],
                1 if lb[i] < ub[i] => grad[i],
                _ => 0.0,
            };
            if wrong > worst.0 + 1e-12 {
                worst = (wrong, Some(i));
            }
        }
        match worst.1 {
            Some(i) => state[i] = 0,
            None => return BoxQpSolution { x, iterations: it + 1, converged: true },
        }
    }
    BoxQpSolution { x, iterations: 4 * N + 8, converged: false }
}

/// Settings of the differential IK.
#[derive(Debug, Clone, Copy)]
pub struct DiffIkConfig {
    /// Pose-error feedback, 1/s.
    pub gain_per_s: f64,
    /// Weight of rotation against translation errors (m per rad).
    pub rotation_weight: f64,
    /// Damping λ, keeping q̇ bounded near singularities.
    pub damping: f64,
    /// Weight μ and gain k of the pull toward the rest posture.
    pub posture_weight: f64,
    pub posture_gain_per_s: f64,
    /// Time constant τ over which a joint may close its distance to a position limit, s.
    pub limit_horizon_s: f64,
}

impl Default for DiffIkConfig {
    fn default() -> Self {
        Self {
            gain_per_s: 30.0,
            rotation_weight: 0.3,
            damping: 1e-4,
            // Off by default: a pull in the null space keeps the joints creeping long after
            // the TCP has arrived, and the box constraints already keep them off the limits.
            posture_weight: 0.0,
            posture_gain_per_s: 1.0,
            limit_horizon_s: 0.05,
        }
    }
}

/// Pose error of `target` relative to `current` as a base-frame 6-vector (translation, then
/// rotation vector).
pub fn pose_error(current: &Isometry3<f64>, target: &Isometry3<f64>) -> Vector6<f64> {
    let dp: Vector3<f64> = target.translation.vector - current.translation.vector;
    let dr = (target.rotation * current.rotation.inverse()).scaled_axis();
    Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
}

/// One tick: the joint velocity that moves the TCP of configuration `q` along `twist` toward
/// `target`, within the joint position and velocity limits. Allocation-free.
pub fn step(
    q: &[f64; N],
    target: &Isometry3<f64>,
    twist: &Vector6<f64>,
    rest: &[f64; N],
    robot: &RobotModel,
    limits: &LimiterConfig,
    cfg: &DiffIkConfig,
) -> (Vec7, BoxQpSolution) {
    let (pose, jac) = robot.kin.jacobian(q, robot.kin.tcp);
    let xi = twist + cfg.gain_per_s * pose_error(&pose, target);
    let w = Vector6::new(1.0, 1.0, 1.0, cfg.rotation_weight, cfg.rotation_weight, cfg.rotation_weight);
    let jw = SMatrix::<f64, 6, N>::from_fn(|r, c| jac[(r, c)] * w[r]);
    let xw = xi.component_mul(&w);
    let reg = cfg.damping + cfg.posture_weight;
    let h = jw.transpose() * jw + Mat7::identity() * reg;
    let pull = Vec7::from_fn(|i, _| cfg.posture_gain_per_s * (rest[i] - q[i]));
    let g = -(jw.transpose() * xw) - cfg.posture_weight * pull;
    let mut lb = Vec7::zeros();
    let mut ub = Vec7::zeros();
    for i in 0..N {
        let l = robot.joints[i];
        let v = limits.speed_scale * l.dq_max_rad_s;
        let lo = (l.q_min_rad + limits.q_margin_rad - q[i]) / cfg.limit_horizon_s;
        let hi = (l.q_max_rad - limits.q_margin_rad - q[i]) / cfg.limit_horizon_s;
        // Beyond a limit (a measured start can be), the bounds demand moving back inside.
        ub[i] = v.min(hi).max(-v);
        lb[i] = (-v).max(lo).min(v).min(ub[i]);
    }
    let sol = solve_box_qp(&h, &g, &lb, &ub);
    (sol.x, sol)
}
