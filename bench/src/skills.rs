//! `r2g bench skills`: does a skill extracted from ONE episode transfer to layouts it never saw?
//! Per gym: one scripted episode (seed 0; a synthetic recorded conversation, not a model),
//! extraction into a fresh library (no admission: every seed below is unseen), then on N seeds
//! with the placement perturbed (default ±5 cm, ±30°) the skill run without a model against the
//! same procedure replaying the episode's absolute targets, both natively judged, same seeds.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use agent_host::session::{self, EpisodeOpts, GymSetup};
use anyhow::Context;
use serde_json::{json, Value};
use skills::learn::{self, LearnOpts};
use skills::run::{self as skill_run, RunOpts};
use skills::Library;

pub struct Options {
    pub gyms: Vec<String>,
    pub seeds: u64,
    pub first_seed: u64,
    pub perturb: String,
    pub jobs: usize,
    pub out: PathBuf,
}

fn record_of(gym: &str, out: &Path) -> anyhow::Result<PathBuf> {
    let o = EpisodeOpts {
        out: Some(out.join(format!("{gym}-episode"))),
        memory: Some(out.join("memory")),
        ..EpisodeOpts::new(gym, "scripted")
    };
    let r = session::episode(&o)?;
    if !r.success {
        anyhow::bail!("the scripted episode of {gym} did not succeed ({}); no skill to extract", r.stop_reason);
    }
    Ok(PathBuf::from(r.run_dir))
}

pub fn run(o: &Options) -> anyhow::Result<Value> {
    std::fs::create_dir_all(&o.out)?;
    let root = session::root();
    let mut rows = Vec::new();
    for gym in &o.gyms {
        let t0 = std::time::Instant::now();
        let record = record_of(gym, &o.out)?;
        let lib_dir = o.out.join(format!("{gym}-library"));
        let _ = std::fs::remove_dir_all(&lib_dir);
        let lo = LearnOpts { admit: None, ..LearnOpts::new(lib_dir.clone(), "scripted") };
        let l = learn::learn(&record, &lo)?;
        let (_, id, _) = l
            .merge
            .written
            .first()
            .cloned()
            .with_context(|| format!("{gym}: extraction wrote no skill: {:?}", l.merge.dropped))?;
        let skill = Library::open(&lib_dir)?.get(&id).cloned().context("the extracted skill")?;
        let absolute = skill_run::recorded_targets(&root, &skill)?;
        let seeds: Vec<u64> = (0..o.seeds).map(|k| o.first_seed + k).collect();
        let results: Mutex<Vec<(u64, bool, bool, Option<String>, String)>> = Mutex::new(Vec::new());
        let next = AtomicUsize::new(0);
        std::thread::scope(|s| {
            for _ in 0..o.jobs.max(1) {
                s.spawn(|| loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&seed) = seeds.get(i) else { break };
                    let one = |abs: bool| -> (bool, String) {
                        let setup = GymSetup { seed, perturb: Some(o.perturb.clone()), ..Default::default() };
                        let mut ro = RunOpts::new(gym, setup);
                        ro.out = Some(
                            o.out.join(format!("{gym}-runs/seed{seed}-{}", if abs { "absolute" } else { "skill" })),
                        );
                        if abs {
                            ro.absolute = Some(absolute.clone());
                        }
                        match skill_run::run(&skill, &ro) {
                            Ok(r) => (r.success, r.stop_reason),
                            Err(e) => (false, format!("error: {e:#}")),
                        }
                    };
                    let (ok_skill, why) = one(false);
                    let (ok_abs, _) = one(true);
                    // Where no perturbed draw fitted, the scene kept its written layout: both
                    // arms then ran on the demonstration's own placement (counted, not hidden).
                    let fallback = placement_fallback(gym, seed, &o.perturb);
                    eprintln!(
                        "bench skills: {gym} seed {seed}: skill {ok_skill} ({why}), absolute {ok_abs}{}",
                        fallback.as_deref().map(|f| format!(" [placement: {f}]")).unwrap_or_default()
                    );
                    if let Ok(mut r) = results.lock() {
                        r.push((seed, ok_skill, ok_abs, fallback, why));
                    }
                });
            }
        });
        let mut res = results.into_inner().unwrap_or_default();
        res.sort_by_key(|r| r.0);
        let n = res.len().max(1) as f64;
        let k_skill = res.iter().filter(|r| r.1).count();
        let k_abs = res.iter().filter(|r| r.2).count();
        let failures: Vec<Value> = res.iter().filter(|r| !r.1).map(|r| json!({"seed": r.0, "reason": r.4})).collect();
        let fallbacks: Vec<Value> =
            res.iter().filter_map(|r| r.3.as_ref().map(|f| json!({"seed": r.0, "note": f}))).collect();
        rows.push(json!({
            "gym": gym, "skill": id, "record": record, "seeds": res.len(), "first_seed": o.first_seed,
            "perturb": o.perturb, "skill_success": k_skill, "absolute_success": k_abs,
            "skill_rate": k_skill as f64 / n, "absolute_rate": k_abs as f64 / n,
            "skill_failures": failures, "placement_fallbacks": fallbacks, "wall_s": t0.elapsed().as_secs_f64(),
        }));
    }
    println!("Skill transfer (one scripted episode per gym — synthetic, no model — extracted, then run on unseen perturbed seeds)");
    println!(
        "{:<18} {:>6} {:>22} {:>26} {:>9}",
        "gym", "seeds", "skill (bound) success", "absolute replay success", "wall s"
    );
    for r in &rows {
        println!(
            "{:<18} {:>6} {:>15} ({:>4.0}%) {:>19} ({:>4.0}%) {:>9.0}",
            r["gym"].as_str().unwrap_or_default(),
            r["seeds"],
            r["skill_success"],
            100.0 * r["skill_rate"].as_f64().unwrap_or(0.0),
            r["absolute_success"],
            100.0 * r["absolute_rate"].as_f64().unwrap_or(0.0),
            r["wall_s"].as_f64().unwrap_or(0.0)
        );
    }
    for r in &rows {
        let n = r["placement_fallbacks"].as_array().map_or(0, Vec::len);
        if n > 0 {
            println!(
                "{}: {n} seed(s) kept the written placement (no perturbed draw fitted)",
                r["gym"].as_str().unwrap_or_default()
            );
        }
    }
    let v = json!({"bench": "skills", "perturb": o.perturb, "gyms": rows});
    println!("{v}");
    Ok(v)
}

/// The note of a perturbed placement that fell back to the written layout, if it did.
fn placement_fallback(gym: &str, seed: u64, perturb: &str) -> Option<String> {
    let go = || -> anyhow::Result<Option<String>> {
        let scene = runtime::launch::resolve_scene(gym)?;
        let mut sim = sim_host::Sim::load(&scene)?;
        sim.seed = seed;
        sim.set_perturbation(Some(perturb.parse().map_err(|e| anyhow::anyhow!("{e}"))?))?;
        Ok(sim.placed.and_then(|p| p.note))
    };
    go().unwrap_or_else(|e| Some(format!("the placement could not be checked: {e:#}")))
}
