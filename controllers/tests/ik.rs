//! Inverse kinematics against the shipped Panda description (and its FR3 limit profile).

use controllers::ik::SplitMix64;
use controllers::kinematics::from_arrays;
use controllers::{IkConfig, IkError, IkSolver, Profile, RobotModel, N};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

/// Counts allocations made by the current thread, so one test can check that solving is
/// allocation-free while the others run in parallel.
struct Counting;

thread_local! {
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

// SAFETY: forwards to the system allocator; the counter is a const-initialised thread local.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn model(profile: Profile) -> RobotModel {
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
    RobotModel::from_urdf_str(&xml, "hand_tcp", profile).expect("model")
}

const HOME: [f64; N] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

fn within(q: &[f64; N], lo: &[f64; N], hi: &[f64; N]) -> bool {
    (0..N).all(|j| q[j] >= lo[j] && q[j] <= hi[j])
}

/// Errors of `q` against `target`, measured here independently of the solver's own figures.
fn errors(robot: &RobotModel, q: &[f64; N], target: &Isometry3<f64>) -> (f64, f64) {
    let pose = robot.kin.fk(q, robot.kin.tcp);
    let dp = (target.translation.vector - pose.translation.vector).norm();
    let dr = target.rotation.angle_to(&pose.rotation);
    (dp, dr)
}

/// FK of random in-limit configurations, then IK back from an unrelated seed.
fn round_trip(profile: Profile, config: IkConfig, count: usize, seed_home: bool) {
    let robot = model(profile);
    let solver = IkSolver::new(&robot, config).expect("solver");
    let (lo, hi) = solver.bounds();
    let (lo, hi) = (*lo, *hi);
    let mut rng = SplitMix64::new(7);
    let mut ok = 0;
    for _ in 0..count {
        let q = rng.config(&lo, &hi);
        let seed = if seed_home { HOME } else { rng.config(&lo, &hi) };
        let target = robot.kin.fk(&q, robot.kin.tcp);
        let s = solver.solve(&target, &seed).expect("valid input");
        assert!(within(&s.q, &lo, &hi), "solution {:?} leaves the limits", s.q);
        assert!(s.position_error_m.is_finite() && s.rotation_error_rad.is_finite());
        let (dp, dr) = errors(&robot, &s.q, &target);
        // The reported errors are the true ones (to rounding).
        assert!((dp - s.position_error_m).abs() < 1e-9, "{dp} vs {}", s.position_error_m);
        assert!((dr - s.rotation_error_rad).abs() < 1e-7, "{dr} vs {}", s.rotation_error_rad);
        if s.ok {
            ok += 1;
            assert!(dp <= config.position_tolerance_m, "position error {dp} m");
            assert!(dr <= config.rotation_tolerance_rad, "rotation error {dr} rad");
        }
    }
    assert!(ok as f64 >= 0.995 * count as f64, "{ok}/{count} solved");
}

#[test]
fn panda_round_trip_from_random_seeds() {
    round_trip(Profile::Panda, IkConfig::default(), 400, false);
}

#[test]
fn panda_round_trip_from_home() {
    round_trip(Profile::Panda, IkConfig::default(), 300, true);
}

#[test]
fn fr3_round_trip_keeps_fr3_limits() {
    // FR3's J6 range starts at 0.4398 rad where the Panda's starts at −0.0175: a solution in
    // the Panda box alone would not pass `within` against the FR3 bounds.
    let fr3 = model(Profile::Fr3);
    let solver = IkSolver::new(&fr3, IkConfig::default()).expect("solver");
    let (lo, _) = solver.bounds();
    assert_eq!(lo[5], 0.4398);
    round_trip(Profile::Fr3, IkConfig::default(), 300, false);
}

#[test]
fn margin_shrinks_the_box_and_is_kept() {
    let margin = 0.05;
    let cfg = IkConfig { limit_margin_rad: margin, ..IkConfig::default() };
    let robot = model(Profile::Panda);
    let solver = IkSolver::new(&robot, cfg).expect("solver");
    let (lo, hi) = solver.bounds();
    for j in 0..N {
        assert!((lo[j] - (robot.joints[j].q_min_rad + margin)).abs() < 1e-12);
        assert!((hi[j] - (robot.joints[j].q_max_rad - margin)).abs() < 1e-12);
    }
    round_trip(Profile::Panda, cfg, 200, false);
}

#[test]
fn seed_outside_limits_is_clamped_and_solution_stays_inside() {
    let robot = model(Profile::Panda);
    let solver = IkSolver::new(&robot, IkConfig::default()).expect("solver");
    let target = robot.kin.fk(&HOME, robot.kin.tcp);
    // q = 0 has J4 = 0 above its limit of −0.0698.
    let s = solver.solve(&target, &[0.0; N]).expect("valid input");
    assert!(s.ok, "{s:?}");
    let (lo, hi) = solver.bounds();
    assert!(within(&s.q, lo, hi), "{:?}", s.q);
}

#[test]
fn unreachable_target_fails_with_finite_errors() {
    let robot = model(Profile::Panda);
    let cfg = IkConfig::default();
    let solver = IkSolver::new(&robot, cfg).expect("solver");
    let target = Isometry3::from_parts(Translation3::new(3.0, 0.0, 0.5), UnitQuaternion::identity());
    let s = solver.solve(&target, &HOME).expect("valid input");
    assert!(!s.ok);
    assert!(s.position_error_m.is_finite() && s.rotation_error_rad.is_finite());
    // The arm reaches about 0.86 m from the shoulder: at least 2 m short.
    assert!(s.position_error_m > 2.0, "{s:?}");
    assert!(s.restarts == cfg.max_restarts || s.iterations >= cfg.max_total_iterations, "{s:?}");
    assert!(s.iterations <= cfg.max_total_iterations);
    let (lo, hi) = solver.bounds();
    assert!(within(&s.q, lo, hi));
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let robot = model(Profile::Panda);
    let solver = IkSolver::new(&robot, IkConfig::default()).expect("solver");
    let good = robot.kin.fk(&HOME, robot.kin.tcp);

    let nan_pos = Isometry3::from_parts(Translation3::new(f64::NAN, 0.0, 0.5), good.rotation);
    let e = solver.solve(&nan_pos, &HOME).unwrap_err();
    assert_eq!(e, IkError::NonFiniteTarget { what: "position" });
    assert!(e.to_string().contains("not finite"), "{e}");

    let inf_pos = Isometry3::from_parts(Translation3::new(0.3, f64::INFINITY, 0.5), good.rotation);
    assert!(matches!(solver.solve(&inf_pos, &HOME), Err(IkError::NonFiniteTarget { .. })));

    let nan_rot = Isometry3::from_parts(
        good.translation,
        UnitQuaternion::new_unchecked(Quaternion::new(f64::NAN, 0.0, 0.0, 0.0)),
    );
    assert_eq!(solver.solve(&nan_rot, &HOME).unwrap_err(), IkError::NonFiniteTarget { what: "orientation" });

    // A zero quaternion normalised at the boundary becomes NaN: still an error.
    let zero = from_arrays([0.3, 0.0, 0.5], [0.0, 0.0, 0.0, 0.0]);
    assert!(solver.solve(&zero, &HOME).is_err());

    let scaled =
        Isometry3::from_parts(good.translation, UnitQuaternion::new_unchecked(Quaternion::new(2.0, 0.0, 0.0, 0.0)));
    assert!(matches!(solver.solve(&scaled, &HOME), Err(IkError::NotUnitQuaternion { .. })));

    let mut seed = HOME;
    seed[3] = f64::NAN;
    let e = solver.solve(&good, &seed).unwrap_err();
    assert!(matches!(e, IkError::NonFiniteSeed { joint: 3, .. }), "{e:?}");
    assert!(e.to_string().contains("seed joint 4"), "{e}");

    let e = solver.solve_frame(&good, controllers::FrameId(10_000), &HOME).unwrap_err();
    assert!(matches!(e, IkError::NoSuchFrame { index: 10_000, .. }), "{e:?}");
}

#[test]
fn bad_settings_are_refused() {
    let robot = model(Profile::Panda);
    let cfg = IkConfig { position_tolerance_m: 0.0, ..IkConfig::default() };
    assert!(matches!(IkSolver::new(&robot, cfg), Err(IkError::BadConfig(_))));
    let cfg = IkConfig { rotation_tolerance_rad: f64::NAN, ..IkConfig::default() };
    assert!(matches!(IkSolver::new(&robot, cfg), Err(IkError::BadConfig(_))));
    // J4's range is 3.002 rad wide: a 1.6 rad margin on both ends leaves nothing.
    let cfg = IkConfig { limit_margin_rad: 1.6, ..IkConfig::default() };
    let e = IkSolver::new(&robot, cfg).unwrap_err();
    assert!(e.to_string().contains("joint 4"), "{e}");
}

#[test]
fn solving_is_deterministic() {
    let robot = model(Profile::Panda);
    let solver = IkSolver::new(&robot, IkConfig::default()).expect("solver");
    let mut rng = SplitMix64::new(99);
    let (lo, hi) = solver.bounds();
    let (lo, hi) = (*lo, *hi);
    for _ in 0..50 {
        let target = robot.kin.fk(&rng.config(&lo, &hi), robot.kin.tcp);
        let seed = rng.config(&lo, &hi);
        let a = solver.solve(&target, &seed).expect("valid");
        let b = solver.clone().solve(&target, &seed).expect("valid");
        assert_eq!(a, b);
    }
}

#[test]
fn other_frames_can_be_placed() {
    let robot = model(Profile::Panda);
    let mut solver = IkSolver::new(&robot, IkConfig::default()).expect("solver");
    let flange = robot.kin.frame("flange").expect("flange frame");
    assert_eq!(solver.frame(), robot.kin.tcp);
    let q = [0.3, -0.4, 0.2, -2.0, 0.1, 1.8, 0.4];
    let target = robot.kin.fk(&q, flange);
    let s = solver.solve_frame(&target, flange, &HOME).expect("valid");
    assert!(s.ok, "{s:?}");
    let got = robot.kin.fk(&s.q, flange);
    assert!((got.translation.vector - target.translation.vector).norm() <= 1e-5);
    // Placing the flange is not placing the TCP: the TCP lands 0.1034 m further along z.
    let tcp = robot.kin.fk(&s.q, robot.kin.tcp);
    assert!(((tcp.translation.vector - got.translation.vector).norm() - 0.1034).abs() < 1e-6);

    solver.set_frame(flange).expect("frame exists");
    let s2 = solver.solve(&target, &HOME).expect("valid");
    assert_eq!(s, s2);
}

#[test]
fn solving_does_not_allocate() {
    let robot = model(Profile::Panda);
    let solver = IkSolver::new(&robot, IkConfig::default()).expect("solver");
    let (lo, hi) = solver.bounds();
    let (lo, hi) = (*lo, *hi);
    let mut rng = SplitMix64::new(3);
    let cases: Vec<_> =
        (0..200).map(|_| (robot.kin.fk(&rng.config(&lo, &hi), robot.kin.tcp), rng.config(&lo, &hi))).collect();
    let far = Isometry3::from_parts(Translation3::new(3.0, 0.0, 0.5), UnitQuaternion::identity());
    let before = ALLOCATIONS.with(Cell::get);
    let mut restarts = 0;
    for (target, seed) in &cases {
        restarts += solver.solve(target, seed).expect("valid").restarts;
    }
    // Failing and refused solves too: the restart loop and the error path.
    assert!(!solver.solve(&far, &HOME).expect("valid").ok);
    let mut nan_seed = HOME;
    nan_seed[0] = f64::NAN;
    assert!(solver.solve(&cases[0].0, &nan_seed).is_err());
    let after = ALLOCATIONS.with(Cell::get);
    assert!(restarts > 0, "the restart path was not exercised");
    assert_eq!(after - before, 0, "solving allocated");
}
