//! Admission: a candidate becomes validated only after
//! (a) its schema holds and every stage's code compiles and passes the base-frame lint,
//! (b) its rules, bound again on the observations recorded at the start of the rounds they came
//!     from (same reference TCP), give back the targets those rounds sent, within tolerance, and
//! (c) model-free runs on held-out seeds (never the seed of a round it was extracted from, with
//!     the placement perturbed) succeed, natively judged, on at least a configured share.
//! Every run becomes evidence; the outcome is a new version either way.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use agent_host::session::GymSetup;
use anyhow::{bail, Context};
use serde::Serialize;
use serde_json::{json, Value};

use crate::format::{Change, Evidence, Outcome, Skill, Source, Stage, Status, Step};
use crate::library::Library;
use crate::record::RunRecord;
use crate::run::{self, RunOpts};
use crate::tools;

#[derive(Debug, Clone)]
pub struct AdmitOpts {
    /// Held-out seeds of the model-free runs.
    pub seeds: Vec<u64>,
    /// Share of them that must succeed.
    pub share: f64,
    pub perturb: Option<String>,
    /// Gym to run in (default: the scene of the record the skill came from).
    pub gym: Option<String>,
    pub robot_config: Option<PathBuf>,
    pub tolerance_m: f64,
    pub tolerance_rad: f64,
}

impl Default for AdmitOpts {
    fn default() -> Self {
        Self {
            seeds: (0..5).map(|k| 90_001 + k).collect(),
            share: 0.8,
            perturb: Some("xy=0.03,yaw=15".into()),
            gym: None,
            robot_config: None,
            tolerance_m: 0.005,
            tolerance_rad: 0.05,
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct AdmitReport {
    pub skill: String,
    pub version: u32,
    pub lint: Vec<String>,
    pub reinstantiation: Vec<Value>,
    pub runs: Vec<Value>,
    pub successes: usize,
    pub validated: bool,
    pub reason: String,
}

fn evidence<'a>(skill: &'a Skill, id: &str) -> anyhow::Result<&'a Evidence> {
    skill
        .evidence
        .iter()
        .find(|e| e.id == id)
        .with_context(|| format!("skill {}: stage source {id} is not among its evidence", skill.id))
}

/// Where a stage's rules are bound again: the observation its source round's motion started
/// from, the reference TCP then, and the observations of the episode before it (the tracker
/// replays them so objects keep the names extraction gave them).
#[derive(Debug, Clone)]
pub struct BindSite {
    pub obs: PathBuf,
    pub reference: Value,
    pub history: Vec<PathBuf>,
}

/// The targets a stage's source round sent, keyed by the stage's rule ids, and where they are
/// bound again ([`BindSite`]). The round's motion is what extraction related: its calls after
/// its own reset(), if it sent one.
pub fn source_targets(
    root: &Path,
    skill: &Skill,
    stage: &Stage,
    src: &str,
) -> anyhow::Result<(BTreeMap<String, Vec<f64>>, BindSite)> {
    let ev = evidence(skill, src)?;
    let Some(dir) = &ev.record else { bail!("evidence {src} names no record folder") };
    let rec = RunRecord::open(Path::new(dir))?;
    let Some(round) = rec.rounds.iter().find(|r| r.n == ev.round) else { bail!("{dir} has no round {}", ev.round) };
    let obs = rec.motion_obs(ev.round).map_err(|why| anyhow::anyhow!("{dir} round {}: {why}", ev.round))?;
    let mut history = rec.observations_upto(&obs);
    history.pop();
    let g = tools::call(root, "targets", &json!({"obs": obs, "calls": round.motion_calls()}))?;
    let moves: Vec<&str> = g["steps"]
        .as_array()
        .map(Vec::as_slice)
        .unwrap_or_default()
        .iter()
        .filter_map(|s| s["move"].as_str())
        .collect();
    let mine: Vec<&str> = stage
        .steps
        .iter()
        .filter_map(|s| if let Step::Move { rule } = s { Some(rule.as_str()) } else { None })
        .collect();
    if moves.len() != mine.len() {
        bail!("stage {}: {} moves, its source round {} sent {}", stage.name, mine.len(), ev.round, moves.len());
    }
    let mut out = BTreeMap::new();
    for (rule, m) in mine.iter().zip(moves) {
        let t: Vec<f64> =
            g["targets"][m].as_array().map(|a| a.iter().filter_map(Value::as_f64).collect()).unwrap_or_default();
        out.insert((*rule).to_string(), t);
    }
    Ok((out, BindSite { obs, reference: g["reference"].clone(), history }))
}

/// Checks (a) and (b); the reasons it fails, empty when it passes.
pub fn check(root: &Path, skill: &Skill, o: &AdmitOpts) -> anyhow::Result<(Vec<String>, Vec<Value>, Vec<String>)> {
    let mut problems = Vec::new();
    if let Err(e) = skill.validate() {
        problems.push(e.to_string());
    }
    let mut sources = Vec::new();
    for stage in &skill.procedure {
        let moves = stage.steps.iter().any(|s| matches!(s, Step::Move { .. }));
        let Some(src) = stage.source.as_deref() else {
            if moves {
                // A rule nobody can reproduce from a recorded round is not evidence-backed.
                problems.push(format!(
                    "stage {}: moves by rules but names no source round to re-instantiate them on",
                    stage.name
                ));
            }
            continue;
        };
        match source_targets(root, skill, stage, src) {
            Ok((targets, at)) => sources
                .push(json!({"obs": at.obs, "history": at.history, "reference": at.reference, "targets": targets})),
            Err(e) => problems.push(format!("stage {}: {e:#}", stage.name)),
        }
    }
    let answer = tools::call(root, "check", &json!({"skill": skill, "sources": sources}))?;
    let lint: Vec<String> = answer["lint"]
        .as_array()
        .map(|a| a.iter().filter_map(|v| v.as_str().map(str::to_string)).collect())
        .unwrap_or_default();
    problems.extend(lint.iter().cloned());
    let rein = answer["reinstantiation"].as_array().cloned().unwrap_or_default();
    for r in &rein {
        if let Some(e) = r["error"].as_str() {
            problems.push(format!("rule {}: {e}", r["rule"]));
        } else {
            let (dp, dr) = (
                r["position_m"].as_f64().unwrap_or(f64::INFINITY),
                r["rotation_rad"].as_f64().unwrap_or(f64::INFINITY),
            );
            if dp > o.tolerance_m || dr > o.tolerance_rad {
                problems.push(format!(
                    "rule {}: bound again on its round's observation it is {:.4} m / {:.4} rad from the recorded target (tolerance {} m / {} rad)",
                    r["rule"], dp, dr, o.tolerance_m, o.tolerance_rad
                ));
            }
        }
    }
    Ok((problems, rein, lint))
}

/// The gym a skill was extracted in: the scene of its first evidence's record.
pub fn source_gym(skill: &Skill) -> Option<String> {
    let dir = skill.evidence.iter().find_map(|e| e.record.clone())?;
    let cfg: Value = serde_json::from_str(&std::fs::read_to_string(Path::new(&dir).join("config.json")).ok()?).ok()?;
    cfg["scene"].as_str().map(str::to_string)
}

/// Runs admission for the newest version of `id` and writes the next version: validated with
/// the runs as evidence, or still a candidate with them (or retired by the caller's housekeeping).
pub fn admit(root: &Path, lib: &mut Library, id: &str, o: &AdmitOpts) -> anyhow::Result<AdmitReport> {
    let skill = lib.get(id).cloned().with_context(|| format!("no skill '{id}' in {}", lib.dir.display()))?;
    let (problems, rein, lint) = check(root, &skill, o)?;
    let mut report = AdmitReport {
        skill: skill.id.clone(),
        version: skill.version,
        lint,
        reinstantiation: rein,
        runs: Vec::new(),
        successes: 0,
        validated: false,
        reason: String::new(),
    };
    if !problems.is_empty() {
        report.reason = problems.join("; ");
        lib.log(
            "admission",
            json!({"skill": id, "version": skill.version, "validated": false, "reason": report.reason}),
        )?;
        return Ok(report);
    }
    let gym =
        o.gym.clone().or_else(|| source_gym(&skill)).with_context(|| format!("skill {id}: no gym to run it in"))?;
    // Held out: a seed no evidence of the skill used; a seed already used moves to the next free one.
    let mut seen: Vec<u64> = skill.evidence.iter().map(|e| e.seed).collect();
    let mut seeds = Vec::new();
    for &s in &o.seeds {
        let mut s = s;
        while seen.contains(&s) {
            s += 1;
        }
        seen.push(s);
        seeds.push(s);
    }
    let mut runs = Vec::new();
    for seed in seeds {
        let setup =
            GymSetup { seed, perturb: o.perturb.clone(), robot_config: o.robot_config.clone(), ..Default::default() };
        let mut ro = RunOpts::new(&gym, setup);
        ro.admission = true;
        // Beside the library it judges, never among the user's own runs.
        ro.out = Some(lib.dir.join("admission").join(format!("{}-v{:04}-seed{seed}", skill.id, skill.version)));
        let r = run::run(&skill, &ro)?;
        report.runs.push(json!({"seed": seed, "success": r.success, "reason": r.stop_reason, "run_dir": r.run_dir}));
        runs.push(r);
    }
    report.successes = runs.iter().filter(|r| r.success).count();
    let needed = (o.share * runs.len() as f64).ceil() as usize;
    report.validated = !runs.is_empty() && report.successes >= needed;
    report.reason = format!("{} of {} held-out runs succeeded (needed {needed})", report.successes, runs.len());
    let mut next = skill.clone();
    next.version += 1;
    let new_ev: Vec<Evidence> = runs
        .iter()
        .map(|r| {
            let name = Path::new(&r.run_dir).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            Evidence {
                id: format!("{name}#0"),
                episode: name,
                round: 0,
                outcome: if r.success { Outcome::Success } else { Outcome::Failure },
                source: Source::Validation,
                seed: r.seed,
                record: Some(r.run_dir.clone()),
                note: r.stop_reason.clone(),
            }
        })
        .collect();
    next.history.push(Change {
        version: next.version,
        op: "admission".into(),
        reason: report.reason.clone(),
        evidence: new_ev.iter().map(|e| e.id.clone()).collect(),
    });
    next.evidence.extend(new_ev);
    if report.validated {
        next.status = Status::Validated;
    }
    lib.write(next)?;
    lib.log(
        "admission",
        json!({"skill": id, "version": skill.version + 1, "validated": report.validated, "reason": report.reason}),
    )?;
    report.version = skill.version + 1;
    Ok(report)
}
