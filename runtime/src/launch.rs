//! Starting and stopping one instance: r2g-sim and r2g-control as child processes, a readiness
//! check that waits until an agent could connect, and a clean stop that leaves no process and
//! no shared-memory service behind.

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use controllers::{Profile, RobotModel};
use ipc_schema::process;
use ipc_schema::{CameraFrame, Mode, Qos, RobotState, Services, SimInfo};

/// Where the gym pack lives: `$R2G_GYMS`, else `gyms/` of the checkout holding this binary,
/// else `./gyms`.
pub fn gyms_dir() -> PathBuf {
    checkout_dir("R2G_GYMS", "gyms")
}

/// Where `r2g up` writes its pid while the instance runs (`r2g down` and scripts read it):
/// `up.pid` in the instance's run folder (`ipc_schema::process::run_dir`).
pub fn up_pid_file(instance: &str) -> PathBuf {
    ipc_schema::process::run_dir(instance).join("up.pid")
}

/// The shipped robot configuration: `$R2G_ROBOT_CONFIG`, else
/// `robot-skill/config/robot.json` of the checkout.
pub fn default_robot_config() -> PathBuf {
    std::env::var_os("R2G_ROBOT_CONFIG")
        .map(PathBuf::from)
        .unwrap_or_else(|| checkout_dir("R2G_SKILL", "robot-skill").join("config").join("robot.json"))
}

/// Where the robot descriptions live: `$R2G_ROBOTS`, else `robots/` of the checkout holding
/// this binary, else `./robots`.
pub fn robots_dir() -> PathBuf {
    checkout_dir("R2G_ROBOTS", "robots")
}

/// `$var` if set, else folder `name` of the checkout holding this binary, else of the checkout
/// it was built from (a `CARGO_TARGET_DIR` outside the checkout), else `./name`.
fn checkout_dir(var: &str, name: &str) -> PathBuf {
    if let Ok(d) = std::env::var(var) {
        return PathBuf::from(d);
    }
    if let Ok(exe) = std::env::current_exe() {
        // target/<profile>/r2g → the checkout root (a test binary in deps/ is one level deeper).
        for root in exe.ancestors().skip(3).take(2) {
            let g = root.join(name);
            if g.is_dir() {
                return g;
            }
        }
    }
    let built_from = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(name);
    if built_from.is_dir() {
        return built_from;
    }
    PathBuf::from(name)
}

/// The robot model a name gives: `panda` or `fr3` (the shipped description with that limit
/// profile) or a URDF file (read with the Panda profile for what URDF cannot express).
pub fn robot_by_name(robot: &str, tcp: &str) -> anyhow::Result<RobotModel> {
    let (path, profile) = match Profile::from_name(robot) {
        Some(p) => (robots_dir().join("panda").join("panda.urdf"), p),
        None => {
            let p = PathBuf::from(robot);
            if !p.is_file() {
                bail!("no robot '{robot}': give panda, fr3 or the path of a URDF file");
            }
            (p, Profile::Panda)
        }
    };
    let xml = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    RobotModel::from_urdf_str(&xml, tcp, profile).with_context(|| format!("loading {}", path.display()))
}

/// The gyms of the pack: folders of `gyms/` that hold a `scene.toml`, sorted.
pub fn gym_names() -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(gyms_dir())
        .map(|d| {
            d.filter_map(|e| e.ok())
                .filter(|e| e.path().join("scene.toml").is_file())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

/// Resolves a gym name, folder or scene file to a scene file.
pub fn resolve_scene(gym: &str) -> anyhow::Result<PathBuf> {
    let p = PathBuf::from(gym);
    if p.is_file() {
        return Ok(p);
    }
    if p.is_dir() && p.join("scene.toml").is_file() {
        return Ok(p.join("scene.toml"));
    }
    let by_name = gyms_dir().join(gym).join("scene.toml");
    if by_name.is_file() {
        return Ok(by_name);
    }
    let known = gym_names();
    bail!(
        "no gym '{gym}': give a gym name ({}), a gym folder or a scene file",
        if known.is_empty() { "none found".into() } else { known.join(", ") }
    )
}

pub fn sibling(name: &str) -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("locating this executable")?;
    let dir = exe.parent().context("executable has no folder")?;
    // Test binaries live one level deeper (target/<profile>/deps).
    for d in [dir, dir.parent().unwrap_or(dir)] {
        let p = d.join(name);
        if p.is_file() {
            return Ok(p);
        }
    }
    bail!("cannot find {name} next to {} (build the workspace first: make build)", exe.display())
}

/// Options of one instance.
#[derive(Debug, Clone)]
pub struct UpOptions {
    pub scene: PathBuf,
    pub instance: String,
    pub mode: Mode,
    pub render_hz: f64,
    /// Extra arguments for r2g-control (e.g. --duration-s, --stats-out).
    pub control_args: Vec<String>,
    /// Extra arguments for r2g-sim (e.g. --trace-dir).
    pub sim_args: Vec<String>,
    /// `config/robot.json` for r2g-control (None: its built-in defaults, the simulation profile).
    pub robot_config: Option<PathBuf>,
    pub ready_timeout: Duration,
}

/// What serves as the robot side of an instance.
#[derive(Debug, Clone)]
pub enum RobotSide {
    /// `r2g-sim`: MuJoCo, cameras, resets, the evaluator.
    Sim,
    /// `r2g-fci`: a Franka arm at `address` (`host` or `host:port`), with extra arguments.
    Fci { address: String, extra: Vec<String> },
}

impl RobotSide {
    /// The robot side's program, also the name of its systemd unit template (`<program>@.service`).
    pub fn program(&self) -> &'static str {
        match self {
            RobotSide::Sim => "r2g-sim",
            RobotSide::Fci { .. } => "r2g-fci",
        }
    }

    /// Whether this robot side can serve an instance in `mode` with `robot_config`: a real arm
    /// only in wall mode with the franka profile (it paces the tick and has no resets).
    pub fn check(&self, mode: Mode, robot_config: Option<&Path>) -> anyhow::Result<()> {
        if matches!(self, RobotSide::Sim) {
            return Ok(());
        }
        let rc = robot_config.context("a real arm needs a robot config (its franka table)")?;
        let profile = crate::RobotConfig::load(rc)?.profile;
        if mode != Mode::Wall || profile != ipc_schema::Profile::Franka {
            bail!(
                "a real arm runs in wall mode with the franka profile (\"profile\": \"franka\" in {}), not in lockstep or the simulation profile",
                rc.display()
            );
        }
        Ok(())
    }
}

/// A running instance. Dropping it stops every process.
pub struct Instance {
    pub name: String,
    pub sim: Child,
    pub control: Child,
    /// The robot side's program (`r2g-sim` or `r2g-fci`), for messages.
    pub side: &'static str,
    /// The devices the robot config names, each its own process (`r2g-robotiq`, one camera host
    /// per camera), started once the runtime publishes state: what it is, and the process
    /// (None once it ended and was reported).
    pub devices: Vec<(String, Option<Child>)>,
    /// Their programs and arguments, not started yet.
    pending_devices: Vec<(String, PathBuf, Vec<String>)>,
}

/// The device processes a robot config names: (what, program, arguments).
pub fn device_processes(
    instance: &str,
    robot_config: &Path,
    config: &crate::RobotConfig,
) -> anyhow::Result<Vec<(String, PathBuf, Vec<String>)>> {
    let mut out = Vec::new();
    if let crate::robot_config::Gripper::Robotiq2f85(r) = &config.gripper {
        let args =
            vec!["--instance".into(), instance.into(), "--robot-config".into(), robot_config.display().to_string()];
        out.push((format!("r2g-robotiq ({})", r.port.display()), sibling("r2g-robotiq")?, args));
    }
    if !config.cameras.is_empty() {
        let host = camera_host_script();
        let python = checkout_dir("R2G_VENV", ".venv").join("bin").join("python");
        for c in &config.cameras {
            let mut args = vec![host.display().to_string(), "--instance".into(), instance.into()];
            args.extend(c.host_args());
            out.push((format!("camera host '{}'", c.name), python.clone(), args));
        }
    }
    Ok(out)
}

/// The camera host's script (`camera-host/py/r2g_camera_host.py` of the checkout).
pub fn camera_host_script() -> PathBuf {
    checkout_dir("R2G_CAMERA_HOST", "camera-host").join("py").join("r2g_camera_host.py")
}

fn spawn(program: &Path, args: &[String]) -> anyhow::Result<Child> {
    let mut cmd = Command::new(program);
    cmd.args(args).stdin(Stdio::null());
    // Children log to our stderr; our stdout stays for the READY line.
    cmd.stdout(Stdio::from(std::io::stderr().as_fd_owned()?));
    // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
            Ok(())
        });
    }
    cmd.spawn().with_context(|| format!("starting {}", program.display()))
}

trait StderrFd {
    fn as_fd_owned(&self) -> anyhow::Result<std::os::fd::OwnedFd>;
}

impl StderrFd for std::io::Stderr {
    fn as_fd_owned(&self) -> anyhow::Result<std::os::fd::OwnedFd> {
        use std::os::fd::AsFd;
        Ok(self.as_fd().try_clone_to_owned()?)
    }
}

impl Instance {
    /// Starts sim-host then runtime and waits until an agent could connect: the runtime
    /// publishes robot state and every camera has delivered a frame.
    pub fn up(opts: &UpOptions) -> anyhow::Result<Self> {
        Self::up_with(opts, &RobotSide::Sim)
    }

    /// [`Self::up`] with another robot side: a real Franka arm served by `r2g-fci` (wall mode and
    /// the Franka profile only; nothing is simulated, so there are no cameras and no resets).
    pub fn up_with(opts: &UpOptions, side: &RobotSide) -> anyhow::Result<Self> {
        Services::new(&opts.instance)?;
        let cleaned = ipc_schema::cleanup_dead_nodes();
        if cleaned > 0 {
            eprintln!("r2g: removed the shared-memory leftovers of {cleaned} dead process(es)");
        }
        for node in [process::control_node(&opts.instance), process::sim_node(&opts.instance)] {
            if process::node_alive(&node) == Some(true) {
                bail!(
                    "instance '{}' is already running ({node} is alive): stop it first, or pick another --instance",
                    opts.instance
                );
            }
        }
        let scene = opts.scene.display().to_string();
        let mut sim_args = vec![
            scene.clone(),
            "--instance".into(),
            opts.instance.clone(),
            "--render-hz".into(),
            opts.render_hz.to_string(),
        ];
        sim_args.extend(opts.sim_args.iter().cloned());
        side.check(opts.mode, opts.robot_config.as_deref())?;
        let mut pending_devices = Vec::new();
        if let Some(rc) = &opts.robot_config {
            // Checked before anything starts (with the calibration files it names), so a bad
            // file fails `r2g up` with its reason and leaves no robot side connected.
            let config = crate::RobotConfig::load(rc)?;
            crate::calibration::Calibration::load(&config.calibration)?;
            pending_devices = device_processes(&opts.instance, rc, &config)?;
            if !config.cameras.is_empty() && opts.mode == Mode::Lockstep {
                bail!("cameras that are devices deliver frames on the wall clock: lockstep is for simulation only");
            }
            for c in &config.cameras {
                sim_args.extend(["--camera-host".into(), c.name.clone()]);
            }
        }
        let sim = match side {
            RobotSide::Sim => spawn(&sibling("r2g-sim")?, &sim_args)?,
            RobotSide::Fci { address, extra } => {
                let mut args = vec![
                    opts.scene.display().to_string(),
                    "--instance".into(),
                    opts.instance.clone(),
                    "--robot".into(),
                    address.clone(),
                ];
                // Present: checked above.
                if let Some(rc) = &opts.robot_config {
                    args.extend(["--robot-config".into(), rc.display().to_string()]);
                }
                args.extend(extra.iter().cloned());
                spawn(&sibling("r2g-fci")?, &args)?
            }
        };
        let mode = if opts.mode == Mode::Lockstep { "lockstep" } else { "wall" };
        let mut control_args = vec![scene, "--instance".into(), opts.instance.clone(), "--mode".into(), mode.into()];
        if let Some(rc) = &opts.robot_config {
            control_args.extend(["--robot-config".into(), rc.display().to_string()]);
        }
        control_args.extend(opts.control_args.iter().cloned());
        let control = match spawn(&sibling("r2g-control")?, &control_args) {
            Ok(c) => c,
            Err(e) => {
                let mut sim = sim;
                let _ = sim.kill();
                let _ = sim.wait();
                return Err(e);
            }
        };
        let mut inst = Self {
            name: opts.instance.clone(),
            sim,
            control,
            side: side.program(),
            devices: Vec::new(),
            pending_devices,
        };
        if let Err(e) = inst.wait_ready(opts) {
            inst.stop();
            return Err(e);
        }
        Ok(inst)
    }

    fn wait_ready(&mut self, opts: &UpOptions) -> anyhow::Result<()> {
        let services = Services::new(&opts.instance)?;
        let node = ipc_schema::node(&format!("r2g-up-{}", opts.instance))?;
        let robot = ipc_schema::open_or_create_pubsub::<RobotState>(&node, &services.robot_state(), Qos::ROBOT_STATE)?
            .subscriber_builder()
            .buffer_size(1)
            .create()?;
        let info = ipc_schema::open_or_create_pubsub::<SimInfo>(&node, &services.sim_info(), Qos::STREAM)?
            .subscriber_builder()
            .create()?;
        let t0 = Instant::now();
        let mut sim_info: Option<SimInfo> = None;
        let mut have_state = false;
        let mut cams: Vec<(
            String,
            iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, CameraFrame, ()>,
            bool,
        )> = Vec::new();
        loop {
            // A device that ends before the instance is ready (a camera that is not there, a
            // calibration that does not fit) fails the start, with its own message above.
            for (what, child) in &mut self.devices {
                if let Some(s) = child.as_mut().map(Child::try_wait).transpose()?.flatten() {
                    bail!("{what} exited ({s}) before the instance was ready");
                }
            }
            if let Some(status) = self.exited()? {
                bail!("{status} before the instance was ready");
            }
            if process::stop_requested() {
                bail!("interrupted while starting");
            }
            if t0.elapsed() > opts.ready_timeout {
                bail!("instance '{}' was not ready within {:?}", opts.instance, opts.ready_timeout);
            }
            if sim_info.is_none() {
                if let Some(s) = info.receive()? {
                    let s = *s;
                    for i in 0..(s.camera_count as usize).min(ipc_schema::MAX_CAMERAS) {
                        let name = s.camera_name(i).to_string();
                        let qos = Qos::CAMERA;
                        let sub =
                            ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, &services.camera(&name), qos)?
                                .subscriber_builder()
                                .create()?;
                        cams.push((name, sub, false));
                    }
                    sim_info = Some(s);
                }
            }
            while robot.receive()?.is_some() {
                have_state = true;
            }
            if have_state && !self.pending_devices.is_empty() {
                // The devices' processes attach to a running runtime (its calibration report
                // and clock): start them now.
                for (what, program, args) in std::mem::take(&mut self.pending_devices) {
                    let child = spawn(&program, &args).with_context(|| format!("starting {what}"))?;
                    self.devices.push((what, Some(child)));
                }
            }
            for c in cams.iter_mut() {
                while c.1.receive()?.is_some() {
                    c.2 = true;
                }
            }
            if have_state && sim_info.is_some() && cams.iter().all(|c| c.2) {
                return Ok(());
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Describes the first child that has exited, if any.
    pub fn exited(&mut self) -> anyhow::Result<Option<String>> {
        let describe = |who: &str, pid: u32, s: ExitStatus| {
            use std::os::unix::process::ExitStatusExt;
            match (s.code(), s.signal()) {
                (Some(c), _) => format!("{who} (pid {pid}) exited with status {c}"),
                (_, Some(sig)) => format!("{who} (pid {pid}) was killed by signal {sig}"),
                _ => format!("{who} (pid {pid}) ended"),
            }
        };
        if let Some(s) = self.sim.try_wait()? {
            return Ok(Some(describe(self.side, self.sim.id(), s)));
        }
        if let Some(s) = self.control.try_wait()? {
            return Ok(Some(describe("r2g-control", self.control.id(), s)));
        }
        // A device process that ends stops nothing: the runtime holds the arm while the gripper
        // is silent, and agents get no frame from a camera that stopped. Said once.
        for (what, child) in &mut self.devices {
            if let Some(c) = child {
                if let Some(s) = c.try_wait()? {
                    eprintln!("r2g: {}; instance '{}' goes on without it", describe(what, c.id(), s), self.name);
                    *child = None;
                }
            }
        }
        Ok(None)
    }

    /// Watches the instance until a stop signal arrives (see
    /// [`process::install_stop_signals`]) or a child exits; the caller then calls [`Self::stop`].
    /// `None`: a stop was requested; `Some(what)`: which child ended and how.
    pub fn supervise(&mut self) -> anyhow::Result<Option<String>> {
        loop {
            if process::stop_requested() {
                return Ok(None);
            }
            if let Some(what) = self.exited()? {
                return Ok(Some(what));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits for r2g-control to end by itself (benchmarks with --duration-s).
    pub fn wait_control(&mut self, timeout: Duration) -> anyhow::Result<ExitStatus> {
        let t0 = Instant::now();
        loop {
            if let Some(s) = self.control.try_wait()? {
                return Ok(s);
            }
            if t0.elapsed() > timeout {
                bail!("r2g-control did not finish within {timeout:?}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// SIGTERM to every process (devices, then the runtime, then the robot side), SIGKILL after
    /// 5 s, then removes what dead processes left.
    pub fn stop(&mut self) {
        let devices = self.devices.iter_mut().filter_map(|(_, c)| c.as_mut());
        let mut all: Vec<&mut Child> = devices.collect();
        all.push(&mut self.control);
        all.push(&mut self.sim);
        for child in all.iter_mut() {
            if matches!(child.try_wait(), Ok(None)) {
                // SAFETY: signals a child we started and have not reaped, by pid.
                unsafe {
                    libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
                }
            }
        }
        let t0 = Instant::now();
        for child in all {
            loop {
                match child.try_wait() {
                    Ok(Some(_)) | Err(_) => break,
                    Ok(None) if t0.elapsed() > Duration::from_secs(5) => {
                        let _ = child.kill();
                        let _ = child.wait();
                        break;
                    }
                    Ok(None) => std::thread::sleep(Duration::from_millis(10)),
                }
            }
        }
        ipc_schema::cleanup_dead_nodes();
    }
}

impl Drop for Instance {
    fn drop(&mut self) {
        self.stop();
    }
}
