//! r2g-sim: the MuJoCo sim-host of one gym instance.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use ipc_schema::process::{self, PeerWatch};
use ipc_schema::{JointCommand, Qos, Services, SimInfo, SimReset, SimState};
use sim_host::render::{self, RenderConfig, Snapshot};
use sim_host::Sim;

/// MuJoCo sim-host: steps physics once per joint command from r2g-control, publishes the
/// measured robot state, and renders the scene's cameras into shared memory.
/// Normally started by `r2g up`, not by hand.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Scene file (TOML) of the gym.
    scene: PathBuf,
    /// Instance name; every shared-memory service is prefixed with it.
    #[arg(long, default_value = "default")]
    instance: String,
    /// Camera frames per second (wall clock); 0 turns rendering off.
    #[arg(long, default_value_t = 10.0)]
    render_hz: f64,
    /// Write the compiled MJCF here and continue (for inspection).
    #[arg(long)]
    dump_mjcf: Option<PathBuf>,
    /// With --dump-mjcf: exit after writing it, starting nothing (tests render ground truth
    /// from the very model the sim-host runs).
    #[arg(long, requires = "dump_mjcf")]
    exit_after_dump: bool,
    /// Record the native trace and judge each episode (ended by a reset or by stopping) into
    /// this folder. Nothing of it crosses to agents.
    #[arg(long)]
    trace_dir: Option<PathBuf>,
    /// Keep running while no control process is there (a service whose control unit is
    /// restarted by the operator); without it the sim-host stops when its control process
    /// goes away, as `r2g up` expects.
    #[arg(long)]
    outlive_control: bool,
    /// A camera whose frames a camera host publishes (a real device, the robot config's
    /// `cameras`); repeatable. It is listed for agents, and a scene camera of that name is not
    /// rendered.
    #[arg(long = "camera-host", value_name = "NAME")]
    camera_hosts: Vec<String>,
    /// Augmentation seed of every episode (0: the scene as written; otherwise each object
    /// moves by its jitter, and by --perturb).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Move free objects further at each reset: `xy=0.05,yaw=30[,objects=block+plate]` (up
    /// to 5 cm in x and y, 30 degrees of yaw), drawn from --seed, clear of everything else.
    #[arg(long, value_name = "SPEC", requires = "seed")]
    perturb: Option<sim_host::placement::Perturbation>,
    /// Serve gymnasium environments: the evaluator's verdict on the episode so far and the seed
    /// of the next episode, on the instance's `env/` services (never opened by `robo`).
    #[arg(long)]
    env: bool,
}

/// Writes an episode's trace and its evaluation; a failure to write is reported, not fatal.
fn finish_episode(sim: &Sim, dir: &std::path::Path, episode: u64, trace: &sim_host::trace::Trace) {
    let evaluation = sim_host::trace::evaluate(&sim.scene, trace);
    let write = || -> anyhow::Result<()> {
        std::fs::create_dir_all(dir)?;
        std::fs::write(dir.join(format!("episode-{episode}.trace.json")), serde_json::to_vec(trace)?)?;
        // Written then renamed, so a reader never sees half a verdict.
        let tmp = dir.join(format!(".episode-{episode}.eval.json.tmp"));
        std::fs::write(&tmp, serde_json::to_vec_pretty(&evaluation)?)?;
        std::fs::rename(&tmp, dir.join(format!("episode-{episode}.eval.json")))?;
        Ok(())
    };
    match write() {
        Ok(()) => eprintln!(
            "r2g-sim: episode {episode} judged: success = {} ({})",
            evaluation.success,
            dir.join(format!("episode-{episode}.eval.json")).display()
        ),
        Err(e) => eprintln!("r2g-sim: cannot write the trace of episode {episode} to {}: {e:#}", dir.display()),
    }
}

fn main() {
    if let Err(e) = run() {
        eprintln!("r2g-sim: error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    let args = Args::parse();
    process::install_stop_signals();
    process::die_with_parent();
    let services = Services::new(&args.instance)?;
    let mut sim = Sim::load(&args.scene).with_context(|| format!("loading scene {}", args.scene.display()))?;
    sim.seed = args.seed;
    sim.set_perturbation(args.perturb.clone())?;
    if let Some(note) = sim.placed.as_ref().and_then(|p| p.note.as_ref()) {
        eprintln!("r2g-sim: {note}");
    }
    if let Some(p) = &args.dump_mjcf {
        std::fs::write(p, &sim.mjcf).with_context(|| format!("writing {}", p.display()))?;
        if args.exit_after_dump {
            return Ok(());
        }
    }

    // A predecessor that was SIGKILLed still holds its ports' slots (one state publisher).
    ipc_schema::cleanup_dead_nodes();
    let node = ipc_schema::node(&process::sim_node(&args.instance))?;
    let state_pub = ipc_schema::open_or_create_pubsub::<SimState>(&node, &services.sim_state(), Qos::STREAM)?
        .publisher_builder()
        .create()?;
    let cmd_sub = ipc_schema::open_or_create_pubsub::<JointCommand>(&node, &services.command(), Qos::STREAM)?
        .subscriber_builder()
        .create()?;
    let reset_sub = ipc_schema::open_or_create_pubsub::<SimReset>(&node, &services.sim_reset(), Qos::CONTROL)?
        .subscriber_builder()
        .create()?;
    let info_pub = ipc_schema::open_or_create_pubsub::<SimInfo>(&node, &services.sim_info(), Qos::STREAM)?
        .publisher_builder()
        .create()?;
    let wake = ipc_schema::open_or_create_event(&node, &services.sim_wake())?.listener_builder().create()?;
    let control_wake =
        ipc_schema::open_or_create_event(&node, &services.control_wake())?.notifier_builder().create()?;

    let mut info =
        SimInfo { schema: ipc_schema::SCHEMA_VERSION, physics_timestep_s: sim.scene.timestep_s, ..Default::default() };
    let rendered: Vec<_> = sim
        .scene
        .cameras
        .iter()
        .cloned()
        .zip(sim.layout.cameras.iter().map(|c| c.1))
        .filter(|(c, _)| !args.camera_hosts.contains(&c.name))
        .collect();
    let render_on = args.render_hz > 0.0 && !rendered.is_empty();
    let mut listed: Vec<&str> =
        if render_on { rendered.iter().map(|(c, _)| c.name.as_str()).collect() } else { Vec::new() };
    listed.extend(args.camera_hosts.iter().map(String::as_str));
    anyhow::ensure!(
        listed.len() <= ipc_schema::MAX_CAMERAS,
        "{} cameras ({}) are more than the {} an instance lists",
        listed.len(),
        listed.join(", "),
        ipc_schema::MAX_CAMERAS
    );
    for (i, name) in listed.iter().enumerate() {
        ipc_schema::write_str(&mut info.camera_names[i], name);
    }
    info.camera_count = listed.len() as u32;
    info_pub.send_copy(info)?;

    let stop = Arc::new(AtomicBool::new(false));
    let snapshot = Arc::new(Mutex::new(Snapshot::default()));
    let render_thread = if render_on {
        let cfg = RenderConfig {
            services: services.clone(),
            cameras: rendered,
            base_body: sim.layout.base_body,
            rate_hz: args.render_hz,
        };
        let (model, snap, st) = (sim.model.clone(), snapshot.clone(), stop.clone());
        Some(std::thread::Builder::new().name("render".into()).spawn(move || {
            if let Err(e) = render::run(model, snap, cfg, st) {
                eprintln!("r2g-sim: rendering stopped: {e:#}");
            }
        })?)
    } else {
        None
    };

    let env = if args.env { Some(sim_host::env_service::EnvService::open(&node, &services)?) } else { None };
    let mut trace = (args.trace_dir.is_some() || env.is_some()).then(|| sim.new_trace());
    let mut episode = 1u64;
    if let Some(t) = trace.as_mut() {
        sim.record(t);
    }
    let control = PeerWatch::spawn(process::control_node(&args.instance), Duration::from_secs(30));
    let mut seq = 1u64;
    let mut reset_id = 0u64;
    let mut last_cmd_seq = 0u64;
    let mut snapshot_dirty = true;
    let mut last_publish = std::time::Instant::now();
    let mut last_info = std::time::Instant::now();
    let host_baseline = process::host_baseline();
    // This run's session: commands computed from another run's state are ignored.
    let session = ((u64::from(std::process::id()) << 32) ^ ipc_schema::monotonic_ns()) | 1;
    let publish = |sim: &Sim, seq: u64, cmd: u64, reset_id: u64| -> anyhow::Result<()> {
        let mut state = sim.measure(seq, cmd, reset_id);
        state.session = session;
        state.published_ns = ipc_schema::monotonic_ns();
        state_pub.send_copy(state)?;
        control_wake.notify()?;
        Ok(())
    };
    publish(&sim, seq, 0, 0)?;
    eprintln!(
        "r2g-sim: instance '{}' scene '{}' ready ({} cameras at {} Hz)",
        args.instance, sim.scene.name, info.camera_count, args.render_hz
    );

    let result = loop {
        if process::stop_requested() {
            break Ok(());
        }
        if control.lost() && !args.outlive_control {
            break Err(anyhow::anyhow!("r2g-control of instance '{}' stopped; sim-host stops too", args.instance));
        }
        // Sleep until the runtime publishes something; the timeout keeps the checks above live.
        let _ = wake.timed_wait(|_| {}, Duration::from_millis(20));
        let mut stepped = false;
        while let Some(r) = reset_sub.receive()? {
            if let (Some(dir), Some(t)) = (&args.trace_dir, trace.as_ref()) {
                finish_episode(&sim, dir, episode, t);
                episode += 1;
            }
            sim.reset();
            if let Some(t) = trace.as_mut() {
                // Made after the reset, so it carries this episode's seed.
                *t = sim.new_trace();
                sim.record(t);
            }
            reset_id = r.id;
            seq += 1;
            sim.reset_state_seq = seq;
            publish(&sim, seq, last_cmd_seq, reset_id)?;
            snapshot_dirty = true;
        }
        // Step once per command sample, oldest first; a stream has at most one buffered.
        while let Some(cmd) = cmd_sub.receive()? {
            if cmd.seq <= last_cmd_seq || cmd.session != session {
                continue;
            }
            last_cmd_seq = cmd.seq;
            sim.step(&cmd);
            if let Some(t) = trace.as_mut() {
                sim.record(t);
            }
            seq += 1;
            publish(&sim, seq, cmd.seq, reset_id)?;
            stepped = true;
        }
        if let (Some(e), Some(t)) = (&env, trace.as_ref()) {
            // After the steps: a verdict judges the trace up to the newest state.
            e.serve(&mut sim, t, reset_id)?;
        }
        snapshot_dirty |= stepped;
        if !stepped && last_publish.elapsed() > Duration::from_millis(20) {
            // Idle (lockstep between requests, or before the runtime starts): repeat the state
            // so late subscribers see it; the runtime ignores repeats.
            publish(&sim, seq, last_cmd_seq, reset_id)?;
        }
        if last_info.elapsed() > Duration::from_millis(200) {
            // History reaches late subscribers with a new send...
            info_pub.send_copy(info)?;
            last_info = std::time::Instant::now();
        } else if !stepped && !host_baseline {
            // ... or when the publisher takes note of them: an agent connecting to an idle
            // instance has the camera list within one idle round, not up to 200 ms later.
            use iceoryx2::port::update_connections::UpdateConnections;
            let _ = info_pub.update_connections();
        }
        if stepped || last_publish.elapsed() > Duration::from_millis(20) {
            last_publish = std::time::Instant::now();
        }
        if snapshot_dirty && render_on {
            if let Ok(mut s) = snapshot.try_lock() {
                s.qpos.clear();
                s.qpos.extend_from_slice(sim.qpos());
                s.sim_time_s = sim.time_s();
                s.state_seq = seq;
                s.reset_id = reset_id;
                snapshot_dirty = false;
            }
        }
    };
    if let (Some(dir), Some(t)) = (&args.trace_dir, trace.as_ref()) {
        finish_episode(&sim, dir, episode, t);
    }
    stop.store(true, Ordering::Relaxed);
    if let Some(t) = render_thread {
        let _ = t.join();
    }
    result
}
