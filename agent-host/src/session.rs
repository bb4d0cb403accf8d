//! Whole runs of the agent host (`r2g episode`, `r2g batch`, `r2g exec`): the stage-code loop
//! against a gym instance started here, with a configured LLM endpoint or the scripted one
//! (`scripted`: a recorded conversation served on loopback), judged afterwards by the native
//! evaluator; and one program in the sandbox against a running instance.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

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
    /// gym's recorded conversation) or "scripted:<conversation.json>".
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

pub fn episode(o: &EpisodeOpts) -> anyhow::Result<EpisodeResult> {
    let root = root();
    let scene = launch::resolve_scene(&o.gym)?;
    let gym = scene.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let stamp = format!("{}-{}", std::process::id(), ipc_schema::monotonic_ns() / 1_000_000);
    let run_dir = o.out.clone().unwrap_or_else(|| root.join("runs").join("episodes").join(format!("{gym}-{stamp}")));
    std::fs::create_dir_all(&run_dir)?;
    let run_dir = std::fs::canonicalize(&run_dir)?;
    let (endpoint, _scripted) = if o.llm == "scripted" || o.llm.starts_with("scripted:") {
        let script = o.llm.strip_prefix("scripted:").map(Path::new);
        let s = Scripted::start(&root, &gym, script, Some(&run_dir.join("llm-log")))?;
        // The scripted server checks that a key is sent, like a real endpoint; it is not secret.
        std::env::set_var("R2G_SCRIPTED_KEY", "scripted-key");
        let e = EndpointConfig {
            provider: o.provider.clone(),
            base_url: format!("http://127.0.0.1:{}", s.port),
            model: format!("scripted-{gym}"),
            api_key_env: Some("R2G_SCRIPTED_KEY".into()),
            temperature: 0.0,
            max_tokens: 4096,
            timeout_s: 60.0,
            retries: 2,
        };
        e.check()?;
        (e, Some(s))
    } else {
        (EndpointConfig::load(Path::new(&o.llm))?, None)
    };
    let trace_dir = run_dir.join("episodes");
    let instance = format!("ep{stamp}");
    let opts = UpOptions {
        scene: scene.clone(),
        instance: instance.clone(),
        mode: if o.wall { Mode::Wall } else { Mode::Lockstep },
        render_hz: 10.0,
        control_args: Vec::new(),
        sim_args: {
            let mut a =
                vec!["--trace-dir".into(), trace_dir.display().to_string(), "--seed".into(), o.seed.to_string()];
            if let Some(p) = &o.perturb {
                a.extend(["--perturb".into(), p.clone()]);
            }
            a
        },
        robot_config: Some(o.robot_config.clone().unwrap_or_else(launch::default_robot_config)),
        ready_timeout: Duration::from_secs(60),
    };
    let mut inst = Instance::up(&opts)?;
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
        skills: String::new(),
    };
    let result = episode::run(&cfg, &instance);
    // Stopping the instance ends the episode: sim-host judges it from its native trace. Only a
    // verdict written after this point is the last episode's (each reset() wrote one before).
    let judged_before = episode::verdict_count(&trace_dir);
    inst.stop();
    let mut result = result?;
    let eval = episode::newest_verdict(&trace_dir, judged_before, Duration::from_secs(10))?;
    result.success = eval["success"].as_bool().unwrap_or(false);
    result.evaluation = eval;
    std::fs::write(run_dir.join("result.json"), serde_json::to_vec_pretty(&result)?)?;
    crate::viewer::write(&run_dir)?;
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
    let root = root();
    let stamp = format!("{}-{}", std::process::id(), ipc_schema::monotonic_ns() / 1_000_000);
    let dir = o.out.clone().unwrap_or_else(|| root.join("runs").join("batches").join(format!("{}-{stamp}", o.gym)));
    let mut rows = Vec::new();
    for i in 0..episodes {
        let seed = if o.seed == 0 { 0 } else { o.seed + u64::from(i) };
        let e = EpisodeOpts { out: Some(dir.join(format!("episode-{i:03}"))), seed, ..o.clone() };
        let r = episode(&e);
        on_episode(i, &r);
        match r {
            Ok(r) => rows.push(serde_json::to_value(&r)?),
            Err(e) => rows.push(json!({"error": format!("{e:#}"), "success": false})),
        }
    }
    let n = rows.len().max(1) as f64;
    let sum = |k: &str| rows.iter().map(|r| r[k].as_f64().unwrap_or(0.0)).sum::<f64>();
    let summary = json!({
        "gym": o.gym, "episodes": rows.len(),
        "success_rate": rows.iter().filter(|r| r["success"] == true).count() as f64 / n,
        "responses_mean": sum("responses") / n,
        "tokens_in": sum("tokens_in"), "tokens_cached": sum("tokens_cached"), "tokens_out": sum("tokens_out"),
        "wall_s": sum("wall_s"), "model_s": sum("model_s"), "exec_s": sum("exec_s"), "overhead_s": sum("overhead_s"),
        "run_dir": dir.display().to_string(),
        // Episodes that could not run at all: an error, or no answer from the endpoint ever.
        "errors": rows.iter().filter(|r| r.get("error").is_some() || (r["responses"] == 0
            && r["stop_reason"].as_str().is_some_and(|s| s.starts_with(crate::episode::ENDPOINT_FAILED)))).count(),
        "per_episode": rows,
    });
    std::fs::create_dir_all(&dir)?;
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
    let cfg = crate::worker::WorkerConfig {
        instance: o.instance.clone(),
        scratch: scratch.clone(),
        log_dir: run_dir.join("logs"),
        root,
        limits,
    };
    if let Some(dir) = &o.memory {
        std::fs::create_dir_all(&scratch).with_context(|| format!("creating {}", scratch.display()))?;
        crate::memory::seed(&scratch, dir)?;
    }
    let mut worker = crate::worker::Worker::new(cfg);
    let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "program.py".into());
    let budget = crate::worker::Budget { control_steps: o.budget, observe_only: o.observe_only };
    let r = worker.run(&code, &name, budget)?;
    let mut v = serde_json::to_value(&r)?;
    v["sandbox"] = serde_json::to_value(&worker.enforced)?;
    if let Some(dir) = &o.memory {
        v["memory_added"] = json!(crate::memory::collect(&scratch, dir, &mut 0));
    }
    Ok(v)
}
