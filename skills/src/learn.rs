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
    /// What answered the extraction: `live`, `scripted` (recorded answers written by us) or
    /// `replayed` (a cassette).
    pub llm_source: String,
    /// Why the model's answer was dropped as a whole, if it was.
    pub answer_dropped: Option<String>,
    pub merge: MergeReport,
    pub admissions: Vec<AdmitReport>,
    pub retired: Vec<String>,
}

/// The default library: runs/skill-library of this checkout (outside robot-skill/, which the
/// sandbox can read: a program sees only the skills selection gives it).
pub fn default_library() -> PathBuf {
    session::root().join("runs/skill-library")
}

/// The extraction endpoint when none is given: the episode's own, except that a scripted
/// episode's extraction is answered by the gym's recorded extraction answers, and a replayed
/// episode's by the extraction recorded beside its cassette (`<run>/extraction-llm/`).
pub fn extraction_llm(episode_llm: &str) -> String {
    if episode_llm == "scripted" || episode_llm.starts_with("scripted:") {
        "scripted".into()
    } else if let Some(c) = episode_llm.strip_prefix("replay:") {
        let dir = Path::new(c).parent().unwrap_or(Path::new("."));
        format!("replay:{}", dir.join("extraction-llm").join("cassette.jsonl").display())
    } else {
        episode_llm.to_string()
    }
}

/// After an episode that was given skills, and judged: each chosen skill gets the verdict as
/// evidence of use (a new version), then housekeeping retires what keeps failing.
pub fn record_use(library: &Path, run_dir: &Path, o: &LearnOpts) -> anyhow::Result<Vec<(String, u32)>> {
    let read =
        |name: &str| -> Option<Value> { serde_json::from_str(&std::fs::read_to_string(run_dir.join(name)).ok()?).ok() };
    let (Some(sel), Some(result)) = (read("skills.json"), read("result.json")) else { return Ok(Vec::new()) };
    let Some(success) = result["success"].as_bool() else { return Ok(Vec::new()) };
    let config = read("config.json").unwrap_or(Value::Null);
    let folder = run_dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let episode = match config["instance"].as_str() {
        Some(i) => format!("{folder}@{i}"),
        None => folder,
    };
    let mut written = Vec::new();
    for id in sel["chosen"].as_array().map(Vec::as_slice).unwrap_or_default().iter().filter_map(Value::as_str) {
        // Episodes of a batch on workers may add use to the same skill at once: a version
        // another wrote first is read again and the next one written.
        for attempt in 0..5 {
            let mut lib = Library::open(library)?;
            let Some(s) = lib.get(id).cloned() else { break };
            if s.evidence.iter().any(|e| e.episode == episode) {
                break;
            }
            let mut n = s.clone();
            n.version += 1;
            let ev = crate::format::Evidence {
                id: format!("{episode}#0"),
                episode: episode.clone(),
                round: 0,
                outcome: if success { crate::format::Outcome::Success } else { crate::format::Outcome::Failure },
                source: crate::format::Source::Use,
                seed: config["seed"].as_u64().unwrap_or(0),
                record: Some(run_dir.display().to_string()),
                note: format!(
                    "given to an episode ({}), natively judged",
                    result["llm_source"].as_str().unwrap_or("?")
                ),
            };
            n.history.push(crate::format::Change {
                version: n.version,
                op: "use".into(),
                reason: ev.note.clone(),
                evidence: vec![ev.id.clone()],
            });
            n.evidence.push(ev);
            let v = n.version;
            match lib.write(n) {
                Ok(()) => {
                    lib.log("used", json!({"skill": id, "episode": episode, "success": success}))?;
                    written.push((id.to_string(), v));
                    break;
                }
                Err(e) if attempt == 4 => return Err(e),
                Err(_) => std::thread::sleep(std::time::Duration::from_millis(50 * (attempt + 1))),
            }
        }
    }
    let mut lib = Library::open(library)?;
    merge::housekeeping(&mut lib, o.retire_below, o.retire_min_runs, o.cap)?;
    Ok(written)
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
    let (endpoint, _guard, llm_source) =
        session::endpoint(&o.llm, &o.provider, &f.record.gym, Some(&script), &llm_dir)?;
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
        llm_source: llm_source.into(),
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

/// The `r2g batch` arguments that run the protocol on one seed into `out` (one job of the
/// protocol on a fleet): the episode's own flags, then the protocol's.
fn seed_job(o: &EpisodeOpts, seed: u64, learn_opts: &LearnOpts, out: &Path, library: &Path) -> Vec<String> {
    let e = EpisodeOpts { seed, library: None, ..o.clone() };
    let mut a = vec![
        "batch".to_string(),
        session::gym_arg(&o.gym),
        "--episodes".into(),
        "1".into(),
        "--skills".into(),
        "learn".into(),
    ];
    a.extend(session::episode_flags(&e));
    a.extend(["--out".into(), out.display().to_string(), "--library".into(), library.display().to_string()]);
    // (--seed came with the episode's flags: given once.)
    a.extend(["--learn-llm".into(), learn_opts.llm.clone()]);
    match &learn_opts.admit {
        Some(ad) => {
            a.extend(["--admit-runs".into(), ad.seeds.len().to_string(), "--admit-share".into(), ad.share.to_string()]);
            if let Some(p) = &ad.perturb {
                a.extend(["--admit-perturb".into(), p.clone()]);
            }
        }
        None => a.extend(["--admit-runs".into(), "0".into()]),
    }
    a
}

/// Copies the library `from` (if any) into a fresh `to`, the library a seed starts with: every
/// skill's version files and the event log, with their modification times (the cap's "unused
/// longest" reads them); admission run folders stay behind.
fn seed_library(from: &Path, to: &Path) -> anyhow::Result<()> {
    fn copy(src: &Path, dst: &Path) -> anyhow::Result<()> {
        std::fs::copy(src, dst).with_context(|| format!("copying {} to {}", src.display(), dst.display()))?;
        if let Ok(t) = std::fs::metadata(src).and_then(|m| m.modified()) {
            std::fs::File::options().write(true).open(dst).and_then(|f| f.set_modified(t))?;
        }
        Ok(())
    }
    std::fs::create_dir_all(to)?;
    let Ok(rd) = std::fs::read_dir(from) else { return Ok(()) };
    for e in rd.flatten() {
        let (name, is_dir) = (e.file_name(), e.file_type().is_ok_and(|t| t.is_dir()));
        if !is_dir {
            if name == "events.jsonl" {
                copy(&e.path(), &to.join(&name))?;
            }
            continue;
        }
        if name == "admission" {
            continue;
        }
        let versions: Vec<_> = std::fs::read_dir(e.path())?
            .flatten()
            .filter(|f| {
                let n = f.file_name().to_string_lossy().into_owned();
                n.starts_with('v') && n.ends_with(".json") && f.file_type().is_ok_and(|t| t.is_file())
            })
            .collect();
        if versions.is_empty() {
            continue;
        }
        let dst = to.join(&name);
        std::fs::create_dir_all(&dst)?;
        for f in versions {
            copy(&f.path(), &dst.join(f.file_name()))?;
        }
    }
    Ok(())
}

fn source_of(v: &Value) -> &str {
    v["llm_source"].as_str().unwrap_or("?")
}

/// `r2g batch --skills learn`: per seed, an episode without skills → extraction → an episode on
/// the same seed given the selected skills, as in the paper (the second execution of a task
/// uses what its first taught). Each seed learns into its own library `<out>/seed-NNN/library`,
/// which starts as a copy of `learn_opts.library`, locally and on a fleet alike (`backend`: one
/// job per seed). Per-arm figures over the episodes that ran; seeds paired.
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
    let second_llm = {
        let s = root.join("agent-host/scripted").join(format!("{gym}-skills.json"));
        if o.llm == "scripted" && s.is_file() {
            format!("scripted:{}", s.display())
        } else {
            o.llm.clone()
        }
    };
    let seed_of = |i: u32| o.seed + u64::from(i) + u64::from(o.seed == 0 && o.perturb.is_some());
    let mut rows = Vec::new();
    if let Some(b) = backend {
        let mut jobs = Vec::new();
        for i in 0..episodes {
            // The job runs the protocol on one seed into <out>/seed-NNN: it copies the
            // library itself (into <out>/seed-NNN/seed-000/library) and learns there.
            let out = dir.join(format!("seed-{i:03}"));
            jobs.push(fleet::Job {
                id: i as usize,
                args: seed_job(o, seed_of(i), learn_opts, &out, &learn_opts.library),
            });
        }
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
        let seed_dir = dir.join(format!("seed-{i:03}"));
        let library = seed_dir.join("library");
        seed_library(&learn_opts.library, &library)?;
        let lo = LearnOpts { library: library.clone(), ..learn_opts.clone() };
        let first = EpisodeOpts {
            out: Some(seed_dir.join(format!("episode-{i:03}-without"))),
            seed,
            skills: None,
            library: None,
            ..o.clone()
        };
        let a = session::episode(&first).map(|r| serde_json::to_value(&r).unwrap_or(Value::Null));
        on_episode("without skills", i, &a);
        let learned = match &a {
            Ok(r) => learn(Path::new(r["run_dir"].as_str().unwrap_or_default()), &lo).map(|l| {
                json!({"written": l.merge.written, "dropped": l.merge.dropped.len(), "llm_source": l.llm_source,
                       "tokens_in": l.exchange.as_ref().map_or(0, |e| e.tokens_in), "tokens_out": l.exchange.as_ref().map_or(0, |e| e.tokens_out),
                       "admissions": l.admissions.iter().map(|x| json!({"skill": x.skill, "validated": x.validated, "reason": x.reason})).collect::<Vec<_>>()})
            }),
            Err(e) => Err(anyhow::anyhow!("no first episode: {e:#}")),
        };
        let second = with_skills(
            &EpisodeOpts {
                out: Some(seed_dir.join(format!("episode-{i:03}-with"))),
                seed,
                llm: second_llm.clone(),
                ..o.clone()
            },
            &library,
        )?;
        let b = session::episode(&second).map(|r| serde_json::to_value(&r).unwrap_or(Value::Null));
        if let Ok(r) = &b {
            record_use(&library, Path::new(r["run_dir"].as_str().unwrap_or_default()), &lo)?;
        }
        on_episode("with skills", i, &b);
        let row = |r: &anyhow::Result<Value>| match r {
            Ok(v) => v.clone(),
            Err(e) => json!({"error": format!("{e:#}"), "success": false}),
        };
        rows.push(json!({"seed": seed, "library": library, "without": row(&a), "learned": learned.unwrap_or_else(|e| json!({"error": format!("{e:#}")})), "with": row(&b)}));
    }
    // Means over the episodes that ran (an error is counted apart, never as zero tokens).
    let arm = |k: &str| {
        let ran: Vec<&Value> =
            rows.iter().map(|r| &r[k]).filter(|v| v.get("error").is_none() && v.is_object()).collect();
        let n = ran.len().max(1) as f64;
        let f = |m: &str| ran.iter().map(|r| r[m].as_f64().unwrap_or(0.0)).sum::<f64>() / n;
        json!({
            "ran": ran.len(), "errors": rows.len() - ran.len(),
            "success_rate": ran.iter().filter(|r| r["success"] == true).count() as f64 / n,
            "responses_mean": f("responses"), "tokens_in_mean": f("tokens_in"), "tokens_out_mean": f("tokens_out"),
            "wall_s_mean": f("wall_s"), "model_s_mean": f("model_s"), "exec_s_mean": f("exec_s"),
            "llm_sources": ran.iter().map(|r| source_of(r)).collect::<std::collections::BTreeSet<_>>(),
        })
    };
    let learned: Vec<&Value> = rows.iter().map(|r| &r["learned"]).filter(|l| l.get("error").is_none()).collect();
    let ln = learned.len().max(1) as f64;
    let (without, with) = (arm("without"), arm("with"));
    let sources: std::collections::BTreeSet<String> = without["llm_sources"]
        .as_array()
        .into_iter()
        .chain(with["llm_sources"].as_array())
        .flatten()
        .chain(learned.iter().map(|l| &l["llm_source"]))
        .filter_map(|v| v.as_str().map(str::to_string))
        .collect();
    let label = if sources.is_empty() {
        "no episode ran".to_string()
    } else if sources.iter().all(|s| s == "live") {
        "a live model in every episode and extraction".to_string()
    } else if sources.iter().all(|s| s == "scripted") {
        "mechanics only: the scripted endpoint replays recorded conversations and extraction answers (synthetic, written by us), not a model".to_string()
    } else {
        format!("mixed sources ({}): not a model's figures", sources.into_iter().collect::<Vec<_>>().join(", "))
    };
    let summary = json!({
        "gym": gym, "episodes": rows.len(), "label": label,
        "libraries": rows.iter().map(|r| r["library"].clone()).collect::<Vec<_>>(),
        "without_skills": without, "with_skills": with,
        "extraction": {"ran": learned.len(), "tokens_in_mean": learned.iter().map(|l| l["tokens_in"].as_f64().unwrap_or(0.0)).sum::<f64>() / ln,
                       "tokens_out_mean": learned.iter().map(|l| l["tokens_out"].as_f64().unwrap_or(0.0)).sum::<f64>() / ln},
        "per_seed": rows, "run_dir": dir,
    });
    let tmp = dir.join("batch.json.partial");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&summary)?)?;
    std::fs::rename(&tmp, dir.join("batch.json"))?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_seed_library_copies_versions_and_events_with_their_times_and_leaves_admission_runs() {
        let base = std::env::temp_dir().join(format!("r2g-seedlib-{}", std::process::id()));
        let (from, to) = (base.join("from"), base.join("to"));
        std::fs::create_dir_all(from.join("a-skill")).expect("mkdir");
        std::fs::create_dir_all(from.join("admission/a-skill-v0001-seed90001/logs")).expect("mkdir");
        std::fs::write(from.join("a-skill/v0001.json"), "{}").expect("write");
        std::fs::write(from.join("events.jsonl"), "{}\n").expect("write");
        let hour_ago = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
        std::fs::File::options()
            .write(true)
            .open(from.join("a-skill/v0001.json"))
            .and_then(|f| f.set_modified(hour_ago))
            .expect("mtime");
        seed_library(&from, &to).expect("a library with admission runs copies");
        assert!(to.join("a-skill/v0001.json").is_file() && to.join("events.jsonl").is_file());
        assert!(!to.join("admission").exists());
        let t = std::fs::metadata(to.join("a-skill/v0001.json")).and_then(|m| m.modified()).expect("mtime");
        assert_eq!(t, hour_ago, "the copy keeps when the version was written");
        let _ = std::fs::remove_dir_all(&base);
    }

    #[test]
    fn a_seed_job_names_its_seed_once() {
        let o =
            EpisodeOpts { perturb: Some("xy=0.05,yaw=30".into()), ..EpisodeOpts::new("pick_block_plate", "scripted") };
        let lo = LearnOpts::new(PathBuf::from("/lib"), "scripted");
        let args = seed_job(&o, 7, &lo, Path::new("/out/seed-003"), Path::new("/lib"));
        assert_eq!(args.iter().filter(|a| *a == "--seed").count(), 1, "{args:?}");
        let at = args.iter().position(|a| a == "--seed").expect("--seed");
        assert_eq!(args[at + 1], "7");
    }
}
