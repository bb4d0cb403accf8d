//! Whole learning steps: `r2g skills extract <run>` (analyse the record, ask the model, merge,
//! admit what is new, retire what failed) and the paper's protocol as a batch
//! (`r2g batch --skills learn`): per seed, a first episode without skills, extraction from it,
//! then a second episode on the same seed with the skills selected from the library.

use std::path::{Path, PathBuf};

use agent_host::episode::Skills;
use agent_host::session::{self, EpisodeOpts};
use anyhow::Context as _;
use serde::Serialize;
use serde_json::{json, Value};

use crate::admit::{self, AdmitOpts, AdmitReport};
use crate::extract::{self, Exchange};
use crate::format::{Backend, Status};
use crate::library::Library;
use crate::merge::{self, Context, MergeReport};
use crate::record::Label;
use crate::select::{LibrarySource, SelectOpts};

#[derive(Debug, Clone)]
pub struct LearnOpts {
    pub library: PathBuf,
    /// Endpoint TOML, or `scripted` (the gym's recorded extraction answers,
    /// agent-host/scripted/<gym>-extract.json) or `scripted:<file>`.
    pub llm: String,
    pub provider: String,
    /// None: no admission runs (candidates stay candidates).
    pub admit: Option<AdmitOpts>,
    pub robot_config: Option<PathBuf>,
    /// Retire skills below this success share after `retire_min_runs` judged runs, and the
    /// least recently used ones while more than `cap` are active.
    pub retire_below: f64,
    pub retire_min_runs: u32,
    pub cap: usize,
}

impl LearnOpts {
    pub fn new(library: PathBuf, llm: &str) -> Self {
        Self {
            library,
            llm: llm.into(),
            provider: "openai".into(),
            admit: Some(AdmitOpts::default()),
            robot_config: None,
            retire_below: 0.3,
            retire_min_runs: 5,
            cap: 64,
        }
    }
}

#[derive(Debug, Serialize)]
pub struct LearnReport {
    pub record: String,
    pub labels: Vec<Label>,
    pub pairs: Vec<(u32, u32)>,
    pub skipped: Vec<(u32, String)>,
    pub exchange: Option<Exchange>,
    /// Why the model's answer was dropped as a whole, if it was.
    pub answer_dropped: Option<String>,
    pub merge: MergeReport,
    pub admissions: Vec<AdmitReport>,
    pub retired: Vec<String>,
}

/// The default library: robot-skill/skills of this checkout.
pub fn default_library() -> PathBuf {
    session::root().join("robot-skill/skills")
}

/// `r2g skills extract`.
pub fn learn(run: &Path, o: &LearnOpts) -> anyhow::Result<LearnReport> {
    let root = session::root();
    let f = extract::analyse(&root, run)?;
    let mut lib = Library::open(&o.library)?;
    let listing: Vec<_> = lib.latest().cloned().collect();
    let prompt = extract::prompt(&f, &listing.iter().collect::<Vec<_>>());
    let script = root.join("agent-host/scripted").join(format!("{}-extract.json", f.record.gym));
    let llm_dir = f.record.dir.join("extraction-llm");
    std::fs::create_dir_all(&llm_dir)?;
    let (endpoint, _guard, _) = session::endpoint(&o.llm, &o.provider, &f.record.gym, Some(&script), &llm_dir)?;
    let exchange = extract::ask(&endpoint, &prompt)?;
    let rc = o.robot_config.clone().unwrap_or_else(runtime::launch::default_robot_config);
    let ctx = Context {
        fingerprint: crate::fingerprint::of(&f.record.scene, &rc)?,
        backend: if f.record.rounds.iter().any(|r| r.state_before["backend"] == "franka") {
            Backend::Real
        } else {
            Backend::Sim
        },
    };
    let (merge, answer_dropped) = match extract::parse_answer(&exchange.answer) {
        Ok(answer) => (merge::apply(&mut lib, &f, &answer, &ctx)?, None),
        Err(why) => {
            lib.log("dropped", json!({"answer": exchange.answer, "reason": why, "record": f.record.name}))?;
            (MergeReport::default(), Some(why))
        }
    };
    let mut admissions = Vec::new();
    if let Some(a) = &o.admit {
        let fresh: Vec<String> = merge.written.iter().map(|(_, id, _)| id.clone()).collect();
        for id in fresh {
            if lib.get(&id).is_some_and(|s| s.status == Status::Candidate) {
                let a = AdmitOpts { robot_config: o.robot_config.clone(), ..a.clone() };
                admissions.push(admit::admit(&root, &mut lib, &id, &a)?);
            }
        }
    }
    let retired = merge::housekeeping(&mut lib, o.retire_below, o.retire_min_runs, o.cap)?;
    let report = LearnReport {
        record: f.record.dir.display().to_string(),
        labels: f.labels,
        pairs: f.pairs,
        skipped: f.skipped,
        exchange: Some(exchange),
        answer_dropped,
        merge,
        admissions,
        retired,
    };
    let p = extract::report_path(run);
    let tmp = p.with_extension("json.partial");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&report)?)?;
    std::fs::rename(&tmp, &p).with_context(|| format!("writing {}", p.display()))?;
    Ok(report)
}

/// An episode given the library's skills.
pub fn with_skills(o: &EpisodeOpts, library: &Path) -> anyhow::Result<EpisodeOpts> {
    let root = session::root();
    let scene = runtime::launch::resolve_scene(&o.gym)?;
    let rc = o.robot_config.clone().unwrap_or_else(runtime::launch::default_robot_config);
    let source = LibrarySource {
        root,
        dir: library.to_path_buf(),
        fingerprint: crate::fingerprint::of(&scene, &rc)?,
        opts: SelectOpts::default(),
    };
    Ok(EpisodeOpts {
        skills: Some(Skills(std::sync::Arc::new(source))),
        library: Some(library.to_path_buf()),
        ..o.clone()
    })
}

/// The `r2g batch` arguments that run the protocol on one seed into `out` with its own library
/// (one job of the protocol on a fleet).
fn seed_job(o: &EpisodeOpts, seed: u64, learn_opts: &LearnOpts, out: &Path) -> Vec<String> {
    let mut a = vec![
        "batch".to_string(),
        o.gym.clone(),
        "--episodes".into(),
        "1".into(),
        "--skills-protocol".into(),
        "learn".into(),
    ];
    a.extend([
        "--llm".into(),
        o.llm.clone(),
        "--provider".into(),
        o.provider.clone(),
        "--learn-llm".into(),
        learn_opts.llm.clone(),
    ]);
    a.extend([
        "--max-decisions".into(),
        o.max_decisions.to_string(),
        "--control-steps".into(),
        o.control_steps.to_string(),
    ]);
    a.extend(["--seed".into(), seed.to_string(), "--out".into(), out.display().to_string()]);
    a.extend(["--library".into(), out.join("library").display().to_string()]);
    match &learn_opts.admit {
        Some(ad) => {
            a.extend(["--admit-runs".into(), ad.seeds.len().to_string(), "--admit-share".into(), ad.share.to_string()]);
            if let Some(p) = &ad.perturb {
                a.extend(["--admit-perturb".into(), p.clone()]);
            }
        }
        None => a.extend(["--admit-runs".into(), "0".into()]),
    }
    if let Some(p) = &o.perturb {
        a.extend(["--perturb".into(), p.clone()]);
    }
    if let Some(rc) = &o.robot_config {
        a.extend(["--robot-config".into(), rc.display().to_string()]);
    }
    a
}

/// `r2g batch --skills-protocol learn`: per seed, an episode without skills → extraction → an
/// episode with the selected skills; per-arm figures with seeds paired. On a fleet (`backend`),
/// each seed is one job learning into its own library (the paper's protocol: the second
/// execution uses what the first taught), the rows streamed into the same summary.
pub fn protocol(
    o: &EpisodeOpts,
    episodes: u32,
    learn_opts: &LearnOpts,
    backend: Option<&fleet::Backend>,
    mut on_episode: impl FnMut(&str, u32, &anyhow::Result<Value>),
) -> anyhow::Result<Value> {
    let root = session::root();
    let gym = runtime::launch::resolve_scene(&o.gym)?
        .parent()
        .and_then(|p| p.file_name())
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let dir = session::run_folder(o.out.as_deref(), "batches", &format!("{gym}-skills"))?;
    let scripted = o.llm == "scripted";
    let second_llm = {
        let s = root.join("agent-host/scripted").join(format!("{gym}-skills.json"));
        if scripted && s.is_file() {
            format!("scripted:{}", s.display())
        } else {
            o.llm.clone()
        }
    };
    let mut rows = Vec::new();
    let seed_of = |i: u32| o.seed + u64::from(i) + u64::from(o.seed == 0 && o.perturb.is_some());
    if let Some(b) = backend {
        let jobs: Vec<fleet::Job> = (0..episodes)
            .map(|i| fleet::Job {
                id: i as usize,
                args: seed_job(o, seed_of(i), learn_opts, &dir.join(format!("seed-{i:03}"))),
            })
            .collect();
        let mut got: Vec<(u64, Value)> = Vec::new();
        fleet::run(&jobs, b, &dir, |r| {
            let i = r["id"].as_u64().unwrap_or(0);
            let row = match &r["value"]["per_seed"][0] {
                v @ Value::Object(_) => v.clone(),
                _ => {
                    json!({"seed": seed_of(i as u32), "error": r.get("error").cloned().unwrap_or_else(|| json!(format!("r2g batch exited with {}: {}", r["rc"], r["stderr_tail"].as_str().unwrap_or("").trim())))})
                }
            };
            for arm in ["without", "with"] {
                let v =
                    if row[arm].is_object() { Ok(row[arm].clone()) } else { Err(anyhow::anyhow!("{}", row["error"])) };
                on_episode(if arm == "with" { "with skills" } else { "without skills" }, i as u32, &v);
            }
            got.push((i, row));
        })?;
        got.sort_by_key(|(i, _)| *i);
        rows = got.into_iter().map(|(_, r)| r).collect();
    }
    for i in 0..if backend.is_some() { 0 } else { episodes } {
        let seed = seed_of(i);
        let first =
            EpisodeOpts { out: Some(dir.join(format!("episode-{i:03}-without"))), seed, skills: None, ..o.clone() };
        let a = session::episode(&first).map(|r| serde_json::to_value(&r).unwrap_or(Value::Null));
        on_episode("without skills", i, &a);
        let learned = match &a {
            Ok(r) => learn(Path::new(r["run_dir"].as_str().unwrap_or_default()), learn_opts).map(|l| {
                json!({"written": l.merge.written, "dropped": l.merge.dropped.len(), "admissions": l.admissions.iter().map(|x| json!({"skill": x.skill, "validated": x.validated, "reason": x.reason})).collect::<Vec<_>>()})
            }),
            Err(e) => Err(anyhow::anyhow!("no first episode: {e:#}")),
        };
        let second = with_skills(
            &EpisodeOpts {
                out: Some(dir.join(format!("episode-{i:03}-with"))),
                seed,
                llm: second_llm.clone(),
                ..o.clone()
            },
            &learn_opts.library,
        )?;
        let b = session::episode(&second).map(|r| serde_json::to_value(&r).unwrap_or(Value::Null));
        on_episode("with skills", i, &b);
        let row = |r: &anyhow::Result<Value>| match r {
            Ok(v) => v.clone(),
            Err(e) => json!({"error": format!("{e:#}"), "success": false}),
        };
        rows.push(json!({"seed": seed, "without": row(&a), "learned": learned.unwrap_or_else(|e| json!({"error": format!("{e:#}")})), "with": row(&b)}));
    }
    let arm = |k: &str| {
        let n = rows.len().max(1) as f64;
        let f = |m: &str| rows.iter().map(|r| r[k][m].as_f64().unwrap_or(0.0)).sum::<f64>() / n;
        json!({
            "success_rate": rows.iter().filter(|r| r[k]["success"] == true).count() as f64 / n,
            "responses_mean": f("responses"), "tokens_in_mean": f("tokens_in"), "tokens_out_mean": f("tokens_out"),
            "wall_s_mean": f("wall_s"), "model_s_mean": f("model_s"), "exec_s_mean": f("exec_s"),
        })
    };
    let summary = json!({
        "gym": gym, "episodes": rows.len(), "library": learn_opts.library,
        "label": if scripted { "mechanics only: the scripted endpoint replays recorded conversations (synthetic, written by us), not a model" } else { "model" },
        "without_skills": arm("without"), "with_skills": arm("with"),
        "per_seed": rows, "run_dir": dir,
    });
    let tmp = dir.join("batch.json.partial");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&summary)?)?;
    std::fs::rename(&tmp, dir.join("batch.json"))?;
    Ok(summary)
}
