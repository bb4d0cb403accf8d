#![doc = include_str!("../README.md")]

pub mod alloc_count;
pub mod calibration;
pub mod control_main;
pub mod controller;
pub mod health;
pub mod launch;
pub mod operator;
pub mod planner;
pub mod robot_config;
pub mod rt;
pub mod stats;

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context};
use controllers::safety::SafetyChecks;
use controllers::RobotModel;
use ipc_schema::process::{self, PeerWatch};
use ipc_schema::{
    GripperState, JointCommand, Mode, Qos, Reply, Request, RobotState, RuntimeInfo, Services, SimReset, SimState,
};

pub use controller::Controller;
pub use robot_config::RobotConfig;
pub use stats::{Histogram, TickStats};

/// How r2g-control runs.
#[derive(Debug, Clone)]
pub struct RunConfig {
    pub instance: String,
    pub mode: Mode,
    /// Scene file; only its `[robot]` table is read (URDF path and TCP link).
    pub scene: PathBuf,
    pub period_ns: u64,
    /// Busy-wait this long before each deadline (0: pure sleep).
    pub spin_ns: u64,
    pub fifo_priority: Option<i32>,
    pub cpu: Option<usize>,
    /// Stop after this long (benchmarks); None runs until SIGINT/SIGTERM.
    pub duration: Option<Duration>,
    /// Wall mode: the robot side counts as lost when no state arrives for this long; the arm
    /// holds and requests are refused until fresh state arrives (the loop keeps cycling).
    pub state_timeout: Duration,
    /// Members of this group may clear faults over the operator socket (besides root and the
    /// runtime's own user).
    pub operator_group: Option<String>,
    /// Called on the loop thread after every wall-mode cycle, outside the tick. Only test
    /// builds set it (runtime/examples/r2g-control-stall.rs stalls the loop thread with it).
    pub after_cycle: Option<fn()>,
    /// Profile and the limits added on top of the robot's (`config/robot.json`).
    pub robot: RobotConfig,
    /// The calibration files `robot` names, as read at start.
    pub calibration: calibration::Calibration,
    /// What `get_state()["setup"]` reports ([`setup_report`]).
    pub setup: String,
}

/// The setup an instance runs, as agents see it (`get_state()["setup"]`): the gym (the scene's
/// folder name) and the SHA-256 of the robot configuration file's bytes (`None`: the built-in
/// defaults). Memory records are keyed by it, so nothing per-episode goes in.
pub fn setup_report(scene: &Path, robot_config: Option<&[u8]>) -> String {
    use sha2::Digest as _;
    let gym = scene.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned());
    let sha = robot_config.map(|b| sha2::Sha256::digest(b).iter().map(|x| format!("{x:02x}")).collect::<String>());
    serde_json::json!({"gym": gym, "robot_config_sha256": sha}).to_string()
}

/// Reads the robot of a scene file: its URDF (relative to the scene), TCP link and limit
/// profile (`limits = "panda" | "fr3"`, default panda).
pub fn robot_from_scene(scene: &Path) -> anyhow::Result<RobotModel> {
    Ok(scene_robot(scene)?.0)
}

/// The robot of a scene and the safety checks for it: its collision geometry, the table as an
/// obstacle, and the workspace (`[safety] workspace_min_m`, `workspace_max_m`, `margin_m`;
/// by default the table's footprint up to 1 m above it, and a 2 mm margin).
pub fn scene_robot(scene: &Path) -> anyhow::Result<(RobotModel, SafetyChecks)> {
    scene_robot_with_tcp(scene, None)
}

/// As [`scene_robot`], with a measured flange-to-TCP transform (row-major 4×4, from
/// [`calibration::Calibration::tcp`]) in place of the description's TCP link: the one place a
/// measured TCP enters the robot model, before anything (IK, checks, the reported `ee_pose`)
/// is built from it.
pub fn scene_robot_with_tcp(
    scene: &Path,
    flange_from_tcp: Option<&calibration::Matrix>,
) -> anyhow::Result<(RobotModel, SafetyChecks)> {
    let text = std::fs::read_to_string(scene).with_context(|| format!("reading scene {}", scene.display()))?;
    let table: toml::Table = toml::from_str(&text).with_context(|| format!("parsing scene {}", scene.display()))?;
    let robot = table.get("robot").and_then(|r| r.as_table()).context("scene has no [robot] table")?;
    let urdf = robot.get("urdf").and_then(|u| u.as_str()).context("scene [robot] has no urdf path")?;
    let tcp = robot.get("tcp_link").and_then(|u| u.as_str()).unwrap_or("hand_tcp");
    let limits = robot.get("limits").and_then(|u| u.as_str()).unwrap_or("panda");
    let profile = controllers::Profile::from_name(limits)
        .with_context(|| format!("scene [robot] limits = \"{limits}\": use \"panda\" or \"fr3\""))?;
    let urdf_path = scene.parent().unwrap_or(Path::new(".")).join(urdf);
    let xml = std::fs::read_to_string(&urdf_path).with_context(|| format!("reading URDF {}", urdf_path.display()))?;
    let mut model = RobotModel::from_urdf_str(&xml, tcp, profile)?;
    if let Some(t) = flange_from_tcp {
        let r = [t[0][0], t[0][1], t[0][2], t[1][0], t[1][1], t[1][2], t[2][0], t[2][1], t[2][2]];
        let iso =
            controllers::kinematics::from_arrays([t[0][3], t[1][3], t[2][3]], controllers::math::quat_from_mat(&r));
        model.kin.set_tcp(iso)?;
    }

    let vec3 = |t: Option<&toml::Table>, key: &str| -> anyhow::Result<Option<[f64; 3]>> {
        let Some(v) = t.and_then(|t| t.get(key)) else { return Ok(None) };
        let a: Vec<f64> = v.clone().try_into().with_context(|| format!("scene: {key} must be 3 numbers"))?;
        anyhow::ensure!(a.len() == 3, "scene: {key} must be 3 numbers, got {}", a.len());
        Ok(Some([a[0], a[1], a[2]]))
    };
    let base = vec3(Some(robot), "base_position_m")?.unwrap_or([0.0; 3]);
    let yaw = robot.get("base_yaw_rad").and_then(|v| v.as_float()).unwrap_or(0.0);
    let tab = table.get("table").and_then(|t| t.as_table());
    let table_spec = match tab {
        Some(t) => {
            let top = vec3(Some(t), "top_center_m")?.context("scene [table] has no top_center_m")?;
            let size: Vec<f64> = t
                .get("size_m")
                .context("scene [table] has no size_m")?
                .clone()
                .try_into()
                .context("scene [table] size_m must be 2 numbers")?;
            anyhow::ensure!(size.len() == 2, "scene [table] size_m must be 2 numbers");
            Some(controllers::safety::Table { top_center_m: top, size_m: [size[0], size[1]] })
        }
        None => None,
    };
    let safety = table.get("safety").and_then(|t| t.as_table());
    let ws = match (vec3(safety, "workspace_min_m")?, vec3(safety, "workspace_max_m")?) {
        (Some(lo), Some(hi)) => Some((lo, hi)),
        (None, None) => None,
        _ => anyhow::bail!("scene [safety] needs both workspace_min_m and workspace_max_m"),
    };
    let margin = safety.and_then(|t| t.get("margin_m")).and_then(|v| v.as_float()).unwrap_or(0.002);
    let checks = SafetyChecks::for_scene(&xml, Some(&urdf_path), &model, base, yaw, table_spec, ws, margin)
        .with_context(|| format!("safety checks for scene {}", scene.display()))?;
    Ok((model, checks))
}

type Pub<T> = iceoryx2::port::publisher::Publisher<iceoryx2::prelude::ipc::Service, T, ()>;
type Sub<T> = iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, T, ()>;
type Notifier = iceoryx2::port::notifier::Notifier<iceoryx2::prelude::ipc::Service>;
type Listener = iceoryx2::port::listener::Listener<iceoryx2::prelude::ipc::Service>;

/// Every port of the runtime, created once before the loop.
struct Ports {
    _node: iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    state_sub: Sub<SimState>,
    cmd_pub: Pub<JointCommand>,
    reset_pub: Pub<SimReset>,
    robot_pub: Pub<RobotState>,
    info_pub: Pub<RuntimeInfo>,
    req_sub: Sub<Request>,
    reply_pub: Pub<Reply>,
    sim_wake: Notifier,
    agent_wake: Notifier,
    wake: Listener,
    /// A gripper driven by its own process (`r2g-robotiq`), when the robot config names one.
    gripper_sub: Option<Sub<GripperState>>,
}

/// How long a gripper driver may stay silent before the arm holds, ns.
const GRIPPER_TIMEOUT_NS: u64 = 250_000_000;

impl Ports {
    fn open(services: &Services, gripper: bool) -> anyhow::Result<Self> {
        let node = ipc_schema::node(&process::control_node(&services.instance))?;
        let gripper_sub = if gripper {
            Some(
                ipc_schema::open_or_create_pubsub::<GripperState>(&node, &services.gripper_state(), Qos::STREAM)?
                    .subscriber_builder()
                    .create()?,
            )
        } else {
            None
        };
        Ok(Self {
            gripper_sub,
            state_sub: ipc_schema::open_or_create_pubsub::<SimState>(&node, &services.sim_state(), Qos::STREAM)?
                .subscriber_builder()
                .create()?,
            cmd_pub: ipc_schema::open_or_create_pubsub::<JointCommand>(&node, &services.command(), Qos::STREAM)?
                .publisher_builder()
                .create()?,
            reset_pub: ipc_schema::open_or_create_pubsub::<SimReset>(&node, &services.sim_reset(), Qos::CONTROL)?
                .publisher_builder()
                .create()?,
            robot_pub: ipc_schema::open_or_create_pubsub::<RobotState>(
                &node,
                &services.robot_state(),
                Qos::ROBOT_STATE,
            )?
            .publisher_builder()
            .create()?,
            info_pub: ipc_schema::open_or_create_pubsub::<RuntimeInfo>(&node, &services.runtime_info(), Qos::STREAM)?
                .publisher_builder()
                .create()?,
            req_sub: ipc_schema::open_or_create_pubsub::<Request>(&node, &services.request(), Qos::REQUESTS)?
                .subscriber_builder()
                .create()?,
            reply_pub: ipc_schema::open_or_create_pubsub::<Reply>(&node, &services.reply(), Qos::REPLIES)?
                .publisher_builder()
                .create()?,
            sim_wake: ipc_schema::open_or_create_event(&node, &services.sim_wake())?.notifier_builder().create()?,
            agent_wake: ipc_schema::open_or_create_event(&node, &services.agent_wake())?.notifier_builder().create()?,
            wake: ipc_schema::open_or_create_event(&node, &services.control_wake())?.listener_builder().create()?,
            _node: node,
        })
    }

    /// Takes the newest state, if any arrived.
    #[inline]
    fn newest_state(&self, latest: &mut SimState) -> anyhow::Result<bool> {
        let mut got = false;
        while let Some(s) = self.state_sub.receive()? {
            *latest = *s;
            got = true;
        }
        Ok(got)
    }

    /// Wall mode: the newest state, if any; a robot side that died mid-sample is no state, and
    /// the loop's silence check decides what that means.
    #[inline]
    fn newest_state_or_none(&self, latest: &mut SimState, stats: &mut TickStats) -> bool {
        self.newest_state(latest).unwrap_or_else(|_| {
            stats.robot_port_errors += 1;
            false
        })
    }

    /// A gripper of its own: takes its newest state into `g`, and the controller learns its
    /// grasp and whether it acts on commands. Allocation-free.
    #[inline]
    fn gripper(&self, g: &mut GripperState, now: u64, ctl: &mut Controller) {
        use controller::GripperReport;
        let Some(sub) = self.gripper_sub.as_ref() else { return };
        while let Ok(Some(s)) = sub.receive() {
            *g = *s;
        }
        let report = if g.seq == 0 {
            GripperReport::NotReady("no state from the gripper driver yet")
        } else if now.saturating_sub(g.published_ns) > GRIPPER_TIMEOUT_NS {
            GripperReport::Fault("the gripper driver published nothing for 250 ms (it stopped or hangs)")
        } else if g.fault == 0 {
            GripperReport::Ready { finger_m: g.finger_m }
        } else if g.clears_itself != 0 {
            GripperReport::NotReady(g.fault_str())
        } else {
            GripperReport::Fault(g.fault_str())
        };
        ctl.gripper_reports(g.grasp, report);
    }

    /// Wall mode: the command to the robot side; a robot side that is gone is counted, not fatal.
    #[inline]
    fn command(&self, cmd: JointCommand, stats: &mut TickStats) {
        if self.cmd_pub.send_copy(cmd).is_err() || self.sim_wake.notify().is_err() {
            stats.robot_port_errors += 1;
        }
    }

    /// Serves every waiting request. Returns true when replies went out and agents need waking.
    /// With a planner (wall mode), the chunks it has finished checking are committed first,
    /// oldest first, then new requests are admitted and their chunks handed to it; without one
    /// (lockstep, or `R2G_ACCEPT_ON_TICK=1`) every request is decided here and now.
    /// Agents come and go (and may be hostile): a failure on their ports is counted, never fatal.
    #[inline]
    fn serve_requests(
        &self,
        ctl: &mut Controller,
        mut planner: Option<&mut planner::Planner>,
        latest: &SimState,
        stats: &mut TickStats,
    ) -> anyhow::Result<bool> {
        use controller::{Admission, Forward};
        let mut replied = false;
        if let Some(p) = planner.as_deref_mut() {
            if !p.alive() {
                // A panic in a chunk's checks: stop, as the same panic on the tick would have.
                bail!("the planner thread stopped (a panic while checking a chunk)");
            }
            p.take_finished(|f| {
                let reply = ctl.commit(f.job, f.outcome, Some(f.plan), latest);
                for r in [reply, ctl.take_accepted()].into_iter().flatten() {
                    self.reply(r, stats);
                    replied = true;
                }
                stats.accept.record(rt::now_ns().saturating_sub(f.received_ns));
            });
        }
        loop {
            let req = match self.req_sub.receive() {
                Ok(Some(r)) => r,
                Ok(None) => break,
                Err(_) => {
                    stats.agent_port_errors += 1;
                    break;
                }
            };
            let received = rt::now_ns();
            let in_flight = planner.as_deref().and_then(planner::Planner::in_flight);
            let (reply, fwd) = match ctl.admit(&req, latest, in_flight) {
                Admission::Answer(reply, fwd) => (reply, fwd),
                Admission::Plan(job) => match planner.as_deref_mut().map(|p| p.submit(&job, &req, received)) {
                    // Replied to when the planner is done (a later tick).
                    Some(true) => (None, Forward::None),
                    Some(false) => {
                        let why = format_args!(
                            "{} chunks of this client are still being checked: wait for their replies before sending more",
                            planner::SLOTS
                        );
                        (Some(Reply::formatted(job.id, job.client, ipc_schema::Status::Rejected, why)), Forward::None)
                    }
                    None => {
                        let outcome = ctl.plan_now(&job, &req);
                        let reply = ctl.commit(&job, outcome, None, latest);
                        stats.accept.record(rt::now_ns().saturating_sub(received));
                        (reply, Forward::None)
                    }
                },
            };
            for r in [reply, ctl.take_accepted()].into_iter().flatten() {
                self.reply(r, stats);
                replied = true;
            }
            if let Forward::Reset { sim_reset_id } = fwd {
                self.reset_pub.send_copy(SimReset { id: sim_reset_id })?;
                self.sim_wake.notify()?;
            }
        }
        Ok(replied)
    }

    #[inline]
    fn reply(&self, r: Reply, stats: &mut TickStats) {
        if self.reply_pub.send_copy(r).is_err() {
            stats.agent_port_errors += 1;
        }
    }

    /// Publishes to agents; a failure is counted, never fatal.
    #[inline]
    fn to_agents(&self, state: RobotState, reply: Option<Reply>, stats: &mut TickStats) {
        if self.robot_pub.send_copy(state).is_err() {
            stats.agent_port_errors += 1;
        }
        if let Some(r) = reply {
            if self.reply_pub.send_copy(r).is_err() {
                stats.agent_port_errors += 1;
            }
        }
    }

    /// Takes note of peers that connected or left since the last call: agents come and go, and
    /// the robot side can die and come back (iceoryx2 maps or unmaps their segments here), so
    /// that the tick's own receive and send find nothing to set up.
    fn update_connections(&self, stats: &mut TickStats) {
        use iceoryx2::port::update_connections::UpdateConnections;
        let agents = [
            self.req_sub.update_connections(),
            self.reply_pub.update_connections(),
            self.robot_pub.update_connections(),
            self.agent_wake.update_connections(),
            self.info_pub.update_connections(),
        ];
        let robot = [
            self.state_sub.update_connections(),
            self.cmd_pub.update_connections(),
            self.reset_pub.update_connections(),
            self.sim_wake.update_connections(),
        ];
        stats.agent_port_errors += agents.iter().filter(|r| r.is_err()).count() as u64;
        stats.robot_port_errors += robot.iter().filter(|r| r.is_err()).count() as u64;
    }

    fn wake_agents(&self, stats: &mut TickStats) {
        if self.agent_wake.notify().is_err() {
            stats.agent_port_errors += 1;
        }
    }
}

fn runtime_info(ctl: &Controller, mode: Mode, period_ns: u64, reflexes: Option<robot_config::Reflexes>) -> RuntimeInfo {
    let mut i = RuntimeInfo {
        schema: ipc_schema::SCHEMA_VERSION,
        mode: mode as u32,
        tick_period_ns: period_ns,
        q_margin_rad: ctl.cfg.q_margin_rad,
        speed_scale: ctl.cfg.speed_scale,
        max_chunk: ctl.cfg.max_chunk as u32,
        default_freq_hz: ctl.cfg.default_freq_hz,
        finger_max_m: ctl.robot.finger_max_m,
        finger_speed_m_s: ctl.robot.finger_speed_m_s,
        profile: ctl.profile() as u32,
        max_joint_step_rad: ctl.cfg.max_joint_step_rad,
        max_tcp_step_m: ctl.cfg.max_tcp_step_m,
        max_tcp_step_rad: ctl.cfg.max_tcp_step_rad,
        reflex_force_n: reflexes.map_or(f64::NAN, |r| r.reflex_force_n),
        operator_force_n: reflexes.map_or(f64::NAN, |r| r.operator_force_n),
        ..Default::default()
    };
    if let Some(s) = ctl.safety() {
        let (lo, hi) = s.workspace.bounds();
        i.has_workspace = u32::from(lo.iter().chain(hi.iter()).any(|v| v.is_finite()));
        (i.workspace_min_m, i.workspace_max_m) = (lo, hi);
        i.collision_margin_m = s.margin_m;
    }
    for (j, l) in ctl.robot.joints.iter().enumerate() {
        i.q_min_rad[j] = l.q_min_rad;
        i.q_max_rad[j] = l.q_max_rad;
        i.dq_max_rad_s[j] = l.dq_max_rad_s;
        i.ddq_max_rad_s2[j] = ctl.cfg.accel_scale * l.ddq_max_rad_s2;
    }
    i
}

/// Runs the runtime until stopped; returns what the ticks recorded.
pub fn run(cfg: &RunConfig) -> anyhow::Result<TickStats> {
    let services = Services::new(&cfg.instance)?;
    let (robot, safety) = scene_robot_with_tcp(&cfg.scene, cfg.calibration.tcp.as_ref().map(|t| &t.1))?;
    let dt_s = cfg.period_ns as f64 * 1e-9;
    let mut ctl = Controller::new(robot, cfg.robot.limiter(), dt_s)
        .with_safety(safety)
        .with_profile(cfg.robot.profile, cfg.robot.reflexes)
        .with_reflex_window(cfg.robot.reflexes.window_s);
    // Leftovers of a robot side or runtime that was SIGKILLed would hold their ports' slots.
    ipc_schema::cleanup_dead_nodes();
    let own_gripper = matches!(cfg.robot.gripper, robot_config::Gripper::Robotiq2f85(_));
    if own_gripper && cfg.mode == Mode::Lockstep {
        bail!("a gripper on its own device (robotiq_2f85) moves on the wall clock: lockstep is for simulation only");
    }
    let ports = Ports::open(&services, own_gripper)?;
    let sim = PeerWatch::spawn(process::sim_node(&cfg.instance), Duration::from_secs(30));
    // The threads beside the loop start before it raises itself to SCHED_FIFO, so they keep
    // the normal scheduler.
    let health = health::Health::new(cfg.mode as u32);
    let policy = operator::Policy::new(cfg.operator_group.as_deref())?;
    let _operator = operator::serve(&cfg.instance, health.clone(), policy)?;
    let notifier = health::spawn_notifier(health.clone());
    // Wall mode checks chunks on a planner thread beside the loop; R2G_ACCEPT_ON_TICK=1 keeps
    // them on the tick thread (the old way, for `r2g bench accept` to compare).
    let on_tick = std::env::var_os("R2G_ACCEPT_ON_TICK").is_some_and(|v| v == "1");
    let mut planner = match (cfg.mode, on_tick) {
        (Mode::Wall, false) => {
            Some(planner::Planner::spawn(ctl.acceptance(), cfg.cpu).context("starting the planner thread")?)
        }
        _ => None,
    };
    let result = run_loops(cfg, &ports, &mut ctl, &sim, &health, planner.as_mut());
    health.stopping.store(true, std::sync::atomic::Ordering::Relaxed);
    if let Some(t) = notifier {
        let _ = t.join();
    }
    result.map(|mut stats| {
        stats.acceptance = if planner.is_some() { "planner" } else { "tick" };
        if let Some(p) = planner {
            stats.planning = p.stop();
        }
        stats
    })
}

fn run_loops(
    cfg: &RunConfig,
    ports: &Ports,
    ctl: &mut Controller,
    sim: &PeerWatch,
    health: &health::Health,
    planner: Option<&mut planner::Planner>,
) -> anyhow::Result<TickStats> {
    // The first state: the sim-host republishes while idle, so this arrives within ~20 ms.
    let mut latest = SimState::default();
    let t0 = std::time::Instant::now();
    while !ports.newest_state(&mut latest)? {
        if process::stop_requested() {
            return Ok(TickStats::default());
        }
        if sim.lost() || t0.elapsed() > Duration::from_secs(60) {
            bail!("no state from r2g-sim of instance '{}': is it running?", cfg.instance);
        }
        let _ = ports.wake.timed_wait(|_| {}, Duration::from_millis(10));
    }
    // The sim-host's listener exists once it has published: register it now rather than in the
    // first tick's notify (which would allocate there).
    {
        use iceoryx2::port::update_connections::UpdateConnections;
        ports.sim_wake.update_connections()?;
        ports.cmd_pub.update_connections()?;
        ports.reset_pub.update_connections()?;
    }
    let reflexes = (cfg.robot.profile == ipc_schema::Profile::Franka).then_some(cfg.robot.reflexes);
    let mut info = runtime_info(ctl, cfg.mode, cfg.period_ns, reflexes);
    let (p, q) = controllers::kinematics::to_arrays(&ctl.robot.kin.flange_from_tcp());
    let report = cfg.calibration.report(&controllers::math::homogeneous(p, q));
    if let Err(len) = info.set_calibration(&report) {
        bail!("the calibration report is {len} bytes, more than the {} that fit", ipc_schema::CALIBRATION_LEN);
    }
    if let Err(len) = info.set_setup(&cfg.setup) {
        bail!("the setup report is {len} bytes, more than the {} that fit", ipc_schema::SETUP_LEN);
    }
    ports.info_pub.send_copy(info)?;
    health.last_state_ns.store(rt::now_ns(), std::sync::atomic::Ordering::Relaxed);

    match cfg.mode {
        Mode::Wall => wall_loop(cfg, ports, ctl, latest, info, health, planner),
        Mode::Lockstep => lockstep_loop(cfg, ports, ctl, sim, latest, info, health),
    }
}

/// How long before each deadline the wall loop registers newly connected agents.
const CONNECT_LEAD_NS: u64 = 200_000;

fn wall_loop(
    cfg: &RunConfig,
    ports: &Ports,
    ctl: &mut Controller,
    mut latest: SimState,
    info: RuntimeInfo,
    health: &health::Health,
    mut planner: Option<&mut planner::Planner>,
) -> anyhow::Result<TickStats> {
    use std::sync::atomic::Ordering::Relaxed;
    let rt = rt::setup(cfg.fifo_priority, cfg.cpu);
    if let Some(w) = rt.warning() {
        eprintln!("r2g-control: {w}");
    }
    health.set_realtime(&rt);
    let mut stats = TickStats::default();
    let period = cfg.period_ns;
    let start = rt::now_ns();
    let end = cfg.duration.map(|d| start + d.as_nanos() as u64);
    let mut deadline = start + period;
    let mut last_state_ns = start;
    let timeout_ns = cfg.state_timeout.as_nanos() as u64;
    // Fresh state while the robot side counted as lost: recover on a later tick, once the
    // connections to its new ports are registered outside the tick and the arm is at rest.
    let mut robot_seen_again = false;
    let mut incoming = latest;
    let mut prev_cmd: Option<JointCommand> = None;
    let mut robot_seq = 0u64;
    let (mut window_max, mut window_end) = (0u64, start + 1_000_000_000);
    let mut clear_pending: Option<(u64, bool)> = None;
    let mut gripper = GripperState::default();
    // Who paces the tick: our clock, or a robot side that publishes one state per robot cycle
    // and uses only the command answering it (a real arm's 1 kHz packets; see the README).
    let paced = latest.paced != 0;
    let mut prev_robot_time_s = latest.sim_time_s;
    // Paced: ticks taken since the last robot state (waiting for one that did not come in time).
    let mut ticks_since_state = 0u32;
    // Tick-to-command latency counts skipped deadlines only when our clock sets them.
    let command_period = if paced { 0 } else { period };
    loop {
        if paced {
            // The next state, or the deadline (two periods after the last one) so that the loop
            // keeps cycling, holds and notices a silent robot side.
            wait_for_state_until(ports, deadline);
        } else {
            if period > 2 * CONNECT_LEAD_NS {
                rt::sleep_until(deadline - CONNECT_LEAD_NS, 0);
                ports.update_connections(&mut stats);
            }
            rt::sleep_until(deadline, cfg.spin_ns);
        }
        let woke = rt::now_ns();
        // Clocked: how late after its deadline the tick starts (paced: after the state, below).
        let mut late = woke.saturating_sub(deadline);
        if !paced {
            stats.wake.record(late);
        }

        // ---- tick: no allocation, no locks, no logging ----
        let scope = alloc_count::TickScope::enter();
        let mut back = None;
        let lost_before = ctl.is_robot_lost();
        // Fresh: a newer state of the same robot side, or any state of a new one (a repeat of
        // the same state, as an idle sim-host sends, proves nothing).
        let fresh = ports.newest_state_or_none(&mut incoming, &mut stats)
            && (incoming.session != latest.session || incoming.seq > latest.seq);
        // A gripper of its own, before anything uses the state: once it has acted on commands,
        // its fingers are the state's (before that the runtime sends it no finger target).
        ports.gripper(&mut gripper, woke, ctl);
        if ctl.gripper_ready() {
            for s in [&mut incoming, &mut latest] {
                (s.finger_m, s.finger_max_m) = (gripper.finger_m, gripper.finger_max_m);
            }
        }
        if paced && fresh {
            // Paced: how long after the robot side published its state the tick starts on it.
            late = woke.saturating_sub(incoming.published_ns);
            stats.wake.record(late);
        }
        if fresh && !ctl.is_robot_lost() && incoming.session != latest.session {
            // Another robot side answers (a restart faster than the timeout): what was running
            // belonged to its predecessor. Stop and resume from its state as after a loss.
            ctl.robot_lost((woke - last_state_ns) as f64 / 1e6);
            stats.robot_losses += 1;
            last_state_ns = woke;
            robot_seen_again = true;
        } else if fresh && !ctl.is_robot_lost() {
            latest = incoming;
            last_state_ns = woke;
            // What the robot itself reports (a real arm's reflexes and their recovery).
            back = ctl.robot_reports(&latest);
        } else if fresh {
            // Back, but not used until its ports are registered (one tick later) and it rests:
            // until then `latest` keeps the lost side's state, so the held command still
            // carries the old session and a restarted robot side ignores it.
            last_state_ns = woke;
            if robot_seen_again && at_rest(&incoming) {
                latest = incoming;
                back = ctl.robot_back(&latest);
                robot_seen_again = false;
            } else {
                robot_seen_again = true;
            }
        } else if !ctl.is_robot_lost() && woke - last_state_ns > timeout_ns + recovery_allowance(&latest) {
            // The robot side is silent: the loop keeps cycling, holds, and reports it.
            ctl.robot_lost((woke - last_state_ns) as f64 / 1e6);
            stats.robot_losses += 1;
            robot_seen_again = false;
        }
        // Every command is checked against the limits, each against the one a tick before (not
        // on a tick whose command restarted at the measured state: a reset, a robot side that
        // came back or recovered).
        let mut checked_tick = |ctl: &mut Controller, stats: &mut TickStats| {
            let (cmd, reply) = ctl.tick(&latest);
            if let (Some(p), false) = (prev_cmd, ctl.take_restarted()) {
                if !ctl.within_limits(&p, &cmd) {
                    stats.limit_violations += 1;
                }
            }
            prev_cmd = Some(cmd);
            (cmd, reply)
        };
        let (mut cmd, mut reply) = checked_tick(ctl, &mut stats);
        if paced && fresh {
            // A robot cycle without a state (a lost packet, or one this loop was too late to
            // read) still moved the robot's own interpolation on: the command covers every
            // cycle since the last state, counting the ticks already taken while waiting (at
            // most 4 cycles are made up; a longer gap is the robot side's loss to handle).
            let cycles = ((latest.sim_time_s - prev_robot_time_s) / (period as f64 * 1e-9)).round();
            for _ in (1 + ticks_since_state)..(cycles.clamp(1.0, 4.0) as u32) {
                let (c, r) = checked_tick(ctl, &mut stats);
                (cmd, reply) = (c, reply.or(r));
            }
            prev_robot_time_s = latest.sim_time_s;
            ticks_since_state = 0;
        } else if paced {
            ticks_since_state = ticks_since_state.saturating_add(1);
        }
        let reply = back.or(reply);
        // While the robot side is lost its command goes out after the tick (below): a robot side
        // that reappears is registered by those sends or the next tick's connection update,
        // never inside a tick.
        let lost = lost_before || ctl.is_robot_lost();
        if !lost {
            ports.command(cmd, &mut stats);
            // Paced, only the answers to a robot state count: a command on a tick that waited
            // in vain answers nothing the robot asked for.
            if !paced || fresh {
                stats.command_sent(woke.saturating_sub(late), command_period, rt::now_ns());
            }
        }
        // Requests after the command is out. A chunk's own checks (IK, path checks: up to about
        // a millisecond) run on the planner thread; the tick only admits and commits.
        let rejected = ports.serve_requests(ctl, planner.as_deref_mut(), &latest, &mut stats)?;
        // The state first: an agent woken by the reply must already see where the arm is.
        robot_seq += 1;
        let stepped = ctl.take_stepped();
        let wake_agents = rejected || reply.is_some() || stepped.is_some();
        ports.to_agents(ctl.robot_state(&latest, robot_seq, Mode::Wall as u32), reply, &mut stats);
        if let Some(r) = stepped {
            ports.reply(r, &mut stats);
        }
        if robot_seq.is_multiple_of(200) {
            // Late subscribers get the limits from history; resend so they never wait long.
            let _ = ports.info_pub.send_copy(info);
        }
        drop(scope);
        // ---- end of tick ----
        if lost {
            ports.command(cmd, &mut stats);
            stats.command_sent(woke.saturating_sub(late), command_period, rt::now_ns());
        }
        if let Some(p) = planner.as_deref_mut() {
            p.wake();
        }
        // Agents come and go, and iceoryx2 registers a new listener inside `notify` (one
        // allocation per new agent), so their wake-up follows the tick instead of joining it.
        if wake_agents {
            ports.wake_agents(&mut stats);
        }

        let done = rt::now_ns();
        stats.compute.record(done - woke);
        stats.ticks += 1;
        if paced {
            // Connections first (the robot's next state is most of a period away), then the
            // deadline for the next state.
            ports.update_connections(&mut stats);
            deadline = done + 2 * period;
        } else {
            deadline = next_deadline(deadline, done, period, &mut stats);
        }
        // What the notifier and the operator socket read: atomics, stored between ticks. A fault
        // reset is answered once a tick has published the state that shows it.
        if let Some((n, cleared)) = clear_pending.take() {
            health.finish_clear(n, cleared);
        }
        if let Some(n) = health.take_clear() {
            clear_pending = Some((n, ctl.clear_fault()));
        }
        window_max = window_max.max(late);
        if done >= window_end {
            health.wake_max_ns.store(window_max, Relaxed);
            (window_max, window_end) = (0, done + 1_000_000_000);
        }
        health.ticks.store(stats.ticks, Relaxed);
        health.overruns.store(stats.overruns, Relaxed);
        health.last_state_ns.store(last_state_ns, Relaxed);
        health.agent_port_errors.store(stats.agent_port_errors, Relaxed);
        let fault = (u32::from(ctl.fault().is_some()) * health::FAULT_OPERATOR)
            | (u32::from(ctl.is_robot_lost()) * health::FAULT_ROBOT_LOST);
        health.fault.store(fault, Relaxed);
        health.limit_violations.store(stats.limit_violations, Relaxed);
        health.cycles.store(stats.ticks, Relaxed);
        if let Some(hook) = cfg.after_cycle {
            hook();
        }
        if process::stop_requested() || end.is_some_and(|e| done >= e) {
            return Ok(stats);
        }
    }
}

fn lockstep_loop(
    cfg: &RunConfig,
    ports: &Ports,
    ctl: &mut Controller,
    sim: &PeerWatch,
    mut latest: SimState,
    info: RuntimeInfo,
    health: &health::Health,
) -> anyhow::Result<TickStats> {
    use std::sync::atomic::Ordering::Relaxed;
    let mut stats = TickStats::default();
    let mut robot_seq = 0u64;
    let start = std::time::Instant::now();
    let mut last_beat = std::time::Instant::now();
    let host_baseline = process::host_baseline();
    loop {
        health.cycles.fetch_add(1, Relaxed);
        health.ticks.store(stats.ticks, Relaxed);
        health.fault.store(u32::from(ctl.fault().is_some()) * health::FAULT_OPERATOR, Relaxed);
        health.last_state_ns.store(rt::now_ns(), Relaxed);
        if let Some(n) = health.take_clear() {
            let cleared = ctl.clear_fault();
            robot_seq += 1;
            ports.to_agents(ctl.robot_state(&latest, robot_seq, Mode::Lockstep as u32), None, &mut stats);
            health.finish_clear(n, cleared);
        }
        if process::stop_requested() || cfg.duration.is_some_and(|d| start.elapsed() >= d) {
            return Ok(stats);
        }
        if sim.lost() {
            bail!("r2g-sim of instance '{}' stopped; the runtime stops too", cfg.instance);
        }
        if ports.serve_requests(ctl, None, &latest, &mut stats)? {
            // A reply can change what the state reports (a cleared fault, the locked type).
            robot_seq += 1;
            ports.to_agents(ctl.robot_state(&latest, robot_seq, Mode::Lockstep as u32), None, &mut stats);
            ports.wake_agents(&mut stats);
        }
        if let Some(sim_id) = ctl.pending_reset() {
            // A reset takes no tick: wait for the state the simulator publishes right after it,
            // so every episode starts from the same state at the same simulated time.
            wait_for_state(ports, sim, &mut latest, |s| s.reset_id == sim_id)?;
            let reply = ctl.complete_reset(&latest);
            robot_seq += 1;
            ports.to_agents(ctl.robot_state(&latest, robot_seq, Mode::Lockstep as u32), reply, &mut stats);
            ports.wake_agents(&mut stats);
        } else if ctl.advancing() {
            // Tick k consumes state k and produces command k; the sim answers with state k+1.
            let t = rt::now_ns();
            let (cmd, reply) = ctl.tick(&latest);
            stats.compute.record(rt::now_ns() - t);
            stats.ticks += 1;
            ports.cmd_pub.send_copy(cmd)?;
            ports.sim_wake.notify()?;
            wait_for_state(ports, sim, &mut latest, |s| s.command_seq >= cmd.seq)?;
            robot_seq += 1;
            let stepped = ctl.take_stepped();
            let wake = reply.is_some() || stepped.is_some();
            ports.to_agents(ctl.robot_state(&latest, robot_seq, Mode::Lockstep as u32), reply, &mut stats);
            if let Some(r) = stepped {
                // After the state it ends on, so the stepping client reads that state.
                ports.reply(r, &mut stats);
            }
            if wake {
                ports.wake_agents(&mut stats);
            }
        } else {
            // Idle: simulated time stands still until an agent asks for something.
            ports.newest_state(&mut latest)?;
            if last_beat.elapsed() > Duration::from_millis(20) {
                robot_seq += 1;
                ports.to_agents(ctl.robot_state(&latest, robot_seq, Mode::Lockstep as u32), None, &mut stats);
                if robot_seq.is_multiple_of(10) {
                    let _ = ports.info_pub.send_copy(info);
                } else if !host_baseline {
                    // A new agent gets the limits from history as soon as they are noted.
                    use iceoryx2::port::update_connections::UpdateConnections;
                    let _ = ports.info_pub.update_connections();
                }
                last_beat = std::time::Instant::now();
            }
            let _ = ports.wake.timed_wait(|_| {}, Duration::from_millis(20));
        }
    }
}

/// Lockstep: takes states until one satisfies `done`; gives up if the simulator dies or is silent.
fn wait_for_state(
    ports: &Ports,
    sim: &PeerWatch,
    latest: &mut SimState,
    done: impl Fn(&SimState) -> bool,
) -> anyhow::Result<()> {
    let waited = std::time::Instant::now();
    loop {
        ports.newest_state(latest)?;
        if done(latest) || process::stop_requested() {
            return Ok(());
        }
        if sim.lost() {
            bail!("r2g-sim stopped while the runtime waited for it");
        }
        if waited.elapsed() > Duration::from_secs(10) {
            bail!("r2g-sim did not answer within 10 s");
        }
        let _ = ports.wake.timed_wait(|_| {}, Duration::from_millis(5));
    }
}

/// Paced wall mode: returns once a state is waiting or at `deadline`. Agents' requests also
/// wake the listener; they are served after the next tick's command, as in clocked mode.
fn wait_for_state_until(ports: &Ports, deadline: u64) {
    loop {
        if ports.state_sub.has_samples().unwrap_or(true) {
            return;
        }
        let now = rt::now_ns();
        if now >= deadline {
            return;
        }
        let _ = ports.wake.timed_wait(|_| {}, Duration::from_nanos(deadline - now));
    }
}

/// How much longer than the state timeout a robot side may stay silent: a real arm's robot side
/// publishes nothing while its bounded automatic error recovery runs (about a second at most).
fn recovery_allowance(latest: &SimState) -> u64 {
    if latest.robot_error == ipc_schema::ROBOT_RECOVERING {
        2_000_000_000
    } else {
        0
    }
}

/// Whether the measured arm is at rest (a robot side that came back is used only then, so the
/// command restarting at the measured joints with zero velocity is no velocity jump).
fn at_rest(s: &SimState) -> bool {
    s.dq_rad_s.iter().all(|v| v.abs() < 0.05)
}

/// The deadline after `deadline`. A tick that ended past it is an overrun: the missed
/// deadlines are skipped rather than burst through to catch up.
#[inline]
fn next_deadline(deadline: u64, done: u64, period: u64, stats: &mut TickStats) -> u64 {
    let next = deadline + period;
    if done > next {
        stats.overruns += 1;
        done + period - (done - next) % period
    } else {
        next
    }
}

/// The baseline every tick figure is compared with: the same absolute-deadline sleep and the
/// same measurement, doing nothing else.
pub fn baseline_loop(duration: Duration, period_ns: u64, spin_ns: u64) -> TickStats {
    let mut stats = TickStats::default();
    let start = rt::now_ns();
    let end = start + duration.as_nanos() as u64;
    let mut deadline = start + period_ns;
    loop {
        rt::sleep_until(deadline, spin_ns);
        let woke = rt::now_ns();
        stats.wake.record(woke.saturating_sub(deadline));
        let done = rt::now_ns();
        stats.compute.record(done - woke);
        stats.command_sent(deadline, period_ns, done);
        stats.ticks += 1;
        deadline = next_deadline(deadline, done, period_ns, &mut stats);
        if done >= end {
            return stats;
        }
    }
}
