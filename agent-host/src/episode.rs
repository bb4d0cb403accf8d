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
use crate::prompt;
use crate::worker::{Budget, Limits, Worker, WorkerConfig};

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
    /// Tags opened and never closed (each taken to the end of the reply).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub unclosed: Vec<String>,
}

impl Decision {
    pub fn parse(text: &str) -> Self {
        let mut unclosed = Vec::new();
        let mut tag = |name: &str| -> Option<String> {
            let open = format!("<{name}>");
            let start = text.find(&open)? + open.len();
            let end = match text[start..].find(&format!("</{name}>")) {
                Some(e) => start + e,
                None => {
                    unclosed.push(name.to_string());
                    text.len()
                }
            };
            Some(text[start..end].trim().to_string())
        };
        let code = tag("code").map(|c| {
            // Tolerate a Markdown fence inside the tag.
            let c = c.trim();
            let c = c.strip_prefix("```python").or_else(|| c.strip_prefix("```")).unwrap_or(c);
            c.strip_suffix("```").unwrap_or(c).trim().to_string()
        });
        let (observation, plan, expected, stop) = (tag("observation"), tag("plan"), tag("expected"), tag("stop"));
        Self {
            observation: observation.unwrap_or_default(),
            plan: plan.unwrap_or_default(),
            code: code.filter(|c| !c.is_empty()),
            expected: expected.unwrap_or_default(),
            stop,
            unclosed,
        }
    }

    /// Why the reply cannot be used as it is: the endpoint cut it off at its token limit
    /// (`truncated`), so an unclosed tag holds a partial program or report. `None`: usable (an
    /// unclosed tag in a reply that ended by itself runs to the end of the reply).
    pub fn problem(&self, truncated: bool) -> Option<String> {
        truncated.then(|| match self.unclosed.as_slice() {
            [] => "the endpoint cut your reply off at its token limit".to_string(),
            tags => format!("the endpoint cut your reply off at its token limit, inside <{}>", tags.join(">, <")),
        })
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
    /// Offline estimates (characters / 4, 765 per image), labelled as such: the input tokens of
    /// every request, and the part of each request's prefix it shares with the one before (what
    /// a provider's prompt cache could serve). For comparisons where the endpoint reports no
    /// cache counts (`tokens_cached` is the provider's own count).
    pub tokens_in_estimated: u64,
    pub tokens_cached_estimated: u64,
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

/// Keeps images only in the newest user messages (long episodes would otherwise pass the
/// endpoints' image and size limits); older ones become a short note. The cut moves `step`
/// messages at a time, so the conversation before it stays the same for `step` requests and a
/// provider's prompt cache keeps serving it (a cut moving every request would end the cached
/// prefix at the first message): between `keep` and `keep + step - 1` messages keep theirs.
fn prune_images(messages: &mut [Message], keep: usize, step: usize) {
    let users: Vec<usize> = messages.iter().enumerate().filter(|(_, m)| m.role == Role::User).map(|(i, _)| i).collect();
    let over = users.len().saturating_sub(keep);
    let cut = over - over % step.max(1);
    for &i in &users[..cut] {
        for p in messages[i].parts.iter_mut() {
            if matches!(p, Part::Png(_)) {
                *p = Part::Text("[an older image, no longer shown]".into());
            }
        }
    }
}

/// Keeps the images a program showed (those after a message's camera images) in the newest
/// user message only: the model has seen them once, and they are the largest and most numerous
/// (bounding every request's size). `cameras_of`: (message index, camera images in it).
fn prune_shown(messages: &mut [Message], cameras_of: &[(usize, usize)]) {
    let newest = messages.iter().rposition(|m| m.role == Role::User);
    for &(i, cameras) in cameras_of {
        if Some(i) == newest {
            continue;
        }
        let Some(m) = messages.get_mut(i) else { continue };
        let mut seen = 0;
        for p in m.parts.iter_mut() {
            if matches!(p, Part::Png(_)) {
                seen += 1;
                if seen > cameras {
                    *p = Part::Text("[an image the program showed, no longer shown]".into());
                }
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

/// Images a program may hand over per run (`show/` in its scratch folder), their largest side
/// in pixels and their largest file size.
pub const MAX_SHOWN: usize = 4;
pub const MAX_SHOWN_SIDE: u32 = 1280;
pub const MAX_SHOWN_BYTES: u64 = 2 << 20;

/// Takes the images a program left in `<scratch>/show/` (`robo_perception.show`): at most
/// [`MAX_SHOWN`] PNG files, by name, each decoded and written again as 8-bit PNG (so an endpoint
/// never sees a file it might refuse), within [`MAX_SHOWN_SIDE`] and [`MAX_SHOWN_BYTES`]. What
/// is refused is named with the reason. The folder is emptied for the next program; no link in
/// it is followed.
pub fn take_shown(scratch: &Path) -> Vec<(prompt::Shown, Option<Vec<u8>>)> {
    use std::io::Read as _;
    use std::os::unix::fs::OpenOptionsExt as _;
    let dir = scratch.join("show");
    let mut out = Vec::new();
    if !std::fs::symlink_metadata(&dir).is_ok_and(|m| m.is_dir()) {
        let _ = std::fs::remove_file(&dir);
        return out;
    }
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .map(|rd| rd.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect())
        .unwrap_or_default();
    names.sort();
    let refuse = |name: &str, why: String| (prompt::Shown::Refused { name: format!("show/{name}"), why }, None);
    let mut taken = 0;
    // Names starting with '.' are files being written (robo_perception's save_png renames them).
    for name in names.iter().filter(|n| !n.starts_with('.')) {
        if taken == MAX_SHOWN {
            out.push(refuse(name, format!("at most {MAX_SHOWN} images are shown per program")));
            continue;
        }
        let file = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
            .open(dir.join(name));
        let Ok(mut file) = file else {
            out.push(refuse(name, "not a regular file".into()));
            continue;
        };
        match file.metadata() {
            Ok(m) if m.is_file() && m.len() <= MAX_SHOWN_BYTES => {}
            Ok(m) if m.is_file() => {
                out.push(refuse(name, format!("{} bytes, more than {MAX_SHOWN_BYTES}", m.len())));
                continue;
            }
            _ => {
                out.push(refuse(name, "not a regular file".into()));
                continue;
            }
        }
        let mut bytes = Vec::new();
        if (&mut file).take(MAX_SHOWN_BYTES).read_to_end(&mut bytes).is_err() {
            out.push(refuse(name, "could not be read".into()));
            continue;
        }
        match normalise_png(&bytes) {
            Ok((png, width, height)) => {
                taken += 1;
                out.push((prompt::Shown::Image { name: format!("show/{name}"), width, height }, Some(png)));
            }
            Err(why) => out.push(refuse(name, why)),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    out
}

/// A PNG file decoded and encoded again as 8-bit RGB(A); its size. Refuses what is no PNG or is
/// larger than [`MAX_SHOWN_SIDE`] on a side.
fn normalise_png(bytes: &[u8]) -> Result<(Vec<u8>, u32, u32), String> {
    let mut d = png::Decoder::new(std::io::Cursor::new(bytes));
    d.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut r = d.read_info().map_err(|e| format!("not a PNG image ({e})"))?;
    let (w, h) = (r.info().width, r.info().height);
    if w > MAX_SHOWN_SIDE || h > MAX_SHOWN_SIDE {
        return Err(format!("{w}x{h} pixels, more than {MAX_SHOWN_SIDE} on a side"));
    }
    let mut buf = vec![0; r.output_buffer_size().ok_or("an image too large to decode")?];
    let frame = r.next_frame(&mut buf).map_err(|e| format!("not a whole PNG image ({e})"))?;
    let (color, data) = match frame.color_type {
        png::ColorType::Rgb => (png::ColorType::Rgb, buf[..frame.buffer_size()].to_vec()),
        png::ColorType::Rgba => (png::ColorType::Rgba, buf[..frame.buffer_size()].to_vec()),
        png::ColorType::Grayscale => {
            (png::ColorType::Rgb, buf[..frame.buffer_size()].iter().flat_map(|&g| [g, g, g]).collect())
        }
        png::ColorType::GrayscaleAlpha => (
            png::ColorType::Rgba,
            buf[..frame.buffer_size()].chunks_exact(2).flat_map(|p| [p[0], p[0], p[0], p[1]]).collect(),
        ),
        png::ColorType::Indexed => return Err("a palette PNG that did not expand".into()),
    };
    let mut out = Vec::new();
    {
        let mut e = png::Encoder::new(&mut out, w, h);
        e.set_color(color);
        e.set_depth(png::BitDepth::Eight);
        let mut wr = e.write_header().map_err(|e| e.to_string())?;
        wr.write_image_data(&data).map_err(|e| e.to_string())?;
    }
    if out.len() as u64 > MAX_SHOWN_BYTES {
        return Err(format!("{} bytes as a PNG, more than {MAX_SHOWN_BYTES}: crop it", out.len()));
    }
    Ok((out, w, h))
}

/// The text of the robot configuration file in force (what `robot-skill/config/robot.json`
/// shows the programs).
fn robot_config_text(cfg: &EpisodeConfig) -> String {
    // The same file GymRun starts the instance with when none is given.
    let p = cfg.robot_config.clone().unwrap_or_else(runtime::launch::default_robot_config);
    std::fs::read_to_string(&p).unwrap_or_else(|e| format!("({} could not be read: {e})", p.display()))
}

/// Runs one episode against a running instance; the caller owns the instance.
pub fn run(cfg: &EpisodeConfig, instance: &str) -> anyhow::Result<EpisodeResult> {
    let t0 = Instant::now();
    let task = instruction(&cfg.scene)?;
    let mut rec = Recorder::new(&cfg.run_dir)?;
    let client = Client::new(cfg.endpoint.clone())?;
    let scratch = cfg.run_dir.join("scratch");
    let mut wc = WorkerConfig::new(instance, &scratch, &cfg.run_dir.join("logs"), &cfg.root, cfg.limits.clone());
    wc.view_dir = cfg.run_dir.join("view");
    wc.memory_dir = Some(cfg.memory_dir.clone());
    wc.robot_config = cfg.robot_config.clone();
    let mut worker = Worker::new(wc);
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
    let system = prompt::system_prompt(&cfg.root, &profile, &robot_config_text(cfg), &skills_text);
    rec.file("system_prompt.md", system.as_bytes())?;
    rec.file(
        "config.json",
        serde_json::to_vec_pretty(&json!({
            "gym": cfg.gym, "scene": cfg.scene, "task": task, "endpoint": cfg.endpoint,
            "max_decisions": cfg.max_decisions, "control_steps": cfg.control_steps, "limits": cfg.limits,
            "lockstep": cfg.lockstep, "instance": instance, "sandbox": worker.enforced,
            "seed": cfg.seed, "perturb": cfg.perturb, "skills": cfg.skills.is_some(),
            "robot_config": cfg.robot_config, "memory": cfg.memory_dir,
        }))?
        .as_slice(),
    )?;

    let mut out =
        EpisodeResult { gym: cfg.gym.clone(), run_dir: cfg.run_dir.display().to_string(), ..Default::default() };
    let mut messages: Vec<Message> = Vec::new();
    let task_budget = Budget { control_steps: cfg.control_steps, observe_only: false };
    let fingerprint = prompt::memory_fingerprint(&first["state"]);
    let facts = prompt::RunFacts {
        profile: &profile,
        max_decisions: cfg.max_decisions,
        budget: task_budget,
        limits: &cfg.limits,
        memory: prompt::memory_counts(Some(&cfg.memory_dir), &fingerprint),
    };
    let first_images = images(&first);
    let cameras: Vec<String> = first_images.iter().map(|(n, _)| n.clone()).collect();
    let first_text = prompt::first_message(&first["state"], &facts, &cameras);
    rec.file("rounds/000/prompt.txt", first_text.as_bytes())?;
    let mut parts = vec![Part::Text(first_text)];
    for (name, png) in first_images {
        rec.file(&format!("rounds/000/{name}.png"), &png)?;
        parts.push(Part::Png(png));
    }
    messages.push(Message { role: Role::User, parts });
    let mut split = HostSplit { setup_s: t0.elapsed().as_secs_f64(), ..HostSplit::default() };
    let mut before = first;
    let mut observe_only = true;
    let mut executions = 0u32;
    let mut estimate = crate::tokens::PrefixEstimate::default();
    // (message index, its camera images): the images after them in a message are the ones its
    // program showed, kept in the newest message only ([`prune_shown`]).
    let mut cameras_of: Vec<(usize, usize)> = Vec::new();
    let stop_reason = loop {
        if out.responses >= cfg.max_decisions {
            break format!("decision budget of {} spent", cfg.max_decisions);
        }
        let round = out.responses + 1;
        prune_shown(&mut messages, &cameras_of);
        prune_images(&mut messages, 6, 3);
        let est = estimate.next(&system, &messages);
        out.tokens_in_estimated += est.input;
        out.tokens_cached_estimated += est.shared_prefix;
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
        let problem = decision.problem(completion.truncated);
        messages.push(Message::text(Role::Assistant, completion.text.clone()));
        let mut record = json!({
            "round": round, "observe_only": observe_only, "decision": decision, "usage": completion.usage,
            "estimate": est, "attempts": completion.attempts, "model_s": completion.wall_s,
            "truncated": completion.truncated,
        });
        if let (Some(why), None) = (&decision.stop, &problem) {
            if !observe_only {
                timed(&mut split.records_s, || rec.round(&record))?;
                break why.clone();
            }
        }
        let mut text = String::new();
        let mut attach = Vec::new();
        let mut camera_count = 0;
        match (&decision.code, &problem) {
            (_, Some(problem)) => {
                text = format!(
                    "Your reply could not be used: {problem} (at most {} tokens per reply). Nothing ran. Send the \
                     decision again, whole and shorter (a program can import a module an earlier program saved).\n",
                    cfg.endpoint.max_tokens
                );
            }
            (Some(code), None) => {
                executions += 1;
                timed(&mut split.records_s, || rec.file(&format!("{dir}/stage.py"), code.as_bytes()))?;
                let budget = if observe_only { Budget { control_steps: 0, observe_only: true } } else { task_budget };
                let r = worker.run(code, &format!("stage-{executions}.py"), budget)?;
                out.exec_s += r.wall_s;
                split.program_start_s += r.host_s;
                out.violations += u32::from(r.violation.is_some());
                let after = timed(&mut split.observe_s, || {
                    worker.host_cmd(json!({"cmd": "observe", "images": true, "raw": raw_at(round)}))
                })?;
                timed(&mut split.records_s, || rec.file(&format!("{dir}/calls.json"), &serde_json::to_vec(&r.calls)?))?;
                let shown = take_shown(&scratch);
                let mut shown_files = Vec::new();
                let camera_images = timed(&mut split.observe_s, || images(&after));
                let cameras: Vec<String> = camera_images.iter().map(|(n, _)| n.clone()).collect();
                camera_count = camera_images.len();
                for (name, png) in camera_images {
                    timed(&mut split.records_s, || rec.file(&format!("{dir}/{name}.png"), &png))?;
                    attach.push(Part::Png(png));
                }
                let mut shown_now: Vec<prompt::Shown> = Vec::new();
                for (s, png) in shown {
                    let (Some(png), prompt::Shown::Image { name, .. }) = (png, &s) else {
                        shown_now.push(s);
                        continue;
                    };
                    // Recorded under a name of ours: the program's may be anything a file may be called.
                    let file = format!("{dir}/shown/{}.png", shown_files.len() + 1);
                    let recorded: anyhow::Result<String> = timed(&mut split.records_s, || rec.file(&file, &png));
                    match recorded {
                        Ok(_) => {
                            shown_files.push(json!({"file": file, "name": name}));
                            attach.push(Part::Png(png));
                            shown_now.push(s);
                        }
                        Err(e) => {
                            let why = format!("could not be recorded ({e})");
                            shown_now.push(prompt::Shown::Refused { name: name.clone(), why });
                        }
                    }
                }
                let shown = shown_now;
                let left = cfg.max_decisions.saturating_sub(out.responses);
                text = prompt::feedback_text(&prompt::Feedback {
                    n: executions,
                    result: &r,
                    before: &before,
                    after: &after,
                    budget,
                    decisions_left: left,
                    max_decisions: cfg.max_decisions,
                    lockstep: cfg.lockstep,
                    shown: &shown,
                    cameras: &cameras,
                });
                let memory = crate::memory::collect(&scratch, &cfg.memory_dir, &mut records_taken);
                worker.refresh_view()?;
                record["exec"] = serde_json::to_value(&r)?;
                record["state_before"] = before["state"].clone();
                record["state_after"] = after["state"].clone();
                record["obs_before"] = json!(obs_before);
                record["obs_after"] = json!(format!("{dir}/obs.npz"));
                record["calls"] = json!(format!("{dir}/calls.json"));
                record["shown"] = json!(shown_files);
                obs_before = format!("{dir}/obs.npz");
                record["memory_added"] = json!(memory);
                before = after;
            }
            (None, None) if decision.stop.is_none() => {
                text = "Your reply had neither a <code> program nor <stop>. Answer in the decision format.\n".into();
            }
            (None, None) => {}
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
        cameras_of.push((messages.len(), camera_count));
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

#[cfg(test)]
mod tests {
    use super::*;

    fn encode(w: u32, h: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut e = png::Encoder::new(&mut out, w, h);
            e.set_color(color);
            e.set_depth(depth);
            e.write_header().expect("header").write_image_data(data).expect("data");
        }
        out
    }

    #[test]
    fn shown_images_are_written_again_as_8_bit_and_oversized_or_broken_ones_refused() {
        // 16-bit grey comes back 8-bit RGB of the same size.
        let grey16 = encode(3, 2, png::ColorType::Grayscale, png::BitDepth::Sixteen, &[0x80; 12]);
        let (png, w, h) = normalise_png(&grey16).expect("a PNG");
        assert_eq!((w, h), (3, 2));
        let info = png::Decoder::new(std::io::Cursor::new(&png)).read_info().expect("decodes").info().clone();
        assert_eq!((info.color_type, info.bit_depth), (png::ColorType::Rgb, png::BitDepth::Eight));
        let big = encode(MAX_SHOWN_SIDE + 1, 1, png::ColorType::Grayscale, png::BitDepth::Eight, &[0; 1281]);
        assert!(normalise_png(&big).unwrap_err().contains("1281x1 pixels"));
        assert!(normalise_png(b"\x89PNG\r\n\x1a\nnot really").unwrap_err().starts_with("not a PNG"));
        let cut = &grey16[..grey16.len() - 20];
        assert!(normalise_png(cut).is_err(), "a file cut short is refused");
    }

    #[test]
    fn a_reply_ending_inside_a_tag_runs_only_when_the_model_ended_it() {
        let d = Decision::parse("<observation>o</observation><code>\nprint(1)\n");
        assert_eq!((d.code.as_deref(), d.unclosed.as_slice()), (Some("print(1)"), &["code".to_string()][..]));
        assert!(d.problem(false).is_none());
        assert!(d.problem(true).is_some_and(|p| p.contains("inside <code>")));
    }
}
