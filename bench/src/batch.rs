//! `r2g bench batch`: episodes per minute of lockstep demonstration replays and of scripted
//! agent episodes (recorded conversations: synthetic model answers) at 1, 2 and N workers, on
//! local workers and as tasks of a local Ray cluster this benchmark starts and stops, with Ray's
//! overhead per task and the parallel efficiency, all in one run; then Ray's overhead per task
//! across three nodes made of namespaces on this machine (`fleet/py/r2g_netns.py bench`, root
//! only; the nodes share the cores, so it is an overhead, never a speed-up).

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use fleet::{Backend, Job};
use serde_json::{json, Value};

/// A local Ray head in a session of our own; stopped (the whole session) on drop.
struct RayHead {
    child: Child,
    address: String,
}

impl RayHead {
    fn start(slots: usize) -> anyhow::Result<Self> {
        let root = agent_host::session::root();
        let port = {
            let l = std::net::TcpListener::bind("127.0.0.1:0")?;
            l.local_addr()?.port()
        };
        let mut cmd = Command::new(root.join(".venv/bin/ray"));
        cmd.args(["start", "--head", "--node-ip-address=127.0.0.1", &format!("--port={port}")])
            .arg(format!("--num-cpus={slots}"))
            .arg(format!("--resources={{\"r2g_gym\": {slots}}}"))
            // Results are a few kB: a small object store starts at once (Ray's default maps
            // 30 % of the machine's memory in /dev/shm).
            .arg("--object-store-memory=209715200")
            .args(["--include-dashboard=false", "--block"])
            .env("RAY_USAGE_STATS_ENABLED", "0")
            // Ray on Linux turns 127.0.0.1 into the machine's address unless multi-node clusters
            // are off: this head stays on loopback.
            .env("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        // SAFETY: setsid in the child before exec: the head and its daemons form our session.
        unsafe {
            use std::os::unix::process::CommandExt;
            cmd.pre_exec(|| {
                libc::setsid();
                Ok(())
            });
        }
        let child = cmd.spawn().context("starting a Ray head (requirements-ray.txt)")?;
        let t0 = Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            if t0.elapsed() > Duration::from_secs(120) {
                bail!("the Ray head did not listen within 120 s");
            }
            std::thread::sleep(Duration::from_millis(300));
        }
        Ok(Self { child, address: format!("127.0.0.1:{port}") })
    }
}

impl Drop for RayHead {
    fn drop(&mut self) {
        let sid = self.child.id() as i32;
        // SAFETY: signals the process group of the head we started, by its id.
        unsafe { libc::kill(-sid, libc::SIGTERM) };
        std::thread::sleep(Duration::from_secs(5));
        // Ray's workers run in groups of their own, in our session: every process left in it.
        if let Ok(out) = Command::new("ps").args(["-o", "pid=", "-s", &sid.to_string()]).output() {
            for pid in String::from_utf8_lossy(&out.stdout).split_whitespace().filter_map(|p| p.parse::<i32>().ok()) {
                // SAFETY: a process of the session we created.
                unsafe { libc::kill(pid, libc::SIGKILL) };
            }
        }
        let _ = self.child.wait();
    }
}

/// One timed batch: (wall s, mean wall of one job inside its worker s, failed jobs).
fn timed(jobs: &[Job], backend: &Backend, dir: &std::path::Path) -> anyhow::Result<(f64, f64, usize)> {
    let t0 = Instant::now();
    let (mut inside, mut failed) = (0.0, 0);
    fleet::run(jobs, backend, dir, |r| {
        inside += r["wall_s"].as_f64().unwrap_or(0.0);
        failed += usize::from(r["rc"].as_i64().is_none() || r["value"].is_null());
    })?;
    Ok((t0.elapsed().as_secs_f64(), inside / jobs.len().max(1) as f64, failed))
}

pub fn run(max_workers: usize, replays: usize, agents: usize) -> anyhow::Result<Value> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut counts = vec![1, 2, max_workers.max(2)];
    counts.dedup();
    let dir = std::env::temp_dir().join(format!("r2g-bench-batch-{}", std::process::id()));
    let gyms = runtime::launch::gym_names();
    let replay_jobs: Vec<Job> = (0..replays)
        .map(|i| Job {
            id: i,
            args: vec![
                "replay".into(),
                gyms[i % gyms.len()].clone(),
                "--out".into(),
                dir.join("replays").display().to_string(),
            ],
        })
        .collect();
    // An episode's run folder is its own: every configuration writes into new ones.
    let agent_jobs = |tag: &str| -> Vec<Job> {
        (0..agents)
            .map(|i| Job {
                id: i,
                args: vec![
                    "episode".into(),
                    "pick_block_plate".into(),
                    "--out".into(),
                    dir.join(format!("agent-{tag}-{i}")).display().to_string(),
                ],
            })
            .collect()
    };
    let head = RayHead::start(*counts.iter().max().unwrap_or(&2))?;
    let mut rows = Vec::new();
    println!("batch throughput on {cores} cores (workers > {cores}: oversubscribed); agent episodes are scripted (synthetic)");
    println!(
        "{:<8} {:<6} {:>8} {:>10} {:>12} {:>11} {:>8}",
        "kind", "where", "workers", "wall s", "episodes/min", "efficiency", "failed"
    );
    for kind in ["replay", "agent"] {
        let mut base: Option<f64> = None;
        for &w in &counts {
            for (place, backend) in [
                ("local", Backend::Local(w)),
                ("ray", Backend::Ray { address: head.address.clone(), max_concurrent: Some(w) }),
            ] {
                let jobs = if kind == "replay" { replay_jobs.clone() } else { agent_jobs(&format!("{place}{w}")) };
                let (wall, inside, failed) = timed(&jobs, &backend, &dir)?;
                let per_min = jobs.len() as f64 / wall * 60.0;
                if place == "local" && w == 1 {
                    base = Some(per_min);
                }
                let eff = base.map_or(1.0, |b| per_min / (b * w as f64));
                let over = w > cores;
                println!(
                    "{kind:<8} {place:<6} {:>8} {wall:>10.1} {per_min:>12.1} {:>10.0}% {failed:>8}",
                    format!("{w}{}", if over { "*" } else { "" }),
                    eff * 100.0
                );
                rows.push(json!({"kind": kind, "where": place, "workers": w, "oversubscribed": over,
                    "episodes": jobs.len(), "wall_s": wall, "episodes_per_min": per_min,
                    "job_wall_mean_s": inside, "efficiency_vs_local_1": eff, "failed": failed}));
            }
        }
    }
    drop(head);
    let _ = std::fs::remove_dir_all(&dir);
    // Ray's cost per task: the same jobs one at a time through Ray and locally, per job.
    let overhead = |kind: &str| -> Option<f64> {
        let find = |place: &str| {
            rows.iter()
                .find(|r| r["kind"] == kind && r["where"] == place && r["workers"] == 1)
                .and_then(|r| Some((r["wall_s"].as_f64()?, r["episodes"].as_f64()?)))
        };
        let ((ray, n), (local, _)) = (find("ray")?, find("local")?);
        Some((ray - local) / n * 1e3)
    };
    let figures = json!({
        "cores": cores,
        "ray_overhead_per_task_ms": {"replay": overhead("replay"), "agent": overhead("agent")},
        "rows": rows,
    });
    println!(
        "Ray overhead per task (1 worker, Ray minus local, per episode): replay {:.0} ms, agent {:.0} ms",
        overhead("replay").unwrap_or(f64::NAN),
        overhead("agent").unwrap_or(f64::NAN)
    );
    let multinode = multinode(replays);
    match &multinode {
        Ok(m) => println!(
            "Ray overhead per task across {} namespaced nodes (head to workers, 1 at a time; the nodes share these \
             {cores} cores: an overhead, not a speed-up): replay {:.0} ms, jobs per node {}",
            m["nodes"],
            m["ray_overhead_per_task_ms"].as_f64().unwrap_or(f64::NAN),
            m["jobs_per_node"]
        ),
        Err(e) => println!("multi-node row left out: {e:#}"),
    }
    let mut figures = figures;
    figures["multinode"] = multinode.unwrap_or_else(|e| json!({"error": format!("{e:#}")}));
    println!("* more workers than cores: oversubscription");
    println!("{figures}");
    Ok(figures)
}

/// The multi-node row: `fleet/py/r2g_netns.py bench` (a head and two workers in network and
/// mount namespaces of their own on this machine; root only), `jobs` replays one at a time
/// through Ray across them and on a local worker, Ray's overhead per task.
fn multinode(jobs: usize) -> anyhow::Result<Value> {
    let root = agent_host::session::root();
    let r2g = std::env::current_exe().context("locating r2g")?;
    let out = Command::new(root.join(".venv/bin/python"))
        .arg(root.join("fleet/py/r2g_netns.py"))
        .args(["bench", "--jobs", &jobs.max(1).to_string(), "--r2g"])
        .arg(&r2g)
        .current_dir(&root)
        .stdin(Stdio::null())
        .output()
        .context("starting fleet/py/r2g_netns.py")?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        bail!("r2g_netns.py bench failed ({}): {}", out.status, err.trim().lines().last().unwrap_or(""));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().rev().find(|l| l.starts_with('{')).context("r2g_netns.py bench printed no result")?;
    Ok(serde_json::from_str(line)?)
}
