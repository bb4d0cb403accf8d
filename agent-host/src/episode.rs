//! One episode of the stage-code loop (the paper's subtask-level closed loop): an
//! observation-only first turn, the task turn, then decisions — each a stage program run in the
//! sandbox against the live gym, its outcome fed back with fresh images — until the model stops
//! or the budget is spent. The native evaluator judges the episode afterwards; the model never
//! sees that verdict. Everything is recorded in the run folder as it happens.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use base64::Engine as _;
use serde::Serialize;
use serde_json::{json, Value};

use crate::llm::{Client, EndpointConfig, Message, Part, Role};
use crate::worker::{Budget, ExecResult, Limits, Worker, WorkerConfig};

/// How an episode's `stop_reason` begins when the LLM endpoint could not answer.
pub const ENDPOINT_FAILED: &str = "the LLM endpoint failed";

pub struct EpisodeConfig {
    pub gym: String,
    pub scene: PathBuf,
    pub root: PathBuf,
    pub endpoint: EndpointConfig,
    pub max_decisions: u32,
    pub control_steps: u64,
    pub limits: Limits,
    pub run_dir: PathBuf,
    pub lockstep: bool,
    pub robot_config: Option<PathBuf>,
    /// Where new memory records from the worker's `memory/` folder are appended.
    pub memory_dir: PathBuf,
    /// Chooses the skills for the system prompt's skills section from the first observation.
    pub skills: Option<Skills>,
    /// The gym's augmentation seed and placement perturbation (recorded in config.json).
    pub seed: u64,
    pub perturb: Option<String>,
}

/// What a skill library offers an episode: agent-host knows nothing of the library's format;
/// the `skills` crate implements this.
pub trait SkillSource: Send + Sync {
    /// Chooses skills for `task` given the episode's first observation (`first_obs`: the raw
    /// frames as a run record keeps them) and `state` (its numeric state). `prompt` goes into
    /// the system prompt, `log` into the run folder's skills.json and the viewer.
    fn choose(&self, task: &str, first_obs: &Path, state: &Value) -> anyhow::Result<ChosenSkills>;
}

pub struct ChosenSkills {
    pub prompt: String,
    pub log: Value,
    /// Files the stage programs may read, relative to the scratch folder (the skills' JSON).
    pub files: Vec<(String, Vec<u8>)>,
}

/// A shared [`SkillSource`].
#[derive(Clone)]
pub struct Skills(pub std::sync::Arc<dyn SkillSource>);

impl std::fmt::Debug for Skills {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Skills(..)")
    }
}

/// A model's structured decision.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct Decision {
    pub observation: String,
    pub plan: String,
    pub code: Option<String>,
    pub expected: String,
    pub stop: Option<String>,
}

fn tag(text: &str, name: &str) -> Option<String> {
    let open = format!("<{name}>");
    let close = format!("</{name}>");
    let start = text.find(&open)? + open.len();
    let end = text[start..].find(&close).map_or(text.len(), |e| start + e);
    Some(text[start..end].trim().to_string())
}

impl Decision {
    pub fn parse(text: &str) -> Self {
        let code = tag(text, "code").map(|c| {
            // Tolerate a Markdown fence inside the tag.
            let c = c.trim();
            let c = c.strip_prefix("```python").or_else(|| c.strip_prefix("```")).unwrap_or(c);
            c.strip_suffix("```").unwrap_or(c).trim().to_string()
        });
        Self {
            observation: tag(text, "observation").unwrap_or_default(),
            plan: tag(text, "plan").unwrap_or_default(),
            code: code.filter(|c| !c.is_empty()),
            expected: tag(text, "expected").unwrap_or_default(),
            stop: tag(text, "stop"),
        }
    }
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct EpisodeResult {
    pub success: bool,
    pub gym: String,
    pub responses: u32,
    pub tokens_in: u64,
    pub tokens_cached: u64,
    pub tokens_out: u64,
    pub tokens_reasoning: u64,
    pub wall_s: f64,
    pub model_s: f64,
    pub exec_s: f64,
    pub overhead_s: f64,
    /// Where `overhead_s` went (see [`HostSplit`]).
    pub host_split: HostSplit,
    pub executions: u32,
    pub violations: u32,
    pub stop_reason: String,
    /// Where the answers came from: "live" (an endpoint, recorded or not), "scripted" (a
    /// conversation written by us) or "replayed" (a cassette).
    pub llm_source: String,
    pub run_dir: String,
    pub evaluation: Value,
}

/// The host's own time in an episode, by what it did (s): starting the episode (reset, first
/// observation, prompts), starting and ending each program's proxy and confined worker,
/// observing after each program (state and PNG images through the proxy), writing the records,
/// and the rest (building messages and feedback, memory records).
#[derive(Debug, Clone, Default, Serialize)]
pub struct HostSplit {
    pub setup_s: f64,
    pub program_start_s: f64,
    pub observe_s: f64,
    pub records_s: f64,
    pub other_s: f64,
}

/// Runs `f`, adding its wall time to `acc`.
fn timed<T>(acc: &mut f64, f: impl FnOnce() -> T) -> T {
    let t = Instant::now();
    let r = f();
    *acc += t.elapsed().as_secs_f64();
    r
}

/// Writes a file whole or not at all (temporary name, then rename).
fn write_atomic(path: &Path, data: &[u8]) -> anyhow::Result<()> {
    let tmp = path.with_extension("partial");
    std::fs::write(&tmp, data)?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}

fn read_doc(root: &Path, rel: &str) -> String {
    std::fs::read_to_string(root.join("robot-skill").join(rel)).unwrap_or_else(|_| format!("({rel} is missing)"))
}

/// The system prompt: the agent-facing documents, the decision format and the skills section.
pub fn system_prompt(root: &Path, profile: &str, skills: &str) -> String {
    let profile_doc = if profile == "franka" { "api/FRANKA.md" } else { "api/SIMULATION.md" };
    let mut s = String::from(
        "You control a robot arm by writing Python stage programs. The documents below (from the \
         robot-skill folder) are your instructions; config/robot.json is at the end.\n\n",
    );
    for doc in ["SKILL.md", "api/README.md", profile_doc] {
        s.push_str(&format!("===== robot-skill/{doc} =====\n{}\n\n", read_doc(root, doc)));
    }
    s.push_str(&format!("===== robot-skill/config/robot.json =====\n{}\n\n", read_doc(root, "config/robot.json")));
    s.push_str(&format!(
        "===== Skills =====\n{}\n\n",
        if skills.is_empty() { "(no skills recorded yet)" } else { skills }
    ));
    s.push_str(DECISION_FORMAT);
    s
}

const DECISION_FORMAT: &str = "===== How to answer =====
Every reply is one decision in this form:
<observation>what the latest images and measured state show</observation>
<plan>what this stage does, its entry conditions and how you will know it worked</plan>
<code>
one complete Python program for this stage (it runs in a fresh process in a sandbox; the current
folder is a scratch folder kept for the whole episode; files you save there stay; print what you
need to verify; only `from robo import reset, get_state, post_actions`, numpy and the standard
library are available; no network)
</code>
<expected>the visible effect you expect once it ran</expected>
When the task is done (or cannot be done), reply with <observation>...</observation> and
<stop>why you stop</stop> instead of code. After each program you get its output, any error,
the measured state before and after, and fresh camera images.
";

fn state_line(s: &Value) -> String {
    let r = |v: &Value| -> String {
        v.as_array()
            .map(|a| a.iter().map(|x| format!("{:.4}", x.as_f64().unwrap_or(f64::NAN))).collect::<Vec<_>>().join(", "))
            .unwrap_or_default()
    };
    format!(
        "joint [{}]; ee_pose [{}]; gripper [{}]; external_force_n [{}]; timestamp {:.3}; control_type {}; fault {}",
        r(&s["joint"]),
        r(&s["ee_pose"]),
        r(&s["gripper"]),
        r(&s["external_force_n"]),
        s["timestamp"].as_f64().unwrap_or(0.0),
        s["control_type"],
        s["fault"],
    )
}

fn images(obs: &Value) -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = obs["images"]
        .as_object()
        .map(|m| {
            m.iter()
                .filter_map(|(k, v)| {
                    let b = base64::engine::general_purpose::STANDARD.decode(v.as_str()?).ok()?;
                    Some((k.clone(), b))
                })
                .collect()
        })
        .unwrap_or_default();
    out.sort();
    out
}

fn feedback_text(
    n: u32,
    r: &ExecResult,
    before: &Value,
    after: &Value,
    budget: u64,
    left: u32,
    lockstep: bool,
) -> String {
    // In lockstep the wall clock says nothing about the robot and would make each request
    // differ from run to run (a replayed cassette needs the same requests): simulated time.
    let took = if lockstep {
        let t = |s: &Value| s["state"]["timestamp"].as_f64().unwrap_or(0.0);
        format!("{:.3} s simulated", t(after) - t(before))
    } else {
        format!("{:.1} s", r.wall_s)
    };
    let mut t = format!(
        "Stage program {n} ended: {}{}; control steps used {} of {budget}; robot calls {}; {took}.\n",
        r.exit,
        r.exit_code.map(|c| format!(" (code {c})")).unwrap_or_default(),
        r.control_steps,
        r.robot_calls,
    );
    if let Some(v) = &r.violation {
        t.push_str(&format!("SANDBOX: {v}\n"));
    }
    if r.budget_refusals > 0 {
        t.push_str(&format!("{} robot call(s) were refused by the control-step budget.\n", r.budget_refusals));
    }
    for (name, body) in [("stdout", &r.stdout), ("stderr", &r.stderr)] {
        t.push_str(&format!("--- {name} ---\n{}\n", if body.is_empty() { "(empty)" } else { body.trim_end() }));
    }
    if let Some(e) = &r.exception {
        t.push_str(&format!("--- exception ---\n{}\n", e.trim_end()));
    }
    t.push_str(&format!(
        "State before: {}\nState after:  {}\n",
        state_line(&before["state"]),
        state_line(&after["state"])
    ));
    let fb = &after["state"]["control_feedback"];
    t.push_str(&format!("Last control_feedback: {} — {}\n", fb["status"], fb["reason"]));
    t.push_str(&format!("Fresh images after the program are attached. Decisions left: {left}.\n"));
    t
}

pub struct Recorder {
    pub dir: PathBuf,
    transcript: std::fs::File,
}

impl Recorder {
    pub fn new(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir.join("rounds"))?;
        let transcript = std::fs::OpenOptions::new().create(true).append(true).open(dir.join("transcript.jsonl"))?;
        Ok(Self { dir: dir.to_path_buf(), transcript })
    }

    /// Appends one round to the transcript, synced: a killed run keeps every finished round.
    pub fn round(&mut self, v: &Value) -> anyhow::Result<()> {
        writeln!(self.transcript, "{v}")?;
        self.transcript.sync_data()?;
        Ok(())
    }

    pub fn file(&self, rel: &str, data: &[u8]) -> anyhow::Result<String> {
        let p = self.dir.join(rel);
        if let Some(d) = p.parent() {
            std::fs::create_dir_all(d)?;
        }
        write_atomic(&p, data)?;
        Ok(rel.to_string())
    }
}

/// Keeps images only in the newest `keep` user messages (long episodes would otherwise pass
/// the endpoints' image and size limits); older ones become a short note.
fn prune_images(messages: &mut [Message], keep: usize) {
    let users: Vec<usize> = messages.iter().enumerate().filter(|(_, m)| m.role == Role::User).map(|(i, _)| i).collect();
    let cut = users.len().saturating_sub(keep);
    for &i in &users[..cut] {
        for p in messages[i].parts.iter_mut() {
            if matches!(p, Part::Png(_)) {
                *p = Part::Text("[an older camera image, no longer shown]".into());
            }
        }
    }
}

fn instruction(scene: &Path) -> anyhow::Result<String> {
    let t: toml::Table = toml::from_str(&std::fs::read_to_string(scene)?)?;
    t.get("task")
        .and_then(|t| t.get("instruction"))
        .and_then(|i| i.as_str())
        .map(str::to_string)
        .filter(|s| !s.is_empty())
        .context("the scene has no [task] instruction")
}

/// Runs one episode against a running instance; the caller owns the instance.
pub fn run(cfg: &EpisodeConfig, instance: &str) -> anyhow::Result<EpisodeResult> {
    let t0 = Instant::now();
    let task = instruction(&cfg.scene)?;
    let mut rec = Recorder::new(&cfg.run_dir)?;
    let client = Client::new(cfg.endpoint.clone())?;
    let scratch = cfg.run_dir.join("scratch");
    let mut worker = Worker::new(WorkerConfig {
        instance: instance.into(),
        scratch: scratch.clone(),
        log_dir: cfg.run_dir.join("logs"),
        root: cfg.root.clone(),
        limits: cfg.limits.clone(),
    });
    // A fresh scratch folder (a reused run folder may hold what an earlier program planted;
    // remove_dir_all follows no links), then earlier memory records as copies in `memory/`.
    if std::fs::symlink_metadata(&scratch).is_ok() {
        std::fs::remove_dir_all(&scratch).with_context(|| format!("clearing {}", scratch.display()))?;
    }
    std::fs::create_dir_all(&scratch)?;
    let mut records_taken = 0usize;
    crate::memory::seed(&scratch, &cfg.memory_dir)?;
    let reset = worker.host_cmd(json!({"cmd": "reset"}))?;
    if reset["ok"] != 1 {
        bail!("reset before the episode failed: {}", reset["feedback"]);
    }
    // Raw frames (RGB, depth, intrinsics, extrinsics) at each round boundary, for extraction.
    std::fs::create_dir_all(cfg.run_dir.join("rounds/000"))?;
    let raw_at = |round: u32| cfg.run_dir.join(format!("rounds/{round:03}/obs.npz")).display().to_string();
    let first = worker.host_cmd(json!({"cmd": "observe", "images": true, "raw": raw_at(0)}))?;
    let mut obs_before = "rounds/000/obs.npz".to_string();
    // The first program's processes start while the first prompt is built and answered (not
    // earlier: on two cores they would slow the reset and the first images).
    worker.prestart_next();
    let profile = first["state"]["backend"].as_str().unwrap_or("simulation").to_string();
    let skills_text = match &cfg.skills {
        Some(Skills(source)) => {
            let chosen = source.choose(&task, &cfg.run_dir.join("rounds/000/obs.npz"), &first["state"])?;
            rec.file("skills.json", &serde_json::to_vec_pretty(&chosen.log)?)?;
            for (rel, body) in &chosen.files {
                let p = scratch.join(rel);
                if let Some(d) = p.parent() {
                    std::fs::create_dir_all(d)?;
                }
                write_atomic(&p, body)?;
            }
            chosen.prompt
        }
        None => String::new(),
    };
    let system = system_prompt(&cfg.root, &profile, &skills_text);
    rec.file("system_prompt.md", system.as_bytes())?;
    rec.file(
        "config.json",
        serde_json::to_vec_pretty(&json!({
            "gym": cfg.gym, "scene": cfg.scene, "task": task, "endpoint": cfg.endpoint,
            "max_decisions": cfg.max_decisions, "control_steps": cfg.control_steps, "limits": cfg.limits,
            "lockstep": cfg.lockstep, "instance": instance, "sandbox": worker.enforced,
            "seed": cfg.seed, "perturb": cfg.perturb, "skills": cfg.skills.is_some(),
        }))?
        .as_slice(),
    )?;

    let mut out =
        EpisodeResult { gym: cfg.gym.clone(), run_dir: cfg.run_dir.display().to_string(), ..Default::default() };
    let mut messages: Vec<Message> = Vec::new();
    let mut parts = vec![Part::Text(format!(
        "First, observation only. Read your instructions (SKILL.md, api/README.md, the {profile} profile document \
         and config/robot.json above). This is what get_state() returns now, with both camera images attached:\n{}\n\
         Report the measured joints, TCP pose, gripper, what each camera shows, and the frame conventions and \
         limits that apply. Do not move the robot in this turn: reset() and post_actions() are refused. You may \
         include a <code> program that only observes. Then wait for the task.",
        state_line(&first["state"])
    ))];
    if let Some(Part::Text(t)) = parts.first() {
        rec.file("rounds/000/prompt.txt", t.as_bytes())?;
    }
    for (name, png) in images(&first) {
        rec.file(&format!("rounds/000/{name}.png"), &png)?;
        parts.push(Part::Png(png));
    }
    messages.push(Message { role: Role::User, parts });
    let mut split = HostSplit { setup_s: t0.elapsed().as_secs_f64(), ..HostSplit::default() };
    let mut before = first;
    let mut observe_only = true;
    let mut executions = 0u32;
    let stop_reason = loop {
        if out.responses >= cfg.max_decisions {
            break format!("decision budget of {} spent", cfg.max_decisions);
        }
        let round = out.responses + 1;
        prune_images(&mut messages, 6);
        let completion = match client.complete(&system, &messages) {
            Ok(c) => c,
            Err(e) => {
                rec.round(&json!({"round": round, "error": e.to_string()}))?;
                break format!("{ENDPOINT_FAILED}: {e}");
            }
        };
        out.responses += 1;
        out.model_s += completion.wall_s;
        out.tokens_in += completion.usage.input;
        out.tokens_cached += completion.usage.cached;
        out.tokens_out += completion.usage.output;
        out.tokens_reasoning += completion.usage.reasoning.unwrap_or(0);
        let dir = format!("rounds/{round:03}");
        timed(&mut split.records_s, || rec.file(&format!("{dir}/response.txt"), completion.text.as_bytes()))?;
        let decision = Decision::parse(&completion.text);
        messages.push(Message::text(Role::Assistant, completion.text.clone()));
        let mut record = json!({
            "round": round, "observe_only": observe_only, "decision": decision, "usage": completion.usage,
            "attempts": completion.attempts, "model_s": completion.wall_s,
        });
        if let Some(why) = &decision.stop {
            if !observe_only {
                timed(&mut split.records_s, || rec.round(&record))?;
                break why.clone();
            }
        }
        let mut text = String::new();
        let mut attach = Vec::new();
        match &decision.code {
            Some(code) => {
                executions += 1;
                timed(&mut split.records_s, || rec.file(&format!("{dir}/stage.py"), code.as_bytes()))?;
                let budget = Budget { control_steps: if observe_only { 0 } else { cfg.control_steps }, observe_only };
                let r = worker.run(code, &format!("stage-{executions}.py"), budget)?;
                out.exec_s += r.wall_s;
                split.program_start_s += r.host_s;
                out.violations += u32::from(r.violation.is_some());
                let after = timed(&mut split.observe_s, || {
                    worker.host_cmd(json!({"cmd": "observe", "images": true, "raw": raw_at(round)}))
                })?;
                timed(&mut split.records_s, || rec.file(&format!("{dir}/calls.json"), &serde_json::to_vec(&r.calls)?))?;
                let left = cfg.max_decisions.saturating_sub(out.responses);
                text = feedback_text(executions, &r, &before, &after, budget.control_steps, left, cfg.lockstep);
                for (name, png) in timed(&mut split.observe_s, || images(&after)) {
                    timed(&mut split.records_s, || rec.file(&format!("{dir}/{name}.png"), &png))?;
                    attach.push(Part::Png(png));
                }
                let memory = crate::memory::collect(&scratch, &cfg.memory_dir, &mut records_taken);
                record["exec"] = serde_json::to_value(&r)?;
                record["state_before"] = before["state"].clone();
                record["state_after"] = after["state"].clone();
                record["obs_before"] = json!(obs_before);
                record["obs_after"] = json!(format!("{dir}/obs.npz"));
                record["calls"] = json!(format!("{dir}/calls.json"));
                obs_before = format!("{dir}/obs.npz");
                record["memory_added"] = json!(memory);
                before = after;
            }
            None if decision.stop.is_none() => {
                text = "Your reply had neither a <code> program nor <stop>. Answer in the decision format.\n".into();
            }
            None => {}
        }
        if observe_only {
            text.push_str(&format!(
                "\nNow the task: \"{task}\". Keep the warm-up short and calibrate only what the task needs. Work \
                 stage by stage; each reply is one decision with one program. Reply with <stop> when done."
            ));
            observe_only = false;
        }
        record["feedback"] = json!(text);
        timed(&mut split.records_s, || {
            rec.file(&format!("{dir}/feedback.txt"), text.as_bytes())?;
            rec.round(&record)
        })?;
        let mut parts = vec![Part::Text(text)];
        parts.extend(attach);
        messages.push(Message { role: Role::User, parts });
    };
    drop(worker);
    out.executions = executions;
    out.stop_reason = stop_reason;
    out.wall_s = t0.elapsed().as_secs_f64();
    out.overhead_s = (out.wall_s - out.model_s - out.exec_s).max(0.0);
    split.other_s =
        (out.overhead_s - split.setup_s - split.program_start_s - split.observe_s - split.records_s).max(0.0);
    out.host_split = split;
    Ok(out)
}

/// The evaluation files sim-host has written into `trace_dir` so far.
fn verdict_files(trace_dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(trace_dir)
        .map(|d| d.flatten().map(|e| e.path()).filter(|p| p.to_string_lossy().ends_with(".eval.json")).collect())
        .unwrap_or_default()
}

/// How many episodes of `trace_dir` have been judged so far (pass it to `newest_verdict` as
/// `after` to wait for the next verdict, never an earlier one).
pub fn verdict_count(trace_dir: &Path) -> usize {
    verdict_files(trace_dir).len()
}

/// The verdict sim-host wrote for the newest episode in `trace_dir`, once more than `after`
/// exist, waiting up to `wait`.
pub fn newest_verdict(trace_dir: &Path, after: usize, wait: Duration) -> anyhow::Result<Value> {
    let t0 = Instant::now();
    loop {
        let mut evals = verdict_files(trace_dir);
        if evals.len() > after {
            evals.sort_by_key(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .and_then(|n| n.trim_start_matches("episode-").split('.').next().map(str::to_string))
                    .and_then(|n| n.parse::<u64>().ok())
                    .unwrap_or(0)
            });
            let p = evals.last().context("an evaluation")?;
            return Ok(serde_json::from_str(&std::fs::read_to_string(p)?)?);
        }
        if t0.elapsed() > wait {
            bail!("no verdict appeared in {}", trace_dir.display());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}
