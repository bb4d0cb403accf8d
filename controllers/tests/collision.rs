//! Collision, obstacle and workspace checks against the shipped Panda description.

use controllers::collision::{Axis, CollisionModel, StaticScene, Violation, Workspace, EXCLUDED_PAIRS};
use controllers::{Profile, RobotModel, N};
use nalgebra::{Isometry3, Vector3};

const HOME: [f64; N] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

/// Elbow folded shut with the shoulder tipped back: the forearm comes down along the upper arm
/// and the hand ends up against link1's capsule. Found by sampling random configurations for one
/// whose closest checked pair is hand/link1 more than 2 cm deep, taking the one nearest to HOME,
/// then rounding to 0.01 rad.
const FOLDED: [f64; N] = [-0.27, -0.17, 0.42, -2.86, -0.15, 1.10, 1.18];

fn setup() -> (RobotModel, CollisionModel) {
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
    let robot = RobotModel::from_urdf_str(&xml, "hand_tcp", Profile::Panda).expect("model");
    let col = CollisionModel::from_urdf_str(&xml, &robot).expect("collision model");
    (robot, col)
}

/// SplitMix64, mapped to [0, 1).
struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A configuration drawn uniformly within the joint limits.
    fn config(&mut self, robot: &RobotModel) -> [f64; N] {
        std::array::from_fn(|j| {
            let l = &robot.joints[j];
            l.q_min_rad + self.unit() * (l.q_max_rad - l.q_min_rad)
        })
    }
}

fn tcp(robot: &RobotModel, q: &[f64; N]) -> Vector3<f64> {
    robot.kin.fk(q, robot.kin.tcp).translation.vector
}

/// Moves the TCP by `delta` (base frame) with damped least squares on position only.
fn shift_tcp(robot: &RobotModel, q: [f64; N], delta: Vector3<f64>) -> [f64; N] {
    let goal = tcp(robot, &q) + delta;
    let mut q = q;
    for _ in 0..100 {
        let (pose, jac) = robot.kin.jacobian(&q, robot.kin.tcp);
        let err = goal - pose.translation.vector;
        let jp = jac.fixed_rows::<3>(0).into_owned();
        let jjt = jp * jp.transpose() + nalgebra::Matrix3::identity() * 1e-6;
        let dq = jp.transpose() * jjt.try_inverse().expect("invertible") * err;
        for (qi, d) in q.iter_mut().zip(dq.iter()) {
            *qi += d;
        }
    }
    assert!((tcp(robot, &q) - goal).norm() < 1e-6, "TCP did not reach the goal");
    q
}

#[test]
fn home_is_free_with_a_centimetre_margin() {
    let (_, col) = setup();
    let scene = StaticScene::new();
    assert_eq!(col.check(&HOME, &scene, &Workspace::unbounded(), 0.01), Ok(()));
    let c = col.clearance(&HOME, &scene).expect("finite");
    let near = c.self_pair.expect("there are checked pairs");
    assert!(near.distance_m > 0.05, "{near:?}");
    assert_eq!(c.obstacle, None);
}

#[test]
fn folded_arm_hits_itself() {
    let (_, col) = setup();
    let scene = StaticScene::new();
    let err = col.check(&FOLDED, &scene, &Workspace::unbounded(), 0.01).expect_err("folded arm must be refused");
    let Violation::SelfCollision { a, b, distance_m, margin_m } = err else { panic!("{err:?}") };
    assert_eq!((a, b), ("link1", "hand"));
    assert!(distance_m < -0.01, "{distance_m}");
    assert_eq!(margin_m, 0.01);
    let text = err.to_string();
    assert!(text.starts_with("link1 would touch or overlap hand (gap -0.0"), "{text}");
    assert!(text.ends_with("needs 0.010 m)"), "{text}");
    // The same pair is what the diagnostics call closest.
    let c = col.clearance(&FOLDED, &scene).expect("finite");
    assert_eq!(c.self_pair.map(|p| (p.a, p.b, p.distance_m)), Some(("link1", "hand", distance_m)));
}

#[test]
fn table_below_the_gripper() {
    let (robot, col) = setup();
    let home_tcp = tcp(&robot, &HOME);
    // Tool points straight down at HOME; the table top is 5 cm below the TCP.
    let top = home_tcp.z - 0.05;
    let mut scene = StaticScene::new();
    let centre = Isometry3::translation(0.5, 0.0, top - 0.02);
    scene.add_box("table", centre, [0.3, 0.5, 0.02]).expect("table");
    let ws = Workspace::unbounded();
    assert_eq!(col.check(&HOME, &scene, &ws, 0.01), Ok(()));
    let c = col.clearance(&HOME, &scene).expect("finite");
    let near = c.obstacle.expect("one obstacle");
    assert_eq!(near.b, "table");
    // The hand's lower capsule (the one franka_description puts around the fingers) reaches
    // 16.6 mm below the TCP, so about 3.3 cm of the 5 cm remain.
    assert_eq!(near.a, "hand");
    assert!((near.distance_m - 0.0334).abs() < 0.001, "{near:?}");

    // TCP 1 cm into the table top.
    let pushed = shift_tcp(&robot, HOME, Vector3::new(0.0, 0.0, -0.06));
    let err = col.check(&pushed, &scene, &ws, 0.01).expect_err("TCP inside the table");
    let Violation::Obstacle { link, obstacle, distance_m, .. } = err else { panic!("{err:?}") };
    assert_eq!(obstacle, "table");
    assert!(link.starts_with("finger_") || link == "hand", "{link}");
    assert!(distance_m <= 0.0, "{distance_m}");
    assert!(err.to_string().contains("obstacle 'table'"), "{err}");
}

#[test]
fn floor_half_space() {
    let (robot, col) = setup();
    let mut scene = StaticScene::new();
    // The robot's own mount stands on z = 0: link0 and link1 reach down to it but are not checked.
    scene.add_half_space("floor", [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]).expect("floor");
    assert_eq!(col.check(&HOME, &scene, &Workspace::unbounded(), 0.01), Ok(()));
    let low = shift_tcp(&robot, HOME, Vector3::new(0.0, 0.0, -0.48));
    let err = col.check(&low, &scene, &Workspace::unbounded(), 0.01).expect_err("TCP at floor level");
    assert!(matches!(err, Violation::Obstacle { obstacle: "floor", .. }), "{err:?}");
}

#[test]
fn tcp_outside_the_workspace_names_the_axis() {
    let (robot, col) = setup();
    let scene = StaticScene::new();
    let x = tcp(&robot, &HOME).x; // about 0.307 m
    let ws = Workspace::new([0.35, -0.5, 0.0], [0.8, 0.5, 1.0]).expect("box");
    let err = col.check(&HOME, &scene, &ws, 0.01).expect_err("TCP short of x min");
    assert_eq!(err, Violation::Workspace { point: "hand_tcp", axis: Axis::X, value: x, min: 0.35, max: 0.8 });
    assert_eq!(err.to_string(), "hand_tcp would be at x = 0.307 m, outside the workspace [0.350, 0.800] m on x");

    let ws = Workspace::new([0.2, -0.5, 0.0], [0.8, 0.5, 0.45]).expect("box");
    let err = col.check(&HOME, &scene, &ws, 0.01).expect_err("TCP above z max");
    assert!(matches!(err, Violation::Workspace { point: "hand_tcp", axis: Axis::Z, .. }), "{err:?}");

    // Only the TCP is checked by default; with bodies, the elbow (above 0.6 m at HOME) is caught.
    let ws = Workspace::new([-0.5, -0.5, 0.0], [0.8, 0.5, 0.6]).expect("box");
    assert_eq!(col.check(&HOME, &scene, &ws, 0.01), Ok(()));
    let err = col.check(&HOME, &scene, &ws.with_bodies(), 0.01).expect_err("elbow above the box");
    let Violation::Workspace { point, axis, value, .. } = err else { panic!("{err:?}") };
    assert_eq!(axis, Axis::Z);
    assert!(value > 0.6 && point.starts_with("link"), "{err}");

    assert!(Workspace::new([0.0; 3], [0.0, 1.0, 1.0]).is_err());
    assert!(Workspace::new([f64::NAN, 0.0, 0.0], [1.0; 3]).is_err());
}

#[test]
fn non_finite_input_is_a_typed_error() {
    let (_, col) = setup();
    let scene = StaticScene::new();
    let ws = Workspace::unbounded();
    let mut q = HOME;
    q[2] = f64::NAN;
    let err = col.check(&q, &scene, &ws, 0.01).expect_err("NaN");
    assert!(matches!(err, Violation::NotFinite { joint: 2, value } if value.is_nan()), "{err:?}");
    assert_eq!(err.to_string(), "joint 3 position is NaN, not a finite number");
    q[2] = 0.0;
    q[6] = f64::INFINITY;
    assert!(matches!(col.check(&q, &scene, &ws, 0.01), Err(Violation::NotFinite { joint: 6, .. })));
    assert!(matches!(col.clearance(&q, &scene), Err(Violation::NotFinite { joint: 6, .. })));
    assert!(matches!(col.check(&HOME, &scene, &ws, f64::NAN), Err(Violation::BadMargin { .. })));
    assert!(matches!(col.check(&HOME, &scene, &ws, -0.01), Err(Violation::BadMargin { .. })));
}

#[test]
fn bad_obstacles_are_refused() {
    let mut scene = StaticScene::new();
    assert!(scene.add_box("flat", Isometry3::identity(), [0.1, 0.1, 0.0]).is_err());
    assert!(scene.add_half_space("none", [0.0; 3], [0.0; 3]).is_err());
    scene.add_box("a", Isometry3::identity(), [0.1; 3]).expect("box");
    assert!(scene.add_half_space("a", [0.0; 3], [0.0, 0.0, 1.0]).is_err(), "duplicate name");
    assert_eq!(scene.names().collect::<Vec<_>>(), ["a"]);
}

/// Backs the choice documented on `MIN_JOINTS_APART` and `EXCLUDED_PAIRS`.
#[test]
fn pair_filter_matches_sampled_contacts() {
    let (robot, col) = setup();
    let names: Vec<&str> = col.body_names().collect();
    let n = names.len();
    let samples = 20_000;
    let mut touching = vec![0usize; n * n];
    let mut min = vec![f64::INFINITY; n * n];
    let mut max = vec![f64::NEG_INFINITY; n * n];
    let mut rng = Rng(1);
    for _ in 0..samples {
        let q = rng.config(&robot);
        for a in 0..n {
            for b in a + 1..n {
                let d = col.body_distance(&q, a, b).expect("finite");
                touching[a * n + b] += usize::from(d <= 0.0);
                min[a * n + b] = min[a * n + b].min(d);
                max[a * n + b] = max[a * n + b].max(d);
            }
        }
    }
    for a in 0..n {
        for b in a + 1..n {
            let i = a * n + b;
            let share = touching[i] as f64 / samples as f64;
            let apart = col.joints_apart(a, b);
            let listed = EXCLUDED_PAIRS.contains(&(names[a], names[b]));
            println!(
                "{:>12} {:<12} {apart} joints apart, touching {:6.2} %, gap {:+.3}..{:+.3} m{}",
                names[a],
                names[b],
                share * 100.0,
                min[i],
                max[i],
                if col.is_checked(a, b) { "" } else { "  (not checked)" }
            );
            assert_eq!(col.is_checked(a, b), apart >= 2 && !listed, "{} {}", names[a], names[b]);
            if apart < 2 {
                // Overlapping at every sample, or never within 4 cm.
                assert!(max[i] <= 1e-3 || min[i] > 0.04, "{} {}: {}..{}", names[a], names[b], min[i], max[i]);
            } else if listed {
                assert!(share > 0.2, "{} {} touch in {share}", names[a], names[b]);
            } else {
                assert!(share < 0.05, "{} {} touch in {share}", names[a], names[b]);
            }
        }
    }
    // link1/link3 depends on joint 2 alone: other joints do not change the gap.
    let (l1, l3) = (0..n).fold((0, 0), |acc, i| match names[i] {
        "link1" => (i, acc.1),
        "link3" => (acc.0, i),
        _ => acc,
    });
    let base = rng.config(&robot);
    let d0 = col.body_distance(&base, l1, l3).expect("finite");
    for _ in 0..100 {
        let mut q = rng.config(&robot);
        q[1] = base[1];
        assert!((col.body_distance(&q, l1, l3).expect("finite") - d0).abs() < 1e-5);
    }
}

/// The bounding-sphere shortcut must not change answers: compare with every checked body pair
/// measured in full.
#[test]
fn broad_phase_agrees_with_exhaustive_distances() {
    let (robot, col) = setup();
    let scene = StaticScene::new();
    let ws = Workspace::unbounded();
    let n = col.body_names().count();
    let mut rng = Rng(4);
    for _ in 0..2000 {
        let q = rng.config(&robot);
        let mut exhaustive = f64::INFINITY;
        for a in 0..n {
            for b in a + 1..n {
                if col.is_checked(a, b) {
                    exhaustive = exhaustive.min(col.body_distance(&q, a, b).expect("finite"));
                }
            }
        }
        let c = col.clearance(&q, &scene).expect("finite");
        assert_eq!(c.self_pair.map(|p| p.distance_m), Some(exhaustive), "{q:?}");
        for margin in [0.0, 0.02, 0.1] {
            let refused = matches!(col.check(&q, &scene, &ws, margin), Err(Violation::SelfCollision { .. }));
            assert_eq!(refused, exhaustive < margin as f32 as f64, "{q:?} margin {margin}");
        }
    }
}

#[test]
fn random_configurations_mostly_free() {
    let (robot, col) = setup();
    let scene = StaticScene::new();
    let ws = Workspace::unbounded();
    let mut rng = Rng(2);
    let samples = 20_000;
    let colliding = (0..samples).filter(|_| col.check(&rng.config(&robot), &scene, &ws, 0.0).is_err()).count();
    let share = colliding as f64 / samples as f64;
    println!("{:.1} % of {samples} random configurations within the joint limits self-collide", share * 100.0);
    assert!(share > 0.0 && share < 0.5, "{share}");
}

/// Prints how long one check takes; timing depends on the machine, so nothing is asserted.
#[test]
fn check_timing() {
    let (robot, col) = setup();
    let mut scene = StaticScene::new();
    scene.add_box("table", Isometry3::translation(0.5, 0.0, -0.02), [0.3, 0.5, 0.02]).expect("table");
    scene.add_half_space("wall", [-0.4, 0.0, 0.0], [1.0, 0.0, 0.0]).expect("wall");
    let ws = Workspace::new([-1.0; 3], [1.0, 1.0, 1.5]).expect("box").with_bodies();
    let mut rng = Rng(3);
    let random: Vec<[f64; N]> = (0..1000).map(|_| rng.config(&robot)).collect();
    let home = vec![HOME; 1000];
    for (what, qs) in [("HOME", &home), ("random configurations", &random)] {
        let rounds = 200;
        let mut refused = 0usize;
        let t = std::time::Instant::now();
        for _ in 0..rounds {
            for q in qs {
                refused += usize::from(col.check(std::hint::black_box(q), &scene, &ws, 0.01).is_err());
            }
        }
        let per = t.elapsed().as_secs_f64() / (rounds * qs.len()) as f64;
        println!(
            "check, {what}: {:.2} us per call ({} shapes, {} body pairs, 2 obstacles, {} of {} refused)",
            per * 1e6,
            col.shape_count(),
            col.checked_body_pairs().len(),
            refused / rounds,
            qs.len()
        );
    }
}
