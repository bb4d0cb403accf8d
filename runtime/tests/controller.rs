//! The controller on its own, against a simulator that follows every command exactly.

use controllers::LimiterConfig;
use ipc_schema::{ControlType, Request, RequestKind, SimState, Status, MAX_CHUNK, WAYPOINT_LEN};
use runtime::controller::Controller;

const HOME: [f64; 7] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

fn scene() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../gyms/pick_block_plate/scene.toml")
}

fn request(id: u64, ct: ControlType, actions: &[[f64; 8]]) -> Box<Request> {
    let mut r = Box::new(Request {
        id,
        client: 1,
        kind: RequestKind::Chunk as u32,
        control_type: ct as u32,
        len: actions.len() as u32,
        _pad: 0,
        freq_hz: 0.0,
        actions: [[0.0; WAYPOINT_LEN]; MAX_CHUNK],
    });
    r.actions[..actions.len()].copy_from_slice(actions);
    r
}

/// Sends a request and ticks until it replies; returns the reply and the ticks it took.
fn run(ctl: &mut Controller, state: &mut SimState, req: &Request) -> (ipc_schema::Reply, u64) {
    let (reply, _) = ctl.request(req, state);
    if let Some(r) = reply {
        return (r, 0);
    }
    finish(ctl, state)
}

/// Ticks until a reply comes.
fn finish(ctl: &mut Controller, state: &mut SimState) -> (ipc_schema::Reply, u64) {
    for tick in 0..60_000 {
        let (cmd, reply) = ctl.tick(state);
        state.seq += 1;
        state.q_rad = cmd.q_rad;
        state.dq_rad_s = cmd.dq_rad_s;
        state.finger_m = cmd.finger_m;
        if let Some(r) = reply {
            return (r, tick);
        }
    }
    panic!("no reply in 60 s");
}

#[test]
fn an_ee_pose_chunk_moves_the_tcp_in_a_straight_line_to_its_target() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let mut ctl = Controller::new(robot.clone(), LimiterConfig::default(), 0.001).with_safety(safety);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let start = robot.kin.fk(&HOME, robot.kin.tcp);
    let aa = start.rotation.scaled_axis();
    let p0 = start.translation.vector;
    let goal = p0 + nalgebra::Vector3::new(0.12, -0.1, -0.08);
    let actions: Vec<[f64; 8]> = (1..=10)
        .map(|k| {
            let p = p0.lerp(&goal, k as f64 / 10.0);
            [p.x, p.y, p.z, aa.x, aa.y, aa.z, 0.0, -1.0]
        })
        .collect();
    let (reply, _) = ctl.request(&request(1, ControlType::EePose, &actions), &state);
    assert!(reply.is_none());
    // Every command keeps the TCP near the segment from start to goal: the jerk-limited
    // tracker lags a little where the reference starts and stops moving.
    let dir = (goal - p0).normalize();
    let mut worst: f64 = 0.0;
    let reply = loop {
        let (cmd, reply) = ctl.tick(&state);
        state.seq += 1;
        state.q_rad = cmd.q_rad;
        state.dq_rad_s = cmd.dq_rad_s;
        let p = robot.kin.fk(&state.q_rad, robot.kin.tcp).translation.vector - p0;
        worst = worst.max((p - dir * p.dot(&dir)).norm());
        if let Some(r) = reply {
            break r;
        }
    };
    assert_eq!(reply.status, Status::Executed as u32, "{}", reply.reason_str());
    assert!(worst < 3e-3, "the TCP left the line by {worst} m");
    eprintln!("largest distance from the line: {:.3} mm", worst * 1e3);
    let end = robot.kin.fk(&state.q_rad, robot.kin.tcp);
    assert!((end.translation.vector - goal).norm() < 1e-4, "{:?}", end.translation.vector - goal);
    assert!(end.rotation.angle_to(&start.rotation) < 1e-4);
}

fn joint_wp(q: [f64; 7], g: f64) -> [f64; 8] {
    let mut w = [g; 8];
    w[..7].copy_from_slice(&q);
    w
}

#[test]
fn a_chunk_from_the_same_client_supersedes_the_running_one_and_others_wait() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let mut ctl = Controller::new(robot, LimiterConfig::default(), 0.001).with_safety(safety);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let mut far = HOME;
    far[0] = 1.0;
    let (reply, _) = ctl.request(&request(1, ControlType::Joint, &[joint_wp(far, -1.0)]), &state);
    assert!(reply.is_none());
    for _ in 0..200 {
        let (cmd, _) = ctl.tick(&state);
        state.q_rad = cmd.q_rad;
        state.seq += 1;
    }
    let mut other = request(2, ControlType::Joint, &[joint_wp(HOME, -1.0)]);
    other.client = 2;
    let (reply, _) = ctl.request(&other, &state);
    let reply = reply.expect("rejected at once");
    assert_eq!(reply.status, Status::Rejected as u32);
    assert!(reply.reason_str().contains("another client"), "{}", reply.reason_str());
    // Mid-motion, the same client turns back: the first request ends as superseded.
    let (reply, _) = ctl.request(&request(3, ControlType::Joint, &[joint_wp(HOME, -1.0)]), &state);
    let reply = reply.expect("the superseded request's reply");
    assert_eq!((reply.id, reply.status), (1, Status::Failed as u32));
    assert!(reply.reason_str().contains("superseded by request 3"), "{}", reply.reason_str());
    let (reply, _) = finish(&mut ctl, &mut state);
    assert_eq!((reply.id, reply.status), (3, Status::Executed as u32), "{}", reply.reason_str());
}

#[test]
fn waypoints_through_the_table_or_the_arm_itself_are_refused() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let mut ctl = Controller::new(robot, LimiterConfig::default(), 0.001).with_safety(safety);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    // Shoulder forward, elbow stretched: the TCP ends 6 cm below the table top.
    let down = [0.0, 1.7, 0.0, -0.2, 0.0, 1.571, 0.785];
    let (reply, _) = run(&mut ctl, &mut state, &request(1, ControlType::Joint, &[joint_wp(down, -1.0)]));
    assert_eq!(reply.status, Status::Rejected as u32);
    assert!(reply.reason_str().contains("table"), "{}", reply.reason_str());
    // The folded configuration the collision tests use: the hand inside link 1.
    let folded = [-0.27, -0.17, 0.42, -2.86, -0.15, 1.10, 1.18];
    let (reply, _) = run(&mut ctl, &mut state, &request(2, ControlType::Joint, &[joint_wp(folded, -1.0)]));
    assert_eq!(reply.status, Status::Rejected as u32);
    assert!(reply.reason_str().contains("link1"), "{}", reply.reason_str());
    assert_eq!(state.q_rad, HOME, "a refused chunk moves nothing");
}

#[test]
fn the_per_tick_check_halts_a_motion_that_acceptance_did_not_catch() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let cfg = LimiterConfig::default();
    // Accepted without checks, then checked every tick: the chunk heads through the table.
    let mut ctl = Controller::new(robot.clone(), cfg, 0.001);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let down = [0.0, 1.7, 0.0, -0.2, 0.0, 1.571, 0.785];
    let (reply, _) = ctl.request(&request(1, ControlType::Joint, &[joint_wp(down, -1.0)]), &state);
    assert!(reply.is_none());
    let mut ctl = ctl.with_safety(safety.clone());
    let mut monitor = controllers::monitor::Monitor::new(0.001);
    monitor.start_at(&HOME, 0.04, &robot);
    let mut halted = None;
    for tick in 0..20_000 {
        let (cmd, reply) = ctl.tick(&state);
        monitor.observe(&cmd.q_rad, cmd.finger_m, &robot, &cfg);
        state.seq += 1;
        state.q_rad = cmd.q_rad;
        state.dq_rad_s = cmd.dq_rad_s;
        if let Some(r) = reply {
            assert_eq!(r.status, Status::Failed as u32);
            assert!(r.reason_str().starts_with("stopped:") && r.reason_str().contains("table"), "{}", r.reason_str());
            halted = Some(tick);
            // While braking, new chunks wait.
            let (again, _) = ctl.request(&request(2, ControlType::Joint, &[joint_wp(HOME, -1.0)]), &state);
            assert!(again.expect("refused").reason_str().contains("stopping"));
        }
        if halted.is_some() && cmd.dq_rad_s.iter().all(|v| *v == 0.0) {
            break;
        }
    }
    assert!(halted.is_some(), "never halted");
    assert_eq!(monitor.violations.total(), 0, "{:?}", monitor.first);
    // It came to rest clear of the table, and takes chunks again.
    safety.check(&state.q_rad).expect("the rest configuration passes the checks");
    let (reply, _) = run(&mut ctl, &mut state, &request(3, ControlType::Joint, &[joint_wp(HOME, -1.0)]));
    assert_eq!(reply.status, Status::Executed as u32, "{}", reply.reason_str());
}

#[test]
fn an_ee_pose_segment_is_checked_between_its_waypoints() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let down = robot.kin.fk(&HOME, robot.kin.tcp).rotation.scaled_axis();
    let wp = |x: f64, y: f64, z: f64| [x, y, z, down.x, down.y, down.z, 0.0, -1.0];
    let fresh = || {
        let state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
        (Controller::new(robot.clone(), LimiterConfig::default(), 0.001).with_safety(safety.clone()), state)
    };
    // Both ends are fine on their own...
    for end in [wp(0.12, 0.45, 0.25), wp(0.12, -0.45, 0.25)] {
        let (mut ctl, mut state) = fresh();
        let (reply, _) = run(&mut ctl, &mut state, &request(1, ControlType::EePose, &[end]));
        assert_eq!(reply.status, Status::Executed as u32, "{:?}: {}", &end[..3], reply.reason_str());
    }
    // ...but the straight line between them passes too close to the base for the arm to follow.
    let (mut ctl, mut state) = fresh();
    let chunk = [wp(0.12, 0.45, 0.25), wp(0.12, -0.45, 0.25)];
    let (reply, _) = run(&mut ctl, &mut state, &request(2, ControlType::EePose, &chunk));
    assert_eq!(reply.status, Status::Rejected as u32);
    assert!(reply.reason_str().starts_with("actions[1]"), "{}", reply.reason_str());
    eprintln!("{}", reply.reason_str());
}
