//! `r2g skills run`: a skill's procedure executed in the sandbox with no model at all — one
//! stage program (`robo_skills.run_skill`) binds the rules to the objects seen now, moves,
//! checks effects and retries — then natively judged like an episode. It costs no tokens.

use std::path::{Path, PathBuf};
use std::time::Instant;

use agent_host::session::{self, GymRun, GymSetup};
use agent_host::worker::{Budget, Limits, Worker, WorkerConfig};
use anyhow::Context;
use serde::Serialize;
use serde_json::{json, Value};

use crate::format::Skill;

#[derive(Debug, Clone)]
pub struct RunOpts {
    pub gym: String,
    pub setup: GymSetup,
    /// Run folder (default runs/skills/<gym>-<stamp>).
    pub out: Option<PathBuf>,
    /// Waypoints the program may post in all.
    pub control_steps: u64,
    pub wall_s: f64,
    /// Baseline only: rule id → a fixed TCP pose to play instead of binding the rule.
    pub absolute: Option<Value>,
    /// An admission run: the skill is a candidate by design (not warned about).
    pub admission: bool,
}

impl RunOpts {
    pub fn new(gym: &str, setup: GymSetup) -> Self {
        Self { gym: gym.into(), setup, out: None, control_steps: 4000, wall_s: 300.0, absolute: None, admission: false }
    }
}

/// Ends like `r2g episode`: one JSON line of this.
#[derive(Debug, Clone, Serialize)]
pub struct RunResult {
    pub success: bool,
    pub gym: String,
    pub skill: String,
    pub version: u32,
    pub seed: u64,
    pub perturb: Option<String>,
    /// A model-free run: always 0.
    pub responses: u32,
    pub tokens_in: u64,
    pub tokens_out: u64,
    pub wall_s: f64,
    pub exec_s: f64,
    /// The procedure's own account: stages, attempts, the reason it stopped.
    pub procedure: Value,
    pub stop_reason: String,
    pub run_dir: String,
    pub evaluation: Value,
    /// The skill's status when it ran (a candidate is not yet admitted).
    pub status: String,
    /// What makes this run's figures weaker: a skill not yet validated, one learned on another
    /// robot (fingerprint differs), a skill file outside any library.
    pub warnings: Vec<String>,
}

const PROGRAM: &str = r#"import json
import robo_skills

with open("skill.json") as f:
    skill = json.load(f)
absolute = None
try:
    with open("absolute.json") as f:
        absolute = json.load(f)
except FileNotFoundError:
    pass
robo_skills.run_skill(skill, absolute=absolute)
"#;

/// A short name for a gym given by name, folder or scene file (`gyms/x/scene.toml` → `x`).
fn gym_name(gym: &str) -> String {
    let p = Path::new(gym);
    let name = if p.file_name().is_some_and(|f| f == "scene.toml") {
        p.parent().and_then(Path::file_name)
    } else {
        p.file_stem()
    };
    name.map_or_else(|| gym.replace('/', "_"), |n| n.to_string_lossy().into_owned())
}

/// What makes a run of `skill` on `o`'s gym weaker than a validated skill on its own robot.
pub fn warnings(skill: &Skill, o: &RunOpts) -> Vec<String> {
    let mut w = Vec::new();
    if skill.status != crate::format::Status::Validated && !o.admission {
        w.push(format!(
            "{} v{} is {:?}, not validated: admission has not confirmed it",
            skill.id, skill.version, skill.status
        ));
    }
    let rc = o.setup.robot_config.clone().unwrap_or_else(runtime::launch::default_robot_config);
    match runtime::launch::resolve_scene(&o.gym).and_then(|scene| crate::fingerprint::of(&scene, &rc)) {
        Ok(fp) if fp != skill.applicability.fingerprint => w.push(format!(
            "{} was learned on another robot (fingerprint {}/{}/{}, this gym's {}/{}/{}): its motions may not mean the same here",
            skill.id,
            skill.applicability.fingerprint.gripper,
            skill.applicability.fingerprint.profile,
            &skill.applicability.fingerprint.kinematics.get(..12).unwrap_or(""),
            fp.gripper,
            fp.profile,
            fp.kinematics.get(..12).unwrap_or(""),
        )),
        Ok(_) => {}
        Err(e) => w.push(format!("this gym's robot fingerprint could not be computed: {e:#}")),
    }
    w
}

pub fn run(skill: &Skill, o: &RunOpts) -> anyhow::Result<RunResult> {
    let t0 = Instant::now();
    let warnings = warnings(skill, o);
    for w in &warnings {
        eprintln!("r2g skills run: warning: {w}");
    }
    let root = session::root();
    let run_dir = session::run_folder(o.out.as_deref(), "skills", &format!("{}-{}", skill.id, gym_name(&o.gym)))?;
    let scratch = run_dir.join("scratch");
    std::fs::create_dir_all(&scratch)?;
    std::fs::write(scratch.join("skill.json"), serde_json::to_vec_pretty(skill)?)?;
    std::fs::write(run_dir.join("skill.json"), serde_json::to_vec_pretty(skill)?)?;
    if let Some(a) = &o.absolute {
        std::fs::write(scratch.join("absolute.json"), serde_json::to_vec(a)?)?;
    }
    std::fs::write(run_dir.join("program.py"), PROGRAM)?;
    let gym = GymRun::start(&o.gym, &run_dir, &o.setup)?;
    let limits = Limits { wall_s: o.wall_s, cpu_s: o.wall_s.ceil() as u64, ..Default::default() };
    let mut wc = WorkerConfig::new(&gym.instance, &scratch, &run_dir.join("logs"), &root, limits);
    wc.robot_config.clone_from(&o.setup.robot_config);
    let mut worker = Worker::new(wc);
    let outcome = (|| -> anyhow::Result<_> {
        let reset = worker.host_cmd(json!({"cmd": "reset"}))?;
        if reset["ok"] != 1 {
            anyhow::bail!("reset before the run failed: {}", reset["feedback"]);
        }
        worker.run(PROGRAM, "skill_run.py", Budget { control_steps: o.control_steps, observe_only: false })
    })();
    drop(worker);
    let evaluation = gym.finish();
    let exec = outcome?;
    let evaluation = evaluation?;
    std::fs::write(run_dir.join("output.txt"), format!("{}\n--- stderr ---\n{}", exec.stdout, exec.stderr))?;
    let procedure = exec
        .stdout
        .lines()
        .rev()
        .find_map(|l| l.strip_prefix("SKILL RESULT "))
        .and_then(|j| serde_json::from_str::<Value>(j).ok())
        .unwrap_or(Value::Null);
    let stop_reason = if procedure.is_null() {
        format!(
            "the program ended without a result ({}{}): {}",
            exec.exit,
            exec.violation.as_deref().map(|v| format!(", {v}")).unwrap_or_default(),
            exec.exception
                .as_deref()
                .or(Some(exec.stderr.as_str()))
                .map(|e| e.lines().last().unwrap_or_default().to_string())
                .unwrap_or_default()
        )
    } else {
        procedure["reason"].as_str().map_or_else(|| "the procedure ran to its end".to_string(), str::to_string)
    };
    let r = RunResult {
        success: evaluation["success"].as_bool().unwrap_or(false),
        gym: o.gym.clone(),
        skill: skill.id.clone(),
        version: skill.version,
        seed: o.setup.seed,
        perturb: o.setup.perturb.clone(),
        responses: 0,
        tokens_in: 0,
        tokens_out: 0,
        wall_s: t0.elapsed().as_secs_f64(),
        exec_s: exec.wall_s,
        procedure,
        stop_reason,
        run_dir: run_dir.display().to_string(),
        evaluation,
        status: format!("{:?}", skill.status).to_lowercase(),
        warnings,
    };
    let tmp = run_dir.join("result.json.partial");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&r)?)?;
    std::fs::rename(&tmp, run_dir.join("result.json")).context("writing result.json")?;
    Ok(r)
}

/// The fixed targets of a skill's source rounds, as recorded (for the absolute-replay baseline):
/// rule id → the pose that round sent, read again from its record (`skill_tools.py targets`).
pub fn recorded_targets(root: &Path, skill: &Skill) -> anyhow::Result<Value> {
    let mut out = serde_json::Map::new();
    for stage in &skill.procedure {
        let Some(src) = stage.source.as_deref() else { continue };
        let (targets, _) = crate::admit::source_targets(root, skill, stage, src)?;
        for (k, v) in targets {
            out.insert(k, json!(v));
        }
    }
    Ok(Value::Object(out))
}
