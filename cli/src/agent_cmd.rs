//! `r2g episode` and `r2g batch`: the agent loop against a gym instance this command starts,
//! with a configured LLM endpoint or the scripted one (`--llm scripted`), judged afterwards by
//! the native evaluator.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use agent::episode::{self, EpisodeConfig, EpisodeResult};
use agent::llm::EndpointConfig;
use anyhow::{bail, Context};
use ipc_schema::Mode;
use runtime::launch::{self, Instance, UpOptions};
use serde_json::{json, Value};

pub struct EpisodeOpts {
    pub gym: String,
    /// An endpoint TOML file, or "scripted".
    pub llm: String,
    /// Wire format the scripted endpoint is spoken in.
    pub provider: String,
    pub max_decisions: u32,
    pub control_steps: u64,
    pub lockstep: bool,
    pub out: Option<PathBuf>,
    pub robot_config: Option<PathBuf>,
    pub wall_s: f64,
}

/// The repo's scripted LLM server, replaying a recorded conversation; stopped on drop.
pub struct Scripted {
    child: Child,
    pub port: u16,
}

impl Scripted {
    pub fn start(root: &Path, gym: &str, log: Option<&Path>) -> anyhow::Result<Self> {
        let script = root.join("agent/scripted").join(format!("{gym}.json"));
        if !script.is_file() {
            bail!("no scripted conversation for gym '{gym}' ({} is missing)", script.display());
        }
        let mut cmd = Command::new(root.join(".venv/bin/python"));
        cmd.arg(root.join("agent/py/scripted_llm.py")).arg("--script").arg(&script).args(["--port", "0"]);
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

fn root() -> PathBuf {
    launch::gyms_dir().parent().map(Path::to_path_buf).unwrap_or_default()
}

pub fn episode(o: &EpisodeOpts) -> anyhow::Result<EpisodeResult> {
    let root = root();
    let scene = launch::resolve_scene(&o.gym)?;
    let gym = scene.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let stamp = format!("{}-{}", std::process::id(), ipc_schema::monotonic_ns() / 1_000_000);
    let run_dir = o.out.clone().unwrap_or_else(|| root.join("runs").join("episodes").join(format!("{gym}-{stamp}")));
    std::fs::create_dir_all(&run_dir)?;
    let (endpoint, _scripted) = if o.llm == "scripted" {
        let s = Scripted::start(&root, &gym, Some(&run_dir.join("llm-log")))?;
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
        mode: if o.lockstep { Mode::Lockstep } else { Mode::Wall },
        render_hz: 10.0,
        control_args: Vec::new(),
        sim_args: vec!["--trace-dir".into(), trace_dir.display().to_string()],
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
        limits: agent::worker::Limits { wall_s: o.wall_s, ..Default::default() },
        run_dir: run_dir.clone(),
        lockstep: o.lockstep,
        robot_config: o.robot_config.clone(),
        memory_dir: run_dir.join("memory"),
        skills: String::new(),
    };
    let result = episode::run(&cfg, &instance);
    // Stopping the instance ends the episode: sim-host judges it from its native trace.
    inst.stop();
    let mut result = result?;
    let eval = episode::newest_verdict(&trace_dir, 0, Duration::from_secs(10))?;
    result.success = eval["success"].as_bool().unwrap_or(false);
    result.evaluation = eval;
    std::fs::write(run_dir.join("result.json"), serde_json::to_vec_pretty(&result)?)?;
    agent::viewer::write(&run_dir)?;
    Ok(result)
}

pub fn batch(o: &EpisodeOpts, episodes: u32) -> anyhow::Result<Value> {
    let root = root();
    let stamp = format!("{}-{}", std::process::id(), ipc_schema::monotonic_ns() / 1_000_000);
    let dir = o.out.clone().unwrap_or_else(|| root.join("runs").join("batches").join(format!("{}-{stamp}", o.gym)));
    let mut rows = Vec::new();
    for i in 0..episodes {
        let e = EpisodeOpts { out: Some(dir.join(format!("episode-{i:03}"))), ..o.clone_opts() };
        match episode(&e) {
            Ok(r) => {
                eprintln!("r2g batch: episode {i}: success {} in {} responses", r.success, r.responses);
                rows.push(serde_json::to_value(&r)?)
            }
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
        "per_episode": rows,
    });
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join("batch.json"), serde_json::to_vec_pretty(&summary)?)?;
    Ok(summary)
}

impl EpisodeOpts {
    fn clone_opts(&self) -> Self {
        Self {
            gym: self.gym.clone(),
            llm: self.llm.clone(),
            provider: self.provider.clone(),
            max_decisions: self.max_decisions,
            control_steps: self.control_steps,
            lockstep: self.lockstep,
            out: self.out.clone(),
            robot_config: self.robot_config.clone(),
            wall_s: self.wall_s,
        }
    }
}
