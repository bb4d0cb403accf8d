//! `r2g bench accept`: the runtime's tick-to-command latency while a client posts the heaviest
//! chunks acceptance meets, back to back: max-length ee_pose chunks that need an IK solve at
//! every sample of their path (accepted, each replacing the one before), and as long ones
//! whose last waypoint no IK reaches (rejected). Measured against the bare clock_nanosleep loop
//! in the same run, once with acceptance on the planner thread and once on the tick thread (the
//! old way, `R2G_ACCEPT_ON_TICK=1`), so the difference is the move.

use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use ipc_schema::{ControlType, Qos, Reply, Request, RequestKind, Services, Status, MAX_CHUNK, WAYPOINT_LEN};
use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use runtime::controller::Controller;
use runtime::launch;

use crate::tick::Beside;
use runtime::stats::Histogram;
use serde_json::{json, Value};

use crate::control::HOME;

const GYM: &str = "pick_block_plate";
/// Half the sideways swing of the accepted chunks, m, and of their turn, rad: every step (and
/// the first, from anywhere on the swing) stays inside the shipped step caps (5 cm, 0.35 rad).
const SWING_M: f64 = 0.02;
const SWING_RAD: f64 = 0.12;
/// Steps of the rejected chunks' final climb, m.
const CLIMB_M: f64 = 0.045;

fn flat(s: &Value, key: &str) -> f64 {
    s.pointer(key).and_then(Value::as_f64).unwrap_or(f64::NAN)
}

fn waypoint(p: Vector3<f64>, r: UnitQuaternion<f64>) -> [f64; WAYPOINT_LEN] {
    let aa = r.scaled_axis();
    [p.x, p.y, p.z, aa.x, aa.y, aa.z, 0.0, -1.0]
}

/// Waypoint `k` of the swing around the home TCP pose: sideways and turning, alternately.
fn swing(home: &Isometry3<f64>, k: usize) -> [f64; WAYPOINT_LEN] {
    let s = if k.is_multiple_of(2) { 1.0 } else { -1.0 };
    let p = home.translation.vector + Vector3::new(0.0, s * SWING_M, 0.0);
    let r = UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, s * SWING_RAD)) * home.rotation;
    waypoint(p, r)
}

fn chunk(id: u64, client: u64, actions: &[[f64; WAYPOINT_LEN]]) -> Box<Request> {
    let mut r = Box::new(Request {
        id,
        client,
        kind: RequestKind::Chunk as u32,
        control_type: ControlType::EePose as u32,
        len: actions.len() as u32,
        step_ticks: 0,
        freq_hz: 0.0,
        actions: [[0.0; WAYPOINT_LEN]; MAX_CHUNK],
    });
    r.actions[..actions.len()].copy_from_slice(actions);
    r
}

/// The two chunks, checked and timed in this process with the runtime's own controller and
/// the limits r2g-control runs with: (accepted, rejected, their acceptance times).
type Waypoints = Vec<[f64; WAYPOINT_LEN]>;

fn heaviest() -> anyhow::Result<(Waypoints, Waypoints, Histogram, Histogram)> {
    let scene = launch::resolve_scene(GYM)?;
    let (robot, safety) = runtime::scene_robot(&scene)?;
    let cfg = runtime::RobotConfig::default();
    let n = cfg.max_chunk_waypoints.min(MAX_CHUNK);
    let fresh = || Controller::new(robot.clone(), cfg.limiter(), 0.001).with_safety(safety.clone());
    let state = ipc_schema::SimState {
        seq: 1,
        q_rad: HOME,
        finger_m: robot.finger_max_m,
        finger_max_m: robot.finger_max_m,
        ..Default::default()
    };
    let home = robot.kin.fk(&HOME, robot.kin.tcp);
    let accepted: Vec<_> = (0..n).map(|k| swing(&home, k)).collect();
    // The rejected one: the same swing, then a climb at the step cap until no IK reaches the
    // last waypoint (so every sample before it is solved first).
    let mut rejected = None;
    for climb in 1..=40usize {
        let mut a: Vec<_> = (0..n - climb).map(|k| swing(&home, k)).collect();
        let last = a[a.len() - 1];
        let from = Vector3::new(last[0], last[1], last[2]);
        let r = UnitQuaternion::from_scaled_axis(Vector3::new(last[3], last[4], last[5]));
        for i in 1..=climb {
            a.push(waypoint(from + Vector3::new(0.0, 0.0, CLIMB_M * i as f64), r));
        }
        let mut ctl = fresh();
        let (reply, _) = ctl.request(&chunk(1, 1, &a), &state);
        match (reply, ctl.last_rejection) {
            (_, Some("unreachable")) => {
                rejected = Some(a);
                break;
            }
            (Some(r), Some(kind)) => {
                bail!("the climb was refused as {kind} before it became unreachable: {}", r.reason_str())
            }
            _ => {}
        }
    }
    let rejected = rejected.context("no climb of up to 40 steps became unreachable")?;
    let (mut acc_h, mut rej_h) = (Histogram::new(), Histogram::new());
    for (a, h, want) in [(&accepted, &mut acc_h, None), (&rejected, &mut rej_h, Some("unreachable"))] {
        for _ in 0..20 {
            let mut ctl = fresh();
            let req = chunk(1, 1, a);
            let t0 = Instant::now();
            let (reply, _) = ctl.request(&req, &state);
            h.record(t0.elapsed().as_nanos() as u64);
            if ctl.last_rejection != want {
                bail!(
                    "a bench chunk was decided otherwise than meant: {:?} ({})",
                    ctl.last_rejection,
                    reply.map(|r| r.reason_str().to_string()).unwrap_or_default()
                );
            }
        }
    }
    Ok((accepted, rejected, acc_h, rej_h))
}

/// What the client saw.
#[derive(Default)]
struct ClientFigures {
    accepted: u64,
    rejected: u64,
    superseded: u64,
    /// Other outcomes (for instance a chunk refused because the arm moved while it was checked).
    other: u64,
    /// From sending a chunk to its `accepted` or `rejected` reply.
    round_trip: Histogram,
}

/// Posts the two chunks alternately, each as soon as the one before has its `accepted` or
/// `rejected` reply, for `seconds`.
fn client(
    instance: &str,
    seconds: f64,
    accepted: &[[f64; WAYPOINT_LEN]],
    rejected: &[[f64; WAYPOINT_LEN]],
) -> anyhow::Result<ClientFigures> {
    let services = Services::new(instance)?;
    let node = ipc_schema::node(&format!("bench-accept-{}", std::process::id()))?;
    let req_pub = ipc_schema::open_or_create_pubsub::<Request>(&node, &services.request(), Qos::REQUESTS)?
        .publisher_builder()
        .create()?;
    let reply_sub = ipc_schema::open_or_create_pubsub::<Reply>(&node, &services.reply(), Qos::REPLIES)?
        .subscriber_builder()
        .create()?;
    let wake = ipc_schema::open_or_create_event(&node, &services.control_wake())?.notifier_builder().create()?;
    let listen = ipc_schema::open_or_create_event(&node, &services.agent_wake())?.listener_builder().create()?;
    let me = (u64::from(std::process::id()) << 32) | 0xacce;
    let mut f = ClientFigures::default();
    let t0 = Instant::now();
    let mut id = 0u64;
    while t0.elapsed().as_secs_f64() < seconds {
        id += 1;
        let req = chunk(id, me, if id % 2 == 1 { accepted } else { rejected });
        let sent = Instant::now();
        req_pub.send_copy(*req)?;
        let _ = wake.notify();
        'wait: loop {
            while let Some(r) = reply_sub.receive()? {
                if r.client != me {
                    continue;
                }
                let status = Status::from_u32(r.status);
                if r.id != id {
                    // The chunk this one replaced.
                    if status == Some(Status::Failed) && r.reason_str().starts_with("superseded") {
                        f.superseded += 1;
                    }
                    continue;
                }
                match (status, id % 2 == 1) {
                    (Some(Status::Accepted), true) => f.accepted += 1,
                    (Some(Status::Rejected), false) => f.rejected += 1,
                    _ => {
                        f.other += 1;
                        if f.other <= 3 {
                            eprintln!("bench accept: request {id}: {} ({})", r.status, r.reason_str());
                        }
                    }
                }
                f.round_trip.record(sent.elapsed().as_nanos() as u64);
                break 'wait;
            }
            if sent.elapsed() > Duration::from_secs(5) {
                bail!("no reply to request {id} within 5 s");
            }
            let _ = listen.timed_wait(|_| {}, Duration::from_millis(2));
        }
    }
    Ok(f)
}

/// One run: the runtime with acceptance `on_tick` or not, the bare loop beside it, the client.
fn one_run(
    on_tick: bool,
    seconds: f64,
    accepted: &[[f64; WAYPOINT_LEN]],
    rejected: &[[f64; WAYPOINT_LEN]],
) -> anyhow::Result<(Value, Value, ClientFigures)> {
    let tag = if on_tick { "tick" } else { "planner" };
    // r2g-control reads it at start; set before any thread of this run exists.
    if on_tick {
        std::env::set_var("R2G_ACCEPT_ON_TICK", "1");
    } else {
        std::env::remove_var("R2G_ACCEPT_ON_TICK");
    }
    let run = Beside::start(&format!("acc{tag}{}", std::process::id()), &launch::resolve_scene(GYM)?, seconds);
    std::env::remove_var("R2G_ACCEPT_ON_TICK");
    let run = run?;
    let figures = client(&run.inst.name, seconds, accepted, rejected);
    let (rt, base) = run.finish("bench accept");
    let (rt, figures) = (rt?, figures?);
    Ok((rt, base, figures))
}

pub fn run(seconds: f64, only: Option<&str>) -> anyhow::Result<Value> {
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 3600.0) {
        bail!("--seconds must be in (0, 3600]");
    }
    let modes: Vec<bool> = match only {
        None => vec![false, true],
        Some("planner") => vec![false],
        Some("tick") => vec![true],
        Some(o) => bail!("--only {o}: use planner or tick"),
    };
    let (accepted, rejected, acc_h, rej_h) = heaviest()?;
    eprintln!(
        "bench accept: chunks of {} waypoints; checked in this process: accepted {:.0} µs, rejected {:.0} µs (max of 20)",
        accepted.len(),
        acc_h.max_us(),
        rej_h.max_us()
    );
    let mut runs = Vec::new();
    for on_tick in modes {
        let tag = if on_tick { "tick" } else { "planner" };
        eprintln!("bench accept: acceptance on the {tag} thread, {seconds} s of chunks back to back...");
        let (rt, base, client) = one_run(on_tick, seconds, &accepted, &rejected)?;
        if rt["acceptance"] != tag {
            bail!("r2g-control checked chunks on the {} thread, not the {tag} one", rt["acceptance"]);
        }
        runs.push((tag, rt, base, client));
    }

    let row = |name: String, s: &Value, c: Option<&ClientFigures>| {
        vec![
            name,
            format!("{}", s["ticks"]),
            format!("{:.1}", flat(s, "/command/p50_us")),
            format!("{:.1}", flat(s, "/command/p99_us")),
            format!("{:.1}", flat(s, "/command/p999_us")),
            format!("{:.1}", flat(s, "/command/max_us")),
            format!("{:.1}", flat(s, "/wake/p999_us")),
            format!("{:.1}", flat(s, "/wake/max_us")),
            format!("{}", s["overruns"]),
            c.map_or("-".into(), |c| format!("{}/{}", c.accepted, c.rejected)),
            s.pointer("/accept/count")
                .filter(|n| n.as_u64() > Some(0))
                .map_or("-".into(), |_| format!("{:.0}/{:.0}", flat(s, "/accept/p50_us"), flat(s, "/accept/max_us"))),
            s.get("tick_allocations").map_or("-".into(), |v| v.to_string()),
        ]
    };
    let mut rows = Vec::new();
    for (tag, rt, base, client) in &runs {
        rows.push(row(format!("runtime, checks on {tag}"), rt, Some(client)));
        rows.push(row("  bare loop, same run".into(), base, None));
    }
    crate::print_table(
        &[
            "loop",
            "ticks",
            "tick→command p50 µs",
            "p99",
            "p99.9",
            "max",
            "wake p99.9",
            "max",
            "overruns",
            "accepted/rejected",
            "accept p50/max µs",
            "allocs in tick",
        ],
        &rows,
    );
    let latency = |s: &Value, h: &str| {
        json!({
            "p50_us": flat(s, &format!("/{h}/p50_us")),
            "p99_us": flat(s, &format!("/{h}/p99_us")),
            "p999_us": flat(s, &format!("/{h}/p999_us")),
            "max_us": flat(s, &format!("/{h}/max_us")),
        })
    };
    let mut out = json!({
        "bench": "accept",
        "seconds": seconds,
        "period_us": 1000,
        "chunk_waypoints": accepted.len(),
        "in_process_accept_us": {"accepted_max": acc_h.max_us(), "accepted_p50": acc_h.quantile_us(0.5),
                                  "rejected_max": rej_h.max_us(), "rejected_p50": rej_h.quantile_us(0.5)},
    });
    for (tag, rt, base, c) in &runs {
        out[*tag] = json!({
            "runtime": {
                "tick_to_command": latency(rt, "command"),
                "wake": latency(rt, "wake"),
                "overruns": rt["overruns"],
                "ticks": rt["ticks"],
                "tick_allocations": rt["tick_allocations"],
                "accept": latency(rt, "accept"),
                "planning": latency(rt, "planning"),
            },
            "baseline": {
                "tick_to_command": latency(base, "command"),
                "wake": latency(base, "wake"),
                "overruns": base["overruns"],
            },
            "client": {
                "accepted": c.accepted, "rejected": c.rejected, "superseded": c.superseded, "other": c.other,
                "reply_p50_us": c.round_trip.quantile_us(0.5), "reply_max_us": c.round_trip.max_us(),
            },
            "worst_ratio_to_baseline": flat(rt, "/command/max_us") / flat(base, "/command/max_us"),
        });
    }
    println!("{out}");
    Ok(out)
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_swing_keeps_inside_the_step_caps() {
        let home = nalgebra::Isometry3::identity();
        let (a, b) = (super::swing(&home, 0), super::swing(&home, 1));
        let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        assert!(d <= 0.05 && 2.0 * super::SWING_RAD <= 0.35);
    }
}
