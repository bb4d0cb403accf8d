//! The controllers against the shipped Panda description.

use controllers::Reference;
use controllers::{ChunkPlan, JointTracker, LimiterConfig, Profile, Rejection, RobotModel, N};

fn panda() -> RobotModel {
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
    RobotModel::from_urdf_str(&xml, "hand_tcp", Profile::Panda).expect("model")
}

const HOME: [f64; N] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

#[test]
fn urdf_gives_the_published_panda_limits() {
    let r = panda();
    assert_eq!(r.joint_names[0], "joint1");
    assert_eq!(r.joint_names[6], "joint7");
    assert_eq!(r.joints[3].q_max_rad, -0.0698);
    assert_eq!(r.joints[3].q_min_rad, -3.0718);
    assert_eq!(r.joints[5].q_min_rad, -0.0175);
    assert_eq!(r.joints[4].dq_max_rad_s, 2.61);
    assert_eq!(r.finger_joint, "finger_joint1");
    assert_eq!(r.finger_max_m, 0.04);
    assert_eq!(r.finger_from_gripper(-1.0), 0.04);
    assert_eq!(r.finger_from_gripper(1.0), 0.0);
}

#[test]
fn malformed_urdf_is_a_clear_error() {
    let e = RobotModel::from_urdf_str("<robot name='x'><link", "tcp", Profile::Panda).unwrap_err();
    assert!(e.to_string().contains("URDF does not parse"), "{e}");
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
    let e = RobotModel::from_urdf_str(&xml, "no_such_link", Profile::Panda).unwrap_err();
    assert!(e.to_string().contains("no link named 'no_such_link'"), "{e}");
    let e = RobotModel::from_urdf_str(&xml, "link4", Profile::Panda).unwrap_err();
    assert!(e.to_string().contains("4 revolute joints, expected 7"), "{e}");
}

fn wp(q: [f64; N], g: f64) -> [f64; 8] {
    let mut w = [0.0; 8];
    w[..N].copy_from_slice(&q);
    w[N] = g;
    w
}

/// Evenly spaced waypoints from `start` to `goal` (excluding `start`).
fn ramp(start: [f64; N], goal: [f64; N], steps: usize, gripper: f64) -> Vec<[f64; 8]> {
    (1..=steps)
        .map(|k| {
            let mut q = start;
            for (j, qj) in q.iter_mut().enumerate() {
                *qj += (goal[j] - start[j]) * k as f64 / steps as f64;
            }
            wp(q, gripper)
        })
        .collect()
}

#[test]
fn bad_chunks_are_rejected_with_the_offending_value() {
    let (r, c) = (panda(), LimiterConfig::default());
    let plan = |a: &[[f64; 8]], f: f64| ChunkPlan::joint(a, f, HOME, &r, &c, None).map(|_| ()).unwrap_err();
    assert_eq!(plan(&[], 0.0), Rejection::Empty);
    let mut nan = wp(HOME, 0.0);
    nan[2] = f64::NAN;
    assert_eq!(plan(&[wp(HOME, 0.0), nan], 0.0), Rejection::NotFinite { waypoint: 1, index: 2 });
    let mut far = HOME;
    far[3] = 0.2;
    match plan(&[wp(far, 0.0)], 0.0) {
        Rejection::JointOutOfRange { waypoint: 0, joint: 3, .. } => {}
        other => panic!("{other:?}"),
    }
    assert!(matches!(plan(&[wp(HOME, 1.5)], 0.0), Rejection::GripperOutOfRange { .. }));
    assert!(matches!(plan(&[wp(HOME, 0.0)], -5.0), Rejection::BadFrequency { .. }));
    assert!(matches!(plan(&[wp(HOME, 0.0)], 1e9), Rejection::BadFrequency { .. }));
    assert!(matches!(plan(&[wp(HOME, 0.0)], 1e-9), Rejection::BadFrequency { .. }));
    assert!(matches!(plan(&vec![wp(HOME, 0.0); 100], 0.5), Rejection::TooSlow { waypoint: 60, .. }));
    assert!(matches!(plan(&vec![wp(HOME, 0.0); 300], 0.0), Rejection::TooLong { len: 300, .. }));
    let msg = Rejection::JointOutOfRange { waypoint: 0, joint: 3, value: 0.2, min: -3.0, max: -0.08 }.to_string();
    assert!(msg.contains("joint 4") && msg.contains("by 0.2800 rad"), "{msg}");
}

#[test]
fn fast_rates_never_buy_speed_past_the_limits() {
    let (r, c) = (panda(), LimiterConfig::default());
    let mut goal = HOME;
    goal[0] = 1.0;
    let plan = ChunkPlan::joint(&[wp(goal, -1.0)], 1000.0, HOME, &r, &c, None).expect("valid");
    // 1 rad at half of 2.175 rad/s takes at least 0.92 s, whatever freq says.
    assert!(plan.duration_s() >= 1.0 / (c.speed_scale * 2.175), "{}", plan.duration_s());
}

/// xorshift: deterministic adversarial inputs without a dependency.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[test]
fn the_limiter_output_never_breaks_a_limit_whatever_the_reference() {
    let (r, c) = (panda(), LimiterConfig::default());
    let dt = 0.001;
    let mut t = JointTracker::at_rest(HOME, 0.04, &r, &c);
    let mut rng = Rng(0x9e3779b97f4a7c15);
    let mut reference =
        Reference { q_rad: HOME, dq_rad_s: [0.0; N], gripper: -1.0, goal_q_rad: HOME, reached: 0, finished: false };
    for tick in 0..200_000 {
        if tick % 37 == 0 {
            for j in 0..N {
                reference.q_rad[j] = match (rng.next() * 6.0) as u32 {
                    0 => f64::NAN,
                    1 => f64::INFINITY,
                    2 => (rng.next() - 0.5) * 1e6,
                    _ => r.joints[j].q_min_rad + rng.next() * (r.joints[j].q_max_rad - r.joints[j].q_min_rad),
                };
                reference.dq_rad_s[j] = if rng.next() < 0.1 { f64::NEG_INFINITY } else { (rng.next() - 0.5) * 100.0 };
                reference.goal_q_rad[j] = match (rng.next() * 4.0) as u32 {
                    0 => f64::NAN,
                    1 => (rng.next() - 0.5) * 1e6,
                    _ => r.joints[j].q_min_rad + rng.next() * (r.joints[j].q_max_rad - r.joints[j].q_min_rad),
                };
            }
            reference.gripper = if rng.next() < 0.1 { f64::NAN } else { (rng.next() - 0.5) * 10.0 };
        }
        let before = t;
        t.step(&reference, dt, &r, &c);
        for j in 0..N {
            let l = r.joints[j];
            let q = t.q_rad[j];
            assert!(
                q.is_finite() && q >= l.q_min_rad + c.q_margin_rad - 1e-12 && q <= l.q_max_rad - c.q_margin_rad + 1e-12,
                "tick {tick} joint {j} q {q}"
            );
            assert!(t.dq_rad_s[j].abs() <= l.dq_max_rad_s + 1e-9, "tick {tick} joint {j} v {}", t.dq_rad_s[j]);
            let dv = (t.dq_rad_s[j] - before.dq_rad_s[j]).abs();
            assert!(dv <= c.accel_scale * l.ddq_max_rad_s2 * dt + 1e-9, "tick {tick} joint {j} dv {dv}");
            assert!((t.q_rad[j] - before.q_rad[j]).abs() <= l.dq_max_rad_s * dt + 1e-9);
        }
        assert!((0.0..=r.finger_max_m).contains(&t.finger_m));
        assert!((t.finger_m - before.finger_m).abs() <= r.finger_speed_m_s * dt + 1e-12);
    }
}

#[test]
fn a_chunk_is_tracked_to_its_last_waypoint() {
    let (r, c) = (panda(), LimiterConfig::default());
    let mut goal = HOME;
    goal[1] = -0.3;
    goal[5] = 2.0;
    let actions = ramp(HOME, goal, 10, 1.0);
    let plan = ChunkPlan::joint(&actions, 0.0, HOME, &r, &c, None).expect("valid");
    let mut t = JointTracker::at_rest(HOME, 0.04, &r, &c);
    let mut time = 0.0;
    loop {
        time += 0.001;
        let reference = plan.sample(time);
        t.step(&reference, 0.001, &r, &c);
        if reference.finished && t.settled_on(&reference, &r) {
            break;
        }
        assert!(time < 10.0, "never settled");
    }
    for (q, g) in t.q_rad.iter().zip(&goal) {
        assert!((q - g).abs() < 1e-6);
    }
    assert_eq!(t.finger_m, 0.0);
}

#[test]
fn a_chunk_near_a_limit_stops_on_target_within_acceleration_limits() {
    let (r, c) = (panda(), LimiterConfig::default());
    let mut start = HOME;
    start[1] = -1.0;
    let mut goal = start;
    goal[0] = 1.2;
    goal[1] = r.joints[1].q_max_rad - c.q_margin_rad - 0.02;
    // One far waypoint and a finely sampled ramp: both must end on target without overshoot.
    for steps in [1usize, 25] {
        let actions = ramp(start, goal, steps, -1.0);
        let plan = ChunkPlan::joint(&actions, 0.0, start, &r, &c, None).expect("valid");
        let mut t = JointTracker::at_rest(start, 0.04, &r, &c);
        let mut time = 0.0;
        loop {
            time += 0.001;
            let reference = plan.sample(time);
            let before = t;
            t.step(&reference, 0.001, &r, &c);
            for j in 0..N {
                let a = c.accel_scale * r.joints[j].ddq_max_rad_s2;
                assert!((t.dq_rad_s[j] - before.dq_rad_s[j]).abs() <= a * 0.001 + 1e-9, "steps {steps} joint {j}");
                let dir = (goal[j] - start[j]).signum();
                assert!(dir * (t.q_rad[j] - goal[j]) <= 1e-9, "steps {steps}: joint {j} passed its target");
            }
            if reference.finished && t.settled_on(&reference, &r) {
                break;
            }
            assert!(time < 20.0, "never settled");
        }
    }
}

#[test]
fn fk_reproduces_the_published_check_values() {
    use std::f64::consts::PI;
    let r = panda();
    let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9);
    let same_rot = |a: [f64; 4], b: [f64; 4]| close(&a, &b) || close(&a, &b.map(|v| -v));
    let home = [0.0, -PI / 4.0, 0.0, -3.0 * PI / 4.0, 0.0, PI / 2.0, PI / 4.0];
    let (p, q) = controllers::kinematics::to_arrays(&r.kin.fk(&home, r.kin.tcp));
    let published = [0.30689, 0.0, 0.48688];
    assert!(p.iter().zip(published).all(|(a, b)| (a - b).abs() < 5e-6), "{p:?}");
    assert!(same_rot(q, [1.0, 0.0, 0.0, 0.0]), "{q:?}");
    let zero = [0.0; N];
    let (p, _) = controllers::kinematics::to_arrays(&r.kin.fk(&zero, r.kin.flange));
    assert!(close(&p, &[0.088, 0.0, 0.926]), "{p:?}");
    let (p, q) = controllers::kinematics::to_arrays(&r.kin.fk(&zero, r.kin.tcp));
    assert!(close(&p, &[0.088, 0.0, 0.8226]), "{p:?}");
    assert!(same_rot(q, [0.923879532511287, 0.38268343236509, 0.0, 0.0]), "{q:?}");
}

#[test]
fn a_measured_flange_to_tcp_transform_replaces_the_description_tcp() {
    use controllers::kinematics::{from_arrays, to_arrays};
    let mut r = panda();
    let described = r.kin.flange_from_tcp();
    let (p, _) = to_arrays(&described);
    assert!((p[2] - 0.1034).abs() < 1e-12, "{p:?}");
    let before = r.kin.fk(&HOME, r.kin.tcp);
    // 3 mm further along the tool axis and 2 mm along tool x, same orientation.
    let (_, q) = to_arrays(&described);
    r.kin.set_tcp(described * from_arrays([0.002, 0.0, 0.003], [0.0, 0.0, 0.0, 1.0])).expect("set");
    assert_eq!(r.kin.frame("tcp"), Some(r.kin.tcp));
    assert!(r.kin.frame("hand_tcp").is_some_and(|f| f != r.kin.tcp), "the description's frame stays");
    let after = r.kin.fk(&HOME, r.kin.tcp);
    let want = before * nalgebra::Translation3::new(0.002, 0.0, 0.003);
    assert!((after.translation.vector - want.translation.vector).norm() < 1e-12);
    assert!(after.rotation.angle_to(&before.rotation) < 1e-12);
    let (_, q2) = to_arrays(&r.kin.flange_from_tcp());
    assert!(q.iter().zip(q2).all(|(a, b)| (a - b).abs() < 1e-12));
    // The Jacobian is the new point's.
    let (pose, _) = r.kin.jacobian(&HOME, r.kin.tcp);
    assert!((pose.translation.vector - after.translation.vector).norm() < 1e-12);
}
