//! Benchmarks of the I/O-free control core, run through the runtime's own `Controller` (the
//! code the 1 kHz tick calls): `r2g bench tick-compute` and `r2g bench limiter-fuzz`.

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::Context;
use controllers::ik::SplitMix64;
use controllers::monitor::Monitor;
use controllers::safety::SafetyChecks;
use controllers::{LimiterConfig, RobotModel, N};
use ipc_schema::{ControlType, JointCommand, Request, RequestKind, SimState, MAX_CHUNK, WAYPOINT_LEN};
use runtime::controller::{Controller, Forward};
use runtime::stats::Histogram;
use serde_json::json;

const DT_S: f64 = 0.001;
pub const HOME: [f64; N] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

/// The Panda of the shipped pick_block_plate gym, with that scene's safety checks (table,
/// workspace, self-collision).
pub fn panda() -> anyhow::Result<(RobotModel, SafetyChecks)> {
    let scene = runtime::launch::resolve_scene("pick_block_plate")?;
    runtime::scene_robot(&scene).context("loading the pick_block_plate robot")
}

fn controller(robot: &RobotModel, safety: &SafetyChecks, cfg: LimiterConfig) -> Controller {
    Controller::new(robot.clone(), cfg, DT_S).with_safety(safety.clone())
}

/// Reproducible inputs: the IK solver's SplitMix64, with the draws these benches need.
pub struct Rng(SplitMix64);
impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(SplitMix64::new(seed))
    }
    pub fn u64(&mut self) -> u64 {
        self.0.next_u64()
    }
    /// Uniform in [0, 1).
    pub fn f(&mut self) -> f64 {
        self.0.next_f64()
    }
    pub fn below(&mut self, n: u64) -> u64 {
        self.u64() % n.max(1)
    }
}

fn empty_request(id: u64, client: u64) -> Box<Request> {
    Box::new(Request {
        id,
        client,
        kind: RequestKind::Chunk as u32,
        control_type: ControlType::Joint as u32,
        len: 0,
        step_ticks: 0,
        freq_hz: 0.0,
        actions: [[0.0; WAYPOINT_LEN]; MAX_CHUNK],
    })
}

/// A simulator that follows every command exactly: the state the controller sees next.
fn follow(state: &mut SimState, cmd: &JointCommand) {
    state.seq += 1;
    state.command_seq = cmd.seq;
    state.sim_time_s += DT_S;
    state.q_rad = cmd.q_rad;
    state.dq_rad_s = cmd.dq_rad_s;
    state.finger_m = cmd.finger_m;
}

fn start_state(robot: &RobotModel) -> SimState {
    SimState {
        seq: 1,
        q_rad: HOME,
        finger_m: robot.finger_max_m,
        finger_max_m: robot.finger_max_m,
        ..SimState::default()
    }
}

/// A configuration drawn uniformly inside the limits (less a small margin).
fn random_q(rng: &mut Rng, robot: &RobotModel, margin: f64) -> [f64; N] {
    std::array::from_fn(|j| {
        let l = robot.joints[j];
        l.q_min_rad + margin + rng.f() * (l.q_max_rad - l.q_min_rad - 2.0 * margin)
    })
}

/// A valid joint chunk: `len` waypoints at `freq` Hz moving toward a random configuration.
fn valid_chunk(rng: &mut Rng, robot: &RobotModel, from: [f64; N], req: &mut Request) {
    let goal = random_q(rng, robot, 0.1);
    let len = 1 + rng.below(20) as usize;
    // Small steps so the chunk keeps pace with its rate, as a policy's chunks do.
    let reach = 0.02 + 0.2 * rng.f();
    for k in 0..len {
        let s = reach * (k + 1) as f64 / len as f64;
        for j in 0..N {
            req.actions[k][j] = from[j] + s * (goal[j] - from[j]);
        }
        req.actions[k][N] = if rng.f() < 0.5 { -1.0 } else { 1.0 };
    }
    req.len = len as u32;
    req.freq_hz = [0.0, 10.0, 20.0, 50.0][rng.below(4) as usize];
}

/// A valid ee_pose chunk: `len` waypoints on a straight line from the current TCP pose to a
/// nearby one (a few centimetres, a few degrees), staying over the table.
fn valid_ee_chunk(rng: &mut Rng, robot: &RobotModel, from: [f64; N], req: &mut Request) {
    let start = robot.kin.fk(&from, robot.kin.tcp);
    let p0 = start.translation.vector;
    let mut goal = p0 + nalgebra::Vector3::new(rng.f() - 0.5, rng.f() - 0.5, rng.f() - 0.5) * 0.1;
    goal.x = goal.x.clamp(0.3, 0.6);
    goal.y = goal.y.clamp(-0.25, 0.25);
    goal.z = goal.z.clamp(0.2, 0.6);
    let turn = nalgebra::Vector3::new(rng.f() - 0.5, rng.f() - 0.5, rng.f() - 0.5) * 0.2;
    let len = 1 + rng.below(10) as usize;
    for k in 0..len {
        let s = (k + 1) as f64 / len as f64;
        let p = p0.lerp(&goal, s);
        let r = nalgebra::UnitQuaternion::from_scaled_axis(turn * s) * start.rotation;
        let aa = r.scaled_axis();
        req.actions[k] = [p.x, p.y, p.z, aa.x, aa.y, aa.z, 0.0, if rng.f() < 0.5 { -1.0 } else { 1.0 }];
    }
    req.len = len as u32;
    req.freq_hz = [0.0, 10.0, 20.0][rng.below(3) as usize];
}

/// `r2g bench tick-compute`: time of one controller tick (interpolation, limiter, checks)
/// while it follows a stream of valid chunks, beside FK + Jacobian alone as a yardstick.
pub fn tick_compute(ticks: u64) -> anyhow::Result<serde_json::Value> {
    let (robot, safety) = panda()?;
    let mut rng = Rng::new(7);
    let mut req = empty_request(0, 1);
    let fk_hist = &mut Histogram::new();
    let mut results = Vec::new();
    let mut all = Histogram::new();
    let mut allocs = 0u64;
    let mut braking = 0;
    // Half the ticks follow joint chunks, half ee_pose chunks (one episode each).
    for ct in [ControlType::Joint, ControlType::EePose] {
        let mut ctl = controller(&robot, &safety, LimiterConfig::default());
        let mut state = start_state(&robot);
        let mut hist = Histogram::new();
        let mut accept = Histogram::new();
        let mut next_chunk = 0u64;
        req.control_type = ct as u32;
        for t in 0..ticks / 2 {
            if t >= next_chunk {
                req.id += 1;
                match ct {
                    ControlType::Joint => valid_chunk(&mut rng, &robot, state.q_rad, &mut req),
                    ControlType::EePose => valid_ee_chunk(&mut rng, &robot, state.q_rad, &mut req),
                }
                // Accepting a chunk happens inside a tick of the real loop: timed on its own.
                let t0 = Instant::now();
                let before = runtime::alloc_count::tick_allocations();
                {
                    let _scope = runtime::alloc_count::TickScope::enter();
                    let _ = ctl.request(&req, &state);
                }
                allocs += runtime::alloc_count::tick_allocations() - before;
                accept.record(t0.elapsed().as_nanos() as u64);
                next_chunk = t + 50;
            }
            let before = runtime::alloc_count::tick_allocations() + runtime::alloc_count::tick_pool_allocations();
            let t0 = Instant::now();
            let (cmd, _reply) = {
                let _scope = runtime::alloc_count::TickScope::enter();
                ctl.tick(&state)
            };
            let ns = t0.elapsed().as_nanos() as u64;
            hist.record(ns);
            allocs += runtime::alloc_count::tick_allocations() + runtime::alloc_count::tick_pool_allocations() - before;
            follow(&mut state, &cmd);
            let t1 = Instant::now();
            let j = robot.kin.jacobian(&state.q_rad, robot.kin.tcp);
            std::hint::black_box(j);
            fk_hist.record(t1.elapsed().as_nanos() as u64);
        }
        braking += ctl.braking_ticks();
        all.merge(&hist);
        results.push((ct.name(), hist, accept));
    }
    // The heaviest chunks acceptance meets: 20 waypoints swinging joint 1 by ±0.4 rad, and 20
    // swinging the TCP by ±0.2 m sideways (path checks and IK samples at their budget).
    let mut long = Vec::new();
    for ct in [ControlType::Joint, ControlType::EePose] {
        let mut h = Histogram::new();
        let start = robot.kin.fk(&HOME, robot.kin.tcp);
        let (p, aa) = (start.translation.vector, start.rotation.scaled_axis());
        req.control_type = ct as u32;
        req.len = 20;
        req.freq_hz = 0.0;
        for k in 0..20 {
            let sgn = if k % 2 == 0 { 1.0 } else { -1.0 };
            req.actions[k] = match ct {
                ControlType::Joint => [HOME[0] + 0.4 * sgn, HOME[1], HOME[2], HOME[3], HOME[4], HOME[5], HOME[6], -1.0],
                ControlType::EePose => [p.x, p.y + 0.2 * sgn, p.z, aa.x, aa.y, aa.z, 0.0, -1.0],
            };
        }
        for _ in 0..20 {
            let mut ctl = controller(&robot, &safety, LimiterConfig::default());
            let state = start_state(&robot);
            let t0 = Instant::now();
            let (reply, _) = ctl.request(&req, &state);
            h.record(t0.elapsed().as_nanos() as u64);
            anyhow::ensure!(reply.is_none(), "the long {} chunk was refused", ct.name());
        }
        long.push((ct.name(), h));
    }
    let counted = runtime::alloc_count::counting_active();
    let row = |name: &str, h: &Histogram| {
        vec![
            name.to_string(),
            format!("{:.2}", h.quantile_us(0.5)),
            format!("{:.2}", h.quantile_us(0.99)),
            format!("{:.2}", h.quantile_us(0.999)),
            format!("{:.2}", h.max_us()),
        ]
    };
    let mut rows: Vec<Vec<String>> = Vec::new();
    for (n, h, a) in &results {
        rows.push(row(&format!("tick, {n} chunks"), h));
        rows.push(row(&format!("accepting a {n} chunk"), a));
    }
    for (n, h) in &long {
        rows.push(row(&format!("accepting a long {n} chunk"), h));
    }
    rows.push(row("tick, all", &all));
    rows.push(row("FK + Jacobian only", fk_hist));
    crate::print_table(&["stage", "median µs", "p99 µs", "p99.9 µs", "max µs"], &rows);
    println!(
        "allocations inside ticks: {allocs} over {ticks} ticks{}",
        if counted { "" } else { " (counting allocator NOT installed: figure not measured)" }
    );
    let per =
        |h: &Histogram| json!({ "median_us": h.quantile_us(0.5), "p99_us": h.quantile_us(0.99), "max_us": h.max_us() });
    let out = json!({
        "ticks": ticks,
        "median_us": all.quantile_us(0.5),
        "p99_us": all.quantile_us(0.99),
        "p999_us": all.quantile_us(0.999),
        "max_us": all.max_us(),
        "joint": per(&results[0].1),
        "ee_pose": per(&results[1].1),
        "accept_joint_chunk": per(&results[0].2),
        "accept_ee_pose_chunk": per(&results[1].2),
        "accept_long_joint_chunk": per(&long[0].1),
        "accept_long_ee_pose_chunk": per(&long[1].1),
        "allocations_per_tick": if counted { json!(allocs as f64 / ticks as f64) } else { json!(null) },
        "braking_ticks": braking,
        "baseline_fk_jacobian": per(fk_hist),
        "p99_ratio_to_fk_jacobian": all.quantile_us(0.99) / fk_hist.quantile_us(0.99),
    });
    println!("{out}");
    Ok(out)
}

/// One adversarial request: mostly hostile values, some valid chunks (so the arm moves and
/// later chunks arrive mid-motion), now and then a reset.
fn adversarial(rng: &mut Rng, robot: &RobotModel, q: [f64; N], episode: ControlType, req: &mut Request) {
    req.kind = RequestKind::Chunk as u32;
    req.control_type = episode as u32;
    match rng.below(20) {
        0 => req.kind = RequestKind::Reset as u32,
        1 => req.kind = rng.u64() as u32,
        2 => req.control_type = if episode == ControlType::Joint { 2 } else { 1 },
        3 => req.control_type = 3 + rng.below(1 << 20) as u32,
        _ => {}
    }
    if rng.below(3) == 0 {
        match episode {
            ControlType::Joint => valid_chunk(rng, robot, q, req),
            ControlType::EePose => valid_ee_chunk(rng, robot, q, req),
        }
        return;
    }
    req.len = match rng.below(6) {
        0 => 0,
        1 => rng.u64() as u32,
        2 => MAX_CHUNK as u32 + rng.below(4) as u32,
        _ => 1 + rng.below(MAX_CHUNK as u64) as u32,
    };
    req.freq_hz = match rng.below(8) {
        0 => f64::NAN,
        1 => -rng.f() * 1e3,
        2 => 1e9,
        3 => rng.f() * 1e-3,
        4 => f64::INFINITY,
        _ => [0.0, 1.0, 20.0, 100.0, 1000.0][rng.below(5) as usize],
    };
    let n = (req.len as usize).min(MAX_CHUNK);
    for k in 0..n {
        for i in 0..WAYPOINT_LEN {
            let l = robot.joints[i.min(N - 1)];
            req.actions[k][i] = match rng.below(12) {
                0 => f64::NAN,
                1 => f64::INFINITY,
                2 => f64::NEG_INFINITY,
                3 => (rng.f() - 0.5) * 1e12,
                4 if i < N => l.q_max_rad - rng.f() * 0.02,
                5 if i < N => l.q_min_rad + rng.f() * 0.02,
                // Joint values in range, or (for ee_pose) positions and rotations around the arm.
                _ if i < N && episode == ControlType::Joint => l.q_min_rad + rng.f() * (l.q_max_rad - l.q_min_rad),
                _ if i < 3 => (rng.f() - 0.5) * 2.0,
                _ if i < 6 => (rng.f() - 0.5) * 8.0,
                _ => (rng.f() - 0.5) * 2.2,
            };
        }
    }
}

/// `r2g bench limiter-fuzz`: adversarial chunks through the controller, every command judged
/// by an independent monitor.
pub fn limiter_fuzz(chunks: u64, seed: u64) -> anyhow::Result<serde_json::Value> {
    let (robot, safety) = panda()?;
    let cfg = LimiterConfig::default();
    let mut ctl = controller(&robot, &safety, cfg);
    let mut episode = ControlType::Joint;
    let mut braking = 0;
    let mut state = start_state(&robot);
    let mut monitor = Monitor::new(DT_S);
    monitor.start_at(&state.q_rad, state.finger_m, &robot);
    let mut rng = Rng::new(seed);
    let mut req = empty_request(0, 1);
    let mut reasons: BTreeMap<&'static str, u64> = BTreeMap::new();
    let (mut accepted, mut superseded, mut resets) = (0u64, 0u64, 0u64);
    let t0 = Instant::now();
    for c in 0..chunks {
        // Episodes of 2,000 requests, alternately joint and ee_pose: a fresh controller, and
        // the simulator puts the arm back home.
        if c > 0 && c % 2000 == 0 {
            braking += ctl.braking_ticks();
            ctl = controller(&robot, &safety, cfg);
            episode = if episode == ControlType::Joint { ControlType::EePose } else { ControlType::Joint };
            state = start_state(&robot);
            monitor.start_at(&state.q_rad, state.finger_m, &robot);
        }
        req.id = c + 1;
        req.client = if rng.below(8) == 0 { 2 } else { 1 };
        adversarial(&mut rng, &robot, state.q_rad, episode, &mut req);
        let (reply, fwd) = ctl.request(&req, &state);
        match (ctl.last_rejection, reply) {
            (Some(kind), _) => *reasons.entry(kind).or_default() += 1,
            (None, Some(r)) if r.id != req.id => {
                superseded += 1;
                accepted += 1;
            }
            (None, Some(_)) => *reasons.entry("other").or_default() += 1,
            (None, None) => accepted += 1,
        }
        if let Forward::Reset { sim_reset_id } = fwd {
            // The simulator puts the arm back home; the command stream starts afresh.
            resets += 1;
            state.reset_id = sim_reset_id;
            state.q_rad = HOME;
            state.dq_rad_s = [0.0; N];
            state.seq += 1;
            monitor.start_at(&HOME, state.finger_m, &robot);
        }
        for _ in 0..rng.below(24) {
            let (cmd, _) = ctl.tick(&state);
            monitor.observe(&cmd.q_rad, cmd.finger_m, &robot, &cfg);
            follow(&mut state, &cmd);
        }
    }
    let secs = t0.elapsed().as_secs_f64();
    let v = monitor.violations;
    let mut rows: Vec<Vec<String>> = reasons.iter().map(|(k, n)| vec![k.to_string(), n.to_string()]).collect();
    rows.push(vec!["(accepted)".into(), accepted.to_string()]);
    crate::print_table(&["rejection reason", "chunks"], &rows);
    println!(
        "{chunks} chunks, {} commands in {secs:.1} s; violations: {} {}",
        monitor.commands,
        v.total(),
        monitor.first.as_deref().unwrap_or("")
    );
    let out = json!({
        "chunks": chunks,
        "commands": monitor.commands,
        "violations": v.total(),
        "violations_by_kind": {
            "not_finite": v.not_finite, "position": v.position, "velocity": v.velocity,
            "acceleration": v.acceleration, "jerk": v.jerk, "tcp_speed": v.tcp_speed, "finger": v.finger,
        },
        "accepted": accepted,
        "superseded": superseded,
        "resets": resets,
        "rejections": reasons,
        "braking_ticks": braking + ctl.braking_ticks(),
        "seed": seed,
        "seconds": secs,
    });
    println!("{out}");
    Ok(out)
}
