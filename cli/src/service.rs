//! `r2g service install|status`: one instance as systemd services on a robot PC. The unit
//! templates, the users, the instance's folders and its iceoryx2 configuration live in
//! `deploy/` (see deploy/README.md); this file fills them in for one instance, checks every
//! value first, and writes all or nothing.

use std::collections::BTreeMap;
use std::net::{Ipv4Addr, SocketAddrV4};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::Subcommand;
use runtime::launch::{self, RobotSide};

const CONTROL_UNIT: &str = include_str!("../../deploy/systemd/r2g-control@.service");
const SIM_UNIT: &str = include_str!("../../deploy/systemd/r2g-sim@.service");
const FCI_UNIT: &str = include_str!("../../deploy/systemd/r2g-fci@.service");
const AGENT_UNIT: &str = include_str!("../../deploy/systemd/r2g-agent@.service");
const ROBOTIQ_UNIT: &str = include_str!("../../deploy/systemd/r2g-robotiq@.service");
const CAMERA_UNIT: &str = include_str!("../../deploy/systemd/r2g-camera@.service");
const TARGET_UNIT: &str = include_str!("../../deploy/systemd/r2g@.target");
const SYSUSERS: &str = include_str!("../../deploy/sysusers.d/r2g.conf");
const TMPFILES: &str = include_str!("../../deploy/tmpfiles.d/r2g@.conf");
const ICEORYX2: &str = include_str!("../../deploy/iceoryx2/instance.toml");
const ICEORYX2_AGENT: &str = include_str!("../../deploy/iceoryx2/agent.toml");

/// The programs that can be an instance's robot side, each with a unit template `<program>@.service`.
const ROBOT_SIDES: [&str; 2] = ["r2g-sim", "r2g-fci"];

/// Keys of `--config` (a flat TOML file), with what each accepts.
const KEYS: &[(&str, &str)] = &[
    ("cpu", "the CPU of the control loop thread (also in the control unit's CPUAffinity=, with the housekeeping CPUs), an online CPU number"),
    ("fifo_priority", "the loop thread's SCHED_FIFO priority, an integer 1..=98"),
    ("housekeeping_cpus", "CPUs of the robot side and the agent, a string such as \"0-2\" or \"0,2\""),
    ("render_hz", "camera frames per second of the robot side, a number 0..=60 (0: no rendering)"),
    ("trace", "record and judge every episode under /var/lib/r2g/<instance>/traces, true or false"),
    ("agent_llm", "the agent batch's LLM: \"scripted\", \"scripted:<conversation.json>\" or an endpoint TOML file"),
    ("agent_episodes", "episodes of the agent batch, an integer 1..=100000"),
    ("fci", "a real Franka arm's FCI address, driven by r2g-fci instead of the simulator: an IPv4 address with an optional port, such as \"172.16.0.2\" (\"\": the simulator)"),
    ("fci_gripper", "also drive the arm's Franka Hand (with fci), true or false"),
];

#[derive(Subcommand, Debug)]
pub enum ServiceCmd {
    /// Write the systemd units and the configuration of one instance (deploy/README.md):
    /// unit templates and per-instance drop-ins under <root>/etc/systemd/system, the instance's
    /// files under <root>/etc/r2g/<instance>, its folders (tmpfiles.d) and the users
    /// (sysusers.d). Every value is checked first; on any error nothing is written.
    Install {
        /// Gym name (see `r2g gyms`), gym folder or scene file; or a robot config (a `.json`
        /// file in robot-skill/config/robot.json's format), then --gym names the scene.
        gym_or_robot_config: String,
        /// Instance name: the systemd instance and the iceoryx2 service prefix (r2g/<name>/...).
        #[arg(long)]
        instance: String,
        /// CPU of the control loop (overrides `cpu` of --config; default: the last online CPU).
        #[arg(long)]
        cpu: Option<usize>,
        /// Install under this folder instead of / (packaging, tests).
        #[arg(long, default_value = "/")]
        root: PathBuf,
        /// Instance settings, a flat TOML file (`key = value`): cpu, fifo_priority,
        /// housekeeping_cpus, render_hz, trace, agent_llm, agent_episodes (deploy/README.md).
        #[arg(long)]
        config: Option<PathBuf>,
        /// With a robot config: the gym (name, folder or scene file) whose scene gives the robot
        /// model, the table and the workspace.
        #[arg(long)]
        gym: Option<String>,
        /// Folder holding r2g, r2g-control and r2g-sim, and r2g-fci with --fci (default: the
        /// folder of this r2g).
        #[arg(long)]
        bin_dir: Option<PathBuf>,
        /// Drive a real Franka arm at this FCI address (an IPv4 address, optionally with a port)
        /// instead of the simulator: r2g-fci@<instance> becomes the robot side, allowed to reach
        /// that address only. Needs a robot config with "profile": "franka" (then --gym).
        /// Overrides `fci` of --config.
        #[arg(long)]
        fci: Option<String>,
        /// Also drive the Franka Hand of that arm (with --fci).
        #[arg(long, requires = "fci")]
        fci_gripper: bool,
    },
    /// Tick health of a running instance, asked from its control process over the operator
    /// socket, and the states of its units when systemd runs here. Exit status 0 only when the
    /// control process answered with no fault and its robot side present.
    Status {
        #[arg(long, default_value = "default")]
        instance: String,
        /// Print the control process's answer as one JSON line instead of a table.
        #[arg(long)]
        json: bool,
    },
}

pub fn run(cmd: ServiceCmd) -> anyhow::Result<i32> {
    match cmd {
        ServiceCmd::Install { gym_or_robot_config, instance, cpu, root, config, gym, bin_dir, fci, fci_gripper } => {
            let args = InstallArgs {
                target: gym_or_robot_config,
                instance,
                cpu,
                root,
                config,
                gym,
                bin_dir,
                fci,
                fci_gripper,
            };
            let plan = plan(&args)?;
            write_all(&args.root, &plan)?;
            report(&args.root, &plan);
            Ok(0)
        }
        ServiceCmd::Status { instance, json } => status(&instance, json),
    }
}

struct InstallArgs {
    target: String,
    instance: String,
    cpu: Option<usize>,
    root: PathBuf,
    config: Option<PathBuf>,
    gym: Option<String>,
    bin_dir: Option<PathBuf>,
    fci: Option<String>,
    fci_gripper: bool,
}

/// The values of one instance, checked.
#[derive(Debug)]
struct Settings {
    cpu: usize,
    fifo_priority: i64,
    housekeeping_cpus: Vec<usize>,
    render_hz: f64,
    trace: bool,
    agent_llm: String,
    agent_episodes: i64,
    /// The arm's FCI address (checked by [`fci_ip`]); None: the simulator.
    fci: Option<String>,
    fci_gripper: bool,
}

/// What `install` writes and removes (paths relative to the root), and notes for the person.
struct Plan {
    instance: String,
    files: Vec<(PathBuf, String)>,
    /// Files of an earlier install that no longer apply, removed once every file is in place.
    stale: Vec<PathBuf>,
    notes: Vec<String>,
}

/// A value of the flat TOML subset `--config` accepts.
#[derive(Debug, Clone, PartialEq)]
enum Value {
    Str(String),
    Int(i64),
    Float(f64),
    Bool(bool),
}

impl Value {
    fn kind(&self) -> &'static str {
        match self {
            Value::Str(_) => "a string",
            Value::Int(_) => "an integer",
            Value::Float(_) => "a number",
            Value::Bool(_) => "a boolean",
        }
    }
}

fn accepted_keys() -> String {
    KEYS.iter().map(|(k, _)| *k).collect::<Vec<_>>().join(", ")
}

fn what(key: &str) -> &'static str {
    KEYS.iter().find(|(k, _)| *k == key).map_or("", |(_, w)| w)
}

/// Parses the instance settings: a TOML file of top-level `key = value` lines (strings,
/// integers, numbers, booleans). Unknown keys, tables and arrays are refused with the key.
fn parse_config(text: &str, file: &Path) -> anyhow::Result<BTreeMap<String, Value>> {
    let table: toml::Table = toml::from_str(text).with_context(|| format!("{} is not valid TOML", file.display()))?;
    let mut out = BTreeMap::new();
    for (key, v) in table {
        if !KEYS.iter().any(|(k, _)| *k == key) {
            bail!("{}: unknown key \"{key}\"; accepted keys: {}", file.display(), accepted_keys());
        }
        let value = match v {
            toml::Value::String(s) => Value::Str(s),
            toml::Value::Integer(n) => Value::Int(n),
            toml::Value::Float(x) if x.is_finite() => Value::Float(x),
            toml::Value::Boolean(b) => Value::Bool(b),
            other => bail!(
                "{}: key \"{key}\" ({}) must be a string, an integer, a number or a boolean, not {}",
                file.display(),
                what(&key),
                other.type_str()
            ),
        };
        out.insert(key, value);
    }
    Ok(out)
}

/// The CPUs the kernel has online (isolated ones included), from sysfs; else as many as this
/// process may use.
fn online_cpus() -> Vec<usize> {
    if let Ok(s) = std::fs::read_to_string("/sys/devices/system/cpu/online") {
        if let Ok(v) = parse_cpu_list(s.trim()) {
            if !v.is_empty() {
                return v;
            }
        }
    }
    (0..std::thread::available_parallelism().map_or(1, |n| n.get())).collect()
}

/// "0-2,4" or "0 1 2" → [0, 1, 2, 4] (sorted, no duplicates).
fn parse_cpu_list(s: &str) -> anyhow::Result<Vec<usize>> {
    let mut out = Vec::new();
    for part in s.split(|c: char| c == ',' || c.is_whitespace()).filter(|p| !p.is_empty()) {
        let num = |t: &str| t.trim().parse::<usize>().with_context(|| format!("{t:?} is not a CPU number"));
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b) = (num(a)?, num(b)?);
                if a > b {
                    bail!("range {part} runs backwards");
                }
                out.extend(a..=b);
            }
            None => out.push(num(part)?),
        }
    }
    if out.is_empty() {
        bail!("no CPU given");
    }
    out.sort_unstable();
    out.dedup();
    Ok(out)
}

fn show_cpus(cpus: &[usize]) -> String {
    // Ranges where they are contiguous, systemd's and the kernel's notation.
    let mut parts = Vec::new();
    let mut i = 0;
    while i < cpus.len() {
        let mut j = i;
        while j + 1 < cpus.len() && cpus[j + 1] == cpus[j] + 1 {
            j += 1;
        }
        parts.push(if j > i { format!("{}-{}", cpus[i], cpus[j]) } else { cpus[i].to_string() });
        i = j + 1;
    }
    parts.join(",")
}

fn settings(args: &InstallArgs) -> anyhow::Result<Settings> {
    let cfg = match &args.config {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("--config {}: cannot read it", p.display()))?;
            parse_config(&text, p)?
        }
        None => BTreeMap::new(),
    };
    let origin = |key: &str| match &args.config {
        Some(p) => format!("{key} (in {})", p.display()),
        None => key.to_string(),
    };
    let online = online_cpus();
    let online_shown = show_cpus(&online);
    let int = |key: &str, lo: i64, hi: i64, default: i64| -> anyhow::Result<i64> {
        match cfg.get(key) {
            None => Ok(default),
            Some(Value::Int(n)) if (lo..=hi).contains(n) => Ok(*n),
            Some(Value::Int(n)) => bail!("{} = {n} is out of range: {}", origin(key), what(key)),
            Some(v) => bail!("{} is {}: {}", origin(key), v.kind(), what(key)),
        }
    };
    let cpu = match (&args.cpu, cfg.get("cpu")) {
        (Some(n), _) => {
            let n = *n;
            if !online.contains(&n) {
                bail!("--cpu {n} is out of range: this machine's online CPUs are {online_shown}");
            }
            n
        }
        (None, Some(Value::Int(n))) => {
            if *n < 0 || !online.contains(&(*n as usize)) {
                bail!("{} = {n} is out of range: this machine's online CPUs are {online_shown}", origin("cpu"));
            }
            *n as usize
        }
        (None, Some(v)) => bail!("{} is {}: {}", origin("cpu"), v.kind(), what("cpu")),
        (None, None) => *online.last().context("no online CPU")?,
    };
    let fifo_priority = int("fifo_priority", 1, 98, 80)?;
    let housekeeping_cpus = match cfg.get("housekeeping_cpus") {
        None => {
            let rest: Vec<usize> = online.iter().copied().filter(|&c| c != cpu).collect();
            if rest.is_empty() {
                online.clone()
            } else {
                rest
            }
        }
        Some(Value::Str(s)) => {
            let v = parse_cpu_list(s)
                .with_context(|| format!("{} = {s:?}: {}", origin("housekeeping_cpus"), what("housekeeping_cpus")))?;
            if let Some(bad) = v.iter().find(|c| !online.contains(c)) {
                bail!(
                    "{} = {s:?}: CPU {bad} is out of range: this machine's online CPUs are {online_shown}",
                    origin("housekeeping_cpus")
                );
            }
            v
        }
        Some(v) => bail!("{} is {}: {}", origin("housekeeping_cpus"), v.kind(), what("housekeeping_cpus")),
    };
    let render_hz = match cfg.get("render_hz") {
        None => 10.0,
        Some(Value::Int(n)) if (0..=60).contains(n) => *n as f64,
        Some(Value::Float(x)) if (0.0..=60.0).contains(x) => *x,
        Some(v @ (Value::Int(_) | Value::Float(_))) => {
            bail!("{} = {} is out of range: {}", origin("render_hz"), show(v), what("render_hz"))
        }
        Some(v) => bail!("{} is {}: {}", origin("render_hz"), v.kind(), what("render_hz")),
    };
    let boolean = |key: &str, default: bool| -> anyhow::Result<bool> {
        match cfg.get(key) {
            None => Ok(default),
            Some(Value::Bool(b)) => Ok(*b),
            Some(v) => bail!("{} is {}: {}", origin(key), v.kind(), what(key)),
        }
    };
    let trace = boolean("trace", true)?;
    let agent_llm = match cfg.get("agent_llm") {
        None => "scripted".to_string(),
        Some(Value::Str(s)) => s.clone(),
        Some(v) => bail!("{} is {}: {}", origin("agent_llm"), v.kind(), what("agent_llm")),
    };
    let agent_episodes = int("agent_episodes", 1, 100_000, 10)?;
    let fci = match (&args.fci, cfg.get("fci")) {
        (Some(a), _) => {
            fci_ip(&format!("--fci {a:?}"), a)?;
            Some(a.clone())
        }
        (None, Some(Value::Str(a))) if a.is_empty() => None,
        (None, Some(Value::Str(a))) => {
            fci_ip(&format!("{} = {a:?}", origin("fci")), a)?;
            Some(a.clone())
        }
        (None, Some(v)) => bail!("{} is {}: {}", origin("fci"), v.kind(), what("fci")),
        (None, None) => None,
    };
    let fci_gripper = args.fci_gripper || boolean("fci_gripper", false)?;
    if fci_gripper && fci.is_none() {
        bail!("{} = true needs fci, the arm's address: {}", origin("fci_gripper"), what("fci"));
    }
    if housekeeping_cpus.contains(&cpu) {
        bail!(
            "{} holds CPU {cpu}, the control loop's own CPU: give the other CPUs ({})",
            origin("housekeeping_cpus"),
            what("housekeeping_cpus")
        );
    }
    Ok(Settings {
        cpu,
        fifo_priority,
        housekeeping_cpus,
        render_hz,
        trace,
        agent_llm,
        agent_episodes,
        fci,
        fci_gripper,
    })
}

/// The IPv4 address in `address` (`a.b.c.d` or `a.b.c.d:port`). The fci unit allows packets to
/// and from exactly that address (IPAddressAllow= takes no host names) and resolves no names.
fn fci_ip(origin: &str, address: &str) -> anyhow::Result<Ipv4Addr> {
    match address.parse::<SocketAddrV4>() {
        Ok(a) => Ok(*a.ip()),
        Err(_) => address.parse::<Ipv4Addr>().map_err(|_| {
            anyhow::anyhow!(
                "{origin}: the arm's FCI address must be an IPv4 address, optionally with a port (such as 172.16.0.2 \
                 or 172.16.0.2:1337), not a host name: r2g-fci@ may exchange packets with that address only"
            )
        }),
    }
}

fn show(v: &Value) -> String {
    match v {
        Value::Str(s) => format!("{s:?}"),
        Value::Int(n) => n.to_string(),
        Value::Float(x) => format!("{x:?}"),
        Value::Bool(b) => b.to_string(),
    }
}

/// Instance names are what both iceoryx2 (the service prefix) and systemd (the `%i` of the
/// templates) take without escaping.
fn check_instance(name: &str) -> anyhow::Result<()> {
    let ok =
        !name.is_empty() && name.len() <= 32 && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    if !ok {
        bail!(
            "--instance {name:?}: an instance name is 1-32 characters of A-Z a-z 0-9 _ - (it is the systemd \
             instance and the iceoryx2 service prefix)"
        );
    }
    ipc_schema::Services::new(name).map_err(|e| anyhow::anyhow!("--instance {name:?}: {e}"))?;
    Ok(())
}

/// A path a unit file can carry as it is, and that the units' sandbox can see.
fn check_path(what: &str, p: &Path) -> anyhow::Result<String> {
    let s = p.to_str().with_context(|| format!("{what} {} is not UTF-8", p.display()))?.to_string();
    if let Some(c) = s.chars().find(|c| c.is_whitespace() || c.is_control() || "%$\"'\\;".contains(*c)) {
        bail!("{what} {s}: the character {c:?} cannot stand in a unit file; move it to a path without it");
    }
    for hidden in ["/home", "/root", "/run/user"] {
        if s == hidden || s.starts_with(&format!("{hidden}/")) {
            bail!(
                "{what} {s} is under {hidden}, which the units hide (ProtectHome=yes): keep the checkout, its \
                 .venv and the binaries outside /home, /root and /run/user (e.g. under /opt)"
            );
        }
    }
    Ok(s)
}

fn absolute(p: &Path) -> anyhow::Result<PathBuf> {
    std::fs::canonicalize(p).with_context(|| format!("{} does not exist", p.display()))
}

fn is_executable(p: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(p).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}

/// The calibration files the robot config names, copied beside the instance's robot.json (the
/// units cannot read the user's folders) as `calibration/tcp.json` and
/// `calibration/camera-NAME.json`, and the robot.json that names those copies. A missing or
/// unreadable TCP file is refused (r2g-control would refuse to start); a camera's is left out
/// with a note (the runtime reports it missing).
fn instance_calibration(
    robot_config: &Path,
    text: &str,
    notes: &mut Vec<String>,
) -> anyhow::Result<(String, Vec<(String, String)>)> {
    let files = runtime::RobotConfig::load(robot_config)?.calibration;
    if files.tcp.is_none() && files.cameras.is_empty() {
        return Ok((text.to_string(), Vec::new()));
    }
    let mut json: serde_json::Value = serde_json::from_str(text)?;
    let mut copies = Vec::new();
    if let Some(tcp) = &files.tcp {
        let body = std::fs::read_to_string(tcp)
            .with_context(|| format!("robot config {}: calibration.tcp {}", robot_config.display(), tcp.display()))?;
        copies.push(("calibration/tcp.json".to_string(), body));
        json["calibration"]["tcp"] = "calibration/tcp.json".into();
    }
    for (cam, path) in &files.cameras {
        let copy = format!("calibration/camera-{cam}.json");
        match std::fs::read_to_string(path) {
            Ok(body) => copies.push((copy.clone(), body)),
            Err(e) => notes.push(format!(
                "calibration of camera {cam}: {} ({e}); the instance reports it missing",
                path.display()
            )),
        }
        json["calibration"]["cameras"][cam.as_str()] = copy.into();
    }
    Ok((serde_json::to_string_pretty(&json)? + "\n", copies))
}

/// Everything `install` would write, after checking every input; writes nothing.
fn plan(args: &InstallArgs) -> anyhow::Result<Plan> {
    let name = args.instance.as_str();
    check_instance(name)?;
    let s = settings(args)?;
    let mut notes = Vec::new();

    // The scene and the robot config.
    let is_robot_config = args.target.to_ascii_lowercase().ends_with(".json");
    let (gym, robot_config) = if is_robot_config {
        let Some(gym) = &args.gym else {
            bail!(
                "{} is a robot config: give the gym whose scene it drives with --gym NAME (the scene gives the robot \
                 model, the table and the workspace r2g-control checks chunks against)",
                args.target
            );
        };
        (gym.clone(), PathBuf::from(&args.target))
    } else {
        if args.gym.is_some() {
            bail!("--gym is only for a robot config argument (a .json file); {} is already the gym", args.target);
        }
        (args.target.clone(), launch::default_robot_config())
    };
    let scene = launch::resolve_scene(&gym).with_context(|| format!("gym {gym:?}"))?;
    let scene = check_path("the scene", &absolute(&scene)?)?;
    let robot_json = std::fs::read_to_string(&robot_config)
        .with_context(|| format!("robot config {}: cannot read it", robot_config.display()))?;
    let config =
        runtime::RobotConfig::parse(&robot_json).with_context(|| format!("robot config {}", robot_config.display()))?;
    let robotiq = match &config.gripper {
        runtime::robot_config::Gripper::Robotiq2f85(r) => Some(r.clone()),
        _ => None,
    };
    let (robot_json, calibration) = instance_calibration(&robot_config, &robot_json, &mut notes)?;

    // The robot side, refused where `r2g up` would refuse it (the control unit runs in wall mode).
    let side = match &s.fci {
        Some(address) => RobotSide::Fci {
            address: address.clone(),
            extra: if s.fci_gripper { vec!["--gripper".into()] } else { vec![] },
        },
        None => RobotSide::Sim,
    };
    side.check(ipc_schema::Mode::Wall, Some(&robot_config)).with_context(|| {
        format!(
            "r2g-fci for the arm at {}: give a robot config with \"profile\": \"franka\" as the first argument and the \
             gym with --gym",
            s.fci.as_deref().unwrap_or_default()
        )
    })?;

    if matches!(side, RobotSide::Fci { .. })
        && std::fs::read_to_string("/sys/kernel/realtime").map_or(true, |v| v.trim() != "1")
    {
        notes.push(format!(
            "this kernel has no real-time support (/sys/kernel/realtime is not 1): r2g-fci@{name} runs with \
             --realtime and refuses to start on it; boot a PREEMPT_RT kernel (deploy/README.md)"
        ));
    }

    // The binaries the units run (r2g-sim in any case: the agent unit's batches start simulated gyms).
    let bin_dir = match &args.bin_dir {
        Some(d) => absolute(d).with_context(|| format!("--bin-dir {}", d.display()))?,
        None => {
            let exe = std::env::current_exe().context("locating this r2g")?;
            absolute(exe.parent().context("r2g has no folder")?)?
        }
    };
    let mut programs = vec!["r2g", "r2g-control", "r2g-sim", side.program()];
    if robotiq.is_some() {
        programs.push("r2g-robotiq");
    }
    for b in programs {
        if !is_executable(&bin_dir.join(b)) {
            bail!(
                "{} has no executable {b}: build the workspace (cargo build --release) or pass --bin-dir with the \
                 folder of the installed binaries",
                bin_dir.display()
            );
        }
    }
    let bin = check_path("the binaries' folder", &bin_dir)?;

    // The checkout the binaries read (gyms, robot descriptions, skill documents, the venv).
    let gyms = check_path("the gyms folder", &absolute(&launch::gyms_dir())?)?;
    let robots = check_path("the robots folder", &absolute(&launch::robots_dir())?)?;
    let skill = match std::env::var_os("R2G_SKILL") {
        Some(d) => PathBuf::from(d),
        None => Path::new(&gyms).parent().context("the gyms folder has no parent")?.join("robot-skill"),
    };
    let skill = check_path("the robot-skill folder", &absolute(&skill)?)?;

    // Only the optional agent unit runs Python: a venv it cannot use is worth a note, not a refusal.
    if let Some(checkout) = Path::new(&gyms).parent() {
        let venv_python = checkout.join(".venv/bin/python");
        match absolute(&venv_python) {
            Err(_) => notes.push(format!(
                "{} is missing: r2g-agent@{name} needs it (make venv); the other units do not",
                venv_python.display()
            )),
            Ok(p) => {
                if let Err(e) = check_path("the venv's interpreter", &p) {
                    notes.push(format!("r2g-agent@{name} cannot start its Python: {e:#}"));
                }
            }
        }
    }

    // The agent batch's LLM.
    let etc = format!("/etc/r2g/{name}");
    let mut files: Vec<(PathBuf, String)> = Vec::new();
    let agent_llm = if s.agent_llm == "scripted" {
        s.agent_llm.clone()
    } else if let Some(conv) = s.agent_llm.strip_prefix("scripted:") {
        let p = absolute(Path::new(conv))
            .with_context(|| format!("agent_llm = {:?}: {}", s.agent_llm, what("agent_llm")))?;
        let p = check_path("agent_llm's conversation", &p)?;
        format!("scripted:{p}")
    } else {
        let p = Path::new(&s.agent_llm);
        agent_host::llm::EndpointConfig::load(p)
            .with_context(|| format!("agent_llm = {:?}: {}", s.agent_llm, what("agent_llm")))?;
        let text = std::fs::read_to_string(p)?;
        files.push((PathBuf::from(format!("etc/r2g/{name}/agent-endpoint.toml")), text));
        format!("{etc}/agent-endpoint.toml")
    };

    // Unit templates, shared by every instance.
    let templates = [
        ("r2g@.target", TARGET_UNIT),
        ("r2g-control@.service", CONTROL_UNIT),
        ("r2g-sim@.service", SIM_UNIT),
        ("r2g-fci@.service", FCI_UNIT),
        ("r2g-agent@.service", AGENT_UNIT),
        ("r2g-robotiq@.service", ROBOTIQ_UNIT),
        ("r2g-camera@.service", CAMERA_UNIT),
    ];
    for (file, text) in templates {
        let rel = PathBuf::from("etc/systemd/system").join(file);
        if let Ok(old) = std::fs::read_to_string(args.root.join(&rel)) {
            if old != text {
                notes.push(format!("replaced {} (it differed; every instance uses it)", rel.display()));
            }
        }
        files.push((rel, text.to_string()));
    }

    // Per-instance drop-ins. The target and the control unit want the instance's robot side: a
    // drop-in can add a dependency, never remove one, so the templates name none.
    let header = format!(
        "# Written by `r2g service install` for instance {name}; the values are in {etc}/instance.toml.\n\
         # Install again (with --config {etc}/instance.toml) rather than editing this file.\n"
    );
    let robot_side = format!("{}@%i.service", side.program());
    let wants_side = format!("[Unit]\nWants={robot_side}\nAfter={robot_side}\n");
    let checkout = format!(
        "Environment=R2G_GYMS={gyms} R2G_ROBOTS={robots} R2G_SKILL={skill}\nEnvironment=\"R2G_BIN_DIR={bin}\"\n"
    );
    let others = show_cpus(&s.housekeeping_cpus).replace(',', " ");
    // The control process may use the housekeeping CPUs and the loop's CPU; the loop thread pins
    // itself to the latter, so its side threads (notifier, operator socket) stay off it.
    let mut control_cpus = s.housekeeping_cpus.clone();
    control_cpus.push(s.cpu);
    control_cpus.sort_unstable();
    let control = format!(
        "{header}{wants_side}[Service]\nEnvironment=R2G_SCENE={scene}\nEnvironment=R2G_CPU={} R2G_FIFO_PRIORITY={}\n\
         {checkout}CPUAffinity={}\nLimitRTPRIO={}\n",
        s.cpu,
        s.fifo_priority,
        show_cpus(&control_cpus).replace(',', " "),
        s.fifo_priority
    );
    let robot = match &side {
        RobotSide::Sim => {
            let mut sim_args: Vec<String> = Vec::new();
            if s.trace {
                sim_args.push(format!("--trace-dir /var/lib/r2g/{name}/traces"));
            }
            // Cameras that are devices: r2g-sim lists them for agents and renders no scene
            // camera of that name (as `r2g up` tells it).
            sim_args.extend(config.cameras.iter().map(|c| format!("--camera-host {}", c.name)));
            let sim_args = sim_args.join(" ");
            format!(
                "{header}[Service]\nEnvironment=R2G_SCENE={scene}\nEnvironment=R2G_RENDER_HZ={}\n\
                 Environment=\"R2G_SIM_ARGS={sim_args}\"\n{checkout}CPUAffinity={others}\n",
                s.render_hz
            )
        }
        // The one address the unit may exchange packets with (its IPAddressDeny=any drops the rest).
        RobotSide::Fci { address, extra } => format!(
            "{header}[Service]\nEnvironment=R2G_SCENE={scene}\nEnvironment=R2G_FCI_ADDRESS={address}\n\
             Environment=\"R2G_FCI_ARGS={}\"\n{checkout}CPUAffinity={others}\nIPAddressAllow={}\n",
            extra.join(" "),
            fci_ip("fci", address)?
        ),
    };
    let agent = format!(
        "{header}[Service]\nEnvironment=R2G_SCENE={scene}\nEnvironment=R2G_AGENT_LLM={agent_llm} R2G_AGENT_EPISODES={}\n\
         {checkout}CPUAffinity={others}\n",
        s.agent_episodes
    );
    // The devices the robot config names, each in a unit of its own that may open only its
    // device: the gripper's serial port, a camera's USB or V4L2 node.
    let mut device_units: Vec<(String, String)> = Vec::new();
    if let Some(r) = &robotiq {
        device_units.push((
            format!("r2g-robotiq@{name}.service"),
            format!("{header}[Service]\n{checkout}CPUAffinity={others}\n{}", serial_device_allow(&r.port)?),
        ));
    }
    if !config.cameras.is_empty() {
        let root = Path::new(&gyms).parent().context("the gyms folder has no parent")?;
        // The venv's own path (its interpreter may be a link into a Python elsewhere).
        let venv_python = root.join(".venv/bin/python");
        if let Err(e) = absolute(&venv_python).and_then(|p| check_path("the venv's interpreter", &p)) {
            notes.push(format!("the camera hosts of instance {name} cannot start their Python: {e:#}"));
        }
        let python = systemd_path(&venv_python.display().to_string())?;
        let host = check_path("the camera host", &absolute(&root.join("camera-host/py/r2g_camera_host.py"))?)?;
        for c in &config.cameras {
            let device = match &c.driver {
                runtime::robot_config::CameraDriver::Realsense { .. } => "DeviceAllow=char-usb_device rw\n".to_string(),
                runtime::robot_config::CameraDriver::Uvc { device } => {
                    format!("DeviceAllow={} rw\n", systemd_path(&device.display().to_string())?)
                }
                runtime::robot_config::CameraDriver::Replay { .. } => String::new(),
            };
            let args: Vec<String> = c.host_args().iter().map(|a| systemd_path(a)).collect::<anyhow::Result<_>>()?;
            device_units.push((
                format!("r2g-camera@{name}.{}.service", c.name),
                format!(
                    "{header}[Unit]\nPartOf=r2g@{name}.target r2g-control@{name}.service\nAfter=r2g-control@{name}.service\n\
                     [Service]\nEnvironment=R2G_IPC_CONFIG=/etc/r2g/{name}/iceoryx2.toml R2G_INSTANCE={name}\n\
                     Environment=\"R2G_PYTHON={python}\" \"R2G_CAMERA_HOST={host}\"\n\
                     Environment=\"R2G_CAMERA_ARGS={}\"\n\
                     ExecStartPre=+/usr/bin/systemd-tmpfiles --create /etc/tmpfiles.d/r2g-{name}.conf\n\
                     BindPaths=/run/r2g/{name}/shm:/dev/shm\nReadWritePaths=/run/r2g/{name}/iceoryx2\n\
                     CPUAffinity={others}\n{device}",
                    args.join(" ")
                ),
            ));
        }
    }
    let wants_devices: String = device_units.iter().map(|(u, _)| format!("Wants={u}\n")).collect();
    let mut drop_ins = vec![
        (format!("r2g@{name}.target"), format!("{header}{wants_side}{wants_devices}")),
        (format!("r2g-control@{name}.service"), control),
        (format!("{}@{name}.service", side.program()), robot),
        (format!("r2g-agent@{name}.service"), agent),
    ];
    drop_ins.extend(device_units);
    for (unit, text) in drop_ins {
        files.push((PathBuf::from(format!("etc/systemd/system/{unit}.d/10-r2g.conf")), text));
    }
    // The other robot side's drop-in from an earlier install goes: without it that unit has no
    // scene and no binaries, so it cannot be started beside this one by mistake.
    let mut stale = Vec::new();
    for other in ROBOT_SIDES.iter().filter(|p| **p != side.program()) {
        let rel = PathBuf::from(format!("etc/systemd/system/{other}@{name}.service.d/10-r2g.conf"));
        if args.root.join(&rel).exists() {
            notes.push(format!(
                "instance {name}'s robot side is now {}@{name}: removing {} (stop {other}@{name}.service if it runs)",
                side.program(),
                rel.display()
            ));
            stale.push(rel);
        }
    }

    // The instance's own files: the iceoryx2 configurations of the control instance and of the
    // agent unit, which has folders of its own (deploy/README.md, "Shared memory").
    files.push((PathBuf::from(format!("etc/r2g/{name}/iceoryx2.toml")), ICEORYX2.replace("@INSTANCE@", name)));
    files.push((
        PathBuf::from(format!("etc/r2g/{name}/agent-iceoryx2.toml")),
        ICEORYX2_AGENT.replace("@INSTANCE@", name),
    ));
    files.push((PathBuf::from(format!("etc/r2g/{name}/robot.json")), robot_json));
    for (file, text) in calibration {
        files.push((PathBuf::from(format!("etc/r2g/{name}/{file}")), text));
    }
    let instance_toml = format!(
        "# r2g instance {name}, written by `r2g service install` (r2g {}).\n\
         # gym: {scene}\n\
         # robot config: {} (copied to {etc}/robot.json)\n\
         # binaries: {bin}\n\
         # `r2g service install {} --instance {name} --config {etc}/instance.toml` writes the same again.\n\
         cpu = {}\n\
         fifo_priority = {}\n\
         housekeeping_cpus = \"{}\"\n\
         render_hz = {:?}\n\
         trace = {}\n\
         agent_llm = {:?}\n\
         agent_episodes = {}\n\
         fci = {:?}\n\
         fci_gripper = {}\n",
        env!("CARGO_PKG_VERSION"),
        absolute(&robot_config)?.display(),
        if is_robot_config { format!("{} --gym {gym}", args.target) } else { gym.clone() },
        s.cpu,
        s.fifo_priority,
        show_cpus(&s.housekeeping_cpus),
        s.render_hz,
        s.trace,
        s.agent_llm,
        s.agent_episodes,
        s.fci.as_deref().unwrap_or_default(),
        s.fci_gripper,
    );
    files.push((PathBuf::from(format!("etc/r2g/{name}/instance.toml")), instance_toml));
    files.push((PathBuf::from(format!("etc/tmpfiles.d/r2g-{name}.conf")), TMPFILES.replace("@INSTANCE@", name)));
    files.push((PathBuf::from("etc/sysusers.d/r2g.conf"), SYSUSERS.to_string()));

    // systemd-sysusers adds memberships but never removes one: a machine installed before still
    // has r2g-agent in group r2g, which would let the agent's user into the control instance's
    // shared memory.
    if let Ok(group) = std::fs::read_to_string(args.root.join("etc/group")) {
        if agent_in_control_group(&group) {
            notes.push(
                "user r2g-agent is a member of group r2g (from an earlier install; systemd-sysusers never removes a \
                 membership), so it can enter the control instance's shared memory: remove it with \
                 gpasswd -d r2g-agent r2g"
                    .to_string(),
            );
        }
    }
    Ok(Plan { instance: name.to_string(), files, stale, notes })
}

/// A value written into a unit file: no whitespace, quotes, backslashes, `%` or `$` (which systemd
/// would split, unquote or expand).
/// The `DeviceAllow=` lines of the gripper's unit. systemd turns a path into the device number
/// it has when the unit starts, so a USB adapter plugged again as another `ttyUSBn` would be
/// refused for as long as r2g-robotiq runs (it never exits on a lost port): a USB serial port is
/// allowed by its driver's class instead (`char-ttyUSB`, `char-ttyACM`: every port of that
/// driver, and nothing else); a fixed port (`ttyS0`, ...) by its path.
fn serial_device_allow(port: &Path) -> anyhow::Result<String> {
    let resolved = std::fs::canonicalize(port).ok();
    let name = resolved.as_deref().unwrap_or(port).file_name().and_then(|n| n.to_str()).unwrap_or("");
    let classes: &[&str] = if name.starts_with("ttyUSB") {
        &["char-ttyUSB"]
    } else if name.starts_with("ttyACM") {
        &["char-ttyACM"]
    } else if resolved.is_none() && port.starts_with("/dev/serial") {
        // A by-id or by-path link of an adapter not plugged in now: either USB serial driver.
        &["char-ttyUSB", "char-ttyACM"]
    } else {
        return Ok(format!("DeviceAllow={} rw\n", systemd_path(&port.display().to_string())?));
    };
    Ok(classes.iter().map(|c| format!("DeviceAllow={c} rw\n")).collect())
}

fn systemd_path(v: &str) -> anyhow::Result<String> {
    if v.is_empty() || v.chars().any(|c| c.is_whitespace() || c.is_control() || "\"'\\%$".contains(c)) {
        bail!("{v:?} cannot be written into a unit file (no spaces, quotes, backslashes, % or $)");
    }
    Ok(v.to_string())
}

/// Whether /etc/group (its text) lists user r2g-agent as a member of group r2g.
fn agent_in_control_group(group: &str) -> bool {
    let Some(line) = group.lines().find(|l| l.split(':').next() == Some("r2g")) else {
        return false;
    };
    line.split(':').nth(3).is_some_and(|members| members.split(',').any(|m| m.trim() == "r2g-agent"))
}

/// Writes every file to a temporary name beside it, then renames them all into place; on an
/// error before the renames, the temporary files are removed and nothing has changed.
fn write_all(root: &Path, plan: &Plan) -> anyhow::Result<()> {
    use std::io::Write;
    let mut temps: Vec<(PathBuf, PathBuf)> = Vec::new();
    let result = (|| -> anyhow::Result<()> {
        for (rel, text) in &plan.files {
            let path = root.join(rel);
            let dir = path.parent().context("file without a folder")?;
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            let file_name = path.file_name().context("file without a name")?.to_string_lossy();
            let tmp = dir.join(format!(".{file_name}.tmp-{}", std::process::id()));
            let mut f = std::fs::File::create(&tmp).with_context(|| format!("writing {}", tmp.display()))?;
            temps.push((tmp.clone(), path.clone()));
            f.write_all(text.as_bytes()).with_context(|| format!("writing {}", tmp.display()))?;
            f.sync_all().with_context(|| format!("writing {}", tmp.display()))?;
        }
        Ok(())
    })();
    if let Err(e) = result {
        for (tmp, _) in &temps {
            let _ = std::fs::remove_file(tmp);
        }
        return Err(e);
    }
    for (tmp, path) in &temps {
        std::fs::rename(tmp, path).with_context(|| format!("renaming {} to {}", tmp.display(), path.display()))?;
    }
    for rel in &plan.stale {
        let path = root.join(rel);
        std::fs::remove_file(&path).with_context(|| format!("removing {}", path.display()))?;
        // Its folder too, when nothing else is left in it.
        if let Some(dir) = path.parent() {
            let _ = std::fs::remove_dir(dir);
        }
    }
    Ok(())
}

fn report(root: &Path, plan: &Plan) {
    let name = &plan.instance;
    for (rel, _) in &plan.files {
        println!("wrote {}", root.join(rel).display());
    }
    for rel in &plan.stale {
        println!("removed {}", root.join(rel).display());
    }
    for n in &plan.notes {
        eprintln!("r2g service install: {n}");
    }
    println!(
        "next, as root:\n  systemd-sysusers /etc/sysusers.d/r2g.conf\n  systemd-tmpfiles --create \
         /etc/tmpfiles.d/r2g-{name}.conf\n  systemctl daemon-reload\n  systemctl start r2g@{name}.target\n  r2g \
         service status --instance {name}"
    );
}

/// Whether systemd is the service manager here (its own test: /run/systemd/system exists).
fn systemd_running() -> bool {
    Path::new("/run/systemd/system").is_dir()
}

fn status(instance: &str, json: bool) -> anyhow::Result<i32> {
    check_instance(instance)?;
    // An installed instance's socket is under /run/r2g, which `run_dir` looks in by itself.
    let answer = runtime::operator::status(instance);
    if json {
        match &answer {
            Ok(v) => println!("{v}"),
            Err(e) => println!("{}", serde_json::json!({"ok": false, "error": format!("{e:#}")})),
        }
    } else {
        match &answer {
            Ok(v) => print_status(v),
            Err(e) => println!("control process: not reachable: {e:#}"),
        }
        units(instance);
    }
    Ok(match answer {
        Ok(v) if v["fault"] == "none" && v["robot_lost"] == false => 0,
        _ => 1,
    })
}

fn print_status(v: &serde_json::Value) {
    let num = |k: &str| v[k].as_f64().map_or_else(|| "?".to_string(), |x| format!("{x}"));
    let fixed = |k: &str, unit: &str| v[k].as_f64().map_or_else(|| "?".to_string(), |x| format!("{x:.1} {unit}"));
    let text = |k: &str| v[k].as_str().map_or_else(|| v[k].to_string(), str::to_string);
    let rows = [
        ("instance", text("instance")),
        ("pid", num("pid")),
        ("mode", text("mode")),
        ("uptime", fixed("uptime_s", "s")),
        ("ticks", num("ticks")),
        ("overruns (missed deadlines)", num("overruns")),
        ("wake latency, max of last 1 s", fixed("wake_max_us", "us")),
        ("age of the last robot state", fixed("state_age_ms", "ms")),
        ("robot lost", if v["robot_lost"] == true { "YES".into() } else { "no".into() }),
        ("fault", text("fault")),
        ("agent port errors", num("agent_port_errors")),
        (
            "systemd watchdog",
            match v["watchdog_usec"].as_u64() {
                Some(0) | None => "off".to_string(),
                Some(us) => format!("{} ms", us / 1000),
            },
        ),
    ];
    for (k, val) in rows {
        println!("{k:<31} {val}");
    }
}

fn units(instance: &str) {
    if !systemd_running() {
        let init = std::fs::read_to_string("/proc/1/comm").unwrap_or_default();
        println!("systemd is not running here (PID 1 is {}): no unit states", init.trim());
        return;
    }
    // The robot side is the one the instance's install wrote a drop-in for.
    let side = ROBOT_SIDES
        .into_iter()
        .find(|p| Path::new(&format!("/etc/systemd/system/{p}@{instance}.service.d")).is_dir())
        .unwrap_or(ROBOT_SIDES[0]);
    for unit in [
        format!("r2g@{instance}.target"),
        format!("r2g-control@{instance}.service"),
        format!("{side}@{instance}.service"),
        format!("r2g-agent@{instance}.service"),
    ] {
        let state = std::process::Command::new("systemctl")
            .args(["is-active", &unit])
            .output()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
            .unwrap_or_else(|e| format!("systemctl failed: {e}"));
        println!("{:<31} {state}", unit);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_toml_values_and_refusals() {
        let f = Path::new("x.toml");
        let c = parse_config("cpu = 3 # loop\nrender_hz = 12.5\ntrace = false\nagent_llm = \"a#b\"\n", f).unwrap();
        assert_eq!(c["cpu"], Value::Int(3));
        assert_eq!(c["render_hz"], Value::Float(12.5));
        assert_eq!(c["trace"], Value::Bool(false));
        assert_eq!(c["agent_llm"], Value::Str("a#b".into()));
        let e = parse_config("cpus = 1\n", f).unwrap_err().to_string();
        assert!(e.contains("unknown key \"cpus\"") && e.contains("accepted keys: cpu,"), "{e}");
        assert!(parse_config("[x]\n", f).is_err());
        assert!(parse_config("cpu = [1]\n", f).is_err());
        assert!(parse_config("cpu = 1\ncpu = 2\n", f).is_err());
    }

    #[test]
    fn a_leftover_agent_membership_in_group_r2g_is_found() {
        assert!(agent_in_control_group("root:x:0:\nr2g:x:990:r2g-agent\n"));
        assert!(agent_in_control_group("r2g:x:990:alice,r2g-agent\n"));
        assert!(!agent_in_control_group("r2g:x:990:\nr2g-agent:x:989:\n"));
        assert!(!agent_in_control_group("r2g-operator:x:988:r2g-agent\n"));
        assert!(!agent_in_control_group(""));
    }

    #[test]
    fn cpu_lists() {
        assert_eq!(parse_cpu_list("0-2,4").unwrap(), vec![0, 1, 2, 4]);
        assert_eq!(parse_cpu_list("3 1 1").unwrap(), vec![1, 3]);
        assert!(parse_cpu_list("2-1").is_err());
        assert_eq!(show_cpus(&[0, 1, 2, 4, 6, 7]), "0-2,4,6-7");
    }
}
