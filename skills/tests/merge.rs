//! Merging on golden fixtures: a record (synthetic: rounds, labels and computed motion written
//! here, not from an episode) and a model's answer in, the library out, compared file by file
//! with tests/golden/ (R2G_BLESS=1 rewrites them). Re-applying changes nothing; evidence is
//! never lost from one version to the next; bad operations are dropped with the reason.

// The rules below carry 3.14159 as written in the golden files they are compared with.
#![allow(clippy::approx_constant)]

use std::path::{Path, PathBuf};

use serde_json::{json, Value};
use skills::extract::{parse_answer, Draft, Findings};
use skills::format::{Backend, Fingerprint, Outcome, Status};
use skills::merge::{apply, Context};
use skills::record::{Label, Round, RunRecord};
use skills::Library;

fn round(n: u32) -> Round {
    Round {
        n,
        observe_only: n == 1,
        plan: format!("stage {n}"),
        code: Some("pass".into()),
        exec: Some(json!({"exit": "ok"})),
        state_before: json!({"timestamp": n as f64, "backend": "simulation"}),
        state_after: json!({"timestamp": n as f64 + 1.0, "backend": "simulation"}),
        obs_before: None,
        obs_after: None,
        calls: Vec::new(),
        feedback: String::new(),
    }
}

fn rule(id: &str, object: &str, feature: &str, z: f64, gripper: f64) -> Value {
    json!({"id": id, "actor": "tcp", "anchor": {"object": object, "feature": feature}, "offset_m": [0.0, 0.0, z],
           "yaw_rad": 0.25, "tilt_rad": [3.14159, 0.0, 0.0], "approach": {"step_m": 0.01}, "gripper": gripper,
           "stop": {"kind": "reached"}})
}

fn draft(n: u32, role: &str, steps: Value, rules: Vec<Value>, checks: Vec<Value>) -> Draft {
    let objects = json!({"red_box": {"prompt": "red box", "class": "box"}, "blue_plate": {"prompt": "blue plate", "class": "plate"}});
    Draft {
        round: n,
        geometry: json!({"steps": steps, "rules": rules, "objects": objects, "targets": {}, "reference": [0.3, 0.0, 0.5, 3.14159, 0.0, 0.0],
                         "roles_of_native": {"block": role, "plate": "blue_plate"}}),
        checks,
        effects: None,
    }
}

/// A synthetic record: 1 observation, 2 approach+grasp (positive), 3 a refused lift
/// (negative), 4 the corrected lift (positive), 5 place (positive).
fn findings(name: &str) -> Findings {
    let labels = vec![
        Label::new(1, Outcome::Unknown, vec!["sent no motion".into()], None),
        Label::new(2, Outcome::Positive, vec![], None),
        Label::new(3, Outcome::Negative, vec!["a chunk was rejected: waypoint 3 too far".into()], None),
        Label::new(4, Outcome::Positive, vec![], None),
        Label::new(5, Outcome::Positive, vec![], None),
    ];
    let mut drafts = std::collections::BTreeMap::new();
    drafts.insert(
        2,
        draft(
            2,
            "red_box",
            json!([{"move": "r1"}, {"move": "r2"}, {"gripper": "close", "settle_s": 1.0}]),
            vec![rule("r1", "red_box", "top_face", 0.1, -1.0), rule("r2", "red_box", "centre", 0.006, -1.0)],
            vec![json!({"kind": "holding"})],
        ),
    );
    drafts.insert(
        4,
        draft(
            4,
            "red_box",
            json!([{"move": "r1"}]),
            vec![rule("r1", "red_box", "top_face", 0.1, 1.0)],
            vec![json!({"kind": "lifted", "object": "red_box", "min_m": 0.04})],
        ),
    );
    // The place round saw the block under another name: roles_of_native maps it back.
    drafts.insert(
        5,
        draft(
            5,
            "red_cube",
            json!([{"move": "r1"}, {"gripper": "open", "settle_s": 0.5}, {"move": "r2"}]),
            vec![rule("r1", "blue_plate", "top_face", 0.03, 1.0), rule("r2", "blue_plate", "top_face", 0.15, -1.0)],
            vec![
                json!({"kind": "on", "object": "red_cube", "support": "blue_plate", "tolerance_m": 0.02}),
                json!({"kind": "released"}),
            ],
        ),
    );
    let record = RunRecord {
        dir: PathBuf::from(format!("/records/{name}")),
        name: name.into(),
        gym: "pick_block_plate".into(),
        task: "Pick up the red block and put it on the plate.".into(),
        scene: PathBuf::from("gyms/pick_block_plate/scene.toml"),
        seed: 7,
        success: Some(true),
        rounds: (1..=5).map(round).collect(),
    };
    Findings { record, labels, pairs: vec![(3, 4)], drafts, skipped: Vec::new(), roles: Default::default() }
}

fn ctx() -> Context {
    Context {
        fingerprint: Fingerprint {
            kinematics: "k".repeat(64),
            gripper: "franka_hand".into(),
            profile: "simulation".into(),
        },
        backend: Backend::Sim,
    }
}

fn temp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("r2g-merge-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// Every version file under `dir` (relative path → JSON), the event log left out.
fn files(dir: &Path) -> std::collections::BTreeMap<String, Value> {
    let mut out = std::collections::BTreeMap::new();
    for id in std::fs::read_dir(dir).into_iter().flatten().flatten().filter(|e| e.path().is_dir()) {
        for f in std::fs::read_dir(id.path()).expect("skill folder").flatten() {
            let rel = format!("{}/{}", id.file_name().to_string_lossy(), f.file_name().to_string_lossy());
            out.insert(rel, serde_json::from_str(&std::fs::read_to_string(f.path()).expect("read")).expect("json"));
        }
    }
    out
}

fn golden(case: &str, dir: &Path) {
    let gold = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden").join(case);
    let got = files(dir);
    if std::env::var_os("R2G_BLESS").is_some() {
        let _ = std::fs::remove_dir_all(&gold);
        for (rel, v) in &got {
            let p = gold.join(rel);
            std::fs::create_dir_all(p.parent().expect("parent")).expect("mkdir");
            std::fs::write(p, serde_json::to_string_pretty(v).expect("json") + "\n").expect("write");
        }
    }
    let want = files(&gold);
    assert_eq!(
        got.keys().collect::<Vec<_>>(),
        want.keys().collect::<Vec<_>>(),
        "the library's files differ from {}",
        gold.display()
    );
    for (rel, v) in &got {
        assert_eq!(v, &want[rel], "{rel} differs from the golden file");
    }
}

const ADD: &str = r#"{"operations": [{"op": "add", "id": "pick-place-on-plate", "name": "Pick and place on a plate",
  "summary": "Grasp a block from above, lift it, place it on a plate.", "task_kind": "pick_place",
  "keywords": ["pick", "place"], "evidence": ["E2", "E4", "E5"],
  "stages": {"E2": "grasp", "E4": "lift", "E5": "place"},
  "recovery": [{"when": "a lift chunk is refused for a step over the cap", "action": "split it into smaller steps", "evidence": ["E3", "E4"]}]}]}"#;

#[test]
fn an_add_builds_the_golden_library_and_applying_it_again_changes_nothing() {
    let dir = temp("add");
    let mut lib = Library::open(&dir).expect("open");
    let f = findings("run-a");
    let rep = apply(&mut lib, &f, &parse_answer(ADD).expect("answer"), &ctx()).expect("apply");
    assert_eq!(rep.written, vec![("add".to_string(), "pick-place-on-plate".to_string(), 1)], "{rep:?}");
    assert!(rep.dropped.is_empty(), "{rep:?}");
    let s = lib.get("pick-place-on-plate").expect("skill");
    // The place round's "red_cube" is the same scene object as "red_box": one role.
    assert_eq!(s.objects.keys().collect::<Vec<_>>(), vec!["blue_plate", "red_box"]);
    assert_eq!(s.procedure.iter().map(|p| p.name.as_str()).collect::<Vec<_>>(), vec!["grasp", "lift", "place"]);
    assert_eq!(s.procedure[2].checks[0].object.as_deref(), Some("red_box"));
    assert_eq!(s.status, Status::Candidate);
    // E3 (negative) is evidence through the recovery entry.
    assert!(s.evidence.iter().any(|e| e.round == 3 && e.outcome == Outcome::Negative));
    golden("add", &dir);
    // Idempotence: the same record and answer again, from a fresh reading of the library.
    let mut lib = Library::open(&dir).expect("reopen");
    let rep = apply(&mut lib, &f, &parse_answer(ADD).expect("answer"), &ctx()).expect("apply again");
    assert!(rep.written.is_empty(), "re-applying wrote {:?}", rep.written);
    golden("add", &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn support_revise_split_and_retire_keep_every_piece_of_evidence() {
    let dir = temp("ops");
    let mut lib = Library::open(&dir).expect("open");
    apply(&mut lib, &findings("run-a"), &parse_answer(ADD).expect("answer"), &ctx()).expect("add");
    let b = findings("run-b");
    let ops = r#"{"operations": [
      {"op": "support", "skill": "pick-place-on-plate", "evidence": ["E2", "E4", "E5"]},
      {"op": "revise", "skill": "pick-place-on-plate", "reason": "the lift was refused as recorded; lift in smaller steps",
       "evidence": ["E3", "E4"], "stages": {"E4": "lift"},
       "recovery": [{"when": "the lift is refused", "action": "lift 2 cm first", "evidence": ["E3"]}]},
      {"op": "split", "skill": "pick-place-on-plate", "id": "pick-place-tall", "context": {"object_classes": "cylinder"},
       "reason": "tall objects need a higher carry", "evidence": ["E2", "E5"], "stages": {"E2": "grasp", "E5": "place"}},
      {"op": "retire", "skill": "pick-place-tall", "reason": "superseded in this test", "evidence": ["E5"]}
    ]}"#;
    let rep = apply(&mut lib, &b, &parse_answer(ops).expect("answer"), &ctx()).expect("apply");
    assert!(rep.dropped.is_empty(), "{:?}", rep.dropped);
    let written: Vec<(&str, &str, u32)> = rep.written.iter().map(|(o, i, v)| (o.as_str(), i.as_str(), *v)).collect();
    assert_eq!(
        written,
        vec![
            ("support", "pick-place-on-plate", 2),
            ("revise", "pick-place-on-plate", 3),
            ("split", "pick-place-tall", 1),
            ("retire", "pick-place-tall", 2)
        ]
    );
    golden("ops", &dir);
    let lib = Library::open(&dir).expect("reopen");
    for (id, versions) in &lib.versions {
        for w in versions.windows(2) {
            for e in &w[0].evidence {
                assert!(
                    w[1].evidence.iter().any(|x| x == e),
                    "{id} v{} lost evidence {} in v{}",
                    w[0].version,
                    e.id,
                    w[1].version
                );
            }
        }
    }
    let s = lib.get("pick-place-on-plate").expect("skill");
    // The revision holds both records' evidence.
    assert!(s.evidence.iter().any(|e| e.episode == "run-a") && s.evidence.iter().any(|e| e.episode == "run-b"));
    assert_eq!(lib.get("pick-place-tall").expect("split").status, Status::Retired);
    // Once more: nothing new.
    let mut lib = Library::open(&dir).expect("reopen");
    let again = apply(&mut lib, &b, &parse_answer(ops).expect("answer"), &ctx()).expect("again");
    assert!(again.written.is_empty(), "{:?}", again.written);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_operations_and_answers_are_dropped_with_the_reason_and_change_nothing() {
    let dir = temp("bad");
    let mut lib = Library::open(&dir).expect("open");
    let f = findings("run-a");
    let ops = r#"{"operations": [
      {"op": "add", "id": "x", "name": "x", "evidence": ["E99"]},
      {"op": "frobnicate", "evidence": ["E2"]},
      "not an object",
      {"op": "add", "id": "only-failures", "name": "y", "evidence": ["E3"]},
      {"op": "support", "skill": "no-such-skill", "evidence": ["E2"]},
      {"op": "add", "id": "nothing", "name": "z", "evidence": []}
    ]}"#;
    let rep = apply(&mut lib, &f, &parse_answer(ops).expect("answer"), &ctx()).expect("apply");
    assert!(rep.written.is_empty(), "{:?}", rep.written);
    let reasons: Vec<&str> = rep.dropped.iter().map(|(_, w)| w.as_str()).collect();
    for (i, needle) in [
        "cites unknown evidence \"E99\"",
        "unknown operation 'frobnicate'",
        "an operation is a JSON object",
        "cites no positive round with computed motion",
        "names skill 'no-such-skill'",
        "cites no evidence",
    ]
    .iter()
    .enumerate()
    {
        assert!(reasons[i].contains(needle), "drop {i}: {:?} lacks {needle}", reasons[i]);
    }
    assert!(files(&dir).is_empty(), "a dropped operation wrote a file");
    let events = Library::open(&dir).expect("reopen").events();
    assert_eq!(events.iter().filter(|e| e["event"] == "dropped").count(), 6, "every drop is logged");
    for bad in ["no json here", "{\"ops\": []}", "{\"operations\": [}", "```json\n{\"operations\": 3}\n```"] {
        assert!(parse_answer(bad).is_err(), "{bad}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_version_is_never_overwritten_and_a_damaged_library_is_named() {
    let dir = temp("store");
    let mut lib = Library::open(&dir).expect("open");
    apply(&mut lib, &findings("run-a"), &parse_answer(ADD).expect("answer"), &ctx()).expect("add");
    let s = lib.get("pick-place-on-plate").expect("skill").clone();
    // Writing version 1 again is refused (the next is 2), whatever the content.
    let e = lib.write(s.clone()).expect_err("v1 exists");
    assert!(e.to_string().contains("the next version is v2"), "{e}");
    // A file whose content disagrees with its name.
    let mut wrong = s.clone();
    wrong.version = 2;
    std::fs::write(dir.join("pick-place-on-plate/v0003.json"), serde_json::to_string(&wrong).expect("json"))
        .expect("write");
    let e = Library::open(&dir).err().expect("a misnamed version");
    assert!(e.to_string().contains("v0003.json"), "{e}");
    std::fs::write(dir.join("pick-place-on-plate/v0003.json"), "{ truncated").expect("write");
    let e = Library::open(&dir).err().expect("a broken file");
    assert!(e.to_string().contains("v0003.json") && e.to_string().contains("not a skill"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn over_the_cap_the_skill_unused_longest_retires_and_a_new_one_counts_from_its_writing() {
    let dir = temp("cap");
    let mut lib = Library::open(&dir).expect("open");
    apply(&mut lib, &findings("run-a"), &parse_answer(ADD).expect("answer"), &ctx()).expect("apply");
    let base = lib.get("pick-place-on-plate").expect("skill").clone();
    for id in ["z-old", "a-new"] {
        let mut s = base.clone();
        s.id = id.into();
        s.version = 1;
        s.status = Status::Validated;
        lib.write(s).expect("write");
    }
    // z-old was written an hour ago and never given to an episode; a-new just now.
    let hour_ago = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
    std::fs::File::options()
        .write(true)
        .open(dir.join("z-old/v0001.json"))
        .and_then(|f| f.set_modified(hour_ago))
        .expect("set mtime");
    let mut lib = Library::open(&dir).expect("reopen");
    let active = lib.active().count();
    let retired = skills::merge::housekeeping(&mut lib, 0.0, u32::MAX, active - 1).expect("housekeeping");
    assert_eq!(retired, vec!["z-old".to_string()]);
    let _ = std::fs::remove_dir_all(&dir);
}
