//! Labels from measured physical effect, on a SYNTHETIC run folder (transcript, calls and native
//! traces written here, not from an episode): a program that moved the block and then raised
//! keeps its motion; fingers shut on purpose while pushing are no failure; a sandbox denial is
//! no motion failure and pairs with nothing; rounds before the episode's last reset() are
//! exploration; a fixture's joint and what the hand touched are effects.

use std::path::{Path, PathBuf};

use serde_json::{json, Value};
use sim_host::trace::{Sample, Trace};
use skills::extract::pair;
use skills::format::Outcome;
use skills::record::{effects, RunRecord};

const BLOCK: u16 = 0;
const TABLE: u16 = 2;
const ROBOT: u16 = 3;
const OPEN_M: f64 = 0.04;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// (t, block x, finger opening, contacts) → samples of the pick_block_plate scene's two objects.
fn trace(samples: &[(f64, f64, f64, &[[u16; 2]])]) -> Trace {
    Trace {
        gym: "pick_block_plate".into(),
        owners: ["block", "plate", "table", "robot", "floor"].map(String::from).to_vec(),
        objects: vec!["block".into(), "plate".into()],
        finger_max_m: OPEN_M,
        samples: samples
            .iter()
            .map(|(t, x, f, c)| Sample {
                t_s: *t,
                objects: vec![[*x, -0.12, 0.02, 1.0, 0.0, 0.0, 0.0], [0.5, 0.15, 0.006, 1.0, 0.0, 0.0, 0.0]],
                joints: vec![],
                tcp_m: [0.4, 0.0, 0.3],
                finger_m: *f,
                arm_rad: Vec::new(),
                contacts: c.to_vec(),
                penetration_m: 0.0,
                penetration_pair: [0, 0],
            })
            .collect(),
        ..Default::default()
    }
}

fn chunk(ok: bool, gripper: f64, t: (f64, f64)) -> Value {
    json!({"fn": "post_actions", "type": "ee_pose", "result": i32::from(ok), "t_before": t.0, "t_after": t.1,
           "actions": [[0.5, -0.12, 0.1, std::f64::consts::PI, 0.0, 0.0, gripper]],
           "feedback": if ok { json!({"status": "executed", "reason": "executed", "executed": 1}) }
                       else { json!({"status": "rejected", "reason": "actions[0]: a step over the cap", "executed": 0}) }})
}

struct R {
    n: u32,
    exec: Value,
    calls: Vec<Value>,
    t: (f64, f64),
    gripper: f64,
}

fn write_record(dir: &Path, rounds: &[R], traces: &[(usize, Trace)]) {
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir.join("episodes")).expect("mkdir");
    let scene = root().join("gyms/pick_block_plate/scene.toml");
    let config = json!({"gym": "pick_block_plate", "task": "Push the block, then pick it up.", "seed": 7,
                        "scene": scene, "instance": "ep1-1-1"});
    std::fs::write(dir.join("config.json"), config.to_string()).expect("config");
    let mut lines = Vec::new();
    for r in rounds {
        let rel = format!("rounds/{:03}/calls.json", r.n);
        std::fs::create_dir_all(dir.join(&rel).parent().expect("parent")).expect("mkdir");
        std::fs::write(dir.join(&rel), Value::Array(r.calls.clone()).to_string()).expect("calls");
        lines.push(
            json!({"round": r.n, "observe_only": r.calls.is_empty(), "decision": {"plan": format!("stage {}", r.n), "code": "pass"},
                   "exec": r.exec, "calls": rel,
                   "state_before": {"timestamp": r.t.0, "gripper": [r.gripper], "backend": "simulation"},
                   "state_after": {"timestamp": r.t.1, "backend": "simulation"},
                   "obs_before": format!("rounds/{:03}/obs.npz", r.n - 1), "obs_after": format!("rounds/{:03}/obs.npz", r.n)})
            .to_string(),
        );
    }
    std::fs::write(dir.join("transcript.jsonl"), lines.join("\n")).expect("transcript");
    for (k, t) in traces {
        std::fs::write(dir.join(format!("episodes/episode-{k}.trace.json")), serde_json::to_string(t).expect("json"))
            .expect("trace");
    }
}

fn ok() -> Value {
    json!({"exit": "ok"})
}

#[test]
fn labels_come_from_what_physics_measured_not_from_how_the_program_ended() {
    let dir = std::env::temp_dir().join(format!("r2g-labels-{}", std::process::id()));
    let sandbox = json!({"exit": "exception", "exc_type": "PermissionError",
                         "violation": "denied by the sandbox: PermissionError: [Errno 13] Permission denied: 'robot-skill/memory'"});
    let rounds = [
        // 1: looks, then dies listing a folder the sandbox denies.
        R { n: 1, exec: sandbox.clone(), calls: vec![], t: (0.0, 0.0), gripper: -1.0 },
        // 2: warm-up probes, then reset() (this record's reset carries t_before).
        R {
            n: 2,
            exec: ok(),
            calls: vec![
                chunk(true, -1.0, (0.0, 1.0)),
                chunk(true, -1.0, (1.0, 2.0)),
                json!({"fn": "reset", "result": 1, "t_before": 2.5, "t_after": 0.0}),
            ],
            t: (0.0, 0.0),
            gripper: -1.0,
        },
        // 3: pushes the block 10 cm, then raises on its own strict check.
        R {
            n: 3,
            exec: json!({"exit": "exception", "exc_type": "AssertionError"}),
            calls: vec![chunk(true, -1.0, (0.0, 1.0))],
            t: (0.0, 1.0),
            gripper: -1.0,
        },
        // 4: closes the fingers on purpose and pushes on with them shut.
        R { n: 4, exec: ok(), calls: vec![chunk(true, 1.0, (1.0, 2.0))], t: (1.0, 2.0), gripper: -1.0 },
        // 5: opens, then closes beside the block: nothing between the fingers, nothing moved.
        R {
            n: 5,
            exec: ok(),
            calls: vec![chunk(true, -1.0, (2.0, 2.5)), chunk(true, 1.0, (2.5, 3.0))],
            t: (2.0, 3.0),
            gripper: 1.0,
        },
        // 6: a chunk the runtime refused.
        R { n: 6, exec: ok(), calls: vec![chunk(false, -1.0, (3.0, 3.0))], t: (3.0, 4.0), gripper: 1.0 },
        // 7: grasps the block.
        R {
            n: 7,
            exec: ok(),
            calls: vec![chunk(true, -1.0, (4.0, 4.5)), chunk(true, 1.0, (4.5, 5.0))],
            t: (4.0, 5.0),
            gripper: 1.0,
        },
        // 8: a sandbox denial before any motion, after the task's motions began.
        R { n: 8, exec: sandbox, calls: vec![], t: (5.0, 5.0), gripper: 1.0 },
    ];
    let before: &[[u16; 2]] = &[[BLOCK, TABLE]];
    let pushing: &[[u16; 2]] = &[[BLOCK, TABLE], [BLOCK, ROBOT]];
    let probes = trace(&[(0.0, 0.42, OPEN_M, before), (1.0, 0.42, OPEN_M, before), (2.5, 0.42, OPEN_M, before)]);
    let task = trace(&[
        (0.0, 0.42, OPEN_M, before),
        (0.5, 0.47, OPEN_M, pushing),
        (1.0, 0.52, OPEN_M, before),
        (1.5, 0.55, 0.0, pushing),
        (2.0, 0.58, 0.0, before),
        (2.5, 0.58, OPEN_M, before),
        (3.0, 0.58, 0.0, before),
        (4.0, 0.58, 0.0, before),
        (4.5, 0.58, OPEN_M, before),
        (5.0, 0.58, 0.02, pushing),
    ]);
    let one = trace(&[(0.0, 0.42, OPEN_M, before)]);
    write_record(&dir, &rounds, &[(1, one), (2, probes), (3, task)]);
    let rec = RunRecord::open(&dir).expect("the record opens");
    assert_eq!(rec.last_reset(), Some((2, 2)));
    let w = rec.windows();
    assert_eq!(w[1], (2, 0.0, 2.5), "the warm-up ran in episode 2 until its reset");
    assert_eq!(w[2], (3, 0.0, 1.0));
    let labels = rec.labels().expect("labels");
    let by = |n: u32| labels.iter().find(|l| l.round == n).expect("label");
    let show = |n: u32| format!("{:?}", by(n));
    // 1: no motion, a sandbox denial: unknown, exploration, never a failure.
    assert_eq!(by(1).outcome, Outcome::Unknown, "{}", show(1));
    assert!(by(1).exploration && !by(1).failed());
    assert!(by(1).notes.iter().any(|n| n.contains("not a motion failure")), "{}", show(1));
    // 2: before the last reset(): exploration, whatever it did.
    assert!(by(2).exploration && by(2).outcome == Outcome::Positive, "{}", show(2));
    // 3: the push happened; the program's own exception is a note.
    assert_eq!(by(3).outcome, Outcome::Positive, "{}", show(3));
    assert!(by(3).notes.iter().any(|n| n.contains("AssertionError") && n.contains("kept")), "{}", show(3));
    let e3 = by(3).effects.as_ref().expect("effects");
    assert!(e3.moved.iter().any(|(o, d)| o == "block" && (*d - 0.10).abs() < 1e-6), "{e3:?}");
    assert_eq!(e3.touched, vec!["block".to_string()]);
    // 4: fingers shut with nothing between them at the end, on purpose: the block moved.
    assert_eq!(by(4).outcome, Outcome::Positive, "{}", show(4));
    assert!(by(4).notes.iter().any(|n| n.contains("on purpose")), "{}", show(4));
    // 5: shut on nothing and nothing happened: a motion failure.
    assert_eq!(by(5).outcome, Outcome::Negative, "{}", show(5));
    assert!(by(5).reasons.iter().any(|r| r.contains("shut on nothing")), "{}", show(5));
    // 6: refused.
    assert_eq!(by(6).outcome, Outcome::Negative, "{}", show(6));
    // 7: grasped; 8: a denial that moved nothing is unknown, not negative.
    assert_eq!(by(7).outcome, Outcome::Positive);
    assert_eq!(by(7).effects.as_ref().map(|e| e.grasped.clone()), Some(vec!["block".to_string()]));
    assert_eq!(by(8).outcome, Outcome::Unknown, "{}", show(8));
    // Only motion failures pair with corrections: the missed grasp and the refused chunk with
    // the grasp; the sandbox denials with nothing.
    assert_eq!(pair(&labels), vec![(5, 7), (6, 7)]);
    // What the gripper was last commanded when each round's motion began.
    assert_eq!(rec.commanded_gripper(-1.0), vec![-1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn motion_after_a_reset_within_a_round_is_the_round_s_and_starts_from_the_first_observation() {
    let dir = std::env::temp_dir().join(format!("r2g-labels-reset-{}", std::process::id()));
    let still: &[[u16; 2]] = &[[BLOCK, TABLE]];
    // A record written before resets carried t_before: the probe's end is its chunk's t_after.
    let rounds = [
        R { n: 1, exec: ok(), calls: vec![], t: (0.0, 0.0), gripper: -1.0 },
        R {
            n: 2,
            exec: ok(),
            calls: vec![
                chunk(true, -1.0, (0.0, 1.0)),
                json!({"fn": "reset", "result": 1, "t_after": 0.0}),
                chunk(true, 1.0, (0.0, 1.0)),
            ],
            t: (0.0, 1.0),
            gripper: -1.0,
        },
    ];
    let same = trace(&[(0.0, 0.42, OPEN_M, still), (1.0, 0.42, OPEN_M, still)]);
    write_record(&dir, &rounds, &[(1, trace(&[(0.0, 0.42, OPEN_M, still)])), (2, same.clone()), (3, same)]);
    let rec = RunRecord::open(&dir).expect("open");
    assert_eq!(rec.windows()[1], (3, 0.0, 1.0));
    assert!(!rec.exploration(2), "its motion came after its own reset()");
    assert!(rec.exploration(1));
    let r2 = &rec.rounds[1];
    assert_eq!(r2.motion_calls().len(), 1);
    // The reset put everything back where the first observation saw it.
    assert_eq!(rec.motion_obs(2).expect("an observation"), dir.join("rounds/000/obs.npz"));
    let labels = rec.labels().expect("labels");
    assert!(labels[1].notes.iter().any(|n| n.contains("before its own reset()")), "{:?}", labels[1]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_fixture_joint_that_moved_and_what_was_touched_are_effects() {
    let scene = sim_host::Scene::load(&root().join("gyms/open_drawer/scene.toml")).expect("scene");
    let sample = |t: f64, q: f64, contacts: Vec<[u16; 2]>| Sample {
        t_s: t,
        objects: vec![],
        joints: vec![q],
        tcp_m: [0.5, 0.0, 0.2],
        finger_m: 0.002,
        arm_rad: Vec::new(),
        contacts,
        penetration_m: 0.0,
        penetration_pair: [0, 0],
    };
    // owners: cabinet 0, table 1, robot 2, floor 3
    let t = Trace {
        gym: "open_drawer".into(),
        owners: ["cabinet", "table", "robot", "floor"].map(String::from).to_vec(),
        objects: vec![],
        joints: vec!["cabinet".into()],
        finger_max_m: OPEN_M,
        samples: vec![sample(0.0, 0.0, vec![[1, 2]]), sample(1.0, 0.1, vec![[0, 2]]), sample(2.0, 0.19, vec![[0, 2]])],
        ..Default::default()
    };
    let e = effects(&scene, &t, 0.0, 2.0).expect("effects");
    assert_eq!(e.joints.len(), 1, "{e:?}");
    assert_eq!((e.joints[0].kind.as_str(), e.joints[0].from, e.joints[0].to), ("slide", 0.0, 0.19));
    assert!(e.joints[0].describe().contains("+0.190 m"), "{}", e.joints[0].describe());
    assert_eq!(e.touched, vec!["cabinet".to_string()], "the table is not counted");
    // Fingers nearly shut on the handle (a fixture) are not shut on nothing.
    assert!(!e.closed_on_nothing);
    assert!(e.physical());
}
