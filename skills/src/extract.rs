//! Extraction: a finished run record in, proposed library operations out. A separate step
//! after the episode (the only place the native verdict and traces are read):
//!
//! 1. every round gets a local effect from what was measured ([`RunRecord::labels`]); rounds
//!    before the episode's last reset() are exploration and never become a skill;
//! 2. motion failures are paired with the next round that succeeded on the same thing (the
//!    correction); a program's own exception or a sandbox denial is no motion failure;
//! 3. for each positive round, the code computes its motion against the objects seen at the
//!    round's start (`skill_tools.py relate_record`: anchor, offset and yaw of each target,
//!    with the TCP measured then as reference; one tracker over the record's observations and
//!    the trace's positions give each scene object one role for the whole record) and its
//!    checks from the trace;
//! 4. the model, through the configured endpoint, names and annotates and proposes operations
//!    (add, support, revise, split, retire) citing evidence ids `E<round>`; it never writes
//!    coordinates: procedures are built from the rounds it cites.
//!
//! The answer must hold a JSON object; what the code can repair in it is repaired (see
//! `merge`), what it cannot is dropped with the reason in the library's event log.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use agent_host::llm::{Client, EndpointConfig, Message, Role};
use anyhow::Context;
use serde::Serialize;
use serde_json::{json, Value};

use crate::format::{CheckKind, Outcome};
use crate::record::{Effects, Label, RunRecord};
use crate::tools;

/// A positive round's motion, related to the objects seen when it began.
#[derive(Debug, Clone, Serialize)]
pub struct Draft {
    pub round: u32,
    /// skill_tools.py relate's answer: steps, rules, objects, targets, reference, roles_of_native.
    pub geometry: Value,
    /// Checks derived from the trace's effects, against perceived roles.
    pub checks: Vec<Value>,
    pub effects: Option<Effects>,
}

/// Everything extraction learned from one record, before the library changes.
pub struct Findings {
    pub record: RunRecord,
    pub labels: Vec<Label>,
    /// (failed round, the round that corrected it).
    pub pairs: Vec<(u32, u32)>,
    pub drafts: BTreeMap<u32, Draft>,
    /// Rounds whose geometry could not be computed, with the reason.
    pub skipped: Vec<(u32, String)>,
    /// Scene object (trace name) → its role, one for the whole record.
    pub roles: BTreeMap<String, String>,
}

impl Findings {
    pub fn label(&self, round: u32) -> Option<&Label> {
        self.labels.iter().find(|l| l.round == round)
    }

    pub fn round(&self, round: u32) -> Option<&crate::record::Round> {
        self.record.rounds.iter().find(|r| r.n == round)
    }
}

/// The objects a round changed (moved, lifted, grasped, set down, dropped or toppled).
fn acted_on(l: &Label) -> std::collections::BTreeSet<&str> {
    let Some(e) = &l.effects else { return Default::default() };
    e.moved
        .iter()
        .chain(&e.rose)
        .chain(&e.fell)
        .chain(&e.toppled)
        .map(|(o, _)| o.as_str())
        .chain(e.grasped.iter().map(String::as_str))
        .chain(e.rests_on.iter().map(|(o, _)| o.as_str()))
        .collect()
}

/// Motion failures and the round that corrected each (see `analyse`). Exploration is neither.
pub fn pair(labels: &[Label]) -> Vec<(u32, u32)> {
    let mut pairs = Vec::new();
    for (i, l) in labels.iter().enumerate() {
        if l.failed() {
            // The correction acts on what the failure acted on; a failure that touched nothing
            // (a missed grasp) is corrected by the next round that grasped something.
            let failed = acted_on(l);
            let corrects = |m: &&Label| {
                m.usable()
                    && if failed.is_empty() {
                        m.effects.as_ref().is_some_and(|e| !e.grasped.is_empty())
                    } else {
                        !acted_on(m).is_disjoint(&failed)
                    }
            };
            if let Some(next) = labels[i + 1..].iter().find(corrects) {
                pairs.push((l.round, next.round));
            }
        }
    }
    pairs
}

/// Steps 1-3 (no model).
pub fn analyse(root: &Path, run: &Path) -> anyhow::Result<Findings> {
    let record = RunRecord::open(run)?;
    let labels = record.labels()?;
    let pairs = pair(&labels);
    let mut drafts = BTreeMap::new();
    let mut skipped = Vec::new();
    let windows = record.windows();
    let initial = sim_host::Scene::load(&record.scene).map_or(-1.0, |s| s.robot.initial_gripper);
    let commanded = record.commanded_gripper(initial);
    // Every round from the episode's last reset() on, in order: the tracker sees each of their
    // observations, so names carry over from round to round; positive ones are related.
    let mut rounds = Vec::new();
    for (((r, l), (episode, t0, t1)), g) in record.rounds.iter().zip(&labels).zip(&windows).zip(&commanded) {
        if l.exploration {
            continue;
        }
        let obs = match record.motion_obs(r.n) {
            Ok(o) => Some(o),
            Err(why) => {
                if l.usable() {
                    skipped.push((r.n, why));
                }
                None
            }
        };
        let e = l.effects.clone().unwrap_or_default();
        // Objects moved without being lifted or held: pushed (a second anchor may measure
        // "past the line" for them).
        let pushed: Vec<&String> = e
            .moved
            .iter()
            .map(|(o, _)| o)
            .filter(|o| !e.rose.iter().any(|(n, _)| n == *o) && !e.grasped.contains(o))
            .collect();
        rounds.push(json!({
            "round": r.n, "obs": obs, "obs_after": r.obs_after, "calls": r.motion_calls(),
            "native": record.native_at(*episode, *t0), "native_after": record.native_at(*episode, *t1),
            "held": record.held_at(*episode, *t0), "held_after": record.held_at(*episode, *t1),
            "relate": l.usable() && obs.is_some(), "pushed": pushed, "gripper_commanded": g,
        }));
    }
    let mut roles = BTreeMap::new();
    let wanted: Vec<u32> =
        rounds.iter().filter(|q| q["relate"] == true).filter_map(|q| q["round"].as_u64()).map(|n| n as u32).collect();
    if !wanted.is_empty() {
        match tools::call(root, "relate_record", &json!({"rounds": rounds})) {
            Ok(answer) => {
                if let Some(m) = answer["roles_of_native"].as_object() {
                    roles = m.iter().filter_map(|(k, v)| Some((k.clone(), v.as_str()?.to_string()))).collect();
                }
                for n in wanted {
                    let g = &answer["rounds"][n.to_string()];
                    if let Some(why) = g["error"].as_str() {
                        skipped.push((n, format!("skill_tools.py relate_record: {why}")));
                        continue;
                    }
                    let Some(l) = labels.iter().find(|l| l.round == n) else { continue };
                    let checks = checks_from(g, l.effects.as_ref());
                    drafts.insert(n, Draft { round: n, geometry: g.clone(), checks, effects: l.effects.clone() });
                }
            }
            Err(e) => skipped.extend(wanted.into_iter().map(|n| (n, format!("{e:#}")))),
        }
    }
    skipped.sort_by_key(|(n, _)| *n);
    Ok(Findings { record, labels, pairs, drafts, skipped, roles })
}

/// Machine-checkable effects of a round, from the trace, written against the roles
/// perception gave the objects (one per scene object for the whole record). An object is never
/// its own support; a fixture part that moved with a joint (a drawer's handle) gets a `moved`
/// check when the round's motion was anchored on it.
fn checks_from(g: &Value, e: Option<&Effects>) -> Vec<Value> {
    let Some(e) = e else { return Vec::new() };
    let role = |native: &str| g["roles_of_native"][native].as_str().map(str::to_string);
    let mut out = Vec::new();
    let kind = |k: CheckKind| serde_json::to_value(k).unwrap_or(Value::Null);
    let grasped_now: Vec<_> = e.grasped.iter().filter_map(|o| role(o)).collect();
    if !grasped_now.is_empty() {
        out.push(json!({"kind": kind(CheckKind::Holding)}));
    }
    for (o, rise) in &e.rose {
        if let Some(r) = role(o) {
            out.push(json!({"kind": kind(CheckKind::Lifted), "object": r, "min_m": (0.5 * rise).max(0.01)}));
        }
    }
    let mut released = false;
    for (o, support) in &e.rests_on {
        if let (Some(r), Some(s)) = (role(o), role(support)) {
            if !e.grasped.contains(o) && r != s {
                out.push(json!({"kind": kind(CheckKind::On), "object": r, "support": s, "tolerance_m": 0.02}));
                released = true;
            }
        }
    }
    // `released` reads an open gripper: written only where the round opened it fully (a hand
    // opened part way on purpose, not to touch a bowl's wall, let go as well).
    if released && g["gripper_end"].as_f64().is_none_or(|v| v <= -0.9) {
        out.push(json!({"kind": kind(CheckKind::Released)}));
    }
    for (o, d) in &e.moved {
        let lifted = e.rose.iter().any(|(n, _)| n == o);
        let resting = e.rests_on.iter().any(|(n, _)| n == o);
        if !lifted && !resting && !e.grasped.contains(o) {
            if let Some(r) = role(o) {
                out.push(json!({"kind": kind(CheckKind::Moved), "object": r, "min_m": (0.5 * d).max(0.01)}));
            }
        }
    }
    // A fixture part pulled or pushed in the hand while its joint moved far (a drawer opened,
    // a door swung): it moved at least half of what both perception and the trace saw.
    if let (Some(part), Some(seen)) = (g["part"].as_str(), g["part_moved_m"].as_f64()) {
        let far = e.joints.iter().map(|j| {
            let d = (j.to - j.from).abs();
            if j.kind == "slide" {
                (d >= ARTICULATION_CHECK_M).then_some(d)
            } else {
                (d >= ARTICULATION_CHECK_DEG).then_some(f64::INFINITY)
            }
        });
        if let Some(d) = far.flatten().reduce(f64::max) {
            out.push(json!({"kind": kind(CheckKind::Moved), "object": part, "min_m": (0.5 * seen.min(d)).max(0.01)}));
        }
    }
    out
}

/// A joint change a moved-part check is written for (smaller ones are within perception's
/// noise on a part seen through the fingers): a slide, m; a hinge, degrees.
const ARTICULATION_CHECK_M: f64 = 0.05;
const ARTICULATION_CHECK_DEG: f64 = 15.0;

/// At most `max` characters of `text` ending on a whole sentence (or, when its first sentence
/// is longer, a whole word), and whether anything was cut.
pub fn whole_sentences(text: &str, max: usize) -> (String, bool) {
    let t = text.split_whitespace().collect::<Vec<_>>().join(" ");
    if t.chars().count() <= max {
        return (t, false);
    }
    let head: String = t.chars().take(max).collect();
    // A sentence ends at . ! ? ; before a space, except after a list number ("2.") or a
    // single letter ("e.g.").
    let ends = |i: usize, c: char| {
        let word = head[..i].rsplit(' ').next().unwrap_or_default();
        matches!(c, '.' | '!' | '?' | ';')
            && head[i + c.len_utf8()..].starts_with(' ')
            && !(c == '.'
                && (word.chars().all(|w| w.is_ascii_digit())
                    || word.rsplit('.').next().is_some_and(|w| w.chars().count() <= 1)))
    };
    let end = head.char_indices().rev().find(|&(i, c)| ends(i, c)).map(|(i, c)| i + c.len_utf8());
    let cut = match end {
        Some(i) if i >= max / 3 => head[..i].to_string(),
        _ => head.rfind(' ').map_or(head.clone(), |i| head[..i].to_string()),
    };
    (cut, true)
}

/// One round's measured effect in words, scene objects named by their roles.
fn effect_text(e: &Effects, roles: &BTreeMap<String, String>) -> String {
    let name = |n: &str| roles.get(n).cloned().unwrap_or_else(|| n.to_string());
    let mut parts = Vec::new();
    for (o, d) in &e.moved {
        parts.push(format!("moved {} {d:.3} m", name(o)));
    }
    for (o, d) in &e.rose {
        parts.push(format!("lifted {} {d:.3} m", name(o)));
    }
    for o in &e.grasped {
        parts.push(format!("holds {}", name(o)));
    }
    for (o, s) in &e.rests_on {
        parts.push(format!("{} rests on {}", name(o), name(s)));
    }
    for j in &e.joints {
        parts.push(j.describe());
    }
    if !e.touched.is_empty() {
        parts.push(format!("touched {}", e.touched.iter().map(|t| name(t)).collect::<Vec<_>>().join(", ")));
    }
    if parts.is_empty() {
        "no physical effect".into()
    } else {
        parts.join("; ")
    }
}

/// How much of a round's plan the prompt shows (whole sentences within it), characters.
pub const PLAN_CHARS: usize = 600;

/// The system prompt of the extraction call, in our words.
pub const SYSTEM: &str = "You turn the record of one robot episode into reusable skills. You do not write \
coordinates or code: the motions are computed from the rounds you cite. You name and annotate, and you \
propose operations on a skill library. Answer with one JSON object and nothing else.";

/// The user message: the task, each round's label, effects and computed motion, the failure /
/// correction pairs, and the library as it is.
pub fn prompt(f: &Findings, library: &[&crate::format::Skill]) -> String {
    let mut s = format!(
        "Task: \"{}\" (gym {}). The simulator judged the episode: {}.\n\nRounds (evidence id, measured local outcome, \
         its physical effect, the stage's plan, and for positive rounds the motion computed against the objects seen at the \
         round's start: offsets in m and yaws in rad in the anchor object's frame, not the robot's base frame; each scene \
         object keeps one name throughout):\n",
        f.record.task,
        f.record.gym,
        match f.record.success {
            Some(true) => "success",
            Some(false) => "failure",
            None => "not judged",
        }
    );
    for l in &f.labels {
        let r = f.round(l.round);
        let (plan, cut) = whole_sentences(r.map(|r| r.plan.as_str()).unwrap_or_default(), PLAN_CHARS);
        let mut line = format!("- E{}: {:?}", l.round, l.outcome);
        if l.exploration {
            line.push_str(" (exploration: before the episode's last reset(); not citable)");
        }
        if !l.reasons.is_empty() && l.outcome != Outcome::Positive {
            line.push_str(&format!("; why: {}", l.reasons.join("; ")));
        }
        if let Some(e) = &l.effects {
            line.push_str(&format!("; effect: {}", effect_text(e, &f.roles)));
        }
        if !l.notes.is_empty() {
            line.push_str(&format!("; note: {}", l.notes.join("; ")));
        }
        if !plan.is_empty() {
            line.push_str(&format!("; plan: {plan}"));
            if cut {
                line.push_str(" [plan cut here]");
            }
        }
        s.push_str(&line);
        s.push('\n');
        if let Some(d) = f.drafts.get(&l.round) {
            let rules: Vec<String> = d.geometry["rules"]
                .as_array()
                .map(|rs| {
                    rs.iter()
                        .map(|r| {
                            let second = r["second_anchor"]["object"]
                                .as_str()
                                .map(|o| format!(", along {} from {o}", r["second_anchor"]["along"]))
                                .unwrap_or_default();
                            format!(
                                "{} {} of {} offset {:?} yaw {:.2}{second}",
                                r["id"].as_str().unwrap_or_default(),
                                r["anchor"]["feature"].as_str().unwrap_or_default(),
                                r["anchor"]["object"].as_str().unwrap_or_default(),
                                r["offset_m"]
                                    .as_array()
                                    .map(|a| a
                                        .iter()
                                        .map(|v| (v.as_f64().unwrap_or(0.0) * 1000.0).round() / 1000.0)
                                        .collect::<Vec<_>>())
                                    .unwrap_or_default(),
                                r["yaw_rad"].as_f64().unwrap_or(0.0)
                            )
                        })
                        .collect()
                })
                .unwrap_or_default();
            s.push_str(&format!(
                "    steps {}; rules: {}; checks: {}\n",
                d.geometry["steps"],
                rules.join(" | "),
                json!(d.checks)
            ));
        }
    }
    if !f.pairs.is_empty() {
        s.push_str("\nMotion failures and the rounds that corrected them:\n");
        for (bad, good) in &f.pairs {
            let why = f.label(*bad).map(|l| l.reasons.join("; ")).unwrap_or_default();
            s.push_str(&format!("- E{bad} failed ({why}); E{good} then succeeded\n"));
        }
    }
    s.push_str("\nThe library now (id, version, status, judged successes/runs, summary):\n");
    if library.is_empty() {
        s.push_str("(empty)\n");
    }
    for k in library {
        let (ok, n) = k.record();
        s.push_str(&format!(
            "- {} v{} {:?} {ok}/{n}: {} [task {}, objects {}]\n",
            k.id,
            k.version,
            k.status,
            k.summary,
            k.applicability.task_kind,
            k.applicability.object_classes.join(", ")
        ));
    }
    s.push_str(
        "\nPropose operations as {\"operations\": [...]}. Each cites evidence ids of THIS record (\"E3\").\n\
- {\"op\": \"add\", \"id\": \"short-slug\", \"name\": \"...\", \"summary\": \"one sentence: what it does, when it applies\", \
\"task_kind\": \"pick_place|stack|push|open|close|hang|insert|other\", \"keywords\": [\"...\"], \"evidence\": [\"E3\", ...] \
(the positive rounds that make up its procedure, in order), \"stages\": {\"E3\": \"approach: what the stage does\", ...} \
(a short stage name of a few words, then after ':' as much description as you like; the description is kept), \
\"recovery\": [{\"when\": \"...\", \"action\": \"...\", \"evidence\": [\"E5\", \"E6\"]}]}\n\
- {\"op\": \"support\", \"skill\": \"id\", \"evidence\": [...]}: this record did what the skill says and confirms it\n\
- {\"op\": \"revise\", \"skill\": \"id\", \"reason\": \"...\", \"evidence\": [...], \"stages\": {...}, \"recovery\": [...]}: \
same situation, but the skill was contradicted; its procedure is rebuilt from the cited rounds, old evidence kept\n\
- {\"op\": \"split\", \"skill\": \"id\", \"id\": \"new-slug\", \"context\": {\"key\": \"value\"}, \"reason\": \"...\", \
\"evidence\": [...], \"stages\": {...}}: a different situation needs another procedure\n\
- {\"op\": \"retire\", \"skill\": \"id\", \"reason\": \"...\", \"evidence\": [...]}\n\
Cite only rounds listed above that are not exploration; a procedure is built from positive rounds (failures belong in \
recovery). Answer with the JSON object only.",
    );
    s
}

/// Pulls the operations out of a model answer: a JSON object `{"operations": [...]}`, bare or in
/// a ```json fence or with prose around it; repaired where the shape is only off by a wrapper (a
/// bare list of operations, one operation object, `"operations"` holding one object).
pub fn parse_answer(text: &str) -> Result<Value, String> {
    let t = text.trim();
    let t = t.strip_prefix("```json").or_else(|| t.strip_prefix("```")).unwrap_or(t);
    let t = t.strip_suffix("```").unwrap_or(t).trim();
    let v: Value = match serde_json::from_str(t) {
        Ok(v) => v,
        Err(_) => {
            let start = t.find('{').ok_or("the answer holds no JSON object")?;
            let end = t.rfind('}').ok_or("the answer holds no JSON object")?;
            if end < start {
                return Err("the answer holds no JSON object".into());
            }
            serde_json::from_str(&t[start..=end]).map_err(|e| format!("the answer is not valid JSON: {e}"))?
        }
    };
    let v = match v {
        Value::Array(ops) => json!({"operations": ops}),
        Value::Object(ref m) if m.contains_key("op") && !m.contains_key("operations") => json!({"operations": [v]}),
        Value::Object(mut m) => {
            if let Some(one @ Value::Object(_)) = m.get("operations").cloned() {
                m.insert("operations".into(), json!([one]));
            }
            Value::Object(m)
        }
        _ => return Err("the answer is JSON but not an object with \"operations\"".into()),
    };
    if !v["operations"].is_array() {
        return Err("the answer has no \"operations\" list".into());
    }
    Ok(v)
}

/// What the model was asked and said (kept in the run folder as extraction.json).
#[derive(Debug, Clone, Serialize)]
pub struct Exchange {
    pub prompt: String,
    pub answer: String,
    pub tokens_in: u64,
    pub tokens_out: u64,
    pub model_s: f64,
}

/// Step 4: asks the endpoint.
pub fn ask(endpoint: &EndpointConfig, prompt_text: &str) -> anyhow::Result<Exchange> {
    let client = Client::new(endpoint.clone())?;
    let c = client
        .complete(SYSTEM, &[Message::text(Role::User, prompt_text.to_string())])
        .context("the extraction call to the LLM endpoint failed")?;
    Ok(Exchange {
        prompt: prompt_text.to_string(),
        answer: c.text,
        tokens_in: c.usage.input,
        tokens_out: c.usage.output,
        model_s: c.wall_s,
    })
}

/// Where extraction writes what it did, beside the record.
pub fn report_path(run: &Path) -> PathBuf {
    run.join("extraction.json")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn label(round: u32, outcome: Outcome, moved: &[&str], grasped: &[&str]) -> Label {
        let effects = Effects {
            moved: moved.iter().map(|o| (o.to_string(), 0.05)).collect(),
            grasped: grasped.iter().map(|o| o.to_string()).collect(),
            ..Default::default()
        };
        Label::new(round, outcome, vec![], Some(effects))
    }

    #[test]
    fn a_failure_pairs_with_the_next_success_on_the_same_object() {
        let labels = vec![
            label(1, Outcome::Negative, &["red_box"], &[]), // knocked the box
            label(2, Outcome::Positive, &["blue_bowl"], &["blue_bowl"]), // another object: no correction
            label(3, Outcome::Positive, &["red_box"], &["red_box"]),
            label(4, Outcome::Negative, &[], &[]), // a miss: touched nothing
            label(5, Outcome::Positive, &["red_box"], &[]), // pushed, grasped nothing
            label(6, Outcome::Positive, &[], &["red_box"]),
        ];
        assert_eq!(pair(&labels), vec![(1, 3), (4, 6)]);
    }
}
