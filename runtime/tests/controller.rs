//! The controller on its own, against a simulator that follows every command exactly.

use controllers::LimiterConfig;
use ipc_schema::{ControlType, Request, RequestKind, SimState, Status, MAX_CHUNK, WAYPOINT_LEN};
use runtime::controller::{Controller, GripperReport};

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
        step_ticks: 0,
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
    finish_pushed(ctl, state, u64::MAX, 0.0)
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
    let (mut halted, mut refused_while_braking) = (None, false);
    for tick in 0..20_000 {
        let (cmd, reply) = ctl.tick(&state);
        monitor.observe(&cmd.q_rad, cmd.finger_m, &robot, &cfg);
        state.seq += 1;
        state.q_rad = cmd.q_rad;
        state.dq_rad_s = cmd.dq_rad_s;
        if ctl.busy() && ctl.active_request() == 0 && !refused_while_braking {
            // Braking after the stop: new chunks wait.
            let (again, _) = ctl.request(&request(2, ControlType::Joint, &[joint_wp(HOME, -1.0)]), &state);
            assert!(again.expect("refused").reason_str().contains("braking"));
            refused_while_braking = true;
        }
        if let Some(r) = reply {
            assert_eq!(r.status, Status::Failed as u32);
            assert!(r.reason_str().starts_with("stopped:") && r.reason_str().contains("table"), "{}", r.reason_str());
            // The reply comes once the arm rests, so the caller can move again at once.
            assert!(cmd.dq_rad_s.iter().all(|v| v.abs() < 1e-6), "{:?}", cmd.dq_rad_s);
            halted = Some(tick);
            break;
        }
    }
    assert!(halted.is_some(), "never halted");
    assert!(refused_while_braking);
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

fn franka(reflex_n: f64, operator_n: f64) -> Controller {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let reflexes = runtime::robot_config::Reflexes {
        reflex_force_n: reflex_n,
        operator_force_n: operator_n,
        ..runtime::RobotConfig::default().reflexes
    };
    Controller::new(robot, LimiterConfig::default(), 0.001)
        .with_safety(safety)
        .with_profile(ipc_schema::Profile::Franka, reflexes)
}

/// Ticks until a reply comes; from tick `at` on, the environment pushes on the arm with `force_n`.
fn finish_pushed(ctl: &mut Controller, state: &mut SimState, at: u64, force_n: f64) -> (ipc_schema::Reply, u64) {
    for tick in 0..60_000 {
        if tick >= at {
            state.external_force_n = [0.0, 0.0, force_n];
        }
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

fn ramp(from: [f64; 7], joint: usize, by: f64, n: usize) -> Vec<[f64; 8]> {
    (1..=n)
        .map(|k| {
            let mut w = [0.0; 8];
            w[..7].copy_from_slice(&from);
            w[joint] += by * k as f64 / n as f64;
            w[7] = -1.0;
            w
        })
        .collect()
}

#[test]
fn franka_reflexes_stop_a_chunk_and_an_operator_fault_holds_until_cleared() {
    let mut ctl = franka(30.0, 80.0);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    // A push of 40 N half a second in: the reflex stops the chunk part-way, after braking.
    let (reply, _) = ctl.request(&request(1, ControlType::Joint, &ramp(HOME, 0, 0.3, 10)), &state);
    assert!(reply.is_none());
    let accepted = ctl.take_accepted().expect("an accepted reply");
    assert_eq!(accepted.status, Status::Accepted as u32);
    assert!(accepted.accepted_ns > 0);
    let (r, _) = finish_pushed(&mut ctl, &mut state, 500, 40.0);
    assert_eq!(r.status, Status::RecoveredReplanRequired as u32, "{}", r.reason_str());
    assert!(r.reason_str().contains("exceeded the 30 N threshold"), "{}", r.reason_str());
    assert!(r.executed > 0 && r.executed < 10, "{}", r.executed);
    assert!(r.first_motion_ns >= r.accepted_ns && r.accepted_ns > 0);
    assert!(state.dq_rad_s.iter().all(|v| v.abs() < 1e-3), "the reply waits until the arm rests");
    // The force stays at 40 N but does not grow: the next chunk (backing off) runs.
    let back = ramp(state.q_rad, 0, -0.1, 3);
    let (r, _) = run(&mut ctl, &mut state, &request(2, ControlType::Joint, &back));
    assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
    // 100 N growing during a chunk: an operator fault; everything is refused until cleared.
    state.external_force_n = [0.0; 3];
    ctl.request(&request(3, ControlType::Joint, &ramp(state.q_rad, 0, 0.2, 10)), &state);
    let (r, _) = finish_pushed(&mut ctl, &mut state, 200, 100.0);
    assert_eq!(r.status, Status::OperatorRequired as u32, "{}", r.reason_str());
    assert!(ctl.fault().is_some_and(|f| f.contains("80 N")));
    let back = request(4, ControlType::Joint, &ramp(state.q_rad, 0, -0.05, 2));
    let (r, _) = run(&mut ctl, &mut state, &back);
    assert_eq!(r.status, Status::OperatorRequired as u32);
    assert!(r.reason_str().contains("needs an operator"), "{}", r.reason_str());
    // The agent channel cannot clear it: only the operator socket calls `clear_fault`.
    let mut clear = request(5, ControlType::Joint, &[]);
    clear.kind = RequestKind::ClearFault as u32;
    let (r, _) = ctl.request(&clear, &state);
    let r = r.expect("an immediate reply");
    assert_eq!(r.status, Status::Rejected as u32);
    assert!(r.reason_str().contains("operator socket"), "{}", r.reason_str());
    assert!(ctl.fault().is_some());
    assert!(ctl.clear_fault());
    assert!(ctl.fault().is_none());
    assert!(!ctl.clear_fault(), "nothing left to clear");
    let back = request(6, ControlType::Joint, &ramp(state.q_rad, 0, -0.05, 2));
    let (r, _) = run(&mut ctl, &mut state, &back);
    assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
}

#[test]
fn franka_reset_refreshes_only_and_control_types_may_alternate() {
    let mut ctl = franka(30.0, 80.0);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let mut reset = request(1, ControlType::Joint, &[]);
    reset.kind = RequestKind::Reset as u32;
    let (r, fwd) = ctl.request(&reset, &state);
    assert!(matches!(fwd, runtime::controller::Forward::None), "nothing goes to the simulator");
    assert!(r.is_some_and(|r| r.status == Status::Executed as u32 && r.reason_str().contains("only refreshes")));
    let (r, _) = run(&mut ctl, &mut state, &request(2, ControlType::Joint, &ramp(HOME, 6, 0.1, 2)));
    assert_eq!(r.status, Status::Executed as u32);
    let (robot, _) = runtime::scene_robot(&scene()).expect("scene");
    let p = robot.kin.fk(&state.q_rad, robot.kin.tcp);
    let (t, aa) = (p.translation.vector, p.rotation.scaled_axis());
    let ee = [t.x, t.y, t.z + 0.01, aa.x, aa.y, aa.z, 0.0, -1.0];
    let (r, _) = run(&mut ctl, &mut state, &request(3, ControlType::EePose, &[ee]));
    assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
}

#[test]
fn step_caps_reject_far_waypoints_with_the_excess_and_pass_split_ones() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let cfg = LimiterConfig { max_joint_step_rad: 0.1, ..LimiterConfig::default() };
    let mut ctl = Controller::new(robot, cfg, 0.001).with_safety(safety);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let (r, _) = ctl.request(&request(1, ControlType::Joint, &ramp(HOME, 2, 0.25, 2)), &state);
    let r = r.expect("rejected at once");
    assert_eq!(r.status, Status::Rejected as u32);
    let why = r.reason_str();
    assert!(why.starts_with("actions[0]: joint 3 changes by 0.1250 rad from the measured position"), "{why}");
    assert!(why.contains("cap is 0.1000 rad") && why.contains("0.0250 rad over"), "{why}");
    let (r, _) = run(&mut ctl, &mut state, &request(2, ControlType::Joint, &ramp(HOME, 2, 0.25, 3)));
    assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
}

/// Commands stay inside the position, velocity and acceleration limits (the limiter's own
/// scaled ones), tick to tick.
fn assert_within_limits(ctl: &Controller, prev: &ipc_schema::JointCommand, cmd: &ipc_schema::JointCommand, dt: f64) {
    for (j, l) in ctl.robot.joints.iter().enumerate() {
        let (q, dq) = (cmd.q_rad[j], cmd.dq_rad_s[j]);
        assert!(q.is_finite() && dq.is_finite(), "tick {}: joint {} not finite", cmd.seq, j + 1);
        assert!(q >= l.q_min_rad && q <= l.q_max_rad, "tick {}: joint {} at {q} outside its limits", cmd.seq, j + 1);
        assert!(dq.abs() <= l.dq_max_rad_s * 1.0001, "tick {}: joint {} at {dq} rad/s", cmd.seq, j + 1);
        let ddq = (dq - prev.dq_rad_s[j]) / dt;
        let max = ctl.cfg.accel_scale * l.ddq_max_rad_s2;
        assert!(ddq.abs() <= max * 1.01, "tick {}: joint {} accelerates at {ddq} > {max} rad/s²", cmd.seq, j + 1);
    }
}

#[test]
fn a_silent_robot_side_stops_the_chunk_within_limits_and_motion_resumes_from_fresh_state() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let mut ctl = Controller::new(robot, LimiterConfig::default(), 0.001).with_safety(safety);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let mut far = HOME;
    far[0] = 1.2;
    far[3] = -1.9;
    let (reply, _) = ctl.request(&request(1, ControlType::Joint, &[joint_wp(far, -1.0)]), &state);
    assert!(reply.is_none());
    let (mut prev, _) = ctl.tick(&state);
    for _ in 0..300 {
        let (cmd, _) = ctl.tick(&state);
        assert_within_limits(&ctl, &prev, &cmd, 0.001);
        state.q_rad = cmd.q_rad;
        state.dq_rad_s = cmd.dq_rad_s;
        state.seq += 1;
        prev = cmd;
    }
    assert!(prev.dq_rad_s.iter().any(|v| v.abs() > 0.1), "mid-chunk, moving");
    // The robot side goes silent: the state stops changing, the loop keeps ticking.
    ctl.robot_lost(100.0);
    assert!(ctl.is_robot_lost());
    let refused = |ctl: &mut Controller, state: &SimState, id| {
        let (r, _) = ctl.request(&request(id, ControlType::Joint, &[joint_wp(HOME, -1.0)]), state);
        let r = r.expect("refused at once");
        assert_eq!(r.status, Status::Rejected as u32);
        assert!(r.reason_str().contains("robot side has published no state"), "{}", r.reason_str());
    };
    refused(&mut ctl, &state, 2);
    let mut stopped = None;
    for _ in 0..3000 {
        let (cmd, reply) = ctl.tick(&state);
        assert_within_limits(&ctl, &prev, &cmd, 0.001);
        prev = cmd;
        if let Some(r) = reply {
            stopped = Some(r);
        }
    }
    let r = stopped.expect("the chunk replied once the command rested");
    assert_eq!((r.id, r.status), (1, Status::Failed as u32));
    assert!(r.reason_str().contains("published no state for 100 ms"), "{}", r.reason_str());
    assert!(prev.dq_rad_s.iter().all(|v| v.abs() < 1e-9), "the command holds still: {:?}", prev.dq_rad_s);
    let held = prev.q_rad;
    assert!((held[0] - far[0]).abs() > 0.1, "it did not go on to the old target");
    refused(&mut ctl, &state, 3);
    // The robot side comes back at another pose (a restarted simulator): the command restarts
    // at rest exactly there, never at the held command or the old target.
    let mut back = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    assert!(ctl.robot_back(&back).is_none(), "the stopped chunk already replied");
    let (cmd, _) = ctl.tick(&back);
    assert_eq!(cmd.q_rad, HOME);
    assert!(cmd.dq_rad_s.iter().all(|v| *v == 0.0));
    let mut moved = HOME;
    moved[6] += 0.2;
    let (r, _) = run(&mut ctl, &mut back, &request(4, ControlType::Joint, &[joint_wp(moved, -1.0)]));
    assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
}

/// Ticks as the paced loop does on each robot state: what the robot reports first, then the
/// tick; `during(tick, state)` changes the state the robot publishes. Returns the first reply.
fn robot_ticks(
    ctl: &mut Controller,
    state: &mut SimState,
    ticks: u64,
    mut during: impl FnMut(u64, &mut SimState),
) -> Option<(ipc_schema::Reply, u64)> {
    for tick in 0..ticks {
        during(tick, state);
        let back = ctl.robot_reports(state);
        let (cmd, reply) = ctl.tick(state);
        state.seq += 1;
        if state.robot_error == ipc_schema::ROBOT_OK {
            (state.q_rad, state.dq_rad_s, state.finger_m) = (cmd.q_rad, cmd.dq_rad_s, cmd.finger_m);
        } else {
            state.dq_rad_s = [0.0; 7]; // the robot stopped itself and holds
        }
        if let Some(r) = back.or(reply) {
            return Some((r, tick));
        }
    }
    None
}

#[test]
fn robot_reflexes_reply_after_the_recovery_and_a_failed_one_waits_for_each_clear() {
    use ipc_schema::{ROBOT_NEEDS_OPERATOR, ROBOT_OK, ROBOT_RECOVERING};
    let mut ctl = franka(30.0, 80.0).with_reflex_window(10.0);
    let mut state =
        SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, paced: 1, ..SimState::default() };
    ctl.tick(&state);

    // A reflex 400 ms into a chunk; the recovery takes 1 s, then the robot reports OK.
    ctl.request(&request(1, ControlType::Joint, &ramp(HOME, 0, 0.3, 10)), &state);
    let (r, tick) = robot_ticks(&mut ctl, &mut state, 5000, |t, s| match t {
        400 => s.robot_error = ROBOT_RECOVERING,
        1400 => (s.robot_error, s.reflexes) = (ROBOT_OK, 1),
        _ => {}
    })
    .expect("a reply");
    assert_eq!(tick, 1400, "the reply waits for the recovery's outcome");
    assert_eq!(r.status, Status::RecoveredReplanRequired as u32, "{}", r.reason_str());
    assert!(r.executed > 0 && r.executed < 10, "{}", r.executed);
    assert!(ctl.fault().is_none());

    // A second reflex within the window: operator_required, latched.
    ctl.request(&request(2, ControlType::Joint, &ramp(state.q_rad, 0, -0.2, 10)), &state);
    let (r, _) = robot_ticks(&mut ctl, &mut state, 5000, |t, s| match t {
        200 => s.robot_error = ROBOT_RECOVERING,
        700 => (s.robot_error, s.reflexes) = (ROBOT_OK, 2),
        _ => {}
    })
    .expect("a reply");
    assert_eq!(r.status, Status::OperatorRequired as u32, "{}", r.reason_str());
    assert!(ctl.fault().is_some());
    assert!(ctl.clear_fault());

    // A reflex whose recovery fails: the chunk's reply is operator_required, never "recovered".
    ctl.request(&request(3, ControlType::Joint, &ramp(state.q_rad, 0, 0.2, 10)), &state);
    let (r, tick) = robot_ticks(&mut ctl, &mut state, 5000, |t, s| match t {
        300 => s.robot_error = ROBOT_RECOVERING,
        1300 => s.robot_error = ROBOT_NEEDS_OPERATOR,
        _ => {}
    })
    .expect("a reply");
    assert_eq!(tick, 1300);
    assert_eq!(r.status, Status::OperatorRequired as u32, "{}", r.reason_str());
    assert!(r.reason_str().contains("recovery did not clear it"), "{}", r.reason_str());
    // Each clear is seen by the robot side (clear_seq grows) and, while its retried recovery
    // keeps failing, the fault is latched again so that the next clear retries once more.
    for _ in 0..2 {
        let before = ctl.tick(&state).0.clear_seq;
        assert!(ctl.fault().is_some());
        assert!(ctl.clear_fault());
        assert_eq!(ctl.tick(&state).0.clear_seq, before + 1);
        assert!(robot_ticks(&mut ctl, &mut state, 50, |_, _| {}).is_none());
        assert!(ctl.fault().is_some(), "a robot still waiting for an operator latches the fault again");
    }
    // The retried recovery succeeds: chunks run again.
    assert!(ctl.clear_fault());
    state.robot_error = ROBOT_OK;
    robot_ticks(&mut ctl, &mut state, 10, |_, _| {});
    let (r, _) = {
        let (reply, _) = ctl.request(&request(4, ControlType::Joint, &ramp(state.q_rad, 0, 0.05, 2)), &state);
        match reply {
            Some(r) => (r, 0),
            None => robot_ticks(&mut ctl, &mut state, 60_000, |_, _| {}).expect("a reply"),
        }
    };
    assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
}

/// Ticks with a gripper of its own reporting each tick, as the wall loop does: `fault(tick)`
/// gives its fault text (None: ready, its fingers where the state has them). Returns the first
/// reply and its tick.
fn gripper_ticks(
    ctl: &mut Controller,
    state: &mut SimState,
    ticks: u64,
    fault: impl Fn(u64) -> Option<&'static str>,
) -> Option<(ipc_schema::Reply, u64)> {
    for tick in 0..ticks {
        let report = match fault(tick) {
            Some(t) => GripperReport::Fault(t),
            None => GripperReport::Ready { finger_m: state.finger_m },
        };
        ctl.gripper_reports(ipc_schema::GRASP_HOLDING, report);
        let (cmd, reply) = ctl.tick(state);
        state.seq += 1;
        (state.q_rad, state.dq_rad_s) = (cmd.q_rad, cmd.dq_rad_s);
        if let Some(r) = reply {
            return Some((r, tick));
        }
    }
    None
}

/// A Robotiq that is still starting (no state from its driver, its port not there yet,
/// activating) holds the arm and refuses chunks but latches nothing, even on the Franka
/// profile: once it acts on commands, chunks run without an operator's clear. Until then the
/// command carries no finger target, and then the gripper's own first reading (fingers half
/// open, the robot side's fully open): nothing closes or opens the fingers by itself.
#[test]
fn a_gripper_still_starting_holds_the_arm_without_needing_an_operator() {
    let mut ctl = franka(30.0, 80.0);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let starting = [
        GripperReport::NotReady("no state from the gripper driver yet"),
        GripperReport::Fault("serial port vanished (unplugged, or no such device): /dev/ttyUSB0"),
        GripperReport::NotReady("activating the gripper (its fingers open and close once)"),
    ];
    for report in starting {
        for _ in 0..50 {
            ctl.gripper_reports(ipc_schema::GRASP_UNKNOWN, report);
            let (cmd, reply) = ctl.tick(&state);
            assert!(reply.is_none());
            assert!(cmd.finger_m.is_nan(), "a finger target before the gripper's first reading: {}", cmd.finger_m);
            state.seq += 1;
        }
        assert!(ctl.fault().is_none(), "latched while starting: {:?}", ctl.fault());
        let (r, _) = ctl.request(&request(1, ControlType::Joint, &[joint_wp(HOME, -1.0)]), &state);
        let r = r.expect("refused at once");
        assert_eq!(r.status, Status::Rejected as u32, "{}", r.reason_str());
        assert!(r.reason_str().contains("the gripper"), "{}", r.reason_str());
    }
    // Ready, fingers at 0.018 m (half open): that is the target, until a chunk says otherwise.
    for _ in 0..50 {
        ctl.gripper_reports(ipc_schema::GRASP_AT_TARGET, GripperReport::Ready { finger_m: 0.018 });
        let (cmd, _) = ctl.tick(&state);
        assert!((cmd.finger_m - 0.018).abs() < 1e-12, "the first target is not the reading: {}", cmd.finger_m);
        state.seq += 1;
    }
    assert!(ctl.fault().is_none() && ctl.gripper_ready());
    let mut target = HOME;
    target[6] += 0.1;
    let (r, _) = ctl.request(&request(2, ControlType::Joint, &[joint_wp(target, 1.0)]), &state);
    assert!(r.is_none(), "refused: {}", r.map(|r| r.reason_str().to_string()).unwrap_or_default());
    // The chunk's own goal goes out at once (fully closed), not a ramp towards it.
    ctl.gripper_reports(ipc_schema::GRASP_MOVING, GripperReport::Ready { finger_m: 0.018 });
    let (cmd, _) = ctl.tick(&state);
    assert_eq!(cmd.finger_m, 0.0);
    // The robot side restarting (lost, then back at rest) restarts the arm at its measured
    // joints but keeps the gripper's goal: its measured opening as the target would loosen a grasp.
    ctl.robot_lost(300.0);
    let back = SimState { seq: state.seq + 1, session: 7, finger_m: 0.012, ..state };
    let _ = ctl.robot_back(&back);
    let (cmd, _) = ctl.tick(&back);
    assert_eq!(cmd.finger_m, 0.0, "the robot side's return changed the gripper's target");
    // Once it has been ready, the same kinds of report latch: a link lost now needs the operator.
    ctl.gripper_reports(ipc_schema::GRASP_UNKNOWN, GripperReport::Fault("no answer from the gripper"));
    assert!(ctl.fault().is_some_and(|f| f.contains("no answer")), "{:?}", ctl.fault());
    // A minor fault (not ready, ends by itself) never latches.
    let mut ctl = franka(30.0, 80.0);
    ctl.gripper_reports(ipc_schema::GRASP_AT_TARGET, GripperReport::Ready { finger_m: 0.0 });
    ctl.tick(&state);
    ctl.gripper_reports(ipc_schema::GRASP_UNKNOWN, GripperReport::NotReady("Robotiq fault 0x08: too hot"));
    assert!(ctl.fault().is_none());
    assert_eq!(ctl.robot_state(&state, 1, 1).fault & 4, 4, "the arm holds while it lasts");
    ctl.gripper_reports(ipc_schema::GRASP_AT_TARGET, GripperReport::Ready { finger_m: 0.0 });
    assert_eq!(ctl.robot_state(&state, 2, 1).fault, 0);
}

#[test]
fn a_gripper_fault_stops_the_chunk_holds_the_arm_and_refuses_chunks_until_clear() {
    for franka_profile in [false, true] {
        let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
        let mut ctl = Controller::new(robot, LimiterConfig::default(), 0.001).with_safety(safety);
        if franka_profile {
            ctl = franka(30.0, 80.0);
        }
        let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
        let (reply, _) = ctl.request(&request(1, ControlType::Joint, &ramp(HOME, 0, 0.4, 10)), &state);
        assert!(reply.is_none());
        let fault = |t: u64| (t >= 300).then_some("Robotiq fault 0x0E: overcurrent");
        let (r, tick) = gripper_ticks(&mut ctl, &mut state, 5000, fault).expect("a reply");
        let want = if franka_profile { Status::OperatorRequired } else { Status::Failed };
        assert_eq!(r.status, want as u32, "{}", r.reason_str());
        assert!(
            r.reason_str().contains("the gripper reports a fault (Robotiq fault 0x0E: overcurrent)"),
            "{}",
            r.reason_str()
        );
        assert!(tick > 300 && r.executed < 10, "stopped part-way, after braking: tick {tick}");
        assert!(state.dq_rad_s.iter().all(|v| v.abs() < 1e-3), "the reply waits until the arm rests");
        let s = ctl.robot_state(&state, 1, 1);
        assert_eq!(s.fault & 4, 4);
        assert_eq!(s.gripper_error_str(), "Robotiq fault 0x0E: overcurrent");
        assert_eq!(s.grasp, ipc_schema::GRASP_HOLDING);
        // Refused while the gripper faults.
        let (r, _) = ctl.request(&request(2, ControlType::Joint, &[joint_wp(HOME, -1.0)]), &state);
        let r = r.expect("refused at once");
        assert_ne!(r.status, Status::Accepted as u32);
        // The gripper clears; on the Franka profile the operator must clear too.
        ctl.gripper_reports(ipc_schema::GRASP_AT_TARGET, GripperReport::Ready { finger_m: state.finger_m });
        if franka_profile {
            let (r, _) = ctl.request(&request(3, ControlType::Joint, &[joint_wp(HOME, -1.0)]), &state);
            assert_eq!(r.expect("refused").status, Status::OperatorRequired as u32);
            assert!(ctl.clear_fault());
        }
        assert_eq!(ctl.robot_state(&state, 2, 1).fault, 0);
        let mut target = state.q_rad;
        target[6] += 0.1;
        let (r, _) = run(&mut ctl, &mut state, &request(4, ControlType::Joint, &[joint_wp(target, -1.0)]));
        assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
    }
}

#[test]
fn a_step_lasts_exactly_its_ticks_and_paces_time_until_the_next_reset() {
    let (robot, safety) = runtime::scene_robot(&scene()).expect("scene");
    let mut ctl = Controller::new(robot, LimiterConfig::default(), 0.001).with_safety(safety);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    // A far target: its segment is stretched past the step's 50 ticks by the velocity limits.
    let mut far = request(1, ControlType::Joint, &ramp(HOME, 0, 0.8, 1));
    far.kind = RequestKind::Step as u32;
    far.step_ticks = 50;
    let (r, _) = ctl.request(&far, &state);
    assert!(r.is_none(), "accepted: {:?}", r.map(|r| r.reason_str().to_string()));
    assert_eq!(ctl.take_accepted().map(|r| r.status), Some(Status::Accepted as u32));
    let mut ticks = 0;
    let stepped = loop {
        assert!(ctl.advancing());
        let (cmd, reply) = ctl.tick(&state);
        ticks += 1;
        state.seq += 1;
        state.q_rad = cmd.q_rad;
        assert!(reply.is_none(), "the far chunk cannot finish within the step");
        if let Some(s) = ctl.take_stepped() {
            break s;
        }
    };
    assert_eq!((ticks, stepped.id, stepped.status), (50, 1, Status::Stepped as u32));
    // The chunk still moves, but time stands still until the next step.
    assert!(ctl.busy() && !ctl.advancing());
    // A second step while one runs is refused; a step of 0 ticks too; and a reset during one.
    let mut hold = request(2, ControlType::Joint, &[]);
    hold.kind = RequestKind::Step as u32;
    hold.step_ticks = 0;
    let (r, _) = ctl.request(&hold, &state);
    assert!(r.is_some_and(|r| r.status == Status::Rejected as u32 && r.reason_str().contains("1 to")));
    hold.step_ticks = 5;
    assert!(ctl.request(&hold, &state).0.is_none(), "a step without waypoints only lets time pass");
    let mut again = hold.clone();
    again.id = 3;
    let (r, _) = ctl.request(&again, &state);
    assert!(r.is_some_and(|r| r.reason_str().contains("already running")));
    let mut reset = request(4, ControlType::Joint, &[]);
    reset.kind = RequestKind::Reset as u32;
    assert!(ctl.request(&reset, &state).0.is_some_and(|r| r.status == Status::Rejected as u32));
    for _ in 0..5 {
        let (cmd, _) = ctl.tick(&state);
        state.q_rad = cmd.q_rad;
    }
    assert_eq!(ctl.take_stepped().map(|r| r.id), Some(2));
    // A reset ends the pacing: a plain chunk advances time again.
    let (_, fwd) = ctl.request(&reset, &state);
    let runtime::controller::Forward::Reset { sim_reset_id } = fwd else { panic!("a reset goes to the simulator") };
    state.reset_id = sim_reset_id;
    state.q_rad = HOME;
    assert!(ctl.complete_reset(&state).is_some());
    let (_, _) = ctl.request(&request(5, ControlType::Joint, &ramp(HOME, 0, 0.05, 1)), &state);
    assert!(ctl.advancing());
}

#[test]
fn on_a_real_arm_a_stepping_clients_reset_leaves_the_moving_chunk_running() {
    // On the sim profile a reset of the pacing client ends what it left moving (the simulator
    // restores the arm); on the Franka profile a reset restores nothing, so the chunk must run
    // (or brake) to its end, never be dropped mid-motion.
    let mut ctl = franka(1e6, 1e6);
    let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
    let mut far = request(1, ControlType::Joint, &ramp(HOME, 0, 0.8, 1));
    far.kind = RequestKind::Step as u32;
    far.step_ticks = 20;
    assert!(ctl.request(&far, &state).0.is_none());
    let stepped = loop {
        let (cmd, reply) = ctl.tick(&state);
        state.seq += 1;
        state.q_rad = cmd.q_rad;
        state.dq_rad_s = cmd.dq_rad_s;
        assert!(reply.is_none());
        if let Some(s) = ctl.take_stepped() {
            break s;
        }
    };
    assert_eq!(stepped.id, 1);
    assert!(ctl.busy(), "the chunk still moves between steps");
    let mut reset = request(2, ControlType::Joint, &[]);
    reset.kind = RequestKind::Reset as u32;
    let (r, fwd) = ctl.request(&reset, &state);
    assert!(matches!(fwd, runtime::controller::Forward::None));
    let r = r.expect("answered at once");
    assert_ne!(
        r.status,
        Status::Executed as u32,
        "a reset on a moving real arm is not a no-op success: {}",
        r.reason_str()
    );
    assert!(ctl.busy(), "the moving chunk was dropped by the reset");
}
