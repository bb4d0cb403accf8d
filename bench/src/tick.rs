//! `r2g bench tick`: wake latency and compute time of the real runtime (wall mode, sim-host
//! stepping and rendering) against a bare clock_nanosleep loop with the same real-time setup.

use std::time::Duration;

use anyhow::{bail, Context};
use ipc_schema::Mode;
use runtime::launch::{self, Instance, UpOptions};
use runtime::TickStats;
use serde_json::{json, Value};

fn flat(s: &Value, key: &str) -> f64 {
    s.pointer(key).and_then(Value::as_f64).unwrap_or(f64::NAN)
}

pub fn run(gym: &str, seconds: f64) -> anyhow::Result<Value> {
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 3600.0) {
        bail!("--seconds must be in (0, 3600]");
    }
    let scene = launch::resolve_scene(gym)?;
    let stats_path = std::env::temp_dir().join(format!("r2g-bench-tick-{}.json", std::process::id()));
    let instance = format!("bench{}", std::process::id());
    eprintln!("bench tick: runtime for {seconds} s (gym {gym}, wall mode, rendering on)...");
    let opts = UpOptions {
        scene,
        instance,
        mode: Mode::Wall,
        render_hz: 10.0,
        control_args: vec![
            "--duration-s".into(),
            seconds.to_string(),
            "--stats-out".into(),
            stats_path.display().to_string(),
        ],
        sim_args: Vec::new(),
        ready_timeout: Duration::from_secs(60),
    };
    let mut inst = Instance::up(&opts)?;
    let status = inst.wait_control(Duration::from_secs_f64(seconds + 60.0))?;
    inst.stop();
    if !status.success() {
        bail!("r2g-control ended with {status}");
    }
    let text = std::fs::read_to_string(&stats_path).with_context(|| format!("reading {}", stats_path.display()))?;
    let _ = std::fs::remove_file(&stats_path);
    let rt: Value = serde_json::from_str(&text)?;

    eprintln!("bench tick: bare clock_nanosleep loop for {seconds} s...");
    let setup = runtime::rt::setup(Some(80), runtime::rt::last_cpu());
    if let Some(w) = setup.warning() {
        eprintln!("bench tick: {w}");
    }
    let base: TickStats = runtime::baseline_loop(Duration::from_secs_f64(seconds), 1_000_000, 0);
    let mut base = base.to_json();
    // The baseline does no work and runs without the counting allocator: no allocation figures.
    if let Some(o) = base.as_object_mut() {
        o.remove("tick_allocations");
        o.remove("tick_pool_allocations");
    }

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
    });
    println!("{out}");
    Ok(out)
}
