//! `r2g bench fci`: the same 5 s joint move through `robo` (bench/py/fci_move.py) on two robot
//! sides in one run: the MuJoCo sim-host (the runtime's own clock paces the tick) and r2g-fci
//! speaking the Franka network protocol to franka-sim on 127.0.0.1 (the robot's states pace it).
//! For each: the final joint error, the runtime's wake and tick-to-command latency, and for FCI
//! the robot cycle's figures at r2g-fci (packets lost, answers late or missing, reply latency from
//! a state's arrival to the command's departure) against the robot's budget.
//!
//! franka-sim runs in its own venv (.venv-franka-sim) with the arm our sim-host compiles, its
//! communication check on and, unless `lenient_peer`, its motion-limit check on too (a command
//! that misses its cycle then reads as a jump and the peer stops the arm, as a real one does).

use std::net::{TcpListener, TcpStream};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use ipc_schema::Mode;
use runtime::launch::{self, Instance, RobotSide, UpOptions};
use serde_json::{json, Value};

const GYM: &str = "pick_block_plate";
/// The reply budget of the Franka control loop the figures are held against (µs): the robot
/// expects each answer within its 1 ms cycle, and libfranka's own guidance leaves about 300 µs
/// of it to the user's computation.
const BUDGET_US: f64 = 300.0;

/// franka-sim, stopped (SIGTERM, then SIGKILL) when dropped.
struct Peer {
    child: Child,
    port: u16,
}

impl Peer {
    fn start(root: &Path, model: &Path, strict: bool, log: &Path) -> anyhow::Result<Self> {
        let python = root.join(".venv-franka-sim/bin/python");
        if !python.is_file() {
            bail!("{} missing: run scripts/setup-venv.sh (make test does)", python.display());
        }
        let port = TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let log_file = std::fs::File::create(log).with_context(|| format!("creating {}", log.display()))?;
        let mut cmd = Command::new(python);
        cmd.arg(root.join("fci/franka-sim/serve.py"))
            .args(["--model", &model.display().to_string(), "--port", &port.to_string()])
            .env("FRANKA_SIM_ENFORCE_COMM_CONSTRAINTS", "1")
            .env("FRANKA_SIM_ENFORCE_MOTION_LIMITS", if strict { "1" } else { "0" })
            .stdin(Stdio::null())
            .stdout(log_file.try_clone()?)
            .stderr(log_file);
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            cmd.pre_exec(|| {
                ipc_schema::process::die_with_parent();
                Ok(())
            });
        }
        let mut peer = Self { child: cmd.spawn().context("starting franka-sim")?, port };
        let t0 = Instant::now();
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            if let Some(s) = peer.child.try_wait()? {
                bail!("franka-sim ended with {s}: {}", tail(log));
            }
            if t0.elapsed() > Duration::from_secs(60) {
                bail!("franka-sim did not listen within 60 s: {}", tail(log));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        Ok(peer)
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            // SAFETY: signals the child we started and have not reaped, by pid.
            unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
            let t0 = Instant::now();
            while matches!(self.child.try_wait(), Ok(None)) && t0.elapsed() < Duration::from_secs(10) {
                std::thread::sleep(Duration::from_millis(50));
            }
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn tail(p: &Path) -> String {
    let t = std::fs::read(p).unwrap_or_default();
    String::from_utf8_lossy(&t[t.len().saturating_sub(1500)..]).into_owned()
}

fn read_json(p: &Path) -> anyhow::Result<Value> {
    let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", p.display()))
}

/// One robot side: the instance, the move through robo, the figures written when it ends.
fn one_side(work: &Path, fci: Option<&Peer>) -> anyhow::Result<Value> {
    let tag = if fci.is_some() { "fci" } else { "sim" };
    let control_stats = work.join(format!("{tag}-control.json"));
    let side_stats = work.join(format!("{tag}-side.json"));
    let config = work.join("robot.json");
    let opts = UpOptions {
        scene: launch::resolve_scene(GYM)?,
        instance: format!("bfci{tag}{}", std::process::id()),
        mode: Mode::Wall,
        render_hz: if fci.is_some() { 0.0 } else { 10.0 },
        control_args: vec!["--stats-out".into(), control_stats.display().to_string()],
        sim_args: Vec::new(),
        robot_config: Some(config),
        ready_timeout: Duration::from_secs(90),
    };
    let side = match fci {
        Some(p) => RobotSide::Fci {
            address: format!("127.0.0.1:{}", p.port),
            extra: vec!["--stats-out".into(), side_stats.display().to_string()],
        },
        None => RobotSide::Sim,
    };
    let mut inst = Instance::up_with(&opts, &side)?;
    let (python, script) = crate::tick::python_script("fci_move.py")?;
    let out = crate::tick::python_command(&python, &script)
        .env("R2G_INSTANCE", &inst.name)
        .stderr(Stdio::inherit())
        .output()
        .context("running bench/py/fci_move.py");
    inst.stop();
    let out = out?;
    let text = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        bail!("{tag}: fci_move.py ended with {}: {text}", out.status);
    }
    let mv: Value = serde_json::from_str(text.lines().last().unwrap_or(""))
        .with_context(|| format!("{tag}: the last line of fci_move.py is not JSON: {text}"))?;
    let mut v = json!({ "move": mv, "runtime": read_json(&control_stats)? });
    if fci.is_some() {
        v["fci"] = read_json(&side_stats)?;
    }
    Ok(v)
}

pub fn run(lenient_peer: bool) -> anyhow::Result<Value> {
    let root: PathBuf = launch::gyms_dir().parent().map(Path::to_path_buf).context("checkout folder")?;
    let work = std::env::temp_dir().join(format!("r2g-bench-fci-{}", std::process::id()));
    std::fs::create_dir_all(&work)?;
    let result = (|| {
        // The franka profile on both sides, chunks of 16 (the default 20 Hz, 0.8 s each).
        let config = json!({
            "profile": "franka",
            "control": {"max_chunk_waypoints": 16},
            "franka": {"reflex_window_s": 60},
        });
        std::fs::write(work.join("robot.json"), config.to_string())?;
        let model = work.join("arm.xml");
        let dump = Command::new(launch::sibling("r2g-sim")?)
            .arg(launch::resolve_scene(GYM)?)
            .args(["--instance", &format!("bfcidump{}", std::process::id()), "--dump-mjcf"])
            .arg(&model)
            .arg("--exit-after-dump")
            .stdin(Stdio::null())
            .status()
            .context("running r2g-sim --dump-mjcf")?;
        if !dump.success() {
            bail!("r2g-sim --dump-mjcf ended with {dump}");
        }
        eprintln!(
            "bench fci: sim-host, then r2g-fci against franka-sim (motion-limit check {})...",
            if lenient_peer { "off" } else { "on" }
        );
        let sim = one_side(&work, None)?;
        let peer = Peer::start(&root, &model, !lenient_peer, &work.join("franka-sim.log"))?;
        let fci = one_side(&work, Some(&peer));
        drop(peer);
        Ok((sim, fci?))
    })();
    let keep = result.is_err();
    if !keep {
        let _ = std::fs::remove_dir_all(&work);
    } else {
        eprintln!("bench fci: logs kept in {}", work.display());
    }
    let (sim, fci) = result?;

    let f = |v: &Value, p: &str| v.pointer(p).and_then(Value::as_f64).unwrap_or(f64::NAN);
    let lat = |v: &Value, p: &str| {
        format!(
            "{:.0} / {:.0} / {:.0}",
            f(v, &format!("{p}/p50_us")),
            f(v, &format!("{p}/p99_us")),
            f(v, &format!("{p}/max_us"))
        )
    };
    let rows = [("sim-host", &sim), ("FCI (franka-sim)", &fci)]
        .iter()
        .map(|(name, v)| {
            vec![
                name.to_string(),
                format!("{:.1e}", f(v, "/move/final_error_rad")),
                format!("{}", v["move"]["reflex_stops"]),
                format!("{}", v["runtime"]["ticks"]),
                format!("{}", v["runtime"]["limit_violations"]),
                lat(v, "/runtime/wake"),
                lat(v, "/runtime/command"),
            ]
        })
        .collect::<Vec<_>>();
    println!("5 s joint move through robo, {GYM}; runtime figures in µs (p50 / p99 / max)");
    crate::print_table(
        &["robot side", "final err rad", "reflex stops", "ticks", "limit violations", "wake", "tick-to-command"],
        &rows,
    );
    let c = &fci["fci"];
    let states = f(c, "/states");
    println!();
    println!("FCI cycle at r2g-fci (state arrival -> command sent), budget {BUDGET_US:.0} µs");
    crate::print_table(
        &["states", "packets lost", "late or missing", "reply p50 / p99 / max µs", "over budget", "robot reflexes"],
        &[vec![
            format!("{states}"),
            format!("{}", c["packets_lost"]),
            format!("{}", c["late_or_missing"]),
            lat(c, "/reply_latency"),
            format!("{:.1}%", 100.0 * over_budget(c)),
            format!("{}", c["reflexes"]),
        ]],
    );
    let strip = |mut v: Value| {
        for p in ["/runtime", "/fci"] {
            if let Some(o) = v.pointer_mut(p).and_then(Value::as_object_mut) {
                for h in o.values_mut() {
                    if let Some(h) = h.as_object_mut() {
                        h.remove("cdf");
                    }
                }
            }
        }
        v
    };
    let out = json!({
        "bench": "fci",
        "gym": GYM,
        "peer": {"name": "franka-sim", "motion_limit_check": !lenient_peer, "communication_check": true},
        "reply_budget_us": BUDGET_US,
        "fci_over_budget_fraction": over_budget(c),
        "sim_host": strip(sim),
        "fci": strip(fci),
    });
    println!("{out}");
    Ok(out)
}

/// The fraction of answers above the budget, from the reply histogram's CDF (linear between its
/// points: every percent, then finer in the tail).
fn over_budget(c: &Value) -> f64 {
    let pts: Vec<(f64, f64)> = c
        .pointer("/reply_latency/cdf")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .filter_map(|p| Some((p.get(0)?.as_f64()?, p.get(1)?.as_f64()?)))
        .collect();
    let below = match pts.iter().position(|(us, _)| *us > BUDGET_US) {
        None => 1.0,
        Some(0) => 0.0,
        Some(i) => {
            let ((u0, f0), (u1, f1)) = (pts[i - 1], pts[i]);
            f0 + (f1 - f0) * (BUDGET_US - u0) / (u1 - u0)
        }
    };
    1.0 - below
}
