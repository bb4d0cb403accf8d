//! Extraction answers in every style a model writes them (property tests, seeded generator):
//! long stage texts, missing and extra fields, evidence repeated or given as numbers, ids with
//! odd characters, unicode or 200 characters long, evidence cited both in the procedure and in
//! recoveries, citations of exploration rounds, of rounds that moved nothing and of rounds the
//! record does not have. A repairable answer is never dropped: it yields one valid skill whose
//! ids fit the budget with every suffix, and every repair is named in the report. The record
//! and its computed motion are SYNTHETIC (written here, not from an episode).

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde_json::{json, Value};
use skills::extract::{parse_answer, whole_sentences, Draft, Findings};
use skills::format::{id_ok, slug_within, Backend, Fingerprint, Outcome, ID_MAX};
use skills::merge::{apply, round_of, stage_name, Context, STAGE_NAME_MAX};
use skills::record::{Label, Round, RunRecord};
use skills::Library;

/// xorshift64*: the same answers on every run.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
    fn chance(&mut self, p: f64) -> bool {
        (self.next() % 10_000) as f64 / 10_000.0 < p
    }
    fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.below(xs.len())]
    }
}

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

fn rule(id: &str, object: &str, z: f64, gripper: f64) -> Value {
    json!({"id": id, "actor": "tcp", "anchor": {"object": object, "feature": "top_face"}, "offset_m": [0.0, 0.0, z],
           "yaw_rad": 0.25, "tilt_rad": [std::f64::consts::PI, 0.0, 0.0], "approach": {"step_m": 0.01}, "gripper": gripper,
           "stop": {"kind": "reached"}})
}

/// A synthetic record: 1 an observation and 2 a warm-up, both before the episode's last
/// reset() (exploration); 3 approach, 4 grasp, 6 lift, 7 place (positive, with motion);
/// 5 a refused lift (negative); 8 sent nothing (unknown).
fn findings() -> Findings {
    let exploration = |mut l: Label| {
        l.exploration = true;
        l
    };
    let labels = vec![
        exploration(Label::new(1, Outcome::Unknown, vec!["sent no motion".into()], None)),
        exploration(Label::new(2, Outcome::Positive, vec![], None)),
        Label::new(3, Outcome::Positive, vec![], None),
        Label::new(4, Outcome::Positive, vec![], None),
        Label::new(5, Outcome::Negative, vec!["a chunk was rejected: a step over the cap".into()], None),
        Label::new(6, Outcome::Positive, vec![], None),
        Label::new(7, Outcome::Positive, vec![], None),
        Label::new(8, Outcome::Unknown, vec!["sent no motion".into()], None),
    ];
    let objects = json!({"orange_bowl": {"prompt": "orange bowl", "class": "bowl"}, "blue_bowl": {"prompt": "blue bowl", "class": "bowl"}});
    let roles = json!({"small_bowl": "orange_bowl", "big_bowl": "blue_bowl"});
    let geometry = |steps: Value, rules: Vec<Value>| {
        json!({"steps": steps, "rules": rules, "objects": objects, "targets": {},
               "reference": [0.3, 0.0, 0.5, std::f64::consts::PI, 0.0, 0.0], "roles_of_native": roles})
    };
    let mut drafts = BTreeMap::new();
    let mut add = |n: u32, steps: Value, rules: Vec<Value>, checks: Vec<Value>| {
        drafts.insert(n, Draft { round: n, geometry: geometry(steps, rules), checks, effects: None });
    };
    add(
        3,
        json!([{"move": "r1"}, {"move": "r2"}]),
        vec![rule("r1", "orange_bowl", 0.1, -1.0), rule("r2", "orange_bowl", 0.03, -1.0)],
        vec![],
    );
    add(
        4,
        json!([{"move": "r1"}, {"gripper": "close", "settle_s": 1.0}]),
        vec![rule("r1", "orange_bowl", 0.0, -1.0)],
        vec![json!({"kind": "holding"})],
    );
    add(
        6,
        json!([{"move": "r1"}]),
        vec![rule("r1", "orange_bowl", 0.12, 1.0)],
        vec![json!({"kind": "lifted", "object": "orange_bowl", "min_m": 0.05})],
    );
    // The place round: its check once read "on blue_bowl, support blue_bowl" (two roles that
    // were one object); such a check is left out, never the stage.
    add(
        7,
        json!([{"move": "r1"}, {"gripper": "open", "settle_s": 0.5}]),
        vec![rule("r1", "blue_bowl", 0.05, 1.0)],
        vec![
            json!({"kind": "on", "object": "orange_bowl", "support": "blue_bowl", "tolerance_m": 0.02}),
            json!({"kind": "on", "object": "blue_bowl", "support": "blue_bowl", "tolerance_m": 0.02}),
        ],
    );
    let record = RunRecord {
        dir: PathBuf::from("/records/synthetic-stack"),
        name: "synthetic-stack@ep1-1-1".into(),
        gym: "stack_bowls".into(),
        task: "Stack the orange bowl inside the blue bowl.".into(),
        scene: PathBuf::from("gyms/stack_bowls/scene.toml"),
        seed: 101,
        success: Some(true),
        rounds: (1..=8).map(round).collect(),
    };
    let roles = [("small_bowl", "orange_bowl"), ("big_bowl", "blue_bowl")]
        .into_iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect();
    Findings { record, labels, pairs: vec![(5, 6)], drafts, skipped: Vec::new(), roles }
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
    let d = std::env::temp_dir().join(format!("r2g-answers-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

const WORDS: [&str; 16] = [
    "approach",
    "the",
    "orange",
    "bowl's",
    "wall",
    "from",
    "above",
    "then",
    "descend",
    "3 cm",
    "(no contact)",
    "—",
    "über",
    "抓取",
    "fingers: straddle",
    "rim;",
];

/// Between `min` and `min + spread` words.
fn text(rng: &mut Rng, min: usize, spread: usize) -> String {
    let n = min + rng.below(spread + 1);
    (0..n).map(|_| *rng.pick(&WORDS)).collect::<Vec<_>>().join(" ")
}

/// One way of writing round `n` as evidence.
fn cite(rng: &mut Rng, n: u32) -> Value {
    match rng.below(6) {
        0 => json!(format!("E{n}")),
        1 => json!(format!("e{n}")),
        2 => json!(format!("E0{n}")),
        3 => json!(n),
        4 => json!(format!("round {n}")),
        _ => json!(format!("E{n} (a stage)")),
    }
}

/// A stage text in one of the styles seen: one word, "name: description" of any length, a
/// long text with no name, an object, unicode.
fn stage_text(rng: &mut Rng) -> Value {
    match rng.below(5) {
        0 => json!(*rng.pick(&["approach", "grasp", "lift", "place"])),
        1 => {
            let name = *rng.pick(&["approach", "grasp and lift", "Stage 3 = carry"]);
            json!(format!("{name}: {}", text(rng, 5, 300)))
        }
        2 => json!(text(rng, 20, 200)),
        3 => json!({"name": "descend", "description": text(rng, 30, 0)}),
        _ => json!("抓取: ü ü ü"),
    }
}

/// A repairable add: at least one cited round has motion; everything else varies.
fn answer(rng: &mut Rng) -> (Value, Vec<u32>, Vec<String>) {
    let usable = [3u32, 4, 6, 7];
    let mut cited: Vec<u32> = usable.iter().copied().filter(|_| rng.chance(0.6)).collect();
    if cited.is_empty() {
        cited.push(*rng.pick(&usable));
    }
    let mut evidence: Vec<Value> = Vec::new();
    for &n in &cited {
        evidence.push(cite(rng, n));
        if rng.chance(0.3) {
            evidence.push(cite(rng, n)); // repeated
        }
    }
    // Citations that cannot be used: exploration, a round that moved nothing, no such round,
    // not an id at all; and a failure (usable as evidence, not as a stage).
    for noise in [json!("E1"), json!("E2"), json!("E8"), json!("E99"), json!("X7"), Value::Null, json!("E5")] {
        if rng.chance(0.35) {
            let at = rng.below(evidence.len() + 1);
            evidence.insert(at, noise);
        }
    }
    let mut op = serde_json::Map::new();
    op.insert("op".into(), json!(*rng.pick(&["add", "Add", " ADD ", "create"])));
    let id = match rng.below(7) {
        0 => Some(json!("nest-bowl-in-bowl")),
        1 => Some(json!("x".repeat(200))),
        2 => Some(json!("Nest the bowl — über 抓取 ü!")),
        3 => Some(json!("Pick & Place!!! (rim pinch)")),
        4 => Some(json!("抓取")),
        5 => Some(json!(42)),
        _ => None,
    };
    if let Some(id) = id {
        op.insert("id".into(), id);
    }
    if rng.chance(0.8) {
        op.insert("name".into(), json!(text(rng, 3, 40)));
    }
    if rng.chance(0.8) {
        op.insert("summary".into(), json!(text(rng, 10, 80)));
    }
    if rng.chance(0.7) {
        op.insert("task_kind".into(), json!(*rng.pick(&["stack", "Pick-Place", "nest / stack", "", "其他"])));
    }
    if rng.chance(0.6) {
        op.insert(
            "keywords".into(),
            if rng.chance(0.5) { json!(["bowl", "stack"]) } else { json!("bowl, nest, stack") },
        );
    }
    op.insert(
        "evidence".into(),
        if evidence.len() == 1 && rng.chance(0.5) { evidence[0].clone() } else { Value::Array(evidence) },
    );
    if rng.chance(0.9) {
        let mut stages = serde_json::Map::new();
        for &n in &cited {
            if rng.chance(0.85) {
                let key = match cite(rng, n) {
                    Value::String(s) => s,
                    other => other.to_string(),
                };
                stages.insert(key, stage_text(rng));
            }
        }
        if rng.chance(0.2) {
            stages.insert("E42".into(), json!("a stage of a round nobody cited"));
        }
        op.insert("stages".into(), Value::Object(stages));
    }
    let mut recovery = Vec::new();
    for _ in 0..rng.below(4) {
        let mut r = serde_json::Map::new();
        r.insert("when".into(), json!(text(rng, 6, 0)));
        if rng.chance(0.85) {
            r.insert("action".into(), json!(text(rng, 8, 0)));
        }
        let mut ev: Vec<Value> = Vec::new();
        for _ in 0..1 + rng.below(3) {
            let n = *rng.pick(&[2u32, 3, 4, 5, 6, 7, 99]);
            ev.push(cite(rng, n));
        }
        r.insert("evidence".into(), Value::Array(ev));
        if rng.chance(0.2) {
            r.insert("confidence".into(), json!(0.7));
        }
        recovery.push(Value::Object(r));
    }
    if recovery.len() == 1 && rng.chance(0.5) {
        op.insert("recovery".into(), recovery[0].clone());
    } else if !recovery.is_empty() || rng.chance(0.5) {
        op.insert("recovery".into(), Value::Array(recovery));
    }
    let mut extra = Vec::new();
    for k in ["confidence", "notes", "preconditions", "object_roles"] {
        if rng.chance(0.3) {
            op.insert(k.into(), json!(text(rng, 4, 0)));
            extra.push(k.to_string());
        }
    }
    let mut answer = json!({"operations": [Value::Object(op)]});
    if rng.chance(0.3) {
        answer["reasoning"] = json!("I looked at every round.");
    }
    (answer, cited, extra)
}

#[test]
fn a_repairable_answer_always_yields_one_valid_skill_and_every_repair_is_named() {
    let f = findings();
    let mut rng = Rng(0x5EED_0031);
    for case in 0..300 {
        let (answer, cited, extra) = answer(&mut rng);
        let dir = temp(&format!("prop-{case}"));
        let mut lib = Library::open(&dir).expect("open");
        let text = serde_json::to_string(&answer).expect("json");
        let parsed = parse_answer(&text).expect("an answer with operations parses");
        let rep = apply(&mut lib, &f, &parsed, &ctx()).expect("apply");
        assert!(rep.dropped.is_empty(), "case {case}: a repairable answer was dropped: {:?}\n{text}", rep.dropped);
        assert_eq!(rep.written.len(), 1, "case {case}: {rep:?}\n{text}");
        let (_, id, v) = &rep.written[0];
        let s = lib.get(id).expect("the written skill").clone();
        assert_eq!(*v, 1);
        s.validate().unwrap_or_else(|e| panic!("case {case}: {e}\n{text}"));
        // Ids fit the budget with room for the suffixes the library adds.
        assert!(id_ok(&s.id) && s.id.len() <= ID_MAX - 4, "case {case}: id {:?}", s.id);
        for r in &s.rules {
            assert!(id_ok(&r.id), "case {case}: rule id {:?}", r.id);
        }
        // The procedure: the cited rounds that have motion, in round order.
        let mut want: Vec<u32> = cited.clone();
        want.sort_unstable();
        let sources: Vec<String> = s.procedure.iter().filter_map(|st| st.source.clone()).collect();
        let expect: Vec<String> = want.iter().map(|n| format!("{}#{n}", f.record.name)).collect();
        assert_eq!(sources, expect, "case {case}\n{text}");
        for st in &s.procedure {
            assert!(st.name.len() <= STAGE_NAME_MAX + 2, "case {case}: stage {:?}", st.name);
            // An object is never its own support.
            assert!(st.checks.iter().all(|c| c.support.is_none() || c.support != c.object), "case {case}");
        }
        // Evidence: each round once; never exploration, never a round that moved nothing,
        // never one the record does not have.
        let mut keys: Vec<u32> = s.evidence.iter().map(|e| e.round).collect();
        let n = keys.len();
        keys.sort_unstable();
        keys.dedup();
        assert_eq!(keys.len(), n, "case {case}: evidence listed twice: {keys:?}");
        assert!(keys.iter().all(|k| [3, 4, 5, 6, 7].contains(k)), "case {case}: evidence {keys:?}\n{text}");
        // Whatever was ignored is named.
        let notes: Vec<&str> = rep.repaired.iter().map(|(_, n)| n.as_str()).collect();
        for k in &extra {
            assert!(
                notes.iter().any(|n| n.contains(&format!("ignored field '{k}'"))),
                "case {case}: {k} unnamed: {notes:?}"
            );
        }
        for bad in ["E1", "E2", "E8", "E99"] {
            if answer["operations"][0]["evidence"].to_string().contains(&format!("\"{bad}\"")) {
                assert!(
                    notes.iter().any(|n| n.contains(bad)),
                    "case {case}: the citation {bad} left out without a note"
                );
            }
        }
        // The same record and answer again: nothing changes.
        let again = apply(&mut lib, &f, &parsed, &ctx()).expect("again");
        assert!(again.written.is_empty() && again.dropped.is_empty(), "case {case}: {again:?}");
        let events = lib.events();
        assert!(events.iter().all(|e| e["event"] != "dropped"), "case {case}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

#[test]
fn long_stage_texts_become_short_names_and_whole_descriptions() {
    let f = findings();
    let long =
        format!("approach: {}", "move above the orange bowl's wall on the side away from the target bowl, ".repeat(6));
    let ans = json!({"operations": [{"op": "add", "id": "nest", "name": "Nest", "evidence": ["E3", "E4", "E6", "E7"],
        "stages": {"E3": long, "E4": "grasp", "E6": "Stage 6 = lift the bowl straight up two centimetres, slowly",
                   "E7": "grasp"}}]});
    let dir = temp("stages");
    let mut lib = Library::open(&dir).expect("open");
    let rep = apply(&mut lib, &f, &ans, &ctx()).expect("apply");
    assert!(rep.dropped.is_empty(), "{:?}", rep.dropped);
    let s = lib.get("nest").expect("skill");
    let names: Vec<&str> = s.procedure.iter().map(|p| p.name.as_str()).collect();
    // Two stages the model named alike stay apart by their round.
    assert_eq!(names, vec!["approach", "grasp", "lift_the_bowl", "grasp_7"]);
    assert_eq!(s.procedure[0].description.as_deref(), Some(long.trim()));
    assert_eq!(s.procedure[1].description, None, "a one-word stage text is its name");
    assert_eq!(s.rules.iter().map(|r| r.id.as_str()).collect::<Vec<_>>()[..3], ["approach_1", "approach_2", "grasp_1"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn what_cannot_be_repaired_is_dropped_naming_why() {
    let f = findings();
    let dir = temp("unrepairable");
    let mut lib = Library::open(&dir).expect("open");
    let ans = json!({"operations": [
        {"op": "add", "id": "nothing-usable", "evidence": ["E2", "E8", "E99"]},
        {"op": "add", "id": "only-failures", "evidence": ["E5"]},
        {"op": "merge", "skill": "x", "evidence": ["E3"]},
        {"op": "support", "skill": "no-such-skill", "evidence": ["E3"]},
    ]});
    let rep = apply(&mut lib, &f, &ans, &ctx()).expect("apply");
    assert!(rep.written.is_empty(), "{:?}", rep.written);
    let why: Vec<&str> = rep.dropped.iter().map(|(_, w)| w.as_str()).collect();
    assert!(why[0].contains("cites no evidence that can be used"), "{}", why[0]);
    for part in ["E8: the round moved nothing", "E2: exploration", "unknown evidence \"E99\""] {
        assert!(why[0].contains(part), "{part} not named in {}", why[0]);
    }
    assert!(why[1].contains("cites no positive round with computed motion"), "{}", why[1]);
    assert!(why[2].contains("unknown operation 'merge'"), "{}", why[2]);
    assert!(why[3].contains("names skill 'no-such-skill'"), "{}", why[3]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn ids_and_stage_names_fit_the_budget_with_every_suffix() {
    let mut rng = Rng(64);
    for _ in 0..500 {
        let t = text(&mut rng, 1, 120);
        for (max, sep) in [(ID_MAX - 4, '-'), (STAGE_NAME_MAX, '_')] {
            let s = slug_within(&t, max, sep);
            assert!(s.len() <= max && (s.is_empty() || id_ok(&s)), "{t:?} -> {s:?}");
        }
        let round = 1 + rng.below(9999) as u32;
        let (name, description) = stage_name(&t, round);
        // The longest rule id a stage can get: a second stage of the same name (`_<round>`),
        // then its rule number.
        let rule = format!("{name}_{round}_{}", 999);
        assert!(id_ok(&name) && id_ok(&rule), "{t:?}: stage {name:?}, rule {rule:?}");
        if let Some(d) = description {
            assert_eq!(d, t.trim());
        }
    }
    assert_eq!(slug_within("Öffne die Schublade", 64, '-'), "offne-die-schublade");
    assert_eq!(slug_within("pick_place", 64, '-'), "pick_place", "an id's own separators stay");
    assert_eq!(stage_name("approach: with the gripper open, above the wall", 3).0, "approach");
    assert_eq!(
        stage_name("Stage \"warm-up + reset + locate handle\" (no task motion yet)", 2).0,
        "warm_up_reset_locate_handle"
    );
    assert_eq!(stage_name("Stage 3 = approach the orange bowl's grasp point from above", 3).0, "approach_the_orange");
    assert_eq!(stage_name("2. lift: raise 2 cm", 4).0, "lift");
    assert_eq!(stage_name("抓取", 5).0, "stage_5");
    for (v, n) in [(json!("E3"), Some(3)), (json!("e03"), Some(3)), (json!(7), Some(7)), (json!("round 4"), Some(4))] {
        assert_eq!(round_of(&v), n, "{v}");
    }
    for v in [json!("E3b"), json!("X"), json!(null), json!(-1), json!("E")] {
        assert_eq!(round_of(&v), None, "{v}");
    }
}

#[test]
fn plans_are_cut_at_a_sentence_end_and_say_so() {
    let plan = "Stage 4 = descend around the wall. 1. Fresh check: re-segment the bowl. 2. Descend in 4 mm steps \
                to z = 0.052 (e.g. 12 waypoints). 3. Close the gripper and wait.";
    let (cut, was_cut) = whole_sentences(plan, 110);
    assert!(was_cut);
    assert_eq!(cut, "Stage 4 = descend around the wall. 1. Fresh check: re-segment the bowl.");
    let (all, was_cut) = whole_sentences(plan, 1000);
    assert!(!was_cut && all == plan);
    // No sentence end within reach: whole words.
    let (words, _) = whole_sentences("one two three four five six", 12);
    assert_eq!(words, "one two");
}

#[test]
fn an_answer_off_only_by_its_wrapper_is_read() {
    let op = r#"{"op": "add", "id": "x", "evidence": ["E3"]}"#;
    for text in [
        format!("{{\"operations\": [{op}]}}"),
        format!("Here you are:\n```json\n{{\"operations\": [{op}]}}\n```\nDone."),
        format!("[{op}, {op}]"),
        op.to_string(),
        format!("{{\"operations\": {op}}}"),
    ] {
        let v = parse_answer(&text).unwrap_or_else(|e| panic!("{text}: {e}"));
        assert!(v["operations"].as_array().is_some_and(|a| !a.is_empty() && a[0]["op"] == "add"), "{text}");
    }
    for bad in ["no json here", "{\"ops\": []}", "{\"operations\": [}", "```json\n{\"operations\": 3}\n```", "42"] {
        assert!(parse_answer(bad).is_err(), "{bad}");
    }
}
