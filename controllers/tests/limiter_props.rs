//! Property tests: whatever chunks arrive, and whenever, the command stream keeps every limit.

use controllers::monitor::Monitor;
use controllers::Reference;
use controllers::{ChunkPlan, JointTracker, LimiterConfig, Profile, RobotModel, N};
use proptest::prelude::*;

fn robot(profile: Profile) -> RobotModel {
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
    RobotModel::from_urdf_str(&xml, "hand_tcp", profile).expect("model")
}

/// A number from the whole hostile range: specials, huge values, and values near the limits.
fn hostile() -> impl Strategy<Value = f64> {
    prop_oneof![
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(f64::NEG_INFINITY),
        -1e12..1e12f64,
        -3.1..3.8f64,
        -3.1..3.8f64,
        -3.1..3.8f64,
    ]
}

/// A waypoint near home: inside the limits of both profiles, yet far enough to move fast.
fn plausible() -> impl Strategy<Value = [f64; 8]> {
    (prop::array::uniform7(-0.6..0.6f64), -1.0..1.0f64).prop_map(|(d, g)| {
        let home = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];
        let mut w = [g; 8];
        for j in 0..N {
            w[j] = home[j] + d[j];
        }
        w
    })
}

fn chunk() -> impl Strategy<Value = (Vec<[f64; 8]>, f64, u32)> {
    let waypoint = prop_oneof![prop::array::uniform8(hostile()), plausible(), plausible()];
    let freq = prop_oneof![Just(0.0), Just(0.0), Just(f64::NAN), -10.0..2000.0f64, 0.4..1000.0f64];
    (prop::collection::vec(waypoint, 0..12), freq, 0u32..400)
}

fn run(profile: Profile, chunks: Vec<(Vec<[f64; 8]>, f64, u32)>) -> Result<(), TestCaseError> {
    let r = robot(profile);
    let cfg = LimiterConfig::default();
    let home = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];
    let mut t = JointTracker::at_rest(home, 0.04, &r, &cfg);
    let mut m = Monitor::new(0.001);
    m.start_at(&t.q_rad, t.finger_m, &r);
    let mut plan = ChunkPlan::hold(t.q_rad, -1.0);
    let mut time = 0.0;
    let mut accepted = 0;
    for (actions, freq, ticks) in chunks {
        // Accepted chunks replace the running one mid-motion, as the runtime does.
        if let Ok(p) = ChunkPlan::joint(&actions, freq, t.q_rad, &r, &cfg, None) {
            plan = p;
            time = 0.0;
            accepted += 1;
        }
        for _ in 0..ticks {
            time += 0.001;
            let reference: Reference = plan.sample(time);
            t.step(&reference, 0.001, &r, &cfg);
            m.observe(&t.q_rad, t.finger_m, &r, &cfg);
        }
    }
    prop_assert_eq!(m.violations.total(), 0, "{:?} ({} chunks accepted)", m.first, accepted);
    ACCEPTED.fetch_add(accepted, std::sync::atomic::Ordering::Relaxed);
    Ok(())
}

static ACCEPTED: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    #[test]
    fn panda_commands_keep_every_limit(chunks in prop::collection::vec(chunk(), 1..30)) {
        run(Profile::Panda, chunks)?;
    }

    #[test]
    fn fr3_commands_keep_every_limit(chunks in prop::collection::vec(chunk(), 1..30)) {
        run(Profile::Fr3, chunks)?;
    }
}

/// The generators do produce chunks that pass validation (else the properties prove little).
#[test]
fn the_generators_reach_the_limiter() {
    let mut runner = proptest::test_runner::TestRunner::deterministic();
    let before = ACCEPTED.load(std::sync::atomic::Ordering::Relaxed);
    runner.run(&prop::collection::vec(chunk(), 1..30), |c| run(Profile::Panda, c)).expect("no violation");
    assert!(ACCEPTED.load(std::sync::atomic::Ordering::Relaxed) - before > 100);
}

/// Chunks that pass validation are then followed: the arm reaches where it was sent.
#[test]
fn valid_waypoints_mostly_pass_and_are_reached() {
    let r = robot(Profile::Panda);
    let cfg = LimiterConfig::default();
    let start = [0.3, -0.5, 0.2, -2.0, 0.1, 1.8, 0.5];
    let goal = [0.5, -0.2, 0.0, -1.8, -0.2, 2.0, 0.9];
    let actions: Vec<[f64; 8]> = (1..=10)
        .map(|k| {
            let mut w = [1.0; 8];
            for j in 0..N {
                w[j] = start[j] + (goal[j] - start[j]) * k as f64 / 10.0;
            }
            w
        })
        .collect();
    let plan = ChunkPlan::joint(&actions, 0.0, start, &r, &cfg, None).expect("valid");
    let mut t = JointTracker::at_rest(start, 0.04, &r, &cfg);
    let mut time = 0.0;
    while !(time > plan.duration_s() && t.settled_on(&plan.sample(time), &r)) {
        time += 0.001;
        t.step(&plan.sample(time), 0.001, &r, &cfg);
        assert!(time < 10.0);
    }
    assert!(t.q_rad.iter().zip(goal).all(|(q, g)| (q - g).abs() < 1e-6));
}

/// With the TCP speed shaping switched off, every joint racing toward a far target at full
/// speed would carry the TCP past its limit: the guard brakes instead, and the monitor sees
/// no violation.
#[test]
fn the_tcp_speed_guard_holds_when_shaping_is_off() {
    let r = robot(Profile::Panda);
    let cfg = LimiterConfig { tcp_speed_scale: 10.0, ..LimiterConfig::default() };
    let a = [-2.5, -1.2, -2.0, -2.8, -2.0, 0.5, -2.0];
    let b = [2.5, 1.2, 2.0, -0.3, 2.0, 3.5, 2.0];
    let mut t = JointTracker::at_rest(a, 0.04, &r, &cfg);
    let mut m = Monitor::new(0.001);
    m.start_at(&t.q_rad, t.finger_m, &r);
    let mut peak: f64 = 0.0;
    for goal in [b, a, b] {
        // A bare reference: far away, no feed-forward, so feedback drives every joint at once.
        let reference =
            Reference { q_rad: goal, dq_rad_s: [0.0; N], gripper: 0.0, goal_q_rad: goal, reached: 0, finished: true };
        for _ in 0..4000 {
            let before = r.kin.fk(&t.q_rad, r.kin.tcp).translation.vector;
            t.step(&reference, 0.001, &r, &cfg);
            m.observe(&t.q_rad, t.finger_m, &r, &cfg);
            peak = peak.max((r.kin.fk(&t.q_rad, r.kin.tcp).translation.vector - before).norm() / 0.001);
        }
    }
    assert_eq!(m.violations.total(), 0, "{:?}", m.first);
    assert!(t.tcp_guard_ticks > 0, "the guard never acted (peak {peak} m/s)");
    assert!(peak <= 0.9 * r.cartesian.v_m_s + 0.01, "peak TCP speed {peak} m/s");
    eprintln!("peak TCP speed {peak:.3} m/s, {} guard ticks", t.tcp_guard_ticks);
}
