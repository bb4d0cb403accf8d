//! `released` is judged from what physically happened (robot contact over the final window and
//! the TCP's distance), not from how far the fingers are open: stack_bowls' own demonstration,
//! run in lockstep and judged by the native evaluator, with its ending changed.

use std::path::PathBuf;

use ipc_schema::{ControlType, Status, MAX_CHUNK, WAYPOINT_LEN};
use lockstep::{read_demo, Episode};

fn scene() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../gyms/stack_bowls/scene.toml")
}

/// Runs `rows` as joint chunks at the demonstration rate, settles, and judges.
fn judge(rows: &[[f64; WAYPOINT_LEN]]) -> (sim_host::trace::Evaluation, f64) {
    let mut ep = Episode::new(&scene(), 0).expect("stack_bowls loads");
    let hz = ep.sim.scene.task.demonstration_hz;
    for chunk in rows.chunks(MAX_CHUNK) {
        let r = ep.run_chunk(ControlType::Joint, chunk, hz);
        assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
    }
    ep.hold(ep.sim.scene.task.settle_s);
    let last = ep.trace.samples.last().expect("samples");
    let bowl = ep.trace.objects.iter().position(|o| o == "small_bowl").expect("small_bowl");
    let p = last.objects[bowl];
    let d = ((p[0] - last.tcp_m[0]).powi(2) + (p[1] - last.tcp_m[1]).powi(2) + (p[2] - last.tcp_m[2]).powi(2)).sqrt();
    (ep.evaluate(), d)
}

fn demo() -> Vec<[f64; WAYPOINT_LEN]> {
    let mut ep_scene = sim_host::Scene::load(&scene()).expect("scene");
    let path = ep_scene.task.demonstration.take().expect("demonstration");
    read_demo(&path).expect("demo.csv")
}

#[test]
fn placed_and_left_with_a_half_closed_gripper_far_away_is_released() {
    let mut rows = demo();
    let last = *rows.last().expect("rows");
    // After the demonstration's retreat, close the fingers to g = 0.4 over one second.
    for k in 1..=20 {
        let mut r = last;
        r[7] = -1.0 + 1.4 * k as f64 / 20.0;
        rows.push(r);
    }
    let (e, d) = judge(&rows);
    let c = &e.checks["released:small_bowl"];
    assert!(c.pass && !c.value["gripper_open"].as_bool().unwrap_or(true), "{c:?} at {d:.3} m");
    assert!(d > 0.15, "the hand ends {d:.3} m from the bowl");
    assert!(e.success, "{:?}", e.checks);
}

#[test]
fn a_bowl_left_touching_a_finger_is_not_released() {
    let rows = demo();
    // Stop just before the fingers start to open: the bowl sits in the big bowl, still held.
    let held = rows.iter().skip(1).position(|r| r[7] > 0.0).expect("the demo closes the gripper") + 1;
    let open_at = rows.iter().skip(held).position(|r| r[7] < 1.0).expect("the demo opens again") + held;
    let (e, d) = judge(&rows[..open_at]);
    let c = &e.checks["released:small_bowl"];
    assert!(!c.pass && c.value["robot_contact"]["with"] == "small_bowl", "{c:?} at {d:.3} m");
    assert!(!e.success);
}
