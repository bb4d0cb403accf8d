#![doc = include_str!("../README.md")]

use std::cell::Cell;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::bail;
use controllers::RobotModel;
use franka::{FrankaError, JointPositions, MoveControllerMode, RealtimeConfig, Robot, RobotOptions};
use ipc_schema::process::{self, PeerWatch};
use ipc_schema::{
    JointCommand, Pose, Qos, Services, SimInfo, SimState, ROBOT_NEEDS_OPERATOR, ROBOT_OK, ROBOT_RECOVERING,
};
use runtime::robot_config::Reflexes;
use runtime::Histogram;

/// How r2g-fci runs.
#[derive(Debug, Clone)]
pub struct Options {
    pub instance: String,
    /// Scene whose `[robot]` names the URDF and TCP (FK of the reported TCP pose, finger range).
    pub scene: PathBuf,
    /// The robot's FCI address, `host` or `host:port` (port 1337 when omitted).
    pub address: String,
    /// Contact and collision thresholds and the reflex window (`config/robot.json`, `franka`).
    pub reflexes: Reflexes,
    /// How long after a robot state the runtime's command may arrive and still be sent, µs. The
    /// robot waits about 300 µs of a 1 ms cycle for the answer; later ones are not sent (the
    /// robot extrapolates that cycle and counts it lost).
    pub reply_budget_us: u64,
    /// Cycles in a row without the runtime's answer after which the motion is finished at the
    /// last sent position (the robot then holds by itself), well before the robot's own
    /// communication reflex (20 lost cycles in a row).
    pub max_missed: u32,
    /// The Franka Hand on the same host (port 1338), driven off the loop thread.
    pub gripper: bool,
    /// Require a real-time kernel (franka-rs `RealtimeConfig::Enforce`).
    pub realtime: bool,
    /// The FCI version the robot must speak (5: Panda, 10: FR3); None takes what it announces.
    pub fci_version: Option<u16>,
    /// Cameras that camera hosts publish for this instance (the robot config's `cameras`): the
    /// camera list agents read names them.
    pub cameras: Vec<String>,
}

/// What one run measured.
#[derive(Default)]
pub struct Stats {
    /// Robot states read (one per robot cycle while a motion runs).
    pub states: u64,
    /// Robot cycles with no state (gaps in the robot's own clock).
    pub packets_lost: u64,
    /// Commands sent in time.
    pub replies: u64,
    /// States the runtime did not answer within the budget.
    pub late_or_missing: u64,
    /// From reading a state to sending the answer, for the commands sent.
    pub reply_latency: Histogram,
    /// Reflexes recovered from, and recoveries that failed.
    pub reflexes: u64,
    pub failed_recoveries: u64,
    /// Motions started (the first, and one after each recovery or silence of the runtime).
    pub motions: u64,
}

impl Stats {
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "states": self.states,
            "packets_lost": self.packets_lost,
            "replies": self.replies,
            "late_or_missing": self.late_or_missing,
            "reply_latency": self.reply_latency.summary(),
            "reflexes": self.reflexes,
            "failed_recoveries": self.failed_recoveries,
            "motions": self.motions,
        })
    }
}

type Pub<T> = iceoryx2::port::publisher::Publisher<iceoryx2::prelude::ipc::Service, T, ()>;
type Sub<T> = iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, T, ()>;

/// The robot side's ports: the same services r2g-sim offers, so the runtime cannot tell.
struct Ports {
    _node: iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    state: Pub<SimState>,
    command: Sub<JointCommand>,
    info: Pub<SimInfo>,
    sim_info: SimInfo,
    wake: iceoryx2::port::listener::Listener<iceoryx2::prelude::ipc::Service>,
    control_wake: iceoryx2::port::notifier::Notifier<iceoryx2::prelude::ipc::Service>,
    /// The largest `JointCommand::clear_seq` received (the operator's resets so far).
    clear_seq: Cell<u64>,
}

impl Ports {
    fn open(instance: &str, cameras: &[String]) -> anyhow::Result<Self> {
        let mut sim_info =
            SimInfo { schema: ipc_schema::SCHEMA_VERSION, physics_timestep_s: 1e-3, ..Default::default() };
        for (i, c) in cameras.iter().take(ipc_schema::MAX_CAMERAS).enumerate() {
            ipc_schema::write_str(&mut sim_info.camera_names[i], c);
            sim_info.camera_count += 1;
        }
        let services = Services::new(instance)?;
        let node = ipc_schema::node(&process::sim_node(instance))?;
        let state = ipc_schema::open_or_create_pubsub::<SimState>(&node, &services.sim_state(), Qos::STREAM)?
            .publisher_builder()
            .create()?;
        let command = ipc_schema::open_or_create_pubsub::<JointCommand>(&node, &services.command(), Qos::STREAM)?
            .subscriber_builder()
            .create()?;
        let info = ipc_schema::open_or_create_pubsub::<SimInfo>(&node, &services.sim_info(), Qos::STREAM)?
            .publisher_builder()
            .create()?;
        let wake = ipc_schema::open_or_create_event(&node, &services.sim_wake())?.listener_builder().create()?;
        let control_wake =
            ipc_schema::open_or_create_event(&node, &services.control_wake())?.notifier_builder().create()?;
        Ok(Self { _node: node, state, command, info, sim_info, wake, control_wake, clear_seq: Cell::new(0) })
    }

    /// The operator's count of fault resets in the newest command received so far.
    fn clear_seq(&self) -> anyhow::Result<u64> {
        self.newest(0)?;
        Ok(self.clear_seq.get())
    }

    fn publish(&self, s: SimState) -> anyhow::Result<()> {
        if s.seq % 200 == 1 {
            // Late subscribers (agents) learn from it which cameras exist: those of the camera
            // hosts (this robot side renders none).
            self.info.send_copy(self.sim_info)?;
        }
        self.state.send_copy(s)?;
        self.control_wake.notify()?;
        Ok(())
    }

    /// The newest command computed from the state `seq` of this session, waiting for it until
    /// `deadline`. Commands for older states are dropped: they are late.
    fn answer(&self, session: u64, seq: u64, deadline: Instant) -> anyhow::Result<Option<JointCommand>> {
        loop {
            let mut found = None;
            while let Some(c) = self.command.receive()? {
                self.clear_seq.set(self.clear_seq.get().max(c.clear_seq));
                if c.session == session && c.state_seq == seq {
                    found = Some(*c);
                }
            }
            if found.is_some() {
                return Ok(found);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            let _ = self.wake.timed_wait(|_| {}, deadline - now);
        }
    }

    /// The newest command of this session, if any (outside a motion: clear requests).
    fn newest(&self, session: u64) -> anyhow::Result<Option<JointCommand>> {
        let mut found = None;
        while let Some(c) = self.command.receive()? {
            self.clear_seq.set(self.clear_seq.get().max(c.clear_seq));
            if c.session == session {
                found = Some(*c);
            }
        }
        Ok(found)
    }
}

/// The Franka Hand, driven from its own thread: the loop only stores the commanded opening and
/// reads the measured one (atomics), the hand's blocking TCP commands never reach it.
struct Hand {
    target_m: Arc<AtomicU64>,
    width_m: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Hand {
    fn start(host: &str, speed_m_s: f64) -> anyhow::Result<Self> {
        let hand = franka::Gripper::new(host).map_err(|e| anyhow::anyhow!("Franka Hand at {host}: {e}"))?;
        let first = hand.read_once().map_err(|e| anyhow::anyhow!("Franka Hand at {host}: {e}"))?;
        let target_m = Arc::new(AtomicU64::new(first.width.to_bits()));
        let width_m = Arc::new(AtomicU64::new(first.width.to_bits()));
        let stop = Arc::new(AtomicBool::new(false));
        let (t, w, s) = (target_m.clone(), width_m.clone(), stop.clone());
        let thread = std::thread::Builder::new().name("franka-hand".into()).spawn(move || {
            let mut sent = f64::NAN;
            while !s.load(Relaxed) {
                let want = f64::from_bits(t.load(Relaxed));
                // A new target more than 2 mm from the last one sent: move there (blocking).
                if !(want - sent).abs().le(&0.002) {
                    if let Err(e) = hand.move_gripper(want, speed_m_s) {
                        eprintln!("r2g-fci: Franka Hand move to {want:.3} m failed: {e}");
                    }
                    sent = want;
                }
                match hand.read_once() {
                    Ok(g) => w.store(g.width.to_bits(), Relaxed),
                    Err(e) => eprintln!("r2g-fci: Franka Hand state: {e}"),
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        })?;
        Ok(Self { target_m, width_m, stop, thread: Some(thread) })
    }
}

impl Drop for Hand {
    fn drop(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Connects to the robot and serves it as the instance's robot side until SIGINT/SIGTERM, the
/// runtime stopping, or the robot connection failing.
pub fn run(opts: &Options) -> anyhow::Result<Stats> {
    let (model, _) = runtime::scene_robot(&opts.scene)?;
    let realtime = if opts.realtime { RealtimeConfig::Enforce } else { RealtimeConfig::Ignore };
    let version = match opts.fci_version {
        None => franka::robot::VersionPolicy::Auto,
        Some(5) => franka::robot::VersionPolicy::Exact(franka::FciVersion::V5),
        Some(10) => franka::robot::VersionPolicy::Exact(franka::FciVersion::V10),
        Some(v) => bail!("FCI version {v} is not one this build speaks: 5 (Panda) or 10 (FR3)"),
    };
    // Threads of our own first: connecting raises this thread to the highest real-time priority
    // (libfranka's way), which threads started afterwards would inherit; these do blocking I/O.
    let control = PeerWatch::spawn(process::control_node(&opts.instance), Duration::from_secs(30));
    let hand = if opts.gripper {
        let host = opts.address.split(':').next().unwrap_or(&opts.address);
        Some(Hand::start(host, model.finger_speed_m_s * 2.0)?)
    } else {
        None
    };
    let robot = Robot::with_options(&opts.address, RobotOptions::new(realtime).with_version(version))
        .map_err(|e| anyhow::anyhow!("connecting to the robot at {}: {}", opts.address, describe(&e)))?;
    let r = &opts.reflexes;
    robot
        .set_collision_behavior_simple(
            r.contact_torque_nm,
            r.collision_torque_nm,
            r.contact_force_n,
            r.collision_force_n,
        )
        .map_err(|e| anyhow::anyhow!("setting the collision thresholds: {e}"))?;

    ipc_schema::cleanup_dead_nodes();
    let ports = Ports::open(&opts.instance, &opts.cameras)?;
    let mut side = Side::new(&model, hand);
    eprintln!(
        "r2g-fci: instance '{}' serves the robot at {} (FCI version {})",
        opts.instance,
        opts.address,
        robot.server_version()
    );
    let mut stats = Stats::default();
    let mut errored: Option<String> = None;
    loop {
        if process::stop_requested() {
            return Ok(stats);
        }
        if control.lost() {
            bail!("r2g-control of instance '{}' stopped; r2g-fci stops too (the robot holds by itself)", opts.instance);
        }
        match errored.take() {
            None => {
                // Idle: states at the robot's rate until the runtime answers one, then move.
                if side.idle_until_answered(&robot, &ports, &control)? {
                    match side.motion(&robot, &ports, opts, &mut stats) {
                        Ok(()) => {}
                        Err(e) if is_reflex(&e) => errored = Some(motion_errors(&robot, &e)),
                        Err(e) => return Err(anyhow::anyhow!("the robot connection failed: {}", describe(&e))),
                    }
                }
            }
            Some(why) => {
                // One of the robot's reflexes stopped the motion: say so, then recover once.
                side.publish_status(&robot, &ports, ROBOT_RECOVERING, &why)?;
                match robot.automatic_error_recovery() {
                    Ok(()) => {
                        stats.reflexes += 1;
                        side.reflexes += 1;
                        eprintln!("r2g-fci: reflex ({why}); automatic recovery cleared it");
                        // The text stays: a runtime that missed the recovering state still learns why.
                        side.publish_status(&robot, &ports, ROBOT_OK, &why)?;
                    }
                    Err(e) => {
                        stats.failed_recoveries += 1;
                        eprintln!("r2g-fci: reflex ({why}); automatic recovery failed: {}", describe(&e));
                        let text = format!("{why}; recovery failed: {}", describe(&e));
                        // Wait for the operator's reset (the runtime counts them in every
                        // command), publishing states meanwhile, then try again. Only one made
                        // after this failure counts: earlier ones (of another fault, or of the
                        // gripper's) are in the count already.
                        let mut clear_seen = ports.clear_seq()?;
                        loop {
                            let cleared = side.idle_until_cleared(&robot, &ports, &control, &text, clear_seen)?;
                            let Some(c) = cleared else { break };
                            clear_seen = c;
                            match robot.automatic_error_recovery() {
                                Ok(()) => {
                                    side.publish_status(&robot, &ports, ROBOT_OK, &why)?;
                                    break;
                                }
                                Err(e) => {
                                    eprintln!("r2g-fci: recovery after the operator's reset failed: {}", describe(&e))
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The state the robot side publishes, and its counters.
struct Side<'m> {
    model: &'m RobotModel,
    hand: Option<Hand>,
    session: u64,
    seq: u64,
    command_seq: u64,
    reflexes: u64,
    error: u32,
    text: String,
}

impl<'m> Side<'m> {
    fn new(model: &'m RobotModel, hand: Option<Hand>) -> Self {
        Self {
            model,
            hand,
            session: new_session(),
            seq: 0,
            command_seq: 0,
            reflexes: 0,
            error: ROBOT_OK,
            text: String::new(),
        }
    }

    fn state(&mut self, rs: &franka::RobotState) -> SimState {
        self.seq += 1;
        let tcp = self.model.kin.fk(&rs.q, self.model.kin.tcp);
        let (p, q) = controllers::kinematics::to_arrays(&tcp);
        let finger_m = self.hand.as_ref().map_or(0.0, |h| 0.5 * f64::from_bits(h.width_m.load(Relaxed)));
        let mut s = SimState {
            seq: self.seq,
            command_seq: self.command_seq,
            // The robot's own clock: the runtime advances one tick per robot cycle it covers.
            sim_time_s: rs.time.as_millis() as f64 * 1e-3,
            q_rad: rs.q,
            dq_rad_s: rs.dq,
            finger_m,
            finger_max_m: self.model.finger_max_m,
            base_from_tcp: Pose { position_m: p, quat_xyzw: q },
            external_force_n: [rs.O_F_ext_hat_K[0], rs.O_F_ext_hat_K[1], rs.O_F_ext_hat_K[2]],
            session: self.session,
            paced: 1,
            robot_error: self.error,
            reflexes: self.reflexes,
            ..Default::default()
        };
        s.set_error(&self.text);
        s.published_ns = ipc_schema::monotonic_ns();
        s
    }

    fn publish_status(&mut self, robot: &Robot, ports: &Ports, error: u32, text: &str) -> anyhow::Result<()> {
        (self.error, self.text) = (error, text.to_string());
        let rs = robot.read_once().map_err(|e| anyhow::anyhow!("reading the robot state: {}", describe(&e)))?;
        let s = self.state(&rs);
        ports.publish(s)
    }

    /// Publishes states until the runtime answers one (true), a stop is requested or the
    /// runtime is gone (false).
    fn idle_until_answered(
        &mut self,
        robot: &Robot,
        ports: &Ports,
        control: &process::PeerWatch,
    ) -> anyhow::Result<bool> {
        self.error = ROBOT_OK;
        loop {
            if process::stop_requested() || control.lost() {
                return Ok(false);
            }
            let rs = robot.read_once().map_err(|e| anyhow::anyhow!("reading the robot state: {}", describe(&e)))?;
            let s = self.state(&rs);
            ports.publish(s)?;
            if ports.answer(self.session, s.seq, Instant::now() + Duration::from_micros(900))?.is_some() {
                return Ok(true);
            }
        }
    }

    /// Publishes states (flagged: needs an operator) until the runtime's commands carry an
    /// operator reset newer than `seen`; returns its count (None: stop requested, or the
    /// runtime is gone).
    fn idle_until_cleared(
        &mut self,
        robot: &Robot,
        ports: &Ports,
        control: &process::PeerWatch,
        text: &str,
        seen: u64,
    ) -> anyhow::Result<Option<u64>> {
        (self.error, self.text) = (ROBOT_NEEDS_OPERATOR, text.to_string());
        loop {
            if process::stop_requested() || control.lost() {
                return Ok(None);
            }
            let rs = robot.read_once().map_err(|e| anyhow::anyhow!("reading the robot state: {}", describe(&e)))?;
            let s = self.state(&rs);
            ports.publish(s)?;
            ports.newest(self.session)?;
            if ports.clear_seq.get() > seen {
                return Ok(Some(ports.clear_seq.get()));
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// One joint-position motion, each robot state answered with the runtime's command for it.
    /// Ends (the motion finished at the last position sent) on a stop request or when the
    /// runtime stops answering; a reflex or a lost connection is the error.
    fn motion(&mut self, robot: &Robot, ports: &Ports, opts: &Options, stats: &mut Stats) -> Result<(), FrankaError> {
        let io = |e: anyhow::Error| FrankaError::Network(format!("shared memory: {e:#}"));
        stats.motions += 1;
        let mut control = robot.start_joint_position_control(MoveControllerMode::JointImpedance)?;
        let budget = Duration::from_micros(opts.reply_budget_us);
        let mut missed = 0u32;
        let mut last_ms: Option<u64> = None;
        loop {
            let (rs, _) = control.read_once()?;
            let read = Instant::now();
            stats.states += 1;
            let now_ms = rs.time.as_millis();
            if let Some(prev) = last_ms {
                stats.packets_lost += now_ms.saturating_sub(prev + 1);
            }
            last_ms = Some(now_ms);
            let s = self.state(&rs);
            ports.publish(s).map_err(io)?;
            // An answer that comes after the budget is not sent: the robot has extrapolated this
            // cycle already, and a late command would be a velocity jump to it.
            let answer =
                ports.answer(self.session, s.seq, read + budget).map_err(io)?.filter(|_| read.elapsed() <= budget);
            let stop = process::stop_requested();
            match answer {
                Some(c) if !stop => {
                    if c.q_rad.iter().any(|v| !v.is_finite()) {
                        // Never reaches the robot: the runtime's limiter does not produce these.
                        stats.late_or_missing += 1;
                        continue;
                    }
                    control.write_once(&JointPositions::new(c.q_rad), None)?;
                    stats.reply_latency.record(read.elapsed().as_nanos() as u64);
                    stats.replies += 1;
                    self.command_seq = c.seq;
                    if let Some(h) = &self.hand {
                        h.target_m.store((2.0 * c.finger_m).to_bits(), Relaxed);
                    }
                    missed = 0;
                }
                _ => {
                    stats.late_or_missing += u64::from(!stop);
                    missed += 1;
                    if stop || missed >= opts.max_missed {
                        // Finish where the robot's own interpolation has the arm now (it went on
                        // past the last command while answers were missing); it holds there.
                        let mut end = JointPositions::new(rs.q_d);
                        end.motion_finished = true;
                        control.write_once(&end, None)?;
                        if !stop {
                            eprintln!(
                                "r2g-fci: the runtime did not answer {missed} robot cycles in a row; motion finished, the arm holds"
                            );
                            // A new session: the runtime takes it as a robot side that came back
                            // (the running chunk fails) and resumes from the measured joints
                            // once the arm rests, never from where its own commands had got to.
                            self.session = new_session();
                        }
                        return Ok(());
                    }
                }
            }
        }
    }
}

/// A session number no earlier run or motion of this process used.
fn new_session() -> u64 {
    ((u64::from(std::process::id()) << 32) ^ ipc_schema::monotonic_ns()) | 1
}

/// A motion that one of the robot's own reflexes ended (rather than a lost connection).
fn is_reflex(e: &FrankaError) -> bool {
    matches!(e, FrankaError::Control(_))
}

/// The robot's own names for what stopped the motion.
fn motion_errors(robot: &Robot, e: &FrankaError) -> String {
    match robot.read_once() {
        Ok(rs) if rs.last_motion_errors.0.iter().any(|&b| b) => rs.last_motion_errors.to_string(),
        Ok(rs) if rs.current_errors.0.iter().any(|&b| b) => rs.current_errors.to_string(),
        _ => describe(e),
    }
}

/// An FCI error in one line (franka-rs prefixes its messages with "libfranka: ").
fn describe(e: &FrankaError) -> String {
    let text = match e {
        FrankaError::IncompatibleVersion { server_version, library_version } => format!(
            "the robot speaks FCI version {server_version} and this build version {library_version}: update the robot's system image or this build (see fci/README.md)"
        ),
        other => other.to_string(),
    };
    text.trim_start_matches("libfranka: ").to_string()
}
