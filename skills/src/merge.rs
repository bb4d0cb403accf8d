//! Applying proposed operations to the library. An answer is first normalised as far as the code
//! can (see [`normalise`]): ids and stage names made to fit the id budget with every suffix,
//! the model's whole stage text kept as the stage's description, evidence merged where cited
//! twice, a citation of a round that cannot be used (not in this record, exploration before the
//! last reset(), a round that sent no motion) dropped alone, fields the format does not know
//! ignored — each with a line in the report and the library's event log. Only what cannot be
//! repaired is dropped, naming why: an operation of no known kind, one left citing nothing, an
//! add whose rounds hold no motion, a skill the library does not have. A stage whose computed
//! pieces are invalid is left out alone. Evidence is keyed by (episode, round), so applying the
//! same record and the same answer twice changes nothing; it is only ever added, never removed.
//! A revision keeps the old evidence beside the new; a split makes a second skill for the other
//! context.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;
use serde_json::{json, Value};

use crate::extract::Findings;
use crate::format::{
    slug_within, Applicability, Backend, Change, Check, CheckKind, Evidence, Fingerprint, MotionRule, ObjectRole,
    Outcome, Recovery, Skill, Source, Stage, Status, Step, ID_MAX, SCHEMA,
};
use crate::library::Library;

/// A skill id before its `-k` suffix (a second skill of the same name), bytes: room for `-999`.
pub const SKILL_ID_BASE: usize = ID_MAX - 4;
/// A stage name, bytes: its rule ids `<stage>_<round>_<k>` stay within [`ID_MAX`].
pub const STAGE_NAME_MAX: usize = 40;

#[derive(Debug, Default, Serialize)]
pub struct MergeReport {
    /// (op, skill id, new version) of every version written.
    pub written: Vec<(String, String, u32)>,
    /// Operations that changed nothing (already applied), with why.
    pub unchanged: Vec<(String, String)>,
    /// Dropped operations and answers, with the reason.
    pub dropped: Vec<(Value, String)>,
    /// What was repaired or left out of the operations (index in the answer, what), whether the
    /// operation was then written, unchanged or dropped.
    pub repaired: Vec<(usize, String)>,
}

/// The fingerprint, backend and instruction every skill extracted here gets.
pub struct Context {
    pub fingerprint: Fingerprint,
    pub backend: Backend,
}

fn evidence_of(f: &Findings, round: u32) -> Evidence {
    let l = f.label(round);
    Evidence {
        id: format!("{}#{round}", f.record.name),
        episode: f.record.name.clone(),
        round,
        outcome: l.map_or(Outcome::Unknown, |l| l.outcome),
        source: Source::Extraction,
        seed: f.record.seed,
        record: Some(f.record.dir.display().to_string()),
        note: l.map(|l| l.reasons.join("; ")).unwrap_or_default(),
    }
}

/// The round an evidence id names: `E3`, `e3`, `E03`, `3`, `"round 3"`, `"E3 (approach)"`.
pub fn round_of(v: &Value) -> Option<u32> {
    if let Some(n) = v.as_u64() {
        return u32::try_from(n).ok();
    }
    let t = v.as_str()?.trim().to_lowercase();
    let t = t.strip_prefix("round").or_else(|| t.strip_prefix('e')).unwrap_or(&t).trim_start();
    let digits: String = t.chars().take_while(char::is_ascii_digit).collect();
    let rest = &t[digits.len()..];
    // "E3b" is no round id; "E3 (approach)" and "E3:" are.
    if digits.is_empty() || rest.starts_with(|c: char| c.is_alphanumeric()) {
        return None;
    }
    digits.parse().ok()
}

/// An operation as the code understands it, after repairs.
#[derive(Debug, Default)]
struct Op {
    kind: String,
    id: Option<String>,
    skill: Option<String>,
    name: Option<String>,
    summary: String,
    task_kind: Option<String>,
    keywords: Vec<String>,
    /// Cited rounds, in the order cited, each once.
    evidence: Vec<u32>,
    /// Round → the model's stage text.
    stages: BTreeMap<u32, String>,
    recovery: Vec<(String, String, Vec<u32>)>,
    context: BTreeMap<String, String>,
    reason: Option<String>,
}

const KINDS: [(&str, &str); 12] = [
    ("add", "add"),
    ("create", "add"),
    ("new", "add"),
    ("support", "support"),
    ("confirm", "support"),
    ("revise", "revise"),
    ("update", "revise"),
    ("split", "split"),
    ("specialise", "split"),
    ("specialize", "split"),
    ("retire", "retire"),
    ("remove", "retire"),
];

/// The fields each kind reads; any other is ignored with a note.
fn fields(kind: &str) -> &'static [&'static str] {
    match kind {
        "add" => &["op", "id", "name", "summary", "task_kind", "keywords", "evidence", "stages", "recovery", "reason"],
        "split" => &[
            "op",
            "skill",
            "id",
            "name",
            "summary",
            "task_kind",
            "keywords",
            "evidence",
            "stages",
            "recovery",
            "context",
            "reason",
        ],
        "support" => &["op", "skill", "evidence", "reason"],
        "revise" => &["op", "skill", "reason", "evidence", "stages", "recovery"],
        _ => &["op", "skill", "reason", "evidence"],
    }
}

fn text_of(v: &Value) -> Option<String> {
    match v {
        Value::String(s) if !s.trim().is_empty() => Some(s.trim().to_string()),
        Value::Number(n) => Some(n.to_string()),
        _ => None,
    }
}

/// Which cited rounds can be used, each once; a note for every citation left out.
fn usable_rounds(f: &Findings, raw: &Value, what: &str, notes: &mut Vec<String>) -> Vec<u32> {
    let items: Vec<&Value> = match raw {
        Value::Array(a) => a.iter().collect(),
        Value::Null => Vec::new(),
        one => vec![one],
    };
    let (first, last) = (f.labels.first().map_or(0, |l| l.round), f.labels.last().map_or(0, |l| l.round));
    let mut out = Vec::new();
    for v in items {
        let Some(n) = round_of(v) else {
            notes.push(format!("{what}: ignored {v}: not an evidence id E<round>"));
            continue;
        };
        let Some(l) = f.label(n) else {
            notes.push(format!("{what}: ignored {v}: cites unknown evidence {v} (this record has E{first}..E{last})"));
            continue;
        };
        if l.exploration {
            notes.push(format!("{what}: ignored E{n}: exploration before the episode's last reset()"));
            continue;
        }
        if l.outcome == Outcome::Unknown {
            notes.push(format!("{what}: ignored E{n}: the round moved nothing ({})", l.reasons.join("; ")));
            continue;
        }
        if out.contains(&n) {
            notes.push(format!("{what}: E{n} cited twice, merged"));
            continue;
        }
        out.push(n);
    }
    out
}

/// The model's operation, repaired where the code can (see the module text); Err when nothing
/// usable is left.
fn normalise(f: &Findings, op: &Value, notes: &mut Vec<String>) -> Result<Op, String> {
    let Some(m) = op.as_object() else { return Err("an operation is a JSON object".into()) };
    let raw_kind = m.get("op").and_then(Value::as_str).unwrap_or_default().trim().to_lowercase();
    let Some(&(_, kind)) = KINDS.iter().find(|(k, _)| *k == raw_kind) else {
        return Err(format!("unknown operation '{raw_kind}' (add, support, revise, split, retire)"));
    };
    if kind != raw_kind {
        notes.push(format!("op '{raw_kind}' read as '{kind}'"));
    }
    let known = fields(kind);
    for k in m.keys().filter(|k| !known.contains(&k.as_str())) {
        notes.push(format!("ignored field '{k}' (a {kind} reads {})", known.join(", ")));
    }
    let mut o = Op { kind: kind.to_string(), ..Default::default() };
    o.id = m.get("id").and_then(text_of);
    o.skill = m.get("skill").and_then(text_of);
    if o.skill.is_none() && kind != "add" && kind != "split" && o.id.is_some() {
        // The skill an operation is about, named under "id" instead of "skill".
        notes.push("the skill is named under \"id\": read as \"skill\"".into());
        o.skill = o.id.clone();
    }
    o.name = m.get("name").and_then(text_of);
    o.summary = m.get("summary").and_then(text_of).unwrap_or_default();
    o.reason = m.get("reason").and_then(text_of);
    o.task_kind = m.get("task_kind").and_then(text_of).map(|t| {
        let k = slug_within(&t, 32, '_').replace('-', "_");
        if k.is_empty() {
            "other".into()
        } else {
            k
        }
    });
    o.keywords = match m.get("keywords") {
        Some(Value::Array(a)) => a.iter().filter_map(text_of).collect(),
        Some(Value::String(t)) => t.split(',').map(|w| w.trim().to_string()).filter(|w| !w.is_empty()).collect(),
        _ => Vec::new(),
    };
    o.evidence = usable_rounds(f, m.get("evidence").unwrap_or(&Value::Null), "evidence", notes);
    match m.get("stages") {
        Some(Value::Object(st)) => {
            for (k, v) in st {
                let text = match v {
                    Value::Object(s) => {
                        let name = s.get("name").and_then(text_of).unwrap_or_default();
                        match s.get("description").and_then(text_of) {
                            Some(d) if !name.is_empty() => format!("{name}: {d}"),
                            Some(d) => d,
                            None => name,
                        }
                    }
                    other => text_of(other).unwrap_or_default(),
                };
                match round_of(&json!(k)) {
                    Some(n) if o.evidence.contains(&n) => {
                        o.stages.insert(n, text);
                    }
                    _ => notes.push(format!("stages: ignored '{k}': not a round of this operation's evidence")),
                }
            }
        }
        Some(Value::Array(a)) => {
            notes.push("stages given as a list: read in the order of the evidence".into());
            for (n, v) in o.evidence.iter().zip(a) {
                if let Some(t) = text_of(v) {
                    o.stages.insert(*n, t);
                }
            }
        }
        Some(Value::Null) | None => {}
        Some(other) => notes.push(format!("stages: ignored {other}: an object {{\"E3\": \"name: description\"}}")),
    }
    let recovery: Vec<&Value> = match m.get("recovery") {
        // Ignored (noted above) where the operation does not read it: no evidence from it either.
        _ if !known.contains(&"recovery") => Vec::new(),
        Some(Value::Array(a)) => a.iter().collect(),
        Some(v @ Value::Object(_)) => vec![v],
        Some(Value::Null) | None => Vec::new(),
        Some(other) => {
            notes.push(format!("recovery: ignored {other}: a list of {{\"when\", \"action\", \"evidence\"}}"));
            Vec::new()
        }
    };
    for (i, r) in recovery.into_iter().enumerate() {
        let (Some(when), Some(action)) = (r.get("when").and_then(text_of), r.get("action").and_then(text_of)) else {
            notes.push(format!("recovery {}: left out: it needs \"when\" and \"action\" texts", i + 1));
            continue;
        };
        let ev = usable_rounds(f, r.get("evidence").unwrap_or(&Value::Null), &format!("recovery {}", i + 1), notes);
        o.recovery.push((when, action, ev));
    }
    if let Some(c) = m.get("context").and_then(Value::as_object) {
        o.context =
            c.iter().map(|(k, v)| (k.clone(), v.as_str().map_or_else(|| v.to_string(), str::to_string))).collect();
    }
    if o.evidence.is_empty() && o.recovery.iter().all(|r| r.2.is_empty()) {
        let cited = m.get("evidence").map_or("nothing".to_string(), Value::to_string);
        return Err(format!("cites no evidence that can be used (cited {cited}; see the notes)"));
    }
    Ok(o)
}

/// A short stage name from the model's stage text, and the text as its description when it
/// says more: a quoted name (`Stage "pull the drawer open"`), else the words before ':' (or a
/// dash, a bracket) when they are few, else the first three words — a leading "Stage 3 =" or
/// "2." left out; an id of at most [`STAGE_NAME_MAX`] bytes.
pub fn stage_name(text: &str, round: u32) -> (String, Option<String>) {
    let text = text.trim();
    let body = without_stage_number(text);
    let quoted = body
        .char_indices()
        .find(|&(i, c)| i < 60 && matches!(c, '"' | '“'))
        .and_then(|(i, c)| {
            let close = if c == '“' { '”' } else { '"' };
            let from = i + c.len_utf8();
            body[from..].find(close).map(|j| &body[from..from + j])
        })
        .filter(|q| !q.trim().is_empty());
    let head = quoted.unwrap_or_else(|| body.split([':', '—', '–', '(', '\n']).next().unwrap_or_default());
    let head = head.split(" - ").next().unwrap_or_default();
    let words: Vec<&str> = head.split_whitespace().collect();
    let short = if !words.is_empty() && (words.len() <= 5 || quoted.is_some()) {
        words.join(" ")
    } else {
        body.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
    };
    let mut name = slug_within(&short, STAGE_NAME_MAX, '_').replace('-', "_");
    if name.is_empty() || name.starts_with(|c: char| c.is_ascii_digit()) {
        name = format!("stage_{round}{}", if name.is_empty() { String::new() } else { format!("_{name}") });
        name = slug_within(&name, STAGE_NAME_MAX, '_');
    }
    let description =
        (slug_within(text, usize::MAX, '_').replace('-', "_") != name && !text.is_empty()).then(|| text.to_string());
    (name, description)
}

/// `text` without a leading stage number: "Stage 3 = approach ..." or "Stage 3: ..." or "2. ..."
/// or "2) ..." -> "approach ...".
fn without_stage_number(text: &str) -> &str {
    let staged = text.get(..5).is_some_and(|w| w.eq_ignore_ascii_case("stage"));
    let after = if staged { text[5..].trim_start() } else { text };
    let rest = after.trim_start_matches(|c: char| c.is_ascii_digit());
    if rest.len() == after.len() {
        return text;
    }
    let sep = rest.trim_start().starts_with(['=', ':', '.', ')', '-', '–', '—']);
    if !staged && !rest.starts_with(['.', ')']) {
        return text; // "2 cm lift" is no stage number
    }
    let rest =
        if sep { &rest.trim_start()[rest.trim_start().chars().next().map_or(0, char::len_utf8)..] } else { rest };
    match rest.trim_start() {
        "" => text,
        r => r,
    }
}

fn recovery_of(f: &Findings, o: &Op) -> Vec<Recovery> {
    o.recovery
        .iter()
        .map(|(when, action, ev)| Recovery {
            when: when.clone(),
            action: action.clone(),
            evidence: ev.iter().map(|n| evidence_of(f, *n).id).collect(),
        })
        .collect()
}

/// One stage built from a round: the object roles, rules and stage it brings.
type StagePieces = (BTreeMap<String, ObjectRole>, Vec<MotionRule>, Stage);

/// What a procedure built from rounds consists of.
struct Built {
    objects: BTreeMap<String, ObjectRole>,
    rules: Vec<MotionRule>,
    procedure: Vec<Stage>,
    classes: Vec<String>,
}

/// The procedure made of the cited positive rounds that have computed motion, in round order.
/// A stage whose computed pieces do not make a valid stage is left out alone, with a note.
fn build(
    f: &Findings,
    rounds: &[u32],
    names: &BTreeMap<u32, String>,
    notes: &mut Vec<String>,
) -> Result<Built, String> {
    let mut rounds: Vec<u32> = rounds.iter().copied().filter(|n| f.drafts.contains_key(n)).collect();
    rounds.sort_unstable();
    if rounds.is_empty() {
        return Err("cites no positive round with computed motion".into());
    }
    // One role per scene object across rounds: the record's roles (extraction's tracker), or
    // the name perception gave it first.
    let mut canon: BTreeMap<String, String> = f.roles.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    let mut objects = BTreeMap::new();
    let (mut rules, mut procedure) = (Vec::new(), Vec::new());
    let mut stage_names = BTreeSet::new();
    let mut why_not = Vec::new();
    for n in rounds {
        let d = &f.drafts[&n];
        let g = &d.geometry;
        let mut rename: BTreeMap<String, String> = BTreeMap::new();
        if let Some(m) = g["roles_of_native"].as_object() {
            for (native, role) in m {
                let role = role.as_str().unwrap_or_default().to_string();
                let c = canon.entry(native.clone()).or_insert_with(|| role.clone()).clone();
                rename.insert(role, c);
            }
        }
        let role_of = |r: &str| rename.get(r).cloned().unwrap_or_else(|| r.to_string());
        let (base, description) = match names.get(&n) {
            Some(t) => stage_name(t, n),
            None => (format!("stage_{n}"), None),
        };
        let mut stage = base.clone();
        if !stage_names.insert(stage.clone()) {
            stage = format!("{base}_{n}");
            stage_names.insert(stage.clone());
        }
        let built = (|| -> Result<StagePieces, String> {
            let mut objs = BTreeMap::new();
            if let Some(m) = g["objects"].as_object() {
                for (role, o) in m {
                    let o: ObjectRole = serde_json::from_value(o.clone()).map_err(|e| format!("object {role}: {e}"))?;
                    objs.entry(role_of(role)).or_insert(o);
                }
            }
            let mut ids = BTreeMap::new();
            let mut rs = Vec::new();
            for (k, r) in g["rules"].as_array().map(Vec::as_slice).unwrap_or_default().iter().enumerate() {
                let mut r = r.clone();
                let new_id = format!("{stage}_{}", k + 1);
                ids.insert(r["id"].as_str().unwrap_or_default().to_string(), new_id.clone());
                r["id"] = json!(new_id);
                r["anchor"]["object"] = json!(role_of(r["anchor"]["object"].as_str().unwrap_or_default()));
                if let Some(o) = r["second_anchor"]["object"].as_str().map(role_of) {
                    r["second_anchor"]["object"] = json!(o);
                }
                rs.push(serde_json::from_value::<MotionRule>(r).map_err(|e| format!("a computed rule: {e}"))?);
            }
            let mut steps = Vec::new();
            for s in g["steps"].as_array().map(Vec::as_slice).unwrap_or_default() {
                let mut s = s.clone();
                if let Some(id) = s["move"].as_str() {
                    s["move"] = json!(ids.get(id).cloned().unwrap_or_default());
                }
                steps.push(serde_json::from_value::<Step>(s).map_err(|e| format!("a computed step: {e}"))?);
            }
            let mut checks = Vec::new();
            for c in &d.checks {
                let mut c = c.clone();
                for k in ["object", "support"] {
                    if let Some(r) = c[k].as_str() {
                        c[k] = json!(role_of(r));
                    }
                }
                let c = serde_json::from_value::<Check>(c).map_err(|e| format!("a computed check: {e}"))?;
                // An object is never its own support (two roles that are one scene object).
                if c.kind == CheckKind::On && c.object == c.support {
                    continue;
                }
                checks.push(c);
            }
            let st = Stage {
                name: stage.clone(),
                description: description.clone(),
                steps,
                checks,
                retries: 1,
                code: None,
                source: Some(evidence_of(f, n).id),
            };
            Ok((objs, rs, st))
        })();
        // Each stage is checked on its own, so one bad stage costs that stage only.
        let checked = built.and_then(|(objs, rs, st)| {
            let probe = Skill {
                schema: SCHEMA,
                id: "probe".into(),
                version: 1,
                status: Status::Candidate,
                name: "probe".into(),
                summary: String::new(),
                applicability: Applicability {
                    task_kind: "other".into(),
                    keywords: Vec::new(),
                    object_classes: vec!["any".into()],
                    fingerprint: Fingerprint::default(),
                    backend: Backend::Sim,
                    context: BTreeMap::new(),
                },
                objects: objs.clone(),
                rules: rs.clone(),
                procedure: vec![st.clone()],
                recovery: Vec::new(),
                evidence: Vec::new(),
                history: Vec::new(),
            };
            probe.validate().map_err(|e| e.to_string().replace("skill probe v1: ", ""))?;
            Ok((objs, rs, st))
        });
        match checked {
            Ok((objs, rs, st)) => {
                for (k, o) in objs {
                    objects.entry(k).or_insert(o);
                }
                rules.extend(rs);
                procedure.push(st);
            }
            Err(why) => {
                notes.push(format!("stage E{n} left out: {why}"));
                why_not.push(format!("E{n}: {why}"));
            }
        }
    }
    if procedure.is_empty() {
        return Err(format!("no stage could be built ({})", why_not.join("; ")));
    }
    let used: BTreeSet<&str> = rules
        .iter()
        .flat_map(|r| {
            std::iter::once(r.anchor.object.as_str()).chain(r.second_anchor.as_ref().map(|s| s.object.as_str()))
        })
        .collect();
    objects.retain(|k, _| {
        used.contains(k.as_str())
            || procedure
                .iter()
                .any(|s| s.checks.iter().any(|c| c.object.as_deref() == Some(k) || c.support.as_deref() == Some(k)))
    });
    let mut classes: Vec<String> = objects.values().map(|o| o.class.clone()).collect();
    classes.sort();
    classes.dedup();
    Ok(Built { objects, rules, procedure, classes })
}

/// A revision's new stages replace the stages of the same name (and their rules); stages with
/// new names are appended; the other stages stay as they were.
fn replace_stages(s: &mut Skill, built: Built) {
    for st in built.procedure {
        let old = s.procedure.iter().position(|p| p.name == st.name);
        let prefix = format!("{}_", st.name);
        if let Some(i) = old {
            s.rules.retain(|r| !r.id.strip_prefix(&prefix).is_some_and(|k| k.bytes().all(|b| b.is_ascii_digit())));
            s.procedure[i] = st;
        } else {
            s.procedure.push(st);
        }
    }
    s.rules.extend(built.rules);
    for (role, o) in built.objects {
        s.objects.entry(role).or_insert(o);
    }
    let mut classes: Vec<String> = s.objects.values().map(|o| o.class.clone()).collect();
    classes.sort();
    classes.dedup();
    s.applicability.object_classes = classes;
}

fn words(text: &str) -> Vec<String> {
    let mut w: Vec<String> =
        text.split(|c: char| !c.is_alphanumeric()).filter(|w| w.len() > 2).map(str::to_lowercase).collect();
    w.sort();
    w.dedup();
    w
}

fn holds_all(s: &Skill, ev: &[Evidence]) -> bool {
    let have: BTreeSet<_> = s.evidence.iter().map(Evidence::key).collect();
    ev.iter().all(|e| have.contains(&e.key()))
}

fn next_version(s: &Skill, op: &str, reason: String, evidence: &[Evidence]) -> Skill {
    let mut n = s.clone();
    n.version += 1;
    n.history.push(Change {
        version: n.version,
        op: op.into(),
        reason,
        evidence: evidence.iter().map(|e| e.id.clone()).collect(),
    });
    n
}

fn add_evidence(s: &mut Skill, ev: &[Evidence]) -> usize {
    let have: BTreeSet<_> = s.evidence.iter().map(Evidence::key).collect();
    let new: Vec<_> = ev.iter().filter(|e| !have.contains(&e.key())).cloned().collect();
    s.evidence.extend(new.iter().cloned());
    new.len()
}

/// Applies the model's answer (already parsed) to the library.
pub fn apply(lib: &mut Library, f: &Findings, answer: &Value, ctx: &Context) -> anyhow::Result<MergeReport> {
    let mut rep = MergeReport::default();
    if let Some(m) = answer.as_object() {
        for k in m.keys().filter(|k| *k != "operations") {
            let note = format!("ignored the answer's field '{k}' (an answer is {{\"operations\": [...]}})");
            lib.log("repaired", json!({"note": note, "record": f.record.name}))?;
            rep.repaired.push((0, note));
        }
    }
    for (i, op) in answer["operations"].as_array().map(Vec::as_slice).unwrap_or_default().iter().enumerate() {
        let mut notes = Vec::new();
        let kind = op["op"].as_str().unwrap_or_default().to_string();
        let outcome =
            normalise(f, op, &mut notes).and_then(|o| apply_one(lib, f, &o, ctx, &mut notes).map(|w| (o.kind, w)));
        if !notes.is_empty() {
            lib.log("repaired", json!({"operation": i + 1, "op": kind, "notes": notes, "record": f.record.name}))?;
            rep.repaired.extend(notes.iter().map(|n| (i + 1, n.clone())));
        }
        match outcome {
            Ok((kind, Some((id, v)))) => {
                lib.log(&kind, json!({"skill": id, "version": v, "record": f.record.name}))?;
                rep.written.push((kind, id, v));
            }
            Ok((kind, None)) => {
                let why = format!("{kind} changes nothing: the library already holds this evidence");
                rep.unchanged.push((kind, why));
            }
            Err(why) => {
                let why = if notes.is_empty() { why } else { format!("{why} [{}]", notes.join("; ")) };
                lib.log("dropped", json!({"operation": op, "reason": why, "record": f.record.name}))?;
                rep.dropped.push((op.clone(), why));
            }
        }
    }
    Ok(rep)
}

/// One repaired operation; Ok(None) when it changes nothing, Err(reason) when it is dropped.
fn apply_one(
    lib: &mut Library,
    f: &Findings,
    op: &Op,
    ctx: &Context,
    notes: &mut Vec<String>,
) -> Result<Option<(String, u32)>, String> {
    let kind = op.kind.as_str();
    let rounds = op.evidence.clone();
    let recovery = recovery_of(f, op);
    // Every round cited, in the procedure or a recovery, is evidence once: the procedure's in
    // round order, then those only a recovery cites.
    let mut all_rounds: Vec<u32> = rounds.clone();
    all_rounds.sort_unstable();
    for (_, _, ev) in &op.recovery {
        for n in ev {
            if !all_rounds.contains(n) {
                all_rounds.push(*n);
            }
        }
    }
    let all_evidence: Vec<Evidence> = all_rounds.iter().map(|n| evidence_of(f, *n)).collect();
    let skill_ref = |lib: &Library| -> Result<Skill, String> {
        let id = op.skill.clone().unwrap_or_default();
        // The id as written, else as an id would be written ("Pick & Place" is pick-place).
        lib.get(&id)
            .or_else(|| lib.get(&slug_within(&id, ID_MAX, '-')))
            .cloned()
            .ok_or_else(|| format!("names skill '{id}', which the library does not have"))
    };
    let write = |lib: &mut Library, s: Skill| -> Result<Option<(String, u32)>, String> {
        s.validate().map_err(|e| e.to_string())?;
        let (id, v) = (s.id.clone(), s.version);
        lib.write(s).map_err(|e| format!("{e:#}"))?;
        Ok(Some((id, v)))
    };
    match kind {
        "add" | "split" => {
            let built = build(f, &rounds, &op.stages, notes)?;
            let parent = if kind == "split" { Some(skill_ref(lib)?) } else { None };
            let name = op.name.clone().or(op.id.clone()).unwrap_or_else(|| "skill".into());
            // The id within the budget that leaves room for a `-k` suffix.
            let mut id = [op.id.as_deref(), Some(name.as_str()), op.task_kind.as_deref()]
                .into_iter()
                .flatten()
                .map(|t| slug_within(t, SKILL_ID_BASE, '-'))
                .find(|s| !s.is_empty())
                .unwrap_or_else(|| "skill".into());
            if op.id.as_deref().is_some_and(|given| given != id) {
                notes.push(format!("id {:?} written as '{id}'", op.id.as_deref().unwrap_or_default()));
            }
            // Re-applying the same record and answer: the skill that holds this evidence is it.
            if lib.latest().any(|s| holds_all(s, &all_evidence) && (s.id == id || s.id.starts_with(&format!("{id}-"))))
            {
                return Ok(None);
            }
            let base = id.clone();
            let mut k = 2;
            while lib.get(&id).is_some() {
                id = format!("{base}-{k}");
                k += 1;
            }
            let mut keywords = words(&f.record.task);
            keywords.extend(op.keywords.iter().map(|w| w.to_lowercase()));
            keywords.sort();
            keywords.dedup();
            let reason = op.reason.clone().unwrap_or_else(|| format!("extracted from {}", f.record.name));
            let s = Skill {
                schema: SCHEMA,
                id,
                version: 1,
                status: Status::Candidate,
                name,
                summary: op.summary.clone(),
                applicability: Applicability {
                    task_kind: op
                        .task_kind
                        .clone()
                        .or_else(|| parent.as_ref().map(|p| p.applicability.task_kind.clone()))
                        .unwrap_or_else(|| "other".into()),
                    keywords,
                    object_classes: built.classes,
                    fingerprint: ctx.fingerprint.clone(),
                    backend: ctx.backend,
                    context: op.context.clone(),
                },
                objects: built.objects,
                rules: built.rules,
                procedure: built.procedure,
                recovery,
                evidence: all_evidence.clone(),
                history: vec![Change {
                    version: 1,
                    op: kind.into(),
                    reason: match &parent {
                        Some(p) => format!("split from {} v{}: {reason}", p.id, p.version),
                        None => reason,
                    },
                    evidence: all_evidence.iter().map(|e| e.id.clone()).collect(),
                }],
            };
            if let Some(p) = &parent {
                if let Some(k) =
                    s.applicability.context.keys().find(|k| p.applicability.context.contains_key(&format!("not_{k}")))
                {
                    // The parent's negation of one value per key is all selection can check.
                    return Err(format!(
                        "the parent already gave its '{k}' context to another skill: split that skill, or the parent on another key"
                    ));
                }
                if s.applicability.context.is_empty() || s.applicability.context == p.applicability.context {
                    return Err(
                        "a split names a context (object_classes or instruction) other than its parent's".into()
                    );
                }
                if let Some(k) =
                    s.applicability.context.keys().find(|k| !["object_classes", "instruction"].contains(&k.as_str()))
                {
                    return Err(format!(
                        "a split's context key '{k}' cannot be checked by selection (object_classes, instruction)"
                    ));
                }
            }
            let new_id = s.id.clone();
            let context = s.applicability.context.clone();
            let out = write(lib, s)?;
            if let Some(p) = parent {
                // The parent keeps everything but the context split off.
                let ctx_text = serde_json::to_string(&op.context).unwrap_or_default();
                let mut n = next_version(&p, "split", format!("the context {ctx_text} now belongs to {new_id}"), &[]);
                for (k, v) in context {
                    n.applicability.context.insert(format!("not_{k}"), v);
                }
                write(lib, n)?;
            }
            Ok(out)
        }
        "support" => {
            let s = skill_ref(lib)?;
            let mut n = next_version(&s, "support", format!("confirmed by {}", f.record.name), &all_evidence);
            if add_evidence(&mut n, &all_evidence) == 0 {
                return Ok(None);
            }
            write(lib, n)
        }
        "revise" => {
            let s = skill_ref(lib)?;
            if holds_all(&s, &all_evidence) {
                return Ok(None);
            }
            // A revision answers a contradiction: something in this record went wrong.
            if !all_evidence.iter().any(|e| matches!(e.outcome, Outcome::Negative | Outcome::Failure)) {
                return Err("a revise cites no failed round (use support for confirmation)".into());
            }
            let reason = op.reason.clone().unwrap_or_else(|| "contradicted".into());
            let mut n = next_version(&s, "revise", reason, &all_evidence);
            match build(f, &rounds, &op.stages, notes) {
                Ok(built) => replace_stages(&mut n, built),
                // Recovery guidance alone is a revision too; its stages stay.
                Err(why) if !recovery.is_empty() => {
                    if let Some(h) = n.history.last_mut() {
                        h.reason.push_str(&format!(" (stages unchanged: {why})"));
                    }
                }
                Err(why) => return Err(format!("a revise that changes nothing: {why}, and no recovery given")),
            }
            n.recovery.extend(recovery);
            add_evidence(&mut n, &all_evidence);
            n.status = Status::Candidate;
            write(lib, n)
        }
        "retire" => {
            let s = skill_ref(lib)?;
            if s.status == Status::Retired {
                return Ok(None);
            }
            let mut n =
                next_version(&s, "retire", op.reason.clone().unwrap_or_else(|| "retired".into()), &all_evidence);
            add_evidence(&mut n, &all_evidence);
            n.status = Status::Retired;
            write(lib, n)
        }
        other => Err(format!("unknown operation '{other}' (add, support, revise, split, retire)")),
    }
}

/// Retires skills that fail too often (at least `min_runs` judged runs, success below
/// `bound`) and, while more than `cap` are active, the least recently given to an episode.
pub fn housekeeping(lib: &mut Library, bound: f64, min_runs: u32, cap: usize) -> anyhow::Result<Vec<String>> {
    let mut retired = Vec::new();
    let weak: Vec<Skill> = lib
        .active()
        .filter(|s| {
            let (k, n) = s.record();
            n >= min_runs && f64::from(k) / f64::from(n) < bound
        })
        .cloned()
        .collect();
    for s in weak {
        let (k, n) = s.record();
        let mut v = next_version(&s, "retire", format!("{k} of {n} judged runs succeeded (below {bound})"), &[]);
        v.status = Status::Retired;
        retired.push(v.id.clone());
        lib.write(v)?;
    }
    let active: Vec<Skill> = lib.active().cloned().collect();
    if active.len() > cap {
        let events = lib.events();
        // Last given to an episode (selected or used), else when it was written first: a skill
        // just added is not "unused for longest" because nothing has had a chance to use it.
        let created = |id: &str| {
            std::fs::metadata(lib.dir.join(id).join("v0001.json"))
                .and_then(|m| m.modified())
                .ok()
                .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                .map_or(0.0, |d| d.as_secs_f64())
        };
        let last_used = |id: &str| {
            events
                .iter()
                .filter(|e| {
                    (e["event"] == "selected"
                        && e["detail"]["chosen"].as_array().is_some_and(|c| c.iter().any(|x| x == id)))
                        || (e["event"] == "used" && e["detail"]["skill"] == id)
                })
                .filter_map(|e| e["at_unix_s"].as_f64())
                .fold(created(id), f64::max)
        };
        let mut by_use: Vec<(f64, Skill)> = active.into_iter().map(|s| (last_used(&s.id), s)).collect();
        by_use.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.id.cmp(&b.1.id)));
        let over = by_use.len() - cap;
        for (_, s) in by_use.into_iter().take(over) {
            let mut v = next_version(&s, "retire", format!("unused while the library was over its cap of {cap}"), &[]);
            v.status = Status::Retired;
            retired.push(v.id.clone());
            lib.write(v)?;
        }
    }
    for id in &retired {
        lib.log("retired", json!({"skill": id}))?;
    }
    Ok(retired)
}
