//! `r2g skills ...`: argument parsing and printing for the skills crate.

use std::path::PathBuf;

use agent_host::session::GymSetup;
use clap::Subcommand;
use serde_json::json;
use skills::admit::AdmitOpts;
use skills::learn::{self, LearnOpts};
use skills::Library;

/// Options every command that admits skills takes.
#[derive(clap::Args, Debug, Clone)]
pub struct AdmitArgs {
    /// Held-out model-free runs a candidate must pass (0: no admission runs).
    #[arg(long, default_value_t = 5)]
    pub admit_runs: u64,
    /// Share of them that must succeed, in (0, 1].
    #[arg(long, default_value_t = 0.8, value_parser = share)]
    pub admit_share: f64,
    /// Placement perturbation of the admission runs.
    #[arg(long, default_value = "xy=0.03,yaw=15")]
    pub admit_perturb: sim_host::placement::Perturbation,
}

fn share(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{s:?} is not a number: {e}"))?;
    if v > 0.0 && v <= 1.0 {
        Ok(v)
    } else {
        Err(format!("{s} is not a share in (0, 1]: 0 would admit a skill that never succeeded"))
    }
}

impl AdmitArgs {
    pub fn opts(&self) -> Option<AdmitOpts> {
        (self.admit_runs > 0).then(|| AdmitOpts {
            seeds: (0..self.admit_runs).map(|k| 90_001 + k).collect(),
            share: self.admit_share,
            perturb: Some(self.admit_perturb.to_string()),
            ..Default::default()
        })
    }
}

#[derive(Subcommand, Debug)]
pub enum SkillsCmd {
    /// One line per skill: id, version, status, natively judged successes / runs, evidence.
    List {
        #[arg(long)]
        library: Option<PathBuf>,
    },
    /// The newest version of a skill, as JSON.
    Show {
        skill: String,
        #[arg(long)]
        library: Option<PathBuf>,
    },
    /// Extract skills from a finished episode's run folder: label each round from measured
    /// state and the native trace, compute object-relative rules of the successful rounds, ask
    /// the model (through the endpoint) to name them and propose add/support/revise/split/retire
    /// operations, merge, admit new candidates, retire failing ones. Writes
    /// <run>/extraction.json; prints a summary line.
    Extract {
        run: PathBuf,
        #[arg(long)]
        library: Option<PathBuf>,
        /// Endpoint TOML, `scripted` (agent-host/scripted/<gym>-extract.json) or `scripted:<file>`.
        #[arg(long, default_value = "scripted")]
        llm: String,
        #[arg(long, default_value = "openai")]
        provider: String,
        #[command(flatten)]
        admit: AdmitArgs,
        #[arg(long)]
        robot_config: Option<PathBuf>,
    },
    /// Admission of a candidate: checks, re-instantiation on its recorded observations, and
    /// model-free runs on held-out seeds; writes the next version.
    Admit {
        skill: String,
        #[arg(long)]
        library: Option<PathBuf>,
        #[command(flatten)]
        admit: AdmitArgs,
        /// Gym to run it in (default: where it was extracted).
        #[arg(long)]
        gym: Option<String>,
    },
    /// Run a skill's procedure in the sandbox with no model, natively judged; one JSON line
    /// like `r2g episode` (success, tokens 0, time, run_dir). Exit 0 on success, 1 otherwise.
    Run {
        /// A skill id of the library, or a skill JSON file.
        skill: String,
        /// Gym name, folder or scene file.
        gym: String,
        #[arg(long)]
        library: Option<PathBuf>,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long, value_name = "SPEC")]
        perturb: Option<sim_host::placement::Perturbation>,
        /// Baseline: play the targets the source rounds sent (absolute base-frame poses) instead
        /// of binding the rules to the objects seen now.
        #[arg(long)]
        absolute: bool,
        #[arg(long)]
        out: Option<PathBuf>,
        #[arg(long)]
        robot_config: Option<PathBuf>,
    },
    /// Which skills an episode would get: selection on an instruction and the object classes
    /// perception sees (comma-separated), for the robot a gym describes.
    Select {
        #[arg(long)]
        instruction: String,
        #[arg(long, value_delimiter = ',')]
        classes: Vec<String>,
        #[arg(long, default_value = "pick_block_plate")]
        gym: String,
        #[arg(long)]
        library: Option<PathBuf>,
        #[arg(long)]
        candidates: bool,
        #[arg(long)]
        robot_config: Option<PathBuf>,
    },
}

fn library(dir: Option<PathBuf>) -> PathBuf {
    dir.unwrap_or_else(learn::default_library)
}

pub fn run(cmd: SkillsCmd) -> anyhow::Result<i32> {
    match cmd {
        SkillsCmd::List { library: dir } => {
            let lib = Library::open(&library(dir))?;
            if lib.versions.is_empty() {
                eprintln!("no skills in {}", lib.dir.display());
            }
            for s in lib.latest() {
                let (k, n) = s.record();
                let ext = s.evidence.iter().filter(|e| e.source == skills::format::Source::Extraction).count();
                println!(
                    "{} v{} {:?} {k}/{n} judged runs succeeded (lower bound {:.2}); {ext} extraction rounds; {}",
                    s.id,
                    s.version,
                    s.status,
                    skills::format::wilson_lower(k, n),
                    s.summary
                );
            }
            Ok(0)
        }
        SkillsCmd::Show { skill, library: dir } => {
            let lib = Library::open(&library(dir))?;
            let s = lib.get(&skill).ok_or_else(|| anyhow::anyhow!("no skill '{skill}' in {}", lib.dir.display()))?;
            println!("{}", serde_json::to_string_pretty(s)?);
            Ok(0)
        }
        SkillsCmd::Extract { run, library: dir, llm, provider, admit, robot_config } => {
            let o = LearnOpts { provider, admit: admit.opts(), robot_config, ..LearnOpts::new(library(dir), &llm) };
            let r = learn::learn(&run, &o)?;
            for (op, why) in &r.merge.dropped {
                eprintln!("r2g skills: dropped {op}: {why}");
            }
            if let Some(why) = &r.answer_dropped {
                eprintln!("r2g skills: the model's answer was dropped: {why}");
            }
            println!(
                "{}",
                json!({
                    "record": r.record, "rounds": r.labels.len(),
                    "positive": r.labels.iter().filter(|l| l.outcome == skills::format::Outcome::Positive).count(),
                    "negative": r.labels.iter().filter(|l| l.outcome == skills::format::Outcome::Negative).count(),
                    "pairs": r.pairs, "written": r.merge.written, "unchanged": r.merge.unchanged.len(),
                    "dropped": r.merge.dropped.len(), "answer_dropped": r.answer_dropped,
                    "admissions": r.admissions.iter().map(|a| json!({"skill": a.skill, "version": a.version, "validated": a.validated, "reason": a.reason})).collect::<Vec<_>>(),
                    "retired": r.retired,
                    "tokens_in": r.exchange.as_ref().map(|e| e.tokens_in), "tokens_out": r.exchange.as_ref().map(|e| e.tokens_out),
                })
            );
            Ok(0)
        }
        SkillsCmd::Admit { skill, library: dir, admit, gym } => {
            let mut lib = Library::open(&library(dir))?;
            let o = AdmitOpts { gym, ..admit.opts().unwrap_or_default() };
            let r = skills::admit::admit(&agent_host::session::root(), &mut lib, &skill, &o)?;
            println!("{}", serde_json::to_string(&r)?);
            Ok(i32::from(!r.validated))
        }
        SkillsCmd::Run { skill, gym, library: dir, seed, perturb, absolute, out, robot_config } => {
            let s = if std::path::Path::new(&skill).is_file() {
                skills::Skill::parse(&std::fs::read_to_string(&skill)?).map_err(|e| anyhow::anyhow!("{skill}: {e}"))?
            } else {
                let lib = Library::open(&library(dir))?;
                lib.get(&skill)
                    .cloned()
                    .ok_or_else(|| anyhow::anyhow!("no skill '{skill}' in {}", lib.dir.display()))?
            };
            if perturb.is_some() && seed == 0 {
                anyhow::bail!("--perturb draws the placement from the seed: give --seed N (N > 0)");
            }
            let setup = GymSetup { seed, perturb: perturb.map(|p| p.to_string()), robot_config, ..Default::default() };
            let mut o = skills::run::RunOpts::new(&gym, setup);
            o.out = out;
            if absolute {
                o.absolute = Some(skills::run::recorded_targets(&agent_host::session::root(), &s)?);
            }
            let r = skills::run::run(&s, &o)?;
            println!("{}", serde_json::to_string(&r)?);
            Ok(i32::from(!r.success))
        }
        SkillsCmd::Select { instruction, classes, gym, library: dir, candidates, robot_config } => {
            let lib = Library::open(&library(dir))?;
            let scene = runtime::launch::resolve_scene(&gym)?;
            let fp =
                skills::fingerprint::of(&scene, &robot_config.unwrap_or_else(runtime::launch::default_robot_config))?;
            let o = skills::select::SelectOpts { include_candidates: candidates, ..Default::default() };
            let sel = skills::select::select(&lib, &instruction, &classes, &fp, skills::format::Backend::Sim, &o);
            println!("{}", serde_json::to_string(&sel)?);
            Ok(0)
        }
    }
}
