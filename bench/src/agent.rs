//! `r2g bench agent`: what the agent host costs per decision, beside the same stage programs
//! run bare.

use std::process::{Command, Stdio};
use std::time::Duration;

use agent_host::episode::EpisodeResult;
use agent_host::session::{self, EpisodeOpts};
use anyhow::bail;
use ipc_schema::Mode;
use runtime::launch::{self, Instance, UpOptions};
use serde_json::{json, Value};

/// `r2g bench agent`: host overhead per decision of the loop (scripted endpoint on loopback, so
/// model time is tiny and measured), beside the same stage programs run bare (plain Python and
/// the real `robo`, no sandbox, no LLM, no records) on a fresh instance in the same run.
pub fn run(episodes: u32) -> anyhow::Result<Value> {
    let root = session::root();
    let gym = "pick_block_plate";
    let dir = std::env::temp_dir().join(format!("r2g-bench-agent-{}", std::process::id()));
    // The host as it was (R2G_HOST_BASELINE=1: each program's proxy and sandbox started when the
    // program comes, a new episode's first frame and the runtime's info for a new agent waiting
    // for their periodic slots) and as it is, episodes alternating in one run so that both see
    // the same machine.
    let mut rows = Vec::new();
    let mut before = Vec::new();
    for i in 0..2 * episodes.max(1) {
        let prestart = i % 2 == 1;
        // The instance's processes inherit it: the baseline is the whole host path as it was.
        std::env::set_var("R2G_HOST_BASELINE", if prestart { "0" } else { "1" });
        let o = EpisodeOpts {
            provider: if (i / 2) % 2 == 0 { "openai" } else { "anthropic" }.into(),
            out: Some(dir.join(format!("episode-{i}"))),
            memory: Some(dir.join("memory")),
            ..EpisodeOpts::new(gym, "scripted")
        };
        let r = session::episode(&o)?;
        if !r.success {
            bail!("benchmark episode {i} did not succeed: {}", r.stop_reason);
        }
        if prestart {
            rows.push(r);
        } else {
            before.push(r);
        }
    }
    std::env::remove_var("R2G_HOST_BASELINE");
    // Baseline: the same programs, bare.
    let programs = session::scripted_programs(&root, gym)?;
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
    let host_before = before.iter().map(|r| r.overhead_s / f64::from(r.responses.max(1)) * 1e3).sum::<f64>()
        / before.len().max(1) as f64;
    // Medians too: on a shared machine one slow episode moves a mean.
    let median = |v: &[EpisodeResult]| {
        let mut x: Vec<f64> = v.iter().map(|r| r.overhead_s / f64::from(r.responses.max(1)) * 1e3).collect();
        x.sort_by(f64::total_cmp);
        x.get(x.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let (median_after, median_before) = (median(&rows), median(&before));
    let per_decision = mean(&|r| (r.wall_s - r.model_s) / f64::from(r.responses.max(1)) * 1e3);
    // The baseline arm's everything-but-model and program time: what prestarting moves out of
    // the host's own account must not reappear in the programs' time or the wall.
    let mean_before =
        |f: &dyn Fn(&EpisodeResult) -> f64| before.iter().map(f).sum::<f64>() / before.len().max(1) as f64;
    let per_decision_before = mean_before(&|r| (r.wall_s - r.model_s) / f64::from(r.responses.max(1)) * 1e3);
    let exec_before = mean_before(&|r| r.exec_s);
    let host = mean(&|r| r.overhead_s / f64::from(r.responses.max(1)) * 1e3);
    let exec = mean(&|r| r.exec_s);
    let per = |f: &dyn Fn(&EpisodeResult) -> f64| mean(&|r| f(r) / f64::from(r.responses.max(1)) * 1e3);
    let split = json!({
        "setup_ms": per(&|r| r.host_split.setup_s),
        "program_start_ms": per(&|r| r.host_split.program_start_s),
        "observe_ms": per(&|r| r.host_split.observe_s),
        "records_ms": per(&|r| r.host_split.records_s),
        "other_ms": per(&|r| r.host_split.other_s),
    });
    let figures = json!({
        "host_split_per_decision": split,
        "episodes": rows.len(),
        "responses": mean(&|r| f64::from(r.responses)),
        "overhead_per_decision_ms": per_decision,
        "overhead_per_decision_ms_without_prestart": per_decision_before,
        "overhead_after_over_before": per_decision / per_decision_before,
        "sandboxed_programs_s_without_prestart": exec_before,
        "host_only_per_decision_ms": host,
        "host_only_per_decision_ms_without_prestart": host_before,
        "host_only_after_over_before": host / host_before,
        "host_only_median_ms": median_after,
        "host_only_median_ms_without_prestart": median_before,
        "model_per_decision_ms": mean(&|r| r.model_s / f64::from(r.responses.max(1)) * 1e3),
        "sandboxed_programs_s": exec,
        "bare_programs_s": bare_s,
        "sandbox_over_bare": exec / bare_s,
        "wall_s": mean(&|r| r.wall_s),
    });
    println!("agent loop on {gym}, scripted endpoint on loopback, lockstep ({} episodes)", rows.len());
    println!("{:<44} {:>10}", "per decision: everything but model time", format!("{per_decision:.1} ms"));
    println!("{:<44} {:>10}", "  the same, the host as it was (baseline)", format!("{per_decision_before:.1} ms"));
    println!("{:<44} {:>10}", "programs in the sandbox, now / baseline", format!("{exec:.2} / {exec_before:.2} s"));
    println!("{:<44} {:>10}", "per decision: host only (no model, no program)", format!("{host:.1} ms"));
    println!("{:<44} {:>10}", "  the same, the host as it was (baseline)", format!("{host_before:.1} ms"));
    println!("{:<44} {:>10}", "  medians: now / the baseline", format!("{median_after:.1} / {median_before:.1} ms"));
    for (label, key) in [
        ("  episode start (reset, first observation)", "setup_ms"),
        ("  program proxy and sandbox start/stop", "program_start_ms"),
        ("  observation after a program (PNGs)", "observe_ms"),
        ("  records (files, synced transcript)", "records_ms"),
        ("  the rest (messages, feedback, memory)", "other_ms"),
    ] {
        println!("{label:<44} {:>10}", format!("{:.1} ms", split[key].as_f64().unwrap_or(f64::NAN)));
    }
    println!("{:<44} {:>10}", "stage programs in the sandbox (per episode)", format!("{exec:.2} s"));
    println!("{:<44} {:>10}", "same programs bare (python + robo)", format!("{bare_s:.2} s"));
    println!("{figures}");
    Ok(figures)
}
