//! The validation gate reruns physics from hashed inputs: twice the same trace hash, any edited
//! input a different evidence, a broken demonstration a failed check. Augmentation keeps only
//! variants that pass it, adapts the demonstration to a moved object, and a visual-only variant
//! keeps its parent's physics exactly.

use std::path::{Path, PathBuf};

use real2sim::augment::{self, Factor};
use real2sim::validate::{self, Options};

mod common;
use common::{root, tmp};

/// A copy of a shipped gym whose scene points back at the checkout's robot.
fn copy_gym(gym: &str, to: &Path) -> PathBuf {
    let src = root().join("gyms").join(gym);
    let dir = to.join(gym);
    std::fs::create_dir_all(&dir).expect("dir");
    let table = real2sim::gym::rebased_scene(&src.join("scene.toml"), &dir).expect("rebase");
    std::fs::write(dir.join("scene.toml"), toml::to_string(&table).expect("toml")).expect("scene");
    std::fs::copy(src.join("demo.csv"), dir.join("demo.csv")).expect("demo");
    dir
}

#[test]
fn the_gate_reproduces_its_trace_and_every_input_edit_changes_the_evidence() {
    let dir = tmp("gate");
    let gym = copy_gym("pick_block_plate", &dir);
    let scene = gym.join("scene.toml");
    let run = |out: &str| validate::validate(&scene, &Options::new(dir.join(out))).expect("validate").0;
    let (a, b) = (run("a"), run("b"));
    assert!(a.success, "{:?}", a.checks);
    for check in [
        "initial_penetration",
        "settles_at_rest",
        "waypoints_reachable",
        "event_timing",
        "task_success",
        "worst_penetration",
        "final_stability",
    ] {
        assert!(a.checks.get(check).is_some_and(|c| c.pass), "{check}: {:?}", a.checks.get(check));
    }
    assert_eq!(a.trace_sha256, b.trace_sha256, "the same inputs, the same trace");
    assert_eq!(a.inputs, b.inputs);
    for key in ["scene", "robot_urdf", "demonstration", "criteria", "seed"] {
        assert_eq!(a.inputs[key].len(), 64, "{key} hashed");
    }
    let evidence: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("a/evidence.json")).expect("evidence")).expect("json");
    assert_eq!(evidence["trace_sha256"], a.trace_sha256);

    // Another seed: the seed's hash and the trace change.
    let mut o = Options::new(dir.join("seeded"));
    o.seed = 3;
    let seeded = validate::validate(&scene, &o).expect("seeded").0;
    assert_ne!(seeded.inputs["seed"], a.inputs["seed"]);
    assert_ne!(seeded.trace_sha256, a.trace_sha256);

    // An edited success rule: the criteria's hash changes, the physics does not.
    let text = std::fs::read_to_string(&scene).expect("scene");
    std::fs::write(&scene, text.replace("min_distance_m = 0.05", "min_distance_m = 0.06")).expect("edit");
    let edited = run("edited");
    assert_ne!(edited.inputs["criteria"], a.inputs["criteria"]);
    assert_ne!(edited.inputs_sha256, a.inputs_sha256);
    assert_eq!(edited.trace_sha256, a.trace_sha256);
    std::fs::write(&scene, &text).expect("restore");

    // A demonstration cut short: the task fails, and says so.
    let demo = std::fs::read_to_string(gym.join("demo.csv")).expect("demo");
    let short: String = demo.lines().take(120).map(|l| format!("{l}\n")).collect();
    std::fs::write(gym.join("demo.csv"), short).expect("cut");
    let cut = run("cut");
    assert!(!cut.success);
    assert!(!cut.checks["task_success"].pass, "{:?}", cut.checks["task_success"]);
    assert_ne!(cut.inputs["demonstration"], a.inputs["demonstration"]);

    // Augmenting a parent that fails the gate: refused, and no pool, whole or partial, is left.
    let pool = dir.join("pool");
    let e = augment::augment(&scene, &augment::Options::new(pool.clone()), &|_: &str| {}).expect_err("failing parent");
    assert!(e.to_string().contains("fails the gate"), "{e}");
    let hidden: Vec<String> = std::fs::read_dir(&dir)
        .expect("list")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|n| n == "pool" || n.starts_with(".pool"))
        .collect();
    assert!(hidden.is_empty(), "left behind: {hidden:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn augmentation_keeps_only_gate_passing_variants_with_an_adapted_demonstration() {
    let dir = tmp("augment");
    let scene = root().join("gyms/pick_block_plate/scene.toml");
    let mut o = augment::Options::new(dir.join("pool"));
    o.candidates = 3;
    o.seed = 7;
    o.factors = vec![Factor::ObjectPose, Factor::Visual];
    o.max_levels = 1;
    o.sheet = false;
    let r = augment::augment(&scene, &o, &|m: &str| eprintln!("augment: {m}")).expect("augment");
    eprintln!("feasible {:?}; per factor {:?}; kept {:?}", r.feasible, r.per_factor, r.kept);
    assert!(!r.kept.is_empty(), "{:?}", r.dropped);
    let parent_ev: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("pool/parent/evidence.json")).expect("parent"))
            .expect("json");
    let parent_trace = parent_ev["trace_sha256"].as_str().expect("trace").to_string();
    // The parent's evidence names its scene relative to itself, and it resolves after the pool's rename.
    let parent_scene = dir.join("pool/parent").join(parent_ev["scene"].as_str().expect("scene"));
    assert!(parent_scene.is_file(), "{}", parent_scene.display());
    let parent_demo = lockstep::read_demo(&root().join("gyms/pick_block_plate/demo.csv")).expect("demo");
    let mut saw_pose = false;
    for name in &r.kept {
        let v = dir.join("pool").join(name);
        let variant: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(v.join("variant.json")).expect("variant")).expect("json");
        assert_eq!(variant["parent"], "pick_block_plate");
        let ev: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(v.join("evidence.json")).expect("evidence")).expect("json");
        assert_eq!(ev["success"], true, "{name}");
        assert_eq!(ev["scene"], "scene.toml", "{name}: the evidence names its scene beside it");
        // The parent's grasps travel with the variant, so the gate checks they recur.
        let events: real2sim::events::EventsFile =
            serde_json::from_str(&std::fs::read_to_string(v.join("events.json")).expect("events")).expect("json");
        assert!(
            events.native.iter().any(|g| g.kind == real2sim::events::Kind::Grasp && g.subject == "block"),
            "{name}: no parent grasp in events.json"
        );
        let factors: Vec<String> = serde_json::from_value(variant["factors"].clone()).expect("factors");
        if factors == ["visual"] {
            assert_eq!(ev["trace_sha256"], parent_trace.as_str(), "{name}: visual only, the same physics");
        }
        if factors.contains(&"object_pose".to_string()) {
            saw_pose = true;
            // The rows near the block were re-solved: the demonstration is not the parent's.
            let demo = lockstep::read_demo(&v.join("demo.csv")).expect("demo");
            assert_eq!(demo.len(), parent_demo.len());
            assert!(demo.iter().zip(&parent_demo).any(|(a, b)| a != b), "{name}: demonstration copied, not adapted");
            assert_eq!(demo[0], parent_demo[0], "the first row never moves");
        }
        // Usable like any gym: `r2g replay` semantics reproduce the gate's trace.
        let rep = lockstep::replay(&v.join("scene.toml"), 0, false, None).expect("replay");
        assert!(rep.evaluation.success, "{name}");
        assert_eq!(rep.evaluation.trace_sha256, ev["trace_sha256"].as_str().expect("trace"));
    }
    let pose_sweeps = r.sweeps.iter().filter(|s| s["factor"] == "object_pose").count();
    assert!(pose_sweeps > 0 && r.feasible.contains_key("pose_xy_m"));
    assert!(saw_pose, "no kept variant moved the object: the adaptation went unchecked");
    let _ = std::fs::remove_dir_all(&dir);
}
