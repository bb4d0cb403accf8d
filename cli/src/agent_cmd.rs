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

#[derive(clap::Args, Debug, Clone)]
pub struct EpisodeOpts {
    /// Gym name (see `r2g gyms`), gym folder, or scene file.
    pub gym: String,
    /// An endpoint TOML file (provider, base_url, model, api_key_env, ...), "scripted" (the
    /// gym's recorded conversation) or "scripted:<conversation.json>".
    #[arg(long, default_value = "scripted")]
    pub llm: String,
    /// Wire format for `--llm scripted`: openai or anthropic.
    #[arg(long, default_value = "openai")]
    pub provider: String,
    #[arg(long, default_value_t = 50)]
    pub max_decisions: u32,
    /// Waypoints one program may post.
    #[arg(long, default_value_t = 600)]
    pub control_steps: u64,
    /// Run the gym in wall-clock time instead of lockstep.
    #[arg(long)]
    pub wall: bool,
    /// Run folder (default: runs/episodes/<gym>-<stamp>; for a batch, its folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long)]
    pub robot_config: Option<PathBuf>,
    /// Wall-clock limit per program, s.
    #[arg(long, default_value_t = 120.0)]
    pub wall_s: f64,
    /// Folder of append-only memory records (default: robot-skill/memory).
    #[arg(long)]
    pub memory: Option<PathBuf>,
}

/// The repo's scripted LLM server, replaying a recorded conversation; stopped on drop.
pub struct Scripted {
    child: Child,
    pub port: u16,
}

impl Scripted {
    pub fn start(root: &Path, gym: &str, script: Option<&Path>, log: Option<&Path>) -> anyhow::Result<Self> {
        let script = script.map_or_else(|| root.join("agent/scripted").join(format!("{gym}.json")), Path::to_path_buf);
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
        lockstep: !o.wall,
        robot_config: o.robot_config.clone(),
        memory_dir: o.memory.clone().unwrap_or_else(|| root.join("robot-skill/memory")),
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
        let e = EpisodeOpts { out: Some(dir.join(format!("episode-{i:03}"))), ..o.clone() };
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

/// The stage programs of a recorded conversation, in order.
fn scripted_programs(root: &Path, gym: &str) -> anyhow::Result<Vec<String>> {
    let path = root.join("agent/scripted").join(format!("{gym}.json"));
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&path)?)?;
    Ok(v["responses"]
        .as_array()
        .context("responses")?
        .iter()
        .filter_map(|r| r.as_str())
        .filter_map(|r| episode::Decision::parse(r).code)
        .collect())
}

/// `r2g bench agent`: host overhead per decision of the loop (scripted endpoint on loopback, so
/// model time is tiny and measured), beside the same stage programs run bare (plain Python and
/// the real `robo`, no sandbox, no LLM, no records) on a fresh instance in the same run.
pub fn bench_agent(episodes: u32) -> anyhow::Result<Value> {
    let root = root();
    let gym = "pick_block_plate";
    let dir = std::env::temp_dir().join(format!("r2g-bench-agent-{}", std::process::id()));
    let mut rows = Vec::new();
    for i in 0..episodes.max(1) {
        let o = EpisodeOpts {
            gym: gym.into(),
            llm: "scripted".into(),
            provider: if i % 2 == 0 { "openai" } else { "anthropic" }.into(),
            max_decisions: 50,
            control_steps: 600,
            wall: false,
            out: Some(dir.join(format!("episode-{i}"))),
            robot_config: None,
            wall_s: 120.0,
            memory: Some(dir.join("memory")),
        };
        let r = episode(&o)?;
        if !r.success {
            bail!("benchmark episode {i} did not succeed: {}", r.stop_reason);
        }
        rows.push(r);
    }
    // Baseline: the same programs, bare.
    let programs = scripted_programs(&root, gym)?;
    let scratch = dir.join("bare");
    std::fs::create_dir_all(&scratch)?;
    let instance = format!("benchagent{}", std::process::id());
    let opts = UpOptions {
        scene: launch::resolve_scene(gym)?,
        instance: instance.clone(),
        mode: Mode::Lockstep,
        render_hz: 10.0,
        control_args: Vec::new(),
        sim_args: Vec::new(),
        robot_config: Some(launch::default_robot_config()),
        ready_timeout: Duration::from_secs(60),
    };
    let mut inst = Instance::up(&opts)?;
    let python = root.join(".venv/bin/python");
    let run_bare = |code: &str| -> anyhow::Result<f64> {
        let t0 = std::time::Instant::now();
        let st = Command::new(&python)
            .args(["-c", code])
            .current_dir(&scratch)
            .env("R2G_INSTANCE", &instance)
            .stdout(Stdio::null())
            .status()?;
        if !st.success() {
            bail!("a bare stage program failed: {st}");
        }
        Ok(t0.elapsed().as_secs_f64())
    };
    let bare = run_bare("import robo; assert robo.reset() == 1")
        .and_then(|_| programs.iter().map(|p| run_bare(p)).sum::<anyhow::Result<f64>>());
    inst.stop();
    let bare_s = bare?;
    let _ = std::fs::remove_dir_all(&dir);

    let mean = |f: &dyn Fn(&EpisodeResult) -> f64| rows.iter().map(f).sum::<f64>() / rows.len() as f64;
    let per_decision = mean(&|r| (r.wall_s - r.model_s) / f64::from(r.responses.max(1)) * 1e3);
    let host = mean(&|r| r.overhead_s / f64::from(r.responses.max(1)) * 1e3);
    let exec = mean(&|r| r.exec_s);
    let figures = json!({
        "episodes": rows.len(),
        "responses": mean(&|r| f64::from(r.responses)),
        "overhead_per_decision_ms": per_decision,
        "host_only_per_decision_ms": host,
        "model_per_decision_ms": mean(&|r| r.model_s / f64::from(r.responses.max(1)) * 1e3),
        "sandboxed_programs_s": exec,
        "bare_programs_s": bare_s,
        "sandbox_over_bare": exec / bare_s,
        "wall_s": mean(&|r| r.wall_s),
    });
    println!("agent loop on {gym}, scripted endpoint on loopback, lockstep ({} episodes)", rows.len());
    println!("{:<44} {:>10}", "per decision: everything but model time", format!("{per_decision:.1} ms"));
    println!("{:<44} {:>10}", "per decision: host only (no model, no program)", format!("{host:.1} ms"));
    println!("{:<44} {:>10}", "stage programs in the sandbox (per episode)", format!("{exec:.2} s"));
    println!("{:<44} {:>10}", "same programs bare (python + robo)", format!("{bare_s:.2} s"));
    println!("{figures}");
    Ok(figures)
}
