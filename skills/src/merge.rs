//! Applying proposed operations to the library. Every operation is checked before anything is
//! written: it must be one of add / support / revise / split / retire, cite evidence of the
//! record at hand (`E<round>`), and yield a valid skill; otherwise it is dropped and the
//! reason logged. Evidence is keyed by (episode, round), so applying the same record and the
//! same answer twice changes nothing; it is only ever added, never removed. A revision keeps
//! the old evidence beside the new; a split makes a second skill for the other context.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;
use serde_json::{json, Value};

use crate::extract::Findings;
use crate::format::{
    slug, Applicability, Backend, Change, Check, Evidence, Fingerprint, MotionRule, ObjectRole, Outcome, Recovery,
    Skill, Source, Stage, Status, Step, SCHEMA,
};
use crate::library::Library;

#[derive(Debug, Default, Serialize)]
pub struct MergeReport {
    /// (op, skill id, new version) of every version written.
    pub written: Vec<(String, String, u32)>,
    /// Operations that changed nothing (already applied), with why.
    pub unchanged: Vec<(String, String)>,
    /// Dropped operations and answers, with the reason.
    pub dropped: Vec<(Value, String)>,
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

/// `E<n>` ids → rounds of this record; an unknown one is an error naming it.
fn cited(f: &Findings, op: &Value, key: &str) -> Result<Vec<u32>, String> {
    let mut out = Vec::new();
    for v in op[key].as_array().map(Vec::as_slice).unwrap_or_default() {
        let s = v.as_str().unwrap_or_default();
        let n = s.strip_prefix('E').and_then(|n| n.parse::<u32>().ok());
        match n {
            Some(n) if f.label(n).is_some() => out.push(n),
            _ => {
                return Err(format!(
                    "cites unknown evidence {v} (this record has E{}..E{})",
                    f.labels.first().map_or(0, |l| l.round),
                    f.labels.last().map_or(0, |l| l.round)
                ))
            }
        }
    }
    out.sort_unstable();
    out.dedup();
    Ok(out)
}

fn recovery_of(f: &Findings, op: &Value) -> Result<Vec<Recovery>, String> {
    let mut out = Vec::new();
    for r in op["recovery"].as_array().map(Vec::as_slice).unwrap_or_default() {
        let (Some(when), Some(action)) = (r["when"].as_str(), r["action"].as_str()) else {
            return Err("a recovery entry needs \"when\" and \"action\" texts".into());
        };
        let ev = cited(f, r, "evidence")?;
        out.push(Recovery {
            when: when.into(),
            action: action.into(),
            evidence: ev.iter().map(|n| evidence_of(f, *n).id).collect(),
        });
    }
    Ok(out)
}

/// What a procedure built from rounds consists of.
struct Built {
    objects: BTreeMap<String, ObjectRole>,
    rules: Vec<MotionRule>,
    procedure: Vec<Stage>,
    classes: Vec<String>,
}

/// The procedure made of the cited positive rounds that have computed motion, in round order.
fn build(f: &Findings, rounds: &[u32], names: &Value) -> Result<Built, String> {
    let rounds: Vec<u32> = rounds.iter().copied().filter(|n| f.drafts.contains_key(n)).collect();
    if rounds.is_empty() {
        return Err("cites no positive round with computed motion".into());
    }
    // One role per scene object across rounds: the name perception gave it first.
    let mut canon: BTreeMap<String, String> = BTreeMap::new();
    let mut objects = BTreeMap::new();
    let (mut rules, mut procedure) = (Vec::new(), Vec::new());
    let mut stage_names = BTreeSet::new();
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
        if let Some(m) = g["objects"].as_object() {
            for (role, o) in m {
                let o: ObjectRole =
                    serde_json::from_value(o.clone()).map_err(|e| format!("E{n}: object {role}: {e}"))?;
                objects.entry(role_of(role)).or_insert(o);
            }
        }
        let base = slug(names[format!("E{n}")].as_str().unwrap_or(&format!("stage-{n}")));
        let mut stage = base.replace('-', "_");
        if !stage_names.insert(stage.clone()) {
            stage = format!("{stage}_{n}");
            stage_names.insert(stage.clone());
        }
        let mut ids = BTreeMap::new();
        for (k, r) in g["rules"].as_array().map(Vec::as_slice).unwrap_or_default().iter().enumerate() {
            let mut r = r.clone();
            let new_id = format!("{stage}_{}", k + 1);
            ids.insert(r["id"].as_str().unwrap_or_default().to_string(), new_id.clone());
            r["id"] = json!(new_id);
            let obj = role_of(r["anchor"]["object"].as_str().unwrap_or_default());
            r["anchor"]["object"] = json!(obj);
            let rule: MotionRule = serde_json::from_value(r).map_err(|e| format!("E{n}: a computed rule: {e}"))?;
            rules.push(rule);
        }
        let mut steps = Vec::new();
        for s in g["steps"].as_array().map(Vec::as_slice).unwrap_or_default() {
            let mut s = s.clone();
            if let Some(id) = s["move"].as_str() {
                s["move"] = json!(ids.get(id).cloned().unwrap_or_default());
            }
            steps.push(serde_json::from_value::<Step>(s).map_err(|e| format!("E{n}: a computed step: {e}"))?);
        }
        let mut checks = Vec::new();
        for c in &d.checks {
            let mut c = c.clone();
            for k in ["object", "support"] {
                if let Some(r) = c[k].as_str() {
                    c[k] = json!(role_of(r));
                }
            }
            checks.push(serde_json::from_value::<Check>(c).map_err(|e| format!("E{n}: a computed check: {e}"))?);
        }
        procedure.push(Stage {
            name: stage,
            steps,
            checks,
            retries: 1,
            code: None,
            source: Some(evidence_of(f, n).id),
        });
    }
    let used: BTreeSet<&str> = rules.iter().map(|r| r.anchor.object.as_str()).collect();
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
    for op in answer["operations"].as_array().map(Vec::as_slice).unwrap_or_default() {
        let kind = op["op"].as_str().unwrap_or_default().to_string();
        match apply_one(lib, f, op, ctx, &kind) {
            Ok(Some((id, v))) => {
                lib.log(&kind, json!({"skill": id, "version": v, "record": f.record.name}))?;
                rep.written.push((kind, id, v));
            }
            Ok(None) => {
                let why = format!("{kind} changes nothing: the library already holds this evidence");
                rep.unchanged.push((kind, why));
            }
            Err(why) => {
                lib.log("dropped", json!({"operation": op, "reason": why, "record": f.record.name}))?;
                rep.dropped.push((op.clone(), why));
            }
        }
    }
    Ok(rep)
}

/// One operation; Ok(None) when it changes nothing, Err(reason) when it is dropped.
fn apply_one(
    lib: &mut Library,
    f: &Findings,
    op: &Value,
    ctx: &Context,
    kind: &str,
) -> Result<Option<(String, u32)>, String> {
    if !op.is_object() {
        return Err("an operation is a JSON object".into());
    }
    let rounds = cited(f, op, "evidence")?;
    if rounds.is_empty() {
        return Err("cites no evidence".into());
    }
    let evidence: Vec<Evidence> = rounds.iter().map(|n| evidence_of(f, *n)).collect();
    let recovery = recovery_of(f, op)?;
    let recovery_rounds: Vec<u32> = op["recovery"]
        .as_array()
        .map(|rs| rs.iter().filter_map(|r| cited(f, r, "evidence").ok()).flatten().collect())
        .unwrap_or_default();
    let mut all_evidence = evidence.clone();
    for n in recovery_rounds {
        if !rounds.contains(&n) {
            all_evidence.push(evidence_of(f, n));
        }
    }
    let skill_ref = |lib: &Library| -> Result<Skill, String> {
        let id = op["skill"].as_str().unwrap_or_default();
        lib.get(id).cloned().ok_or_else(|| format!("names skill '{id}', which the library does not have"))
    };
    let write = |lib: &mut Library, s: Skill| -> Result<Option<(String, u32)>, String> {
        s.validate().map_err(|e| e.to_string())?;
        let (id, v) = (s.id.clone(), s.version);
        lib.write(s).map_err(|e| format!("{e:#}"))?;
        Ok(Some((id, v)))
    };
    match kind {
        "add" | "split" => {
            let built = build(f, &rounds, &op["stages"])?;
            let parent = if kind == "split" { Some(skill_ref(lib)?) } else { None };
            let name = op["name"].as_str().or(op["id"].as_str()).unwrap_or("skill").to_string();
            let mut id = slug(op["id"].as_str().unwrap_or(&name));
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
            keywords.extend(
                op["keywords"]
                    .as_array()
                    .map(Vec::as_slice)
                    .unwrap_or_default()
                    .iter()
                    .filter_map(|w| w.as_str())
                    .map(str::to_lowercase),
            );
            keywords.sort();
            keywords.dedup();
            let context: BTreeMap<String, String> = op["context"]
                .as_object()
                .map(|m| {
                    m.iter()
                        .map(|(k, v)| (k.clone(), v.as_str().map_or_else(|| v.to_string(), str::to_string)))
                        .collect()
                })
                .unwrap_or_default();
            let reason =
                op["reason"].as_str().map_or_else(|| format!("extracted from {}", f.record.name), str::to_string);
            let s = Skill {
                schema: SCHEMA,
                id,
                version: 1,
                status: Status::Candidate,
                name,
                summary: op["summary"].as_str().unwrap_or_default().to_string(),
                applicability: Applicability {
                    task_kind: op["task_kind"]
                        .as_str()
                        .map(str::to_string)
                        .or_else(|| parent.as_ref().map(|p| p.applicability.task_kind.clone()))
                        .unwrap_or_else(|| "other".into()),
                    keywords,
                    object_classes: built.classes,
                    fingerprint: ctx.fingerprint.clone(),
                    backend: ctx.backend,
                    context,
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
                let mut n =
                    next_version(&p, "split", format!("the context {} now belongs to {new_id}", op["context"]), &[]);
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
            let reason = op["reason"].as_str().unwrap_or("contradicted").to_string();
            let mut n = next_version(&s, "revise", reason, &all_evidence);
            match build(f, &rounds, &op["stages"]) {
                Ok(built) => replace_stages(&mut n, built),
                // Recovery guidance alone is a revision too; its stages stay.
                Err(why) if !recovery.is_empty() => {
                    n.history.last_mut().map(|h| h.reason.push_str(&format!(" (stages unchanged: {why})")));
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
                next_version(&s, "retire", op["reason"].as_str().unwrap_or("retired").to_string(), &all_evidence);
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
