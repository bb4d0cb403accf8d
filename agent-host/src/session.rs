//! Whole runs of the agent host (`r2g episode`, `r2g batch`, `r2g exec`): the stage-code loop
//! against a gym instance started here, with a configured LLM endpoint or the scripted one
//! (`scripted`: a recorded conversation served on loopback), a live endpoint whose answers are
//! recorded (`record:`) or a cassette replayed without a network (`replay:`), judged afterwards
//! by the native evaluator; and one program in the sandbox against a running instance.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use crate::cassette::{CassetteMode, CassetteSpec};
use crate::episode::{self, EpisodeConfig, EpisodeResult};
use crate::llm::EndpointConfig;
use anyhow::{bail, Context};
use ipc_schema::Mode;
use runtime::launch::{self, Instance, UpOptions};
use serde_json::{json, Value};

/// What one episode runs; `r2g episode` fills it from its arguments.
#[derive(Debug, Clone)]
pub struct EpisodeOpts {
    /// Gym name (see `r2g gyms`), gym folder, or scene file.
    pub gym: String,
    /// An endpoint TOML file (provider, base_url, model, api_key_env, ...), "scripted" (the
    /// gym's recorded conversation), "scripted:<conversation.json | cassette.jsonl>",
    /// "record:<endpoint.toml>" (answers recorded to `<run>/cassette.jsonl`) or
    /// "replay:<cassette.jsonl>".
    pub llm: String,
    /// Wire format for `--llm scripted`: openai or anthropic.
    pub provider: String,
    pub max_decisions: u32,
    /// Waypoints one program may post.
    pub control_steps: u64,
    /// Run the gym in wall-clock time instead of lockstep.
    pub wall: bool,
    /// Run folder (default: runs/episodes/<gym>-<stamp>; for a batch, its folder).
    pub out: Option<PathBuf>,
    pub robot_config: Option<PathBuf>,
    /// Wall-clock limit per program, s.
    pub wall_s: f64,
    /// Folder of append-only memory records (default: robot-skill/memory).
    pub memory: Option<PathBuf>,
    /// Augmentation seed of the gym (0: as written); a batch gives episode i `seed + i` when
    /// it is not 0.
    pub seed: u64,
    /// Placement perturbation drawn from the seed, as r2g-sim's `--perturb` takes it
    /// (sim_host::placement; `r2g` parses it before it gets here).
    pub perturb: Option<String>,
    /// Chooses skills for the episode's prompt (the `skills` crate's selection); None: none.
    pub skills: Option<crate::episode::Skills>,
    /// The skill library `skills` selects from, for episodes run as separate processes
    /// (`--skills use --library DIR`).
    pub library: Option<PathBuf>,
}

impl EpisodeOpts {
    /// An episode of `gym` answered by `llm` with the command line's defaults (50 decisions,
    /// 600 control steps, lockstep, 120 s per program, seed 0, nothing else).
    pub fn new(gym: &str, llm: &str) -> Self {
        Self {
            gym: gym.into(),
            llm: llm.into(),
            provider: "openai".into(),
            max_decisions: 50,
            control_steps: 600,
            wall: false,
            out: None,
            robot_config: None,
            wall_s: 120.0,
            memory: None,
            seed: 0,
            perturb: None,
            skills: None,
            library: None,
        }
    }
}

/// The repo's scripted LLM server, replaying a recorded conversation; stopped on drop.
pub struct Scripted {
    child: Child,
    pub port: u16,
}

impl Scripted {
    pub fn start(root: &Path, gym: &str, script: Option<&Path>, log: Option<&Path>) -> anyhow::Result<Self> {
        let script =
            script.map_or_else(|| root.join("agent-host/scripted").join(format!("{gym}.json")), Path::to_path_buf);
        if !script.is_file() {
            bail!("no scripted conversation for gym '{gym}' ({} is missing)", script.display());
        }
        let mut cmd = Command::new(root.join(".venv/bin/python"));
        cmd.arg(root.join("agent-host/py/scripted_llm.py")).arg("--script").arg(&script).args(["--port", "0"]);
        if let Some(l) = log {
            cmd.arg("--log").arg(l);
        }
        // SAFETY: prctl in the child before exec; async-signal-safe.
        unsafe {
            use std::os::unix::process::CommandExt;
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM, 0, 0, 0);
                Ok(())
            });
        }
        let mut child = cmd.stdout(Stdio::piped()).stdin(Stdio::null()).spawn().context("starting the scripted LLM")?;
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().context("stdout")?).read_line(&mut line)?;
        let port = line.trim().strip_prefix("LISTENING ").and_then(|p| p.parse().ok());
        match port {
            Some(port) => Ok(Self { child, port }),
            None => {
                let _ = child.kill();
                let _ = child.wait();
                bail!("the scripted LLM did not start: {line:?}")
            }
        }
    }
}

impl Drop for Scripted {
    fn drop(&mut self) {
        // SAFETY: signals our own child by pid.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let _ = self.child.wait();
    }
}

/// The checkout the binaries run from (its `gyms/`, `.venv/`, `agent-host/`, `robot-skill/`).
pub fn root() -> PathBuf {
    launch::gyms_dir().parent().map(Path::to_path_buf).unwrap_or_default()
}

/// An LLM endpoint for a run and what answers it (`live`, `scripted`, `replayed`): a TOML file;
/// `record:<toml>` (that endpoint, every exchange kept in `<run_dir>/cassette.jsonl`);
/// `replay:<cassette>` (answers from a cassette, no network); or the scripted server replaying a
/// recorded conversation (`scripted` = `default_script` or the gym's, `scripted:<file>`),
/// started here and stopped when the returned guard drops.
pub fn endpoint(
    llm: &str,
    provider: &str,
    gym: &str,
    default_script: Option<&Path>,
    run_dir: &Path,
) -> anyhow::Result<(EndpointConfig, Option<Scripted>, &'static str)> {
    let root = root();
    let log = run_dir.join("llm-log");
    if llm == "scripted" || llm.starts_with("scripted:") {
        let script = llm.strip_prefix("scripted:").map(Path::new).or(default_script);
        let s = Scripted::start(&root, gym, script, Some(&log))?;
        // The scripted server checks that a key is sent, like a real endpoint; it is not secret.
        std::env::set_var("R2G_SCRIPTED_KEY", "scripted-key");
        let e = EndpointConfig {
            provider: provider.to_string(),
            base_url: format!("http://127.0.0.1:{}", s.port),
            model: format!("scripted-{gym}"),
            api_key_env: Some("R2G_SCRIPTED_KEY".into()),
            temperature: 0.0,
            max_tokens: 4096,
            timeout_s: 60.0,
            retries: 2,
            cassette: None,
        };
        e.check()?;
        Ok((e, Some(s), "scripted"))
    } else if let Some(toml) = llm.strip_prefix("record:") {
        let mut e = EndpointConfig::load(Path::new(toml))?;
        e.cassette = Some(CassetteSpec { mode: CassetteMode::Record, path: run_dir.join("cassette.jsonl") });
        Ok((e, None, "live"))
    } else if let Some(path) = llm.strip_prefix("replay:") {
        // Read whole here: a malformed cassette is refused before anything starts.
        let path = std::fs::canonicalize(path).with_context(|| format!("the cassette {path}"))?;
        let mut e = crate::cassette::Player::open(&path)?.endpoint;
        e.model = format!("replayed:{}", e.model);
        Ok((e, None, "replayed"))
    } else {
        Ok((EndpointConfig::load(Path::new(llm))?, None, "live"))
    }
}

/// A gym instance started for one run (lockstep unless `wall`), its episodes judged into
/// `<run_dir>/episodes`.
pub struct GymRun {
    pub inst: Instance,
    pub instance: String,
    pub trace_dir: PathBuf,
    pub scene: PathBuf,
    pub gym: String,
}

/// Where a run's objects start and how it is driven.
#[derive(Debug, Clone, Default)]
pub struct GymSetup {
    pub wall: bool,
    pub seed: u64,
    pub perturb: Option<String>,
    pub robot_config: Option<PathBuf>,
}

impl GymRun {
    pub fn start(gym_or_scene: &str, run_dir: &Path, setup: &GymSetup) -> anyhow::Result<Self> {
        let scene = launch::resolve_scene(gym_or_scene)?;
        let gym =
            scene.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let trace_dir = run_dir.join("episodes");
        let instance = format!("ep{}-{}", std::process::id(), unique());
        let mut sim_args =
            vec!["--trace-dir".into(), trace_dir.display().to_string(), "--seed".into(), setup.seed.to_string()];
        if let Some(p) = &setup.perturb {
            sim_args.extend(["--perturb".into(), p.clone()]);
        }
        let opts = UpOptions {
            scene: scene.clone(),
            instance: instance.clone(),
            mode: if setup.wall { Mode::Wall } else { Mode::Lockstep },
            render_hz: 10.0,
            control_args: Vec::new(),
            sim_args,
            robot_config: Some(setup.robot_config.clone().unwrap_or_else(launch::default_robot_config)),
            ready_timeout: Duration::from_secs(60),
        };
        let inst = Instance::up(&opts)?;
        Ok(Self { inst, instance, trace_dir, scene, gym })
    }

    /// Stops the instance, which ends (and judges) the last episode; that verdict.
    pub fn finish(mut self) -> anyhow::Result<Value> {
        // Only a verdict written after this point is the last episode's (each reset() wrote one before).
        let judged_before = episode::verdict_count(&self.trace_dir);
        self.inst.stop();
        episode::newest_verdict(&self.trace_dir, judged_before, Duration::from_secs(10))
    }
}

/// A number no other call in this process returns: milliseconds since boot, and a count for
/// runs started in the same millisecond (threads of one benchmark).
fn unique() -> String {
    static COUNT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    format!("{}-{}", ipc_schema::monotonic_ns() / 1_000_000, COUNT.fetch_add(1, std::sync::atomic::Ordering::Relaxed))
}

/// A fresh run folder: `out`, or `runs/<kind>/<gym>-<pid>-<ms>-<n>`, canonical.
pub fn run_folder(out: Option<&Path>, kind: &str, gym: &str) -> anyhow::Result<PathBuf> {
    let stamp = format!("{}-{}", std::process::id(), unique());
    let dir = out.map_or_else(|| root().join("runs").join(kind).join(format!("{gym}-{stamp}")), Path::to_path_buf);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(std::fs::canonicalize(&dir)?)
}

pub fn episode(o: &EpisodeOpts) -> anyhow::Result<EpisodeResult> {
    let root = root();
    let scene = launch::resolve_scene(&o.gym)?;
    let gym = scene.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let run_dir = run_folder(o.out.as_deref(), "episodes", &gym)?;
    let (endpoint, _scripted, source) = endpoint(&o.llm, &o.provider, &gym, None, &run_dir)?;
    let setup =
        GymSetup { wall: o.wall, seed: o.seed, perturb: o.perturb.clone(), robot_config: o.robot_config.clone() };
    let gym_run = GymRun::start(&o.gym, &run_dir, &setup)?;
    let cfg = EpisodeConfig {
        gym: gym.clone(),
        scene,
        root: root.clone(),
        endpoint,
        max_decisions: o.max_decisions,
        control_steps: o.control_steps,
        limits: crate::worker::Limits { wall_s: o.wall_s, ..Default::default() },
        run_dir: run_dir.clone(),
        lockstep: !o.wall,
        robot_config: o.robot_config.clone(),
        memory_dir: o.memory.clone().unwrap_or_else(|| root.join("robot-skill/memory")),
        skills: o.skills.clone(),
        seed: o.seed,
        perturb: o.perturb.clone(),
    };
    let result = episode::run(&cfg, &gym_run.instance);
    let eval = gym_run.finish();
    let mut result = result?;
    result.llm_source = source.into();
    if source == "replayed" && result.stop_reason.starts_with(episode::ENDPOINT_FAILED) {
        // Not a task failure: the replay no longer matches its recording.
        bail!("{} (run folder {})", result.stop_reason, run_dir.display());
    }
    let eval = eval?;
    result.success = eval["success"].as_bool().unwrap_or(false);
    result.evaluation = eval;
    // The page first, the result last and whole: a run folder with result.json is complete.
    crate::viewer::write_with(&run_dir, serde_json::to_value(&result)?)?;
    let path = run_dir.join("result.json");
    let tmp = run_dir.join(".result.json.partial");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&result)?)?;
    std::fs::rename(&tmp, &path)?;
    Ok(result)
}

/// Runs `episodes` episodes one after the other (each in `<out>/episode-NNN`), telling
/// `on_episode` how each went, and returns the metrics: success rate, responses, tokens and the
/// wall-time split, with every episode's result (also written to `<out>/batch.json`).
pub fn batch(
    o: &EpisodeOpts,
    episodes: u32,
    mut on_episode: impl FnMut(u32, &anyhow::Result<EpisodeResult>),
) -> anyhow::Result<Value> {
    let dir = batch_dir(o);
    let mut rows = Vec::new();
    for i in 0..episodes {
        let r = episode(&batch_episode(o, &dir, i));
        on_episode(i, &r);
        match r {
            Ok(r) => rows.push(serde_json::to_value(&r)?),
            Err(e) => rows.push(json!({"error": format!("{e:#}"), "success": false})),
        }
    }
    summarize(o, &dir, rows)
}

fn batch_dir(o: &EpisodeOpts) -> PathBuf {
    let stamp = format!("{}-{}", std::process::id(), ipc_schema::monotonic_ns() / 1_000_000);
    o.out.clone().unwrap_or_else(|| root().join("runs").join("batches").join(format!("{}-{stamp}", o.gym)))
}

/// The options of `o` as `r2g episode`/`r2g batch` flags (paths made absolute: a job may run
/// in another folder or on another node), without the gym, `--out` or the subcommand.
pub fn episode_flags(o: &EpisodeOpts) -> Vec<String> {
    let abs = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf()).display().to_string();
    // An endpoint file is a path; `scripted[:file]`, `record:file` and `replay:file` carry one.
    let llm = match o.llm.split_once(':') {
        Some((kind, file)) if ["scripted", "record", "replay"].contains(&kind) => {
            format!("{kind}:{}", abs(Path::new(file)))
        }
        None if o.llm != "scripted" => abs(Path::new(&o.llm)),
        _ => o.llm.clone(),
    };
    let mut a: Vec<String> = vec!["--llm".into(), llm];
    a.extend(["--provider".into(), o.provider.clone(), "--max-decisions".into(), o.max_decisions.to_string()]);
    a.extend(["--control-steps".into(), o.control_steps.to_string(), "--wall-s".into(), o.wall_s.to_string()]);
    if o.wall {
        a.push("--wall".into());
    }
    if let Some(rc) = &o.robot_config {
        a.extend(["--robot-config".into(), abs(rc)]);
    }
    if let Some(m) = &o.memory {
        a.extend(["--memory".into(), abs(m)]);
    }
    if o.seed != 0 {
        a.extend(["--seed".into(), o.seed.to_string()]);
    }
    if let Some(p) = &o.perturb {
        a.extend(["--perturb".into(), p.clone()]);
    }
    if let Some(lib) = &o.library {
        a.extend(["--skills".into(), "use".into(), "--library".into(), abs(lib)]);
    }
    a
}

/// The gym as a job names it: a pack name as it is, a folder or scene file absolute.
pub fn gym_arg(gym: &str) -> String {
    let p = Path::new(gym);
    if p.exists() {
        std::path::absolute(p).map(|p| p.display().to_string()).unwrap_or_else(|_| gym.to_string())
    } else {
        gym.to_string()
    }
}

/// The `r2g episode` arguments that run `o` into `out` (one job of a batch on a fleet).
pub fn episode_args(o: &EpisodeOpts, out: &Path) -> Vec<String> {
    let mut a: Vec<String> = vec!["episode".into(), gym_arg(&o.gym)];
    a.extend(episode_flags(o));
    a.extend(["--out".into(), out.display().to_string()]);
    a
}

/// Episode i of a batch: its own folder, and seed `seed + i` unless the seed is 0 (the scene as
/// written for every episode), the same locally and on a fleet.
fn batch_episode(o: &EpisodeOpts, dir: &Path, i: u32) -> EpisodeOpts {
    let seed = if o.seed == 0 { 0 } else { o.seed + u64::from(i) };
    EpisodeOpts { out: Some(dir.join(format!("episode-{i:03}"))), seed, ..o.clone() }
}

/// [`batch`] on a fleet: every episode an `r2g episode` job on `backend` (local workers, or Ray
/// tasks across machines), each into `<out>/episode-NNN`. Results stream back as they finish
/// (`on_episode` with the episode's number and its result or error) into the same records and
/// summary as a local batch. Paths in the options must be valid on every node.
pub fn batch_on(
    o: &EpisodeOpts,
    episodes: u32,
    backend: &fleet::Backend,
    mut on_episode: impl FnMut(u32, &Value),
) -> anyhow::Result<Value> {
    let dir = std::path::absolute(batch_dir(o))?;
    let jobs: Vec<fleet::Job> = (0..episodes)
        .map(|i| {
            let e = batch_episode(o, &dir, i);
            let out = e.out.clone().unwrap_or_default();
            fleet::Job { id: i as usize, args: episode_args(&e, &out) }
        })
        .collect();
    let mut rows: Vec<(u64, Value)> = Vec::new();
    fleet::run(&jobs, backend, &dir, |r| {
        let i = r["id"].as_u64().unwrap_or(0);
        let row = match (&r["value"], r.get("error")) {
            (v @ Value::Object(_), _) => v.clone(),
            (_, Some(e)) => json!({"error": e, "success": false}),
            _ => {
                json!({"error": format!("r2g episode exited with {}: {}", r["rc"], r["stderr_tail"].as_str().unwrap_or("").trim()), "success": false})
            }
        };
        on_episode(i as u32, &row);
        rows.push((i, row));
    })?;
    rows.sort_by_key(|(i, _)| *i);
    summarize(o, &dir, rows.into_iter().map(|(_, r)| r).collect())
}

/// The batch's metrics over its episodes' results, written to `<dir>/batch.json`.
fn summarize(o: &EpisodeOpts, dir: &Path, rows: Vec<Value>) -> anyhow::Result<Value> {
    let n = rows.len().max(1) as f64;
    let sum = |k: &str| rows.iter().map(|r| r[k].as_f64().unwrap_or(0.0)).sum::<f64>();
    let summary = json!({
        "gym": o.gym, "episodes": rows.len(),
        "success_rate": rows.iter().filter(|r| r["success"] == true).count() as f64 / n,
        "responses_mean": sum("responses") / n,
        "tokens_in": sum("tokens_in"), "tokens_cached": sum("tokens_cached"), "tokens_out": sum("tokens_out"),
        "tokens_in_estimated": sum("tokens_in_estimated"), "tokens_cached_estimated": sum("tokens_cached_estimated"),
        "wall_s": sum("wall_s"), "model_s": sum("model_s"), "exec_s": sum("exec_s"), "overhead_s": sum("overhead_s"),
        "run_dir": dir.display().to_string(),
        // Episodes that could not run at all: an error, or no answer from the endpoint ever.
        "errors": rows.iter().filter(|r| r.get("error").is_some() || (r["responses"] == 0
            && r["stop_reason"].as_str().is_some_and(|s| s.starts_with(crate::episode::ENDPOINT_FAILED)))).count(),
        "per_episode": rows,
    });
    std::fs::create_dir_all(dir)?;
    let tmp = dir.join("batch.json.tmp");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&summary)?)?;
    std::fs::rename(&tmp, dir.join("batch.json"))?;
    Ok(summary)
}

/// The stage programs of a recorded conversation, in order.
pub fn scripted_programs(root: &Path, gym: &str) -> anyhow::Result<Vec<String>> {
    let path = root.join("agent-host/scripted").join(format!("{gym}.json"));
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&path)?)?;
    Ok(v["responses"]
        .as_array()
        .context("responses")?
        .iter()
        .filter_map(|r| r.as_str())
        .filter_map(|r| episode::Decision::parse(r).code)
        .collect())
}

/// What `r2g exec` runs: one program in the sandbox against a running instance.
#[derive(Debug, Clone)]
pub struct ExecOpts {
    pub instance: String,
    /// Waypoints the program may post.
    pub budget: u64,
    pub wall_s: f64,
    pub cpu_s: u64,
    /// Refuse reset and post_actions (an observation-only turn).
    pub observe_only: bool,
    /// Scratch folder (default: a new one under runs/exec/).
    pub scratch: Option<PathBuf>,
    /// Memory folder: its records are copied into the scratch folder's `memory/` before the
    /// program runs, and the program's new records appended to it afterwards, as in an
    /// episode. `None`: no memory (the scratch folder has no `memory/`).
    pub memory: Option<PathBuf>,
    /// The robot configuration the instance runs with, shown to the program as
    /// `robot-skill/config/robot.json` (None: the shipped one).
    pub robot_config: Option<PathBuf>,
}

/// Runs the program in `file` once in a confined worker; the result (stdout, stderr, exit,
/// violation, control steps) with what the sandbox enforced under `"sandbox"`.
pub fn exec(file: &Path, o: &ExecOpts) -> anyhow::Result<Value> {
    let code = std::fs::read_to_string(file).with_context(|| format!("reading {}", file.display()))?;
    let root = root();
    let stamp = format!("{}-{}", std::process::id(), ipc_schema::monotonic_ns());
    let run_dir = root.join("runs").join("exec").join(&stamp);
    let scratch = o.scratch.clone().unwrap_or_else(|| run_dir.join("scratch"));
    let limits = crate::worker::Limits { wall_s: o.wall_s, cpu_s: o.cpu_s, ..Default::default() };
    let mut cfg = crate::worker::WorkerConfig::new(&o.instance, &scratch, &run_dir.join("logs"), &root, limits);
    cfg.memory_dir.clone_from(&o.memory);
    cfg.robot_config.clone_from(&o.robot_config);
    if let Some(dir) = &o.memory {
        std::fs::create_dir_all(&scratch).with_context(|| format!("creating {}", scratch.display()))?;
        crate::memory::seed(&scratch, dir)?;
    }
    let config_shown = cfg.robot_config.clone().unwrap_or_else(launch::default_robot_config);
    let mut worker = crate::worker::Worker::new(cfg);
    // The configuration the program is shown should be the one the instance reports.
    let mut warnings = Vec::new();
    let state = worker.host_cmd(json!({"cmd": "observe", "images": false}))?;
    let reported = &state["state"]["setup"]["robot_config_sha256"];
    let shown = std::fs::read(&config_shown).map(|b| {
        use sha2::Digest as _;
        sha2::Sha256::digest(b).iter().map(|x| format!("{x:02x}")).collect::<String>()
    });
    if reported.is_string() && shown.as_ref().ok().map(|s| json!(s)).as_ref() != Some(reported) {
        warnings.push(format!(
            "the program was shown {} as robot-skill/config/robot.json, but instance '{}' runs another configuration \
             (SHA-256 {reported}); pass the instance's file with --robot-config",
            config_shown.display(),
            o.instance
        ));
    }
    let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "program.py".into());
    let budget = crate::worker::Budget { control_steps: o.budget, observe_only: o.observe_only };
    let r = worker.run(&code, &name, budget)?;
    let mut v = serde_json::to_value(&r)?;
    v["sandbox"] = serde_json::to_value(&worker.enforced)?;
    v["warnings"] = json!(warnings);
    if let Some(dir) = &o.memory {
        v["memory_added"] = json!(crate::memory::collect(&scratch, dir, &mut 0));
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts(seed: u64) -> EpisodeOpts {
        EpisodeOpts {
            seed,
            perturb: Some("xy=0.05,yaw=30".into()),
            library: Some(PathBuf::from("lib")),
            ..EpisodeOpts::new("pick_block_plate", "scripted")
        }
    }

    #[test]
    fn a_fleet_job_runs_the_episode_a_local_batch_would() {
        let dir = Path::new("/tmp/b");
        for (seed, i, want) in [(5u64, 0u32, Some("5")), (5, 3, Some("8")), (0, 3, None)] {
            let e = batch_episode(&opts(seed), dir, i);
            let args = episode_args(&e, e.out.as_deref().expect("out"));
            let flag = |f: &str| args.iter().position(|a| a == f).map(|k| args[k + 1].clone());
            assert_eq!(flag("--seed").as_deref(), want, "{args:?}");
            assert_eq!(flag("--out").as_deref(), Some(format!("/tmp/b/episode-{i:03}").as_str()));
            assert_eq!(flag("--perturb").as_deref(), Some("xy=0.05,yaw=30"));
            // Paths are absolute: a job may run in another folder.
            assert!(flag("--library").is_some_and(|l| l.starts_with('/')), "{args:?}");
        }
    }
}
