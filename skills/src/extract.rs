//! Extraction: a finished run record in, proposed library operations out. A separate step
//! after the episode (the only place the native verdict and traces are read):
//!
//! 1. every round gets a local effect from what was measured ([`RunRecord::labels`]);
//! 2. failed rounds are paired with the next round that succeeded (the correction);
//! 3. for each positive round, the code computes its motion against the objects seen at the
//!    round's start (`skill_tools.py relate`: anchor, offset and yaw of each target, with the
//!    TCP measured then as reference) and its checks from the trace;
//! 4. the model, through the configured endpoint, names and annotates and proposes operations
//!    (add, support, revise, split, retire) citing evidence ids `E<round>`; it never writes
//!    coordinates: procedures are built from the rounds it cites.
//!
//! The answer must be JSON; a malformed answer or an operation citing unknown evidence is
//! dropped with the reason in the library's event log.

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

/// Failed rounds and the round that corrected each (see `analyse`).
pub fn pair(labels: &[Label]) -> Vec<(u32, u32)> {
    let mut pairs = Vec::new();
    for (i, l) in labels.iter().enumerate() {
        if l.outcome == Outcome::Negative {
            // The correction acts on what the failure acted on; a failure that touched nothing
            // (a missed grasp) is corrected by the next round that grasped something.
            let failed = acted_on(l);
            let corrects = |m: &&Label| {
                m.outcome == Outcome::Positive
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
    for l in labels.iter().filter(|l| l.outcome == Outcome::Positive) {
        let Some(r) = record.rounds.iter().find(|r| r.n == l.round) else { continue };
        let Some(obs) = &r.obs_before else {
            skipped.push((l.round, "the record has no observation from the round's start".into()));
            continue;
        };
        let native = record.native_positions(l.round);
        let req = json!({"obs": obs, "calls": r.calls, "native": native});
        match tools::call(root, "relate", &req) {
            Ok(g) => {
                let checks = checks_from(&g, l.effects.as_ref());
                drafts.insert(l.round, Draft { round: l.round, geometry: g, checks, effects: l.effects.clone() });
            }
            Err(e) => skipped.push((l.round, format!("{e:#}"))),
        }
    }
    Ok(Findings { record, labels, pairs, drafts, skipped })
}

/// Machine-checkable effects of a round, from the trace, written against the roles
/// perception gave the objects when the round began.
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
    for (o, support) in &e.rests_on {
        if let (Some(r), Some(s)) = (role(o), role(support)) {
            if !e.grasped.contains(o) {
                out.push(json!({"kind": kind(CheckKind::On), "object": r, "support": s, "tolerance_m": 0.02}));
                out.push(json!({"kind": kind(CheckKind::Released)}));
            }
        }
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
    out
}

/// The system prompt of the extraction call, in our words.
pub const SYSTEM: &str = "You turn the record of one robot episode into reusable skills. You do not write \
coordinates or code: the motions are computed from the rounds you cite. You name and annotate, and you \
propose operations on a skill library. Answer with one JSON object and nothing else.";

/// The user message: the task, each round's label, effects and computed motion, the failure /
/// correction pairs, and the library as it is.
pub fn prompt(f: &Findings, library: &[&crate::format::Skill]) -> String {
    let mut s = format!(
        "Task: \"{}\" (gym {}). The simulator judged the episode: {}.\n\nRounds (evidence id, measured local effect, why, \
         the stage's plan, and for positive rounds the motion computed against the objects seen at the round's start):\n",
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
        let plan: String = r.map(|r| r.plan.chars().take(240).collect()).unwrap_or_default();
        s.push_str(&format!(
            "- E{}: {:?}; {}; plan: {}\n",
            l.round,
            l.outcome,
            l.reasons.join("; "),
            plan.replace('\n', " ")
        ));
        if let Some(d) = f.drafts.get(&l.round) {
            let rules: Vec<String> = d.geometry["rules"]
                .as_array()
                .map(|rs| {
                    rs.iter()
                        .map(|r| {
                            format!(
                                "{} {} of {} offset {:?} yaw {:.2}",
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
        s.push_str("\nFailures and the rounds that corrected them:\n");
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
(the positive rounds that make up its procedure, in order), \"stages\": {\"E3\": \"approach\", ...}, \
\"recovery\": [{\"when\": \"...\", \"action\": \"...\", \"evidence\": [\"E5\", \"E6\"]}]}\n\
- {\"op\": \"support\", \"skill\": \"id\", \"evidence\": [...]}: this record did what the skill says and confirms it\n\
- {\"op\": \"revise\", \"skill\": \"id\", \"reason\": \"...\", \"evidence\": [...], \"stages\": {...}, \"recovery\": [...]}: \
same situation, but the skill was contradicted; its procedure is rebuilt from the cited rounds, old evidence kept\n\
- {\"op\": \"split\", \"skill\": \"id\", \"id\": \"new-slug\", \"context\": {\"key\": \"value\"}, \"reason\": \"...\", \
\"evidence\": [...], \"stages\": {...}}: a different situation needs another procedure\n\
- {\"op\": \"retire\", \"skill\": \"id\", \"reason\": \"...\", \"evidence\": [...]}\n\
Cite only rounds listed above. Answer with the JSON object only.",
    );
    s
}

/// Pulls the JSON object out of a model answer (bare, or in a ```json fence).
pub fn parse_answer(text: &str) -> Result<Value, String> {
    let t = text.trim();
    let t = t.strip_prefix("```json").or_else(|| t.strip_prefix("```")).unwrap_or(t);
    let t = t.strip_suffix("```").unwrap_or(t).trim();
    let start = t.find('{').ok_or("the answer holds no JSON object")?;
    let end = t.rfind('}').ok_or("the answer holds no JSON object")?;
    let v: Value = serde_json::from_str(&t[start..=end]).map_err(|e| format!("the answer is not valid JSON: {e}"))?;
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
        Label {
            round,
            outcome,
            reasons: vec![],
            effects: Some(Effects {
                moved: moved.iter().map(|o| (o.to_string(), 0.05)).collect(),
                grasped: grasped.iter().map(|o| o.to_string()).collect(),
                ..Default::default()
            }),
        }
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
