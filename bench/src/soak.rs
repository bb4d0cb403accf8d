//! `r2g bench soak`: one instance in wall mode with both cameras rendering and a Python agent
//! (`bench/py/soak_agent.py`) posting joint chunks and reading RGB-D the whole time, for N
//! minutes. Reports the control loop's missed ticks and wake p99.9 beside a bare loop measured
//! first in the same run on the same CPU, the RSS of every process from after a warm-up to the
//! end, the shared-memory files before and after, and what a stalled agent (SIGSTOP for
//! `--stall-s` in the middle of the run) costs the loop against an equal window just before.

use std::collections::BTreeSet;
use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use ipc_schema::{process, Mode};
use runtime::launch::{self, Instance, UpOptions};
use serde_json::{json, Value};

/// What `r2g bench soak` takes.
#[derive(Debug, Clone)]
pub struct Options {
    pub minutes: f64,
    pub gym: String,
    /// Seconds the agent is stopped in the middle of the run.
    pub stall_s: f64,
    /// Seconds between samples of RSS and tick health.
    pub sample_s: f64,
}

/// The tick period and the FIFO priority r2g-control runs with by default.
const PERIOD_NS: u64 = 1_000_000;
const CONTROL_FIFO: i32 = 80;
/// How often tick health is read around the stall: `wake_max_us` covers the last second.
const WINDOW_POLL: Duration = Duration::from_millis(500);

fn validate(o: &Options) -> anyhow::Result<()> {
    if !(o.minutes.is_finite() && o.minutes > 0.0 && o.minutes <= 24.0 * 60.0) {
        bail!("--minutes must be in (0, 1440]");
    }
    let run_s = o.minutes * 60.0;
    if !(o.stall_s.is_finite() && o.stall_s >= 0.5 && 3.0 * o.stall_s <= run_s) {
        bail!(
            "--stall-s must be at least 0.5 and at most a third of the run ({:.1} s for --minutes {})",
            run_s / 3.0,
            o.minutes
        );
    }
    if !(o.sample_s.is_finite() && (0.5..=60.0).contains(&o.sample_s)) {
        bail!("--sample-s must be in [0.5, 60]");
    }
    Ok(())
}

/// `VmRSS` of a process, KiB.
fn rss_kib(pid: u32) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = text.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Every shared-memory file of iceoryx2 this machine holds: `/dev/shm/<prefix>*` and every file
/// under the root path (both from the configuration every r2g process reads, `$R2G_IPC_CONFIG`
/// or iceoryx2's defaults).
fn shm_files() -> anyhow::Result<BTreeSet<String>> {
    let cfg = ipc_schema::ipc_config().context("reading the iceoryx2 configuration")?;
    let prefix = cfg.global.prefix.to_string();
    let root = PathBuf::from(cfg.global.root_path().to_string());
    let mut files = BTreeSet::new();
    if let Ok(dir) = std::fs::read_dir("/dev/shm") {
        for e in dir.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with(&prefix) {
                files.insert(format!("/dev/shm/{name}"));
            }
        }
    }
    fn walk(dir: &Path, files: &mut BTreeSet<String>, depth: usize) {
        let Ok(rd) = std::fs::read_dir(dir) else { return };
        for e in rd.flatten() {
            let p = e.path();
            match e.file_type() {
                Ok(t) if t.is_dir() && depth < 8 => walk(&p, files, depth + 1),
                Ok(t) if !t.is_dir() => {
                    files.insert(p.display().to_string());
                }
                _ => {}
            }
        }
    }
    walk(&root, &mut files, 0);
    Ok(files)
}

/// One reading of `runtime::operator::status`.
#[derive(Debug, Clone)]
struct Health {
    at: Instant,
    ticks: Option<u64>,
    overruns: Option<u64>,
    wake_max_us: Option<f64>,
    state_age_ms: Option<f64>,
    fault: bool,
    robot_lost: bool,
    agent_port_errors: Option<u64>,
}

fn read_health(instance: &str, warned: &mut bool) -> Option<Health> {
    match runtime::operator::status(instance) {
        Ok(v) => Some(Health {
            at: Instant::now(),
            ticks: v["ticks"].as_u64(),
            overruns: v["overruns"].as_u64(),
            wake_max_us: v["wake_max_us"].as_f64(),
            state_age_ms: v["state_age_ms"].as_f64(),
            // "none", or the fault's name.
            fault: v["fault"].as_str().is_some_and(|f| !f.is_empty() && f != "none") || v["fault"] == true,
            robot_lost: v["robot_lost"] == true,
            agent_port_errors: v["agent_port_errors"].as_u64(),
        }),
        Err(e) => {
            if !*warned {
                eprintln!("bench soak: tick health unavailable ({e:#}); further failures are not shown");
                *warned = true;
            }
            None
        }
    }
}

/// What the agent printed last, and when its first chunk succeeded.
#[derive(Default)]
struct AgentSeen {
    last: Option<Value>,
    first_ok: Option<Instant>,
}

/// Everything this bench started; dropping it stops the agent (by its pid), then the instance,
/// and removes the stats file, on every path out of [`run`].
struct Started {
    agent: Option<Child>,
    agent_status: Option<ExitStatus>,
    inst: Option<Instance>,
    stats_path: PathBuf,
}

impl Started {
    fn agent_pid(&self) -> Option<u32> {
        self.agent.as_ref().map(Child::id)
    }

    /// Sends `sig` to the agent if it is our unreaped child (so its pid is still its own).
    fn signal_agent(&mut self, sig: libc::c_int) -> bool {
        let Some(a) = self.agent.as_mut() else { return false };
        if !matches!(a.try_wait(), Ok(None)) {
            return false;
        }
        // SAFETY: signals a child we started and have not reaped, by pid.
        unsafe { libc::kill(a.id() as libc::pid_t, sig) == 0 }
    }

    /// SIGCONT (it may be stopped) and SIGTERM, SIGKILL after 5 s.
    fn stop_agent(&mut self) {
        self.signal_agent(libc::SIGCONT);
        self.signal_agent(libc::SIGTERM);
        if let Some(mut a) = self.agent.take() {
            let t0 = Instant::now();
            loop {
                match a.try_wait() {
                    Ok(Some(s)) => {
                        self.agent_status = Some(s);
                        break;
                    }
                    Ok(None) if t0.elapsed() < Duration::from_secs(5) => std::thread::sleep(Duration::from_millis(20)),
                    _ => {
                        let _ = a.kill();
                        self.agent_status = a.wait().ok();
                        break;
                    }
                }
            }
        }
    }

    fn stop_all(&mut self) {
        self.stop_agent();
        if let Some(mut inst) = self.inst.take() {
            inst.stop();
        }
    }
}

impl Drop for Started {
    fn drop(&mut self) {
        self.stop_all();
        let _ = std::fs::remove_file(&self.stats_path);
    }
}

/// The agent, killed (SIGKILL: it may be stopped, and a stopped process takes no other signal)
/// if this process dies.
fn start_agent(instance: &str) -> anyhow::Result<Child> {
    use std::os::unix::process::CommandExt;
    let (python, script) = crate::tick::python_script("soak_agent.py")?;
    let mut cmd = Command::new(python);
    cmd.arg(script).env("R2G_INSTANCE", instance).stdin(Stdio::null()).stdout(Stdio::piped());
    // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    cmd.spawn().context("starting the soak agent")
}

/// Reads the agent's count lines as they come.
fn watch_agent(child: &mut Child) -> (Arc<Mutex<AgentSeen>>, std::thread::JoinHandle<()>) {
    let seen = Arc::new(Mutex::new(AgentSeen::default()));
    let out = child.stdout.take();
    let s = seen.clone();
    let handle = std::thread::spawn(move || {
        let Some(out) = out else { return };
        for line in std::io::BufReader::new(out).lines() {
            let Ok(line) = line else { break };
            match serde_json::from_str::<Value>(&line) {
                Ok(v) if v.is_object() => {
                    let mut g = s.lock().unwrap_or_else(|e| e.into_inner());
                    if g.first_ok.is_none() && v["chunks_ok"].as_u64().is_some_and(|n| n > 0) {
                        g.first_ok = Some(Instant::now());
                    }
                    g.last = Some(v);
                }
                _ => eprintln!("soak agent: {line}"),
            }
        }
    });
    (seen, handle)
}

/// RSS of every process, by name.
fn rss_all(st: &Started) -> Vec<(&'static str, Option<u64>)> {
    let inst = st.inst.as_ref();
    vec![
        ("r2g-sim", inst.and_then(|i| rss_kib(i.sim.id()))),
        ("r2g-control", inst.and_then(|i| rss_kib(i.control.id()))),
        ("agent", st.agent_pid().and_then(rss_kib)),
        ("r2g-bench", rss_kib(std::process::id())),
    ]
}

fn stat(s: &Value, key: &str) -> f64 {
    s.pointer(key).and_then(Value::as_f64).unwrap_or(f64::NAN)
}

/// Missed ticks, largest wake, ticks and measured seconds of a window.
type Window = (Option<u64>, Option<f64>, Option<u64>, Option<f64>);

/// The window between two readings: missed ticks and ticks are their differences; the largest
/// wake is that of the readings inside it, each covering its last second.
fn window(hs: &[Health], from: &Option<Health>, to: &Option<Health>) -> Window {
    let (Some(a), Some(b)) = (from, to) else { return (None, None, None, None) };
    let missed = match (a.overruns, b.overruns) {
        (Some(x), Some(y)) => Some(y.saturating_sub(x)),
        _ => None,
    };
    let ticks = match (a.ticks, b.ticks) {
        (Some(x), Some(y)) => Some(y.saturating_sub(x)),
        _ => None,
    };
    let lo = a.at + Duration::from_millis(950);
    let max = hs
        .iter()
        .chain(std::iter::once(b))
        .filter(|h| h.at >= lo && h.at <= b.at)
        .filter_map(|h| h.wake_max_us)
        .fold(None, |m: Option<f64>, w| Some(m.map_or(w, |m| m.max(w))));
    (missed, max, ticks, Some((b.at - a.at).as_secs_f64()))
}

pub fn run(o: &Options) -> anyhow::Result<Value> {
    validate(o)?;
    let run_s = o.minutes * 60.0;
    let scene = launch::resolve_scene(&o.gym)?;
    // Fail before measuring anything if the agent cannot run.
    crate::tick::python_script("soak_agent.py")?;
    let warmup = Duration::from_secs_f64((run_s * 0.1).min(10.0));

    // 1. The bare loop alone, on the CPU and at the priority the control loop will use.
    let base_s = (run_s * 0.1).clamp(1.0, 60.0);
    let cpu = runtime::rt::last_cpu();
    eprintln!("bench soak: bare loop for {base_s:.1} s on CPU {cpu:?}...");
    let (base, warning) = std::thread::spawn(move || {
        let setup = runtime::rt::setup(Some(CONTROL_FIFO), cpu);
        (runtime::baseline_loop(Duration::from_secs_f64(base_s), PERIOD_NS, 0).to_json(), setup.warning())
    })
    .join()
    .map_err(|_| anyhow::anyhow!("the baseline loop panicked"))?;
    if let Some(w) = warning {
        eprintln!("bench soak: baseline: {w}");
    }
    // The baseline thread's mlockall covers the whole process: undo it, so this process's RSS
    // counts what it touches, not everything it maps.
    // SAFETY: plain syscall.
    unsafe {
        libc::munlockall();
    }
    // From here on a stop signal ends the run in order (agent, instance, shared memory).
    process::install_stop_signals();

    // 2. Shared-memory files before.
    let shm_before = shm_files()?;

    // 3. The instance, cameras rendering; r2g-control writes its statistics when stopped.
    let stats_path = std::env::temp_dir().join(format!("r2g-bench-soak-{}.json", std::process::id()));
    let _ = std::fs::remove_file(&stats_path);
    let instance = format!("soak{}", std::process::id());
    let robot_config = Some(launch::default_robot_config()).filter(|p| p.is_file());
    let opts = UpOptions {
        scene,
        instance: instance.clone(),
        mode: Mode::Wall,
        render_hz: 10.0,
        control_args: vec!["--stats-out".into(), stats_path.display().to_string()],
        sim_args: Vec::new(),
        robot_config,
        ready_timeout: Duration::from_secs(60),
    };
    eprintln!(
        "bench soak: {} min on gym {} (wall mode, cameras at 10 Hz), agent stalled {} s in the middle",
        o.minutes, o.gym, o.stall_s
    );
    let mut st = Started { agent: None, agent_status: None, inst: None, stats_path: stats_path.clone() };
    st.inst = Some(Instance::up(&opts)?);
    let t0 = Instant::now();

    // 4. The agent.
    let mut child = start_agent(&instance)?;
    let (seen, reader) = watch_agent(&mut child);
    st.agent = Some(child);

    // 5, 6. Samples, and the stall.
    let mut warned = false;
    let mut health: Vec<Health> = Vec::new();
    let check = |st: &mut Started| -> anyhow::Result<()> {
        if process::stop_requested() {
            bail!("interrupted");
        }
        if let Some(inst) = st.inst.as_mut() {
            if let Some(what) = inst.exited()? {
                bail!("{what} during the soak");
            }
        }
        if let Some(a) = st.agent.as_mut() {
            if let Some(s) = a.try_wait()? {
                bail!("the soak agent ended by itself ({s})");
            }
        }
        Ok(())
    };
    let first_ok = loop {
        check(&mut st)?;
        if let Some(t) = seen.lock().unwrap_or_else(|e| e.into_inner()).first_ok {
            break t;
        }
        if t0.elapsed() > Duration::from_secs(120) {
            bail!("the soak agent had no successful chunk within 120 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let half = Duration::from_secs_f64(run_s / 2.0 - o.stall_s / 2.0);
    let stall = Duration::from_secs_f64(o.stall_s);
    let warm_at = first_ok + warmup;
    // The window before the stall starts after the warm-up.
    let stall_at = (t0 + half).max(warm_at + stall);
    let stall_end = stall_at + stall;
    let before_at = stall_at - stall;
    let mut end = t0 + Duration::from_secs_f64(run_s);
    if end < stall_end + Duration::from_secs(2) {
        end = stall_end + Duration::from_secs(2);
        eprintln!(
            "bench soak: the agent took {:.1} s to its first chunk: the run is extended to {:.1} s",
            (first_ok - t0).as_secs_f64(),
            (end - t0).as_secs_f64()
        );
    }

    let mut rss_start: Option<Vec<(&str, Option<u64>)>> = None;
    let mut rss_max: Vec<Option<u64>> = vec![None; 4];
    let (mut h_before, mut h_stall, mut h_cont): (Option<Health>, Option<Health>, Option<Health>) = (None, None, None);
    let mut stalled = false;
    let mut stall_done = false;
    let mut next_sample = Instant::now();
    let mut next_progress = Instant::now() + Duration::from_secs(60);
    let sample_every = Duration::from_secs_f64(o.sample_s);
    let mut samples = 0u64;
    loop {
        check(&mut st)?;
        let now = Instant::now();
        if now >= end && stall_done {
            break;
        }
        if rss_start.is_none() && now >= warm_at {
            rss_start = Some(rss_all(&st));
        }
        let in_window = now >= before_at && !stall_done;
        if h_before.is_none() && now >= before_at {
            h_before = read_health(&instance, &mut warned);
        }
        if !stalled && !stall_done && now >= stall_at {
            h_stall = read_health(&instance, &mut warned);
            if !st.signal_agent(libc::SIGSTOP) {
                bail!("could not stop the soak agent");
            }
            stalled = true;
            eprintln!("bench soak: agent stopped (SIGSTOP) for {} s", o.stall_s);
        }
        if stalled && now >= stall_end {
            h_cont = read_health(&instance, &mut warned);
            st.signal_agent(libc::SIGCONT);
            stalled = false;
            stall_done = true;
            eprintln!("bench soak: agent continued (SIGCONT)");
        }
        if now >= next_sample || (in_window && health.last().is_none_or(|h| now - h.at >= WINDOW_POLL)) {
            if let Some(h) = read_health(&instance, &mut warned) {
                health.push(h);
            }
            if now >= next_sample {
                for (m, (_, v)) in rss_max.iter_mut().zip(rss_all(&st)) {
                    *m = (*m).max(v);
                }
                samples += 1;
                next_sample += sample_every;
            }
        }
        if now >= next_progress {
            let chunks = seen.lock().unwrap_or_else(|e| e.into_inner()).last.as_ref().map(|v| v["chunks"].clone());
            let h = health.last();
            eprintln!(
                "bench soak: {:.1}/{:.1} min, agent chunks {}, ticks {}, missed {}, control RSS {} KiB",
                (now - t0).as_secs_f64() / 60.0,
                (end - t0).as_secs_f64() / 60.0,
                chunks.unwrap_or(Value::Null),
                h.and_then(|h| h.ticks).map_or("?".into(), |v| v.to_string()),
                h.and_then(|h| h.overruns).map_or("?".into(), |v| v.to_string()),
                st.inst.as_ref().and_then(|i| rss_kib(i.control.id())).map_or("?".into(), |v| v.to_string()),
            );
            next_progress += Duration::from_secs(60);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let rss_end = rss_all(&st);
    for (m, (_, v)) in rss_max.iter_mut().zip(rss_end.iter()) {
        *m = (*m).max(*v);
    }
    let h_last = read_health(&instance, &mut warned);
    let shm_during = shm_files()?.len();
    let seconds = t0.elapsed().as_secs_f64();

    // 7. Stop everything, then read what the control loop recorded and what shared memory is left.
    st.stop_agent();
    let _ = reader.join();
    let agent = seen.lock().unwrap_or_else(|e| e.into_inner()).last.clone().unwrap_or(Value::Null);
    if let Some(mut inst) = st.inst.take() {
        inst.stop();
        if let Ok(Some(s)) = inst.control.try_wait() {
            if !s.success() {
                eprintln!("bench soak: r2g-control ended with {s}");
            }
        }
    }
    let text = std::fs::read_to_string(&stats_path)
        .with_context(|| format!("reading {} (r2g-control's statistics)", stats_path.display()))?;
    let rt: Value = serde_json::from_str(&text).context("r2g-control's statistics")?;
    let shm_after = shm_files()?;
    let left_over: Vec<&String> = shm_after.difference(&shm_before).collect();

    // 8. Figures.
    let (stall_missed, stall_wake, stall_ticks, stall_s) = window(&health, &h_stall, &h_cont);
    let (before_missed, before_wake, before_ticks, before_s) = window(&health, &h_before, &h_stall);
    let rss_start = rss_start.unwrap_or_default();
    let mut rss = serde_json::Map::new();
    let mut rss_rows = Vec::new();
    for (i, (name, end_kib)) in rss_end.iter().enumerate() {
        let start = rss_start.get(i).and_then(|r| r.1);
        let growth = match (start, end_kib) {
            (Some(a), Some(b)) => Some(*b as i64 - a as i64),
            _ => None,
        };
        rss.insert(name.to_string(), json!({"start": start, "end": end_kib, "growth": growth, "max": rss_max[i]}));
        let show = |v: Option<u64>| v.map_or("-".into(), |v| v.to_string());
        rss_rows.push(vec![
            name.to_string(),
            show(start),
            show(*end_kib),
            growth.map_or("-".into(), |g| format!("{g:+}")),
            show(rss_max[i]),
        ]);
    }
    let fault_samples = health.iter().filter(|h| h.fault).count();
    let lost_samples = health.iter().filter(|h| h.robot_lost).count();
    let max_state_age =
        health.iter().filter_map(|h| h.state_age_ms).fold(None, |m: Option<f64>, a| Some(m.map_or(a, |m| m.max(a))));
    let n = |v: Option<u64>| v.map_or("-".into(), |v| v.to_string());
    let f = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.1}"));

    let row = |name: &str, s: &Value| {
        vec![
            name.to_string(),
            format!("{}", s["ticks"]),
            format!("{:.1}", stat(s, "/wake/p50_us")),
            format!("{:.1}", stat(s, "/wake/p99_us")),
            format!("{:.1}", stat(s, "/wake/p999_us")),
            format!("{:.1}", stat(s, "/wake/max_us")),
            format!("{:.1}", stat(s, "/compute/p99_us")),
            format!("{}", s["overruns"]),
        ]
    };
    println!("soak: {:.1} min of wall-mode control with cameras and an agent (gym {})", seconds / 60.0, o.gym);
    crate::print_table(
        &["loop", "ticks", "wake p50 µs", "p99", "p99.9", "max", "compute p99 µs", "missed ticks"],
        &[row("runtime", &rt), row(&format!("bare loop ({base_s:.0} s, first)"), &base)],
    );
    println!();
    crate::print_table(
        &["window", "seconds", "ticks", "missed ticks", "wake max µs"],
        &[
            vec!["before stall".into(), f(before_s), n(before_ticks), n(before_missed), f(before_wake)],
            vec!["agent stopped".into(), f(stall_s), n(stall_ticks), n(stall_missed), f(stall_wake)],
        ],
    );
    println!();
    crate::print_table(&["process", "RSS start KiB", "end", "growth", "max"], &rss_rows);
    println!();
    println!(
        "shared-memory files: {} before, {} while running, {} after, {} left over{}",
        shm_before.len(),
        shm_during,
        shm_after.len(),
        left_over.len(),
        if left_over.is_empty() {
            String::new()
        } else {
            format!(": {}", left_over.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", "))
        }
    );
    println!(
        "agent: {} chunks ({} executed, {} not), {} errors, {} images, {} depth images; health samples {} (fault in {}, robot lost in {}, max state age {} ms)",
        agent["chunks"],
        agent["chunks_ok"],
        agent["chunks_failed"],
        agent["errors"],
        agent["images"],
        agent["depths"],
        health.len(),
        fault_samples,
        lost_samples,
        f(max_state_age),
    );
    let wake_p999 = stat(&rt, "/wake/p999_us");
    let base_p999 = stat(&base, "/wake/p999_us");
    let out = json!({
        "bench": "soak",
        "minutes": o.minutes,
        "gym": o.gym,
        "seconds": seconds,
        "ticks": rt["ticks"],
        "missed_ticks": rt["overruns"],
        "wake_p50_us": stat(&rt, "/wake/p50_us"),
        "wake_p99_us": stat(&rt, "/wake/p99_us"),
        "wake_p999_us": wake_p999,
        "wake_max_us": stat(&rt, "/wake/max_us"),
        "compute_p99_us": stat(&rt, "/compute/p99_us"),
        "tick_allocations": rt.get("tick_allocations"),
        "baseline_wake_p999_us": base_p999,
        "baseline_wake_max_us": stat(&base, "/wake/max_us"),
        "baseline_seconds": base_s,
        "ratio": wake_p999 / base_p999,
        "stall": {
            "seconds": o.stall_s,
            "measured_s": stall_s,
            "ticks": stall_ticks,
            "missed_ticks": stall_missed,
            "wake_max_us": stall_wake,
            "before_measured_s": before_s,
            "before_ticks": before_ticks,
            "before_missed_ticks": before_missed,
            "before_wake_max_us": before_wake,
        },
        "rss_kib": rss,
        "rss_samples": samples,
        "shm_files": {"before": shm_before.len(), "during": shm_during, "after": shm_after.len(), "left_over": left_over},
        "agent_chunks": agent["chunks"],
        "agent_chunks_ok": agent["chunks_ok"],
        "agent_errors": agent["errors"],
        "agent_images": agent["images"],
        "agent_exit": st.agent_status.map(|s| s.to_string()),
        "health": {
            "samples": health.len(),
            "fault_samples": fault_samples,
            "robot_lost_samples": lost_samples,
            "max_state_age_ms": max_state_age,
            "agent_port_errors": h_last.as_ref().and_then(|h| h.agent_port_errors),
        },
    });
    println!("{out}");
    Ok(out)
}
