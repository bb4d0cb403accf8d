//! r2g-control as a service would run it: the systemd notify protocol on a datagram socket this
//! test owns (readiness, watchdog pings that follow the loop thread, STATUS, STOPPING), and the
//! robot side dying under a running chunk and coming back. The real binaries, started one by one
//! (not through `r2g up`, which stops the whole instance when a child dies).

use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use integration_tests::{bin_dir, instance, root};
use ipc_schema::{JointCommand, Qos, Reply, Request, RequestKind, RobotState, RuntimeInfo, Services, Status, N_JOINTS};

fn scene() -> PathBuf {
    root().join("gyms/pick_block_plate/scene.toml")
}

/// Processes this test started; every one is stopped by pid when the test ends, pass or fail.
#[derive(Default)]
struct Procs(Vec<Child>);

impl Procs {
    fn add(&mut self, c: Child) -> i32 {
        let pid = c.id() as i32;
        self.0.push(c);
        pid
    }

    fn signal(&self, pid: i32, sig: i32) {
        assert!(self.0.iter().any(|c| c.id() as i32 == pid), "only our own children");
        // SAFETY: a child this test started, by pid.
        unsafe {
            libc::kill(pid, sig);
        }
    }

    /// Waits for `pid` to exit; its exit code.
    fn wait(&mut self, pid: i32, timeout: Duration) -> Option<i32> {
        let c = self.0.iter_mut().find(|c| c.id() as i32 == pid)?;
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            if let Ok(Some(st)) = c.try_wait() {
                return st.code();
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }
}

impl Drop for Procs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            if matches!(c.try_wait(), Ok(None)) {
                // SAFETY: a child this test started, by pid.
                unsafe {
                    libc::kill(c.id() as i32, libc::SIGTERM);
                }
            }
        }
        for c in &mut self.0 {
            let t0 = Instant::now();
            while matches!(c.try_wait(), Ok(None)) && t0.elapsed() < Duration::from_secs(5) {
                std::thread::sleep(Duration::from_millis(20));
            }
            let _ = c.kill();
            let _ = c.wait();
        }
        ipc_schema::cleanup_dead_nodes();
    }
}

fn sim(inst: &str) -> Child {
    Command::new(bin_dir().join("r2g-sim"))
        .arg(scene())
        .args(["--instance", inst, "--render-hz", "0"])
        .stdin(Stdio::null())
        .spawn()
        .expect("spawn r2g-sim")
}

/// A control process; `notify`: the test's NOTIFY_SOCKET and the watchdog interval (µs). The
/// shell sets WATCHDOG_PID to its own pid and execs, as systemd sets it to the main pid.
fn control(program: &Path, inst: &str, notify: Option<(&Path, u64)>, extra: &[&str]) -> Child {
    let mut cmd = Command::new("/bin/sh");
    cmd.arg("-c").arg(r#"WATCHDOG_PID=$$ exec "$0" "$@""#).arg(program).arg(scene());
    cmd.args(["--instance", inst]).args(extra).stdin(Stdio::null());
    // Losing and regaining the robot side must not allocate inside a tick either.
    cmd.env("R2G_ABORT_ON_TICK_ALLOC", "1");
    if let Some((sock, usec)) = notify {
        cmd.env("NOTIFY_SOCKET", sock).env("WATCHDOG_USEC", usec.to_string());
    }
    cmd.spawn().expect("spawn r2g-control")
}

/// Every datagram on the test's notify socket, with its arrival time.
struct NotifyLog {
    msgs: Arc<Mutex<Vec<(Instant, String)>>>,
    stop: Arc<AtomicBool>,
    dir: PathBuf,
}

impl NotifyLog {
    fn bind(tag: &str) -> (Self, PathBuf) {
        let dir = std::env::temp_dir().join(format!("r2g-notify-{}-{tag}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("notify.sock");
        let sock = UnixDatagram::bind(&path).expect("bind the notify socket");
        sock.set_read_timeout(Some(Duration::from_millis(50))).expect("timeout");
        let msgs = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let (m, s) = (msgs.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut buf = vec![0u8; 4096];
            while !s.load(Ordering::Relaxed) {
                if let Ok(n) = sock.recv(&mut buf) {
                    let text = String::from_utf8_lossy(&buf[..n]).into_owned();
                    m.lock().unwrap_or_else(|e| e.into_inner()).push((Instant::now(), text));
                }
            }
        });
        (Self { msgs, stop, dir }, path)
    }

    fn all(&self) -> Vec<(Instant, String)> {
        self.msgs.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    fn with(&self, key: &str) -> Vec<(Instant, String)> {
        self.all().into_iter().filter(|(_, m)| m.lines().any(|l| l == key || l.starts_with(key))).collect()
    }

    fn wait_for(&self, key: &str, timeout: Duration) -> Option<(Instant, String)> {
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            if let Some(m) = self.with(key).into_iter().next() {
                return Some(m);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        None
    }
}

impl Drop for NotifyLog {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn quantile(mut v: Vec<f64>, q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

#[test]
fn readiness_waits_for_the_first_cycle_and_the_watchdog_follows_the_loop_thread() {
    let stall_bin = bin_dir().join("examples").join("r2g-control-stall");
    assert!(stall_bin.is_file(), "{} missing (cargo test builds it)", stall_bin.display());
    let inst = instance("wd");
    let (log, sock) = NotifyLog::bind("wd");
    let watchdog_us = 200_000u64;
    let mut procs = Procs::default();
    let ctl = procs.add(control(&stall_bin, &inst, Some((&sock, watchdog_us)), &[]));
    // No robot side yet: no cycle, so no READY.
    std::thread::sleep(Duration::from_millis(1500));
    assert!(log.with("READY=1").is_empty(), "READY before any control cycle: {:?}", log.all());
    let sim_started = Instant::now();
    procs.add(sim(&inst));
    let (ready_at, ready) = log.wait_for("READY=1", Duration::from_secs(60)).expect("READY=1 within 60 s");
    assert!(ready_at > sim_started);
    let ticks: u64 = ready
        .lines()
        .find_map(|l| l.strip_prefix("STATUS=first control cycle done; ticks "))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("READY comes with the tick count: {ready:?}"));
    assert!(ticks >= 1, "READY after the first completed cycle: {ready:?}");

    // Pings under load: both cores busy with other work for 4 s.
    let busy = Arc::new(AtomicBool::new(true));
    let hogs: Vec<_> = (0..2)
        .map(|_| {
            let b = busy.clone();
            std::thread::spawn(move || {
                let mut x = 0u64;
                while b.load(Ordering::Relaxed) {
                    x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
                }
                x
            })
        })
        .collect();
    let load_from = Instant::now();
    std::thread::sleep(Duration::from_secs(4));
    busy.store(false, Ordering::Relaxed);
    for h in hogs {
        let _ = h.join();
    }
    let pings: Vec<Instant> = log.with("WATCHDOG=1").into_iter().map(|(t, _)| t).filter(|t| *t >= load_from).collect();
    let gaps: Vec<f64> = pings.windows(2).map(|w| (w[1] - w[0]).as_secs_f64() * 1e3).collect();
    assert!(gaps.len() >= 10, "pings every {} ms under load, got {}", watchdog_us / 2000, pings.len());
    let p99 = quantile(gaps.clone(), 0.99);
    eprintln!(
        "watchdog ping interval under load: p50 {:.1} ms, p99 {p99:.1} ms, max {:.1} ms ({} pings; WatchdogSec {} ms)",
        quantile(gaps.clone(), 0.5),
        quantile(gaps.clone(), 1.0),
        gaps.len() + 1,
        watchdog_us / 1000
    );
    assert!(p99 < (watchdog_us / 1000) as f64, "a ping gap of {p99:.1} ms would let the watchdog fire");

    // Stall the loop thread alone (the notifier thread keeps running): the pings stop.
    let stall = Duration::from_secs(3);
    procs.signal(ctl, libc::SIGUSR1);
    let stalled_at = Instant::now();
    std::thread::sleep(stall + Duration::from_millis(1500));
    let after: Vec<Instant> = log.with("WATCHDOG=1").into_iter().map(|(t, _)| t).filter(|t| *t >= stalled_at).collect();
    let limit = Duration::from_micros(2 * watchdog_us);
    let last_early = after.iter().filter(|t| **t - stalled_at <= limit).max();
    let during: Vec<f64> = after
        .iter()
        .map(|t| (*t - stalled_at).as_secs_f64() * 1e3)
        .filter(|ms| *ms > limit.as_secs_f64() * 1e3 && *ms < stall.as_secs_f64() * 1e3)
        .collect();
    eprintln!(
        "loop thread stalled for {} s: last ping {:?} ms after the stall began, pings during the stall: {during:?}",
        stall.as_secs(),
        last_early.map(|t| (*t - stalled_at).as_millis())
    );
    assert!(during.is_empty(), "pings went on while the loop thread was stalled: {during:?} ms");
    assert!(
        after.iter().any(|t| *t - stalled_at > stall),
        "pings resume once the loop cycles again: {:?}",
        after.iter().map(|t| (*t - stalled_at).as_millis()).collect::<Vec<_>>()
    );
    assert!(!log.with("STATUS=ticks ").is_empty(), "STATUS lines with the tick figures: {:?}", log.all());

    procs.signal(ctl, libc::SIGTERM);
    assert_eq!(procs.wait(ctl, Duration::from_secs(10)), Some(0), "a clean stop");
    assert!(log.wait_for("STOPPING=1", Duration::from_secs(2)).is_some(), "STOPPING=1 on the way out");
}

/// A minimal agent on the instance's services: posts chunks, reads replies, robot state,
/// limits, and every joint command it can catch.
struct Agent {
    _node: iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    req: iceoryx2::port::publisher::Publisher<iceoryx2::prelude::ipc::Service, Request, ()>,
    replies: iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, Reply, ()>,
    state: iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, RobotState, ()>,
    info: iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, RuntimeInfo, ()>,
    wake: iceoryx2::port::notifier::Notifier<iceoryx2::prelude::ipc::Service>,
    client: u64,
}

impl Agent {
    fn connect(inst: &str) -> Self {
        let s = Services::new(inst).expect("services");
        let node = ipc_schema::node(&format!("t-agent-{}", std::process::id())).expect("node");
        let req = ipc_schema::open_or_create_pubsub::<Request>(&node, &s.request(), Qos::REQUESTS)
            .expect("request service")
            .publisher_builder()
            .create()
            .expect("publisher");
        let replies = ipc_schema::open_or_create_pubsub::<Reply>(&node, &s.reply(), Qos::REPLIES)
            .expect("reply service")
            .subscriber_builder()
            .create()
            .expect("subscriber");
        let state = ipc_schema::open_or_create_pubsub::<RobotState>(&node, &s.robot_state(), Qos::ROBOT_STATE)
            .expect("state service")
            .subscriber_builder()
            .buffer_size(1)
            .create()
            .expect("subscriber");
        let info = ipc_schema::open_or_create_pubsub::<RuntimeInfo>(&node, &s.runtime_info(), Qos::STREAM)
            .expect("info service")
            .subscriber_builder()
            .create()
            .expect("subscriber");
        let wake = ipc_schema::open_or_create_event(&node, &s.control_wake())
            .expect("wake service")
            .notifier_builder()
            .create()
            .expect("notifier");
        Self { _node: node, req, replies, state, info, wake, client: 0x7e57_0000 + u64::from(std::process::id()) }
    }

    fn newest_state(&self, timeout: Duration) -> RobotState {
        let t0 = Instant::now();
        let mut last = None;
        while t0.elapsed() < timeout {
            while let Ok(Some(s)) = self.state.receive() {
                last = Some(*s);
            }
            if let Some(s) = last {
                return s;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        panic!("no robot state within {timeout:?}");
    }

    fn limits(&self) -> RuntimeInfo {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(10) {
            if let Ok(Some(i)) = self.info.receive() {
                return *i;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        panic!("no runtime info");
    }

    /// A joint chunk from `from` to `goal` in waypoints no farther apart than the step cap.
    fn post(&self, id: u64, from: [f64; N_JOINTS], goal: [f64; N_JOINTS], gripper: f64, step_cap: f64) {
        let far = (0..N_JOINTS).map(|j| (goal[j] - from[j]).abs()).fold(0.0, f64::max);
        let n = ((far / (0.8 * step_cap)).ceil() as usize).clamp(1, ipc_schema::MAX_CHUNK);
        let mut sample = self.req.loan_uninit().expect("loan");
        let p = sample.payload_mut().as_mut_ptr();
        // SAFETY: p points at a Request-sized sample we own; zeroed, then the fields are set.
        let sample = unsafe {
            std::ptr::write_bytes(p, 0, 1);
            (*p).id = id;
            (*p).client = self.client;
            (*p).kind = RequestKind::Chunk as u32;
            (*p).control_type = ipc_schema::ControlType::Joint as u32;
            (*p).len = n as u32;
            for k in 0..n {
                let a = (k + 1) as f64 / n as f64;
                let mut wp = [0.0; ipc_schema::WAYPOINT_LEN];
                for j in 0..N_JOINTS {
                    wp[j] = from[j] + a * (goal[j] - from[j]);
                }
                wp[N_JOINTS] = gripper;
                (*p).actions[k] = wp;
            }
            sample.assume_init()
        };
        sample.send().expect("send");
        self.wake.notify().expect("wake");
    }

    /// The next reply to request `id` with a final status (not `accepted`).
    fn outcome(&self, id: u64, timeout: Duration) -> Reply {
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            while let Ok(Some(r)) = self.replies.receive() {
                if r.client == self.client && r.id == id && r.status != Status::Accepted as u32 {
                    return *r;
                }
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        panic!("no outcome for request {id} within {timeout:?}");
    }
}

/// Catches every joint command it can (the stream keeps only the newest sample).
fn watch_commands(inst: &str, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<Vec<(Instant, JointCommand)>> {
    let inst = inst.to_string();
    std::thread::spawn(move || {
        let s = Services::new(&inst).expect("services");
        let node = ipc_schema::node(&format!("t-cmdwatch-{}", std::process::id())).expect("node");
        let sub = ipc_schema::open_or_create_pubsub::<JointCommand>(&node, &s.command(), Qos::STREAM)
            .expect("command service")
            .subscriber_builder()
            .create()
            .expect("subscriber");
        let mut seen = Vec::new();
        while !stop.load(Ordering::Relaxed) {
            while let Ok(Some(c)) = sub.receive() {
                seen.push((Instant::now(), *c));
            }
            std::thread::sleep(Duration::from_micros(100));
        }
        seen
    })
}

#[test]
fn a_killed_robot_side_holds_the_arm_refuses_chunks_and_motion_resumes_from_measured_state() {
    let inst = instance("rl");
    let mut procs = Procs::default();
    let ctl_bin = bin_dir().join("r2g-control");
    let sim1 = procs.add(sim(&inst));
    /// Removes the folder when the test ends, pass or fail.
    struct TempDir(PathBuf);
    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
    let stats_dir = std::env::temp_dir().join(format!("r2g-rl-{}", std::process::id()));
    std::fs::create_dir_all(&stats_dir).expect("temp dir");
    let _cleanup = TempDir(stats_dir.clone());
    let stats_file = stats_dir.join("stats.json");
    let stats_arg = stats_file.display().to_string();
    let ctl = procs.add(control(&ctl_bin, &inst, None, &["--state-timeout-ms", "100", "--stats-out", &stats_arg]));
    let agent = Agent::connect(&inst);
    let info = agent.limits();
    let home = agent.newest_state(Duration::from_secs(60));
    let stop = Arc::new(AtomicBool::new(false));
    let watcher = watch_commands(&inst, stop.clone());
    std::thread::sleep(Duration::from_millis(200));
    let cap = info.max_joint_step_rad;
    let wait_back = |what: &str| -> RobotState {
        let t0 = Instant::now();
        loop {
            let s = agent.newest_state(Duration::from_secs(5));
            if s.fault & 2 == 0 {
                return s;
            }
            assert!(t0.elapsed() < Duration::from_secs(60), "the robot side never came back after {what}");
            std::thread::sleep(Duration::from_millis(20));
        }
    };

    // The robot side hangs for 400 ms mid-chunk (SIGSTOP), then goes on: the chunk fails, the
    // arm brakes to rest on the held command, and requests are taken again once it rests.
    let mut near = home.q_rad;
    near[0] += 0.6;
    agent.post(10, home.q_rad, near, home.gripper, cap);
    std::thread::sleep(Duration::from_millis(300));
    procs.signal(sim1, libc::SIGSTOP);
    std::thread::sleep(Duration::from_millis(400));
    procs.signal(sim1, libc::SIGCONT);
    let r = agent.outcome(10, Duration::from_secs(10));
    assert_eq!(r.status, Status::Failed as u32, "{}", r.reason_str());
    assert!(r.reason_str().contains("robot side published no state"), "{}", r.reason_str());
    let rested = wait_back("a hang");
    assert!(rested.dq_rad_s.iter().all(|v| v.abs() < 0.05), "resumed only at rest: {:?}", rested.dq_rad_s);
    let home = rested;

    // A long move of joints 1 and 4; the robot side dies in the middle of it.
    let mut far = home.q_rad;
    far[0] += 1.2;
    far[3] += 0.5;
    agent.post(1, home.q_rad, far, home.gripper, cap);
    std::thread::sleep(Duration::from_millis(400));
    let mid = agent.newest_state(Duration::from_secs(1));
    if let Ok(Some(r)) = agent.replies.receive() {
        assert_ne!(r.status, Status::Rejected as u32, "{}", r.reason_str());
    }
    assert!((mid.q_rad[0] - home.q_rad[0]).abs() > 0.01, "moving when the robot side dies");
    procs.signal(sim1, libc::SIGKILL);
    let killed_at = Instant::now();
    let r = agent.outcome(1, Duration::from_secs(10));
    assert_eq!(r.status, Status::Failed as u32, "{}", r.reason_str());
    assert!(r.reason_str().contains("robot side published no state"), "{}", r.reason_str());
    eprintln!("chunk reply {:.0} ms after the kill: {}", killed_at.elapsed().as_secs_f64() * 1e3, r.reason_str());
    let lost = agent.newest_state(Duration::from_secs(1));
    assert_eq!(lost.fault & 2, 2, "the state reports the lost robot side");
    agent.post(2, lost.q_rad, home.q_rad, home.gripper, cap);
    let r = agent.outcome(2, Duration::from_secs(5));
    assert_eq!(r.status, Status::Rejected as u32, "{}", r.reason_str());
    assert!(r.reason_str().contains("robot side has published no state"), "{}", r.reason_str());
    assert!(integration_tests::running(ctl), "the control process keeps running");
    std::thread::sleep(Duration::from_millis(500));

    // The robot side restarts (at its home pose): motion resumes from the measured state.
    let sim2_at = Instant::now();
    procs.add(sim(&inst));
    let back = wait_back("a restart");
    eprintln!("robot side back {:.0} ms after its restart", sim2_at.elapsed().as_secs_f64() * 1e3);
    std::thread::sleep(Duration::from_millis(300));
    let mut goal = back.q_rad;
    goal[6] += 0.2;
    agent.post(3, back.q_rad, goal, back.gripper, cap);
    let r = agent.outcome(3, Duration::from_secs(30));
    assert_eq!(r.status, Status::Executed as u32, "{}", r.reason_str());
    stop.store(true, Ordering::Relaxed);
    let cmds = watcher.join().expect("watcher");

    // Every command caught stayed inside the limits; consecutive ones also within the
    // acceleration limit. After the restart the command starts where the arm measurably is.
    let mut pairs = 0;
    for (i, (_, c)) in cmds.iter().enumerate() {
        for j in 0..N_JOINTS {
            assert!(c.q_rad[j].is_finite() && c.dq_rad_s[j].is_finite(), "command {} not finite", c.seq);
            assert!(
                c.q_rad[j] >= info.q_min_rad[j] && c.q_rad[j] <= info.q_max_rad[j],
                "command {} joint {} at {} outside its limits",
                c.seq,
                j + 1,
                c.q_rad[j]
            );
            assert!(c.dq_rad_s[j].abs() <= info.dq_max_rad_s[j] * 1.0001, "command {} joint {} too fast", c.seq, j + 1);
        }
        if let Some((_, p)) = i.checked_sub(1).map(|k| &cmds[k]) {
            if c.seq == p.seq + 1 {
                pairs += 1;
                for j in 0..N_JOINTS {
                    let ddq = (c.dq_rad_s[j] - p.dq_rad_s[j]) / 1e-3;
                    assert!(
                        ddq.abs() <= info.ddq_max_rad_s2[j] * 1.01,
                        "command {} joint {} accelerates at {ddq:.2} rad/s² (limit {:.2})",
                        c.seq,
                        j + 1,
                        info.ddq_max_rad_s2[j]
                    );
                }
            }
        }
    }
    let span = cmds.last().map_or(0, |l| l.1.seq) - cmds.first().map_or(0, |f| f.1.seq);
    eprintln!("commands caught: {} of {span} ticks, {pairs} consecutive pairs checked for acceleration", cmds.len());
    assert!(cmds.len() as u64 > span / 4, "the watcher saw too few commands to say anything");
    let during: Vec<&JointCommand> =
        cmds.iter().filter(|(t, _)| *t > killed_at && *t < sim2_at).map(|(_, c)| c).collect();
    assert!(!during.is_empty(), "commands kept coming while the robot side was gone");
    let held = during.last().expect("some");
    assert!(held.dq_rad_s.iter().all(|v| v.abs() < 1e-9), "the arm was held still: {:?}", held.dq_rad_s);
    assert!((held.q_rad[0] - far[0]).abs() > 0.05, "the held command did not go on to the old target");
    // The first command of the new robot side's session (the only ones it follows).
    let first_after = cmds
        .iter()
        .map(|(_, c)| c)
        .find(|c| c.seq > held.seq && c.session != held.session)
        .expect("a command after the restart");
    let dist =
        |a: &[f64; N_JOINTS], b: &[f64; N_JOINTS]| (0..N_JOINTS).map(|j| (a[j] - b[j]).abs()).fold(0.0, f64::max);
    assert!(dist(&held.q_rad, &back.q_rad) > 0.01, "the restarted robot side stands elsewhere than the held command");
    let jump = dist(&first_after.q_rad, &back.q_rad);
    assert!(jump < 1e-3, "the first new command is the measured pose, not an old target (off by {jump} rad)");

    // r2g-control checked every command it sent (not only those caught here).
    procs.signal(ctl, libc::SIGTERM);
    assert_eq!(procs.wait(ctl, Duration::from_secs(10)), Some(0));
    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats_file).expect("stats-out")).expect("stats JSON");
    eprintln!(
        "r2g-control: {} ticks, {} limit violations, {} robot losses, {} tick allocations, {} tick frees",
        stats["ticks"],
        stats["limit_violations"],
        stats["robot_losses"],
        stats["tick_allocations"],
        stats["tick_frees"]
    );
    assert_eq!(stats["limit_violations"], 0, "{stats}");
    assert_eq!(stats["robot_losses"], 2, "one hang, one kill: {stats}");
    assert_eq!(stats["tick_allocations"], 0, "{stats}");
}
