//! The tick's box-QP solver against the Clarabel interior-point solver, and differential IK
//! tracking a straight TCP line on the Panda.

use clarabel::algebra::CscMatrix;
use clarabel::solver::{DefaultSettingsBuilder, DefaultSolver, IPSolver, NonnegativeConeT, SolverStatus};
use controllers::diffik::{self, solve_box_qp, DiffIkConfig, Mat7, Vec7};
use controllers::{LimiterConfig, Profile, RobotModel, N};
use nalgebra::{Isometry3, Translation3, Vector6};

struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn clarabel(h: &Mat7, g: &Vec7, lb: &Vec7, ub: &Vec7) -> Vec<f64> {
    // Upper triangle of H; constraints [I; −I] x + s = [ub; −lb], s ≥ 0.
    let p: Vec<Vec<f64>> = (0..N).map(|r| (0..N).map(|c| if c >= r { h[(r, c)] } else { 0.0 }).collect()).collect();
    let p = CscMatrix::from(&p);
    let a: Vec<Vec<f64>> = (0..2 * N)
        .map(|r| {
            (0..N)
                .map(|c| {
                    if r % N == c {
                        if r < N {
                            1.0
                        } else {
                            -1.0
                        }
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    let a = CscMatrix::from(&a);
    let b: Vec<f64> = (0..2 * N).map(|r| if r < N { ub[r] } else { -lb[r - N] }).collect();
    let settings = DefaultSettingsBuilder::default()
        .verbose(false)
        .tol_gap_abs(1e-12)
        .tol_gap_rel(1e-12)
        .tol_feas(1e-12)
        .build()
        .expect("settings");
    let mut solver =
        DefaultSolver::new(&p, g.as_slice(), &a, &b, &[NonnegativeConeT(2 * N)], settings).expect("solver");
    solver.solve();
    assert!(matches!(solver.solution.status, SolverStatus::Solved | SolverStatus::AlmostSolved));
    solver.solution.x.clone()
}

#[test]
fn box_qp_matches_clarabel_on_random_problems() {
    let mut rng = Rng(0x2545f4914f6cdd1d);
    let mut active = 0;
    for case in 0..500 {
        let m = Mat7::from_fn(|_, _| rng.f() * 2.0 - 1.0);
        let h = m.transpose() * m + Mat7::identity() * (1e-3 + rng.f());
        let g = Vec7::from_fn(|_, _| (rng.f() - 0.5) * 10.0);
        let lb = Vec7::from_fn(|_, _| -rng.f() * 2.0);
        let ub = Vec7::from_fn(|_, _| rng.f() * 2.0);
        let ours = solve_box_qp(&h, &g, &lb, &ub);
        assert!(ours.converged, "case {case}");
        let theirs = clarabel(&h, &g, &lb, &ub);
        let cost = |x: &Vec7| 0.5 * x.dot(&(h * x)) + g.dot(x);
        let theirs_v = Vec7::from_column_slice(&theirs);
        for i in 0..N {
            assert!(ours.x[i] >= lb[i] - 1e-12 && ours.x[i] <= ub[i] + 1e-12, "case {case}: bounds");
            assert!((ours.x[i] - theirs[i]).abs() < 1e-5, "case {case}: {:?} vs {theirs:?}", ours.x);
        }
        // Ours is exact: never worse than the interior-point answer.
        assert!(cost(&ours.x) <= cost(&theirs_v) + 1e-9, "case {case}");
        active += (0..N).filter(|&i| ours.x[i] == lb[i] || ours.x[i] == ub[i]).count();
    }
    assert!(active > 500, "the problems should exercise the bounds ({active} active)");
}

fn panda() -> RobotModel {
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
    RobotModel::from_urdf_str(&xml, "hand_tcp", Profile::Panda).expect("model")
}

#[test]
fn differential_ik_follows_a_straight_line_within_limits() {
    let r = panda();
    let lim = LimiterConfig::default();
    let cfg = DiffIkConfig::default();
    let home = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];
    let start = r.kin.fk(&home, r.kin.tcp);
    let goal = Isometry3::from_parts(
        Translation3::from(start.translation.vector + nalgebra::Vector3::new(0.15, 0.2, -0.1)),
        start.rotation,
    );
    let mut q = home;
    let dt = 0.001;
    let steps = 1000;
    let vel = (goal.translation.vector - start.translation.vector) / (steps as f64 * dt);
    let mut worst: f64 = 0.0;
    for k in 1..=steps + 300 {
        let s = (k as f64 / steps as f64).min(1.0);
        let target = Isometry3::from_parts(
            Translation3::from(start.translation.vector.lerp(&goal.translation.vector, s)),
            start.rotation,
        );
        let twist = if k <= steps { Vector6::new(vel.x, vel.y, vel.z, 0.0, 0.0, 0.0) } else { Vector6::zeros() };
        let (dq, sol) = diffik::step(&q, &target, &twist, &home, &r, &lim, &cfg);
        assert!(sol.converged);
        for j in 0..N {
            assert!(dq[j].abs() <= lim.speed_scale * r.joints[j].dq_max_rad_s + 1e-12);
            q[j] += dq[j] * dt;
            assert!(q[j] >= r.joints[j].q_min_rad && q[j] <= r.joints[j].q_max_rad);
        }
        let now = r.kin.fk(&q, r.kin.tcp);
        worst = worst.max((now.translation.vector - target.translation.vector).norm());
    }
    let end = r.kin.fk(&q, r.kin.tcp);
    let err = (end.translation.vector - goal.translation.vector).norm();
    assert!(err < 1e-5, "ended {err} m from the goal");
    assert!(end.rotation.angle_to(&goal.rotation) < 1e-5);
    assert!(worst < 2e-3, "TCP left the line by {worst} m");
}
