//! `r2g bench tick` / `r2g bench jitter`: wake latency and compute time of the real runtime
//! (wall mode, sim-host stepping and rendering both cameras; for `jitter` also a Python agent
//! polling get_state and posting chunks through `robo`) against a bare clock_nanosleep loop
//! with the same real-time setup, in the same run.

use std::time::Duration;

use anyhow::{bail, Context};
use ipc_schema::Mode;
use runtime::launch::{self, Instance, UpOptions};
use serde_json::{json, Value};

fn flat(s: &Value, key: &str) -> f64 {
    s.pointer(key).and_then(Value::as_f64).unwrap_or(f64::NAN)
}

/// The Python of the project's venv and one of its bench scripts, if `make robo` has installed them.
pub(crate) fn python_script(name: &str) -> anyhow::Result<(std::path::PathBuf, std::path::PathBuf)> {
    let root = launch::gyms_dir().parent().map(std::path::Path::to_path_buf).unwrap_or_default();
    let python = root.join(".venv/bin/python");
    let script = root.join("bench/py").join(name);
    if !python.is_file() || !script.is_file() {
        bail!("this bench needs {} and {} (run `make robo`)", python.display(), script.display());
    }
    Ok((python, script))
}

/// A command running `python script`, which gets SIGTERM if this process dies (a stopped
/// `r2g bench` leaves no script behind; the scripts stop their own instances on SIGTERM).
pub(crate) fn python_command(python: &std::path::Path, script: &std::path::Path) -> std::process::Command {
    use std::os::unix::process::CommandExt;
    let mut cmd = std::process::Command::new(python);
    cmd.arg(script);
    // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
    unsafe {
        cmd.pre_exec(|| {
            ipc_schema::process::die_with_parent();
            Ok(())
        });
    }
    cmd
}

/// Prints a finished bench script's stdout and parses its last line, the JSON figures.
pub(crate) fn script_figures(out: &std::process::Output, script: &str) -> anyhow::Result<Value> {
    let text = String::from_utf8_lossy(&out.stdout);
    print!("{text}");
    if !out.status.success() {
        bail!("{script} ended with {}", out.status);
    }
    let last = text.lines().last().unwrap_or("");
    serde_json::from_str(last).with_context(|| format!("the last line of {script} is not JSON: {last}"))
}

/// The runtime (wall mode, rendering on) for `seconds` with its figures written at the end, and
/// the bare loop beside it over the same window (start-up included), on the same CPU at one
/// FIFO priority above it: the runtime can never delay it, so it is the best wake-up this
/// machine gives under the same load. Used by `bench tick` and `bench accept`.
pub(crate) struct Beside {
    pub inst: Instance,
    baseline: std::thread::JoinHandle<(Value, Option<String>)>,
    stats_path: std::path::PathBuf,
    seconds: f64,
}

impl Beside {
    pub(crate) fn start(instance: &str, scene: &std::path::Path, seconds: f64) -> anyhow::Result<Self> {
        let stats_path = std::env::temp_dir().join(format!("r2g-bench-{instance}.json"));
        let opts = UpOptions {
            scene: scene.to_path_buf(),
            instance: instance.to_string(),
            mode: Mode::Wall,
            render_hz: 10.0,
            control_args: vec![
                // A few seconds more than the measured window, which starts once the instance is up.
                "--duration-s".into(),
                (seconds + 3.0).to_string(),
                "--stats-out".into(),
                stats_path.display().to_string(),
            ],
            sim_args: Vec::new(),
            robot_config: None,
            ready_timeout: Duration::from_secs(60),
        };
        let cpu = runtime::rt::last_cpu();
        let window = Duration::from_secs_f64(seconds + 3.5);
        let baseline = std::thread::spawn(move || {
            let setup = runtime::rt::setup(Some(81), cpu);
            let warning = setup.warning();
            (runtime::baseline_loop(window, 1_000_000, 0).to_json(), warning)
        });
        match Instance::up(&opts) {
            Ok(inst) => Ok(Self { inst, baseline, stats_path, seconds }),
            Err(e) => {
                let _ = baseline.join();
                Err(e)
            }
        }
    }

    /// Waits for both loops to end and stops the instance; the runtime's figures (an error if
    /// r2g-control failed) and the baseline's (without allocation figures: it does no work and
    /// runs without the counting allocator).
    pub(crate) fn finish(mut self, bench: &str) -> (anyhow::Result<Value>, Value) {
        let (mut base, warning) = self.baseline.join().unwrap_or_else(|_| (json!({"error": "panicked"}), None));
        if let Some(w) = warning {
            eprintln!("{bench}: {w}");
        }
        if let Some(o) = base.as_object_mut() {
            o.remove("tick_allocations");
            o.remove("tick_pool_allocations");
        }
        let status = self.inst.wait_control(Duration::from_secs_f64(self.seconds + 60.0));
        self.inst.stop();
        let rt = (|| {
            let status = status?;
            if !status.success() {
                bail!("r2g-control ended with {status}");
            }
            let path = &self.stats_path;
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let _ = std::fs::remove_file(path);
            Ok(serde_json::from_str(&text)?)
        })();
        (rt, base)
    }
}

pub fn run(gym: &str, seconds: f64, client: bool) -> anyhow::Result<Value> {
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 3600.0) {
        bail!("--seconds must be in (0, 3600]");
    }
    eprintln!("bench tick: runtime for {seconds} s (gym {gym}, wall mode, rendering on)...");
    let load = if client { Some(python_script("load_client.py")?) } else { None };
    let run = Beside::start(&format!("bench{}", std::process::id()), &launch::resolve_scene(gym)?, seconds)?;
    // The agent stops by itself when the runtime does.
    let agent = match &load {
        Some((python, script)) => Some(
            python_command(python, script)
                .arg(format!("{}", seconds + 5.0))
                .env("R2G_INSTANCE", &run.inst.name)
                .stdout(std::process::Stdio::piped())
                .spawn()
                .context("starting the Python agent load")?,
        ),
        None => None,
    };
    let (rt, base) = run.finish("bench tick");
    let agent_figures = agent.and_then(|a| a.wait_with_output().ok()).map(|o| {
        let text = String::from_utf8_lossy(&o.stdout).into_owned();
        text.lines().last().and_then(|l| serde_json::from_str::<Value>(l).ok()).unwrap_or(json!({"error": text}))
    });
    let rt = rt?;

    let row = |name: &str, s: &Value| {
        vec![
            name.to_string(),
            format!("{}", s["ticks"]),
            format!("{:.1}", flat(s, "/wake/p50_us")),
            format!("{:.1}", flat(s, "/wake/p99_us")),
            format!("{:.1}", flat(s, "/wake/p999_us")),
            format!("{:.1}", flat(s, "/wake/max_us")),
            format!("{:.1}", flat(s, "/compute/p50_us")),
            format!("{:.1}", flat(s, "/compute/p99_us")),
            format!("{:.1}", flat(s, "/compute/max_us")),
            format!("{}", s["overruns"]),
            s.get("tick_allocations").map(|v| v.to_string()).unwrap_or_else(|| "-".into()),
        ]
    };
    crate::print_table(
        &[
            "loop",
            "ticks",
            "wake p50 µs",
            "p99",
            "p99.9",
            "max",
            "compute p50 µs",
            "p99",
            "max",
            "overruns",
            "allocs in tick",
        ],
        &[row("runtime", &rt), row("baseline", &base)],
    );
    let summary = |s: &Value| {
        json!({
            "ticks": s["ticks"],
            "overruns": s["overruns"],
            "p50_us": flat(s, "/wake/p50_us"),
            "p99_us": flat(s, "/wake/p99_us"),
            "p999_us": flat(s, "/wake/p999_us"),
            "max_us": flat(s, "/wake/max_us"),
            "compute_p50_us": flat(s, "/compute/p50_us"),
            "compute_p99_us": flat(s, "/compute/p99_us"),
            "compute_max_us": flat(s, "/compute/max_us"),
            "tick_allocations": s.get("tick_allocations"),
            "tick_pool_allocations": s.get("tick_pool_allocations"),
        })
    };
    let out = json!({
        "bench": "tick",
        "seconds": seconds,
        "period_us": 1000,
        "runtime": summary(&rt),
        "baseline": summary(&base),
        "p999_ratio": flat(&rt, "/wake/p999_us") / flat(&base, "/wake/p999_us"),
        "agent_load": agent_figures,
    });
    println!("{out}");
    let mut out = out;
    out["cdf"] = json!({"runtime": rt["wake"]["cdf"], "baseline": base["wake"]["cdf"]});
    Ok(out)
}
