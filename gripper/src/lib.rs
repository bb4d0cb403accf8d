//! `r2g-robotiq`: a Robotiq 2F-85 on a serial port as the gripper of an instance (see this
//! crate's README). All serial I/O happens here, in its own process: the runtime's tick only
//! reads the newest [`GripperState`] and writes its finger target into the command it publishes
//! anyway; this driver polls the gripper, publishes what it reads, and sends a new position
//! request when the target changes.

pub mod robotiq;

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use anyhow::Context;
use ipc_schema::process::{self, PeerWatch};
use ipc_schema::{GripperState, JointCommand, Qos, RuntimeInfo, Services, GRIPPER_LINK_LOST, GRIPPER_NOT_READY};
use robotiq::{Command, Frames, Scale, Status};
use runtime::robot_config::Robotiq;

type Pub<T> = iceoryx2::port::publisher::Publisher<iceoryx2::prelude::ipc::Service, T, ()>;
type Sub<T> = iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, T, ()>;

/// How long one answer may take before the request counts as unanswered.
const ANSWER_TIMEOUT: Duration = Duration::from_millis(100);
/// Unanswered or broken exchanges in a row before the link counts as lost.
const MAX_FAILURES: u32 = 3;
/// How long the activation may take.
const ACTIVATION_TIMEOUT: Duration = Duration::from_secs(15);

/// The process's node name for an instance.
pub fn node_name(instance: &str) -> String {
    format!("r2g-robotiq-{instance}")
}

/// What went wrong on the line, in words, and whether the port itself is gone.
#[derive(Debug)]
pub struct LinkError {
    pub text: String,
    /// The device vanished or broke (not just one bad answer): reopen it.
    pub fatal: bool,
}

fn io_error(port: &str, e: &std::io::Error) -> LinkError {
    use std::io::ErrorKind as K;
    let fatal = !matches!(e.kind(), K::TimedOut | K::WouldBlock | K::Interrupted);
    let text = if fatal {
        format!("serial port failed ({e}): the device vanished or was unplugged: {port}")
    } else {
        format!("no answer from the gripper within {} ms on {port}", ANSWER_TIMEOUT.as_millis())
    };
    LinkError { text, fatal }
}

/// One Modbus RTU link to the gripper.
pub struct Link {
    port: Box<dyn serialport::SerialPort>,
    path: String,
    frames: Frames,
}

impl Link {
    pub fn open(path: &str, baud: u32, slave: u8) -> Result<Self, LinkError> {
        let port = serialport::new(path, baud)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(serialport::FlowControl::None)
            .timeout(ANSWER_TIMEOUT)
            .open()
            .map_err(|e| {
                let text = if std::path::Path::new(path).exists() {
                    format!("cannot open the serial port ({e}): {path}")
                } else {
                    format!("serial port vanished (unplugged, or no such device): {path}")
                };
                LinkError { text, fatal: true }
            })?;
        Ok(Self { port, path: path.into(), frames: Frames::new(slave) })
    }

    /// Sends `frame` and reads its whole answer.
    fn exchange(&mut self, frame: &[u8]) -> Result<Vec<u8>, LinkError> {
        // Bytes left over from an earlier, late answer would be taken for this one.
        let _ = self.port.clear(serialport::ClearBuffer::Input);
        self.port.write_all(frame).map_err(|e| io_error(&self.path, &e))?;
        let mut answer = vec![0u8; 3];
        self.read_exact(&mut answer)?;
        let len = robotiq::answer_len(&answer).map_err(|e| LinkError {
            text: format!("the gripper on {} sent a frame that is not an answer: {}", self.path, robotiq::describe(e)),
            fatal: false,
        })?;
        if len < 3 {
            return Err(LinkError { text: format!("the gripper on {} sent a short frame", self.path), fatal: false });
        }
        answer.resize(len, 0);
        self.read_exact(&mut answer[3..])?;
        Ok(answer)
    }

    fn read_exact(&mut self, buf: &mut [u8]) -> Result<(), LinkError> {
        let deadline = Instant::now() + ANSWER_TIMEOUT;
        let mut got = 0;
        while got < buf.len() {
            if Instant::now() > deadline {
                return Err(io_error(&self.path, &std::io::Error::from(std::io::ErrorKind::TimedOut)));
            }
            match self.port.read(&mut buf[got..]) {
                // A pty whose other end closed reads 0 bytes: the device is gone.
                Ok(0) => {
                    return Err(LinkError {
                        text: format!("serial port closed (end of file): the device vanished: {}", self.path),
                        fatal: true,
                    })
                }
                Ok(n) => got += n,
                Err(e) => return Err(io_error(&self.path, &e)),
            }
        }
        Ok(())
    }

    pub fn write(&mut self, c: &Command) -> Result<(), LinkError> {
        let (req, frame) = self.frames.write(c);
        let answer = self.exchange(&frame)?;
        robotiq::parse_write(&req, &answer).map_err(|e| self.bad(e))
    }

    pub fn status(&mut self) -> Result<Status, LinkError> {
        let (req, frame) = self.frames.read_status(3);
        let answer = self.exchange(&frame)?;
        robotiq::parse_status(&req, &answer).map_err(|e| self.bad(e))
    }

    fn bad(&self, e: rmodbus::ErrorKind) -> LinkError {
        LinkError { text: format!("the gripper on {}: {}", self.path, robotiq::describe(e)), fatal: false }
    }
}

/// What a run measured (`--stats-out`).
#[derive(Debug, Default)]
pub struct Stats {
    pub polls: u64,
    /// Status read round trips, µs.
    pub poll_us: Vec<u32>,
    pub writes: u64,
    pub crc_errors: u64,
    pub timeouts: u64,
    pub link_losses: u64,
    pub reactivations: u64,
    /// Per position request: count, µs from the request written to the first status showing the
    /// fingers stopped (at the target, or on an object), and the `gOBJ` it ended with.
    pub moves: Vec<(u8, u64, u8)>,
}

impl Stats {
    pub fn to_json(&self) -> serde_json::Value {
        fn quantiles(mut v: Vec<u64>) -> serde_json::Value {
            v.sort_unstable();
            let q = |f: f64| v.get(((v.len() as f64 - 1.0) * f).round() as usize).copied().unwrap_or(0);
            serde_json::json!({"n": v.len(), "p50": q(0.5), "p99": q(0.99), "max": v.last().copied().unwrap_or(0)})
        }
        let moves = |object: u8| quantiles(self.moves.iter().filter(|m| m.2 == object).map(|m| m.1).collect());
        serde_json::json!({
            "polls": self.polls, "writes": self.writes, "crc_errors": self.crc_errors,
            "timeouts": self.timeouts, "link_losses": self.link_losses, "reactivations": self.reactivations,
            "poll_us": quantiles(self.poll_us.iter().map(|&u| u64::from(u)).collect()),
            "move_to_target_us": moves(3),
            "move_to_object_us": moves(2),
        })
    }
}

struct Ports {
    _node: iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    state: Pub<GripperState>,
    command: Sub<JointCommand>,
    info: Sub<RuntimeInfo>,
}

impl Ports {
    fn open(instance: &str) -> anyhow::Result<Self> {
        let services = Services::new(instance)?;
        let node = ipc_schema::node(&node_name(instance))?;
        Ok(Self {
            state: ipc_schema::open_or_create_pubsub::<GripperState>(&node, &services.gripper_state(), Qos::STREAM)?
                .publisher_builder()
                .create()
                .context("the gripper state publisher (is another r2g-robotiq serving this instance?)")?,
            command: ipc_schema::open_or_create_pubsub::<JointCommand>(&node, &services.command(), Qos::STREAM)?
                .subscriber_builder()
                .create()?,
            info: ipc_schema::open_or_create_pubsub::<RuntimeInfo>(&node, &services.runtime_info(), Qos::STREAM)?
                .subscriber_builder()
                .create()?,
            _node: node,
        })
    }
}

/// The driver's view of the runtime: its newest command and its robot model's finger range.
#[derive(Default)]
struct Wanted {
    finger_max_m: Option<f64>,
    finger_m: Option<f64>,
    clear_seq: u64,
}

impl Wanted {
    fn update(&mut self, ports: &Ports) {
        while let Ok(Some(i)) = ports.info.receive() {
            if i.finger_max_m.is_finite() && i.finger_max_m > 0.0 {
                self.finger_max_m = Some(i.finger_max_m);
            }
        }
        while let Ok(Some(c)) = ports.command.receive() {
            if c.finger_m.is_finite() {
                self.finger_m = Some(c.finger_m);
            }
            self.clear_seq = c.clear_seq;
        }
    }
}

/// Runs the driver until SIGINT/SIGTERM or the runtime stopping.
pub fn run(instance: &str, cfg: &Robotiq, poll: Duration) -> anyhow::Result<Stats> {
    let control = PeerWatch::spawn(process::control_node(instance), Duration::from_secs(30));
    ipc_schema::cleanup_dead_nodes();
    let ports = Ports::open(instance)?;
    let path = cfg.port.display().to_string();
    let scale = Scale { closed: cfg.closed_count };
    let mut stats = Stats::default();
    let mut wanted = Wanted::default();
    let mut out = GripperState::default();
    let mut publish = |out: &mut GripperState, fault: u32, text: &str| {
        out.seq += 1;
        out.published_ns = ipc_schema::monotonic_ns();
        out.fault = fault;
        out.set_fault_text(text);
        let _ = ports.state.send_copy(*out);
    };
    let mut link: Option<Link> = None;
    // Reset the gripper before activating it (clears a device fault; drops what it holds).
    let mut reset = false;
    let mut reported = String::new();
    let mut say = |text: &str| {
        if reported != text {
            eprintln!("r2g-robotiq: {text}");
            reported = text.to_string();
        }
    };
    'session: loop {
        if process::stop_requested() {
            return Ok(stats);
        }
        anyhow::ensure!(!control.lost(), "r2g-control of instance '{instance}' stopped; r2g-robotiq stops too");
        wanted.update(&ports);
        out.finger_max_m = wanted.finger_max_m.unwrap_or(0.0);
        // Connect and activate.
        let Some(l) = link.as_mut() else {
            match Link::open(&path, cfg.baud, cfg.slave) {
                Ok(l) => link = Some(l),
                Err(e) => {
                    say(&e.text);
                    publish(&mut out, GRIPPER_LINK_LOST, &e.text);
                    std::thread::sleep(Duration::from_millis(500));
                }
            }
            continue;
        };
        let activated = activate(l, std::mem::take(&mut reset), &mut out, &mut publish, &mut stats);
        if let Err(e) = activated {
            say(&e.text);
            publish(&mut out, if e.fatal { GRIPPER_LINK_LOST } else { GRIPPER_NOT_READY }, &e.text);
            if e.fatal {
                stats.link_losses += 1;
                link = None;
            }
            std::thread::sleep(Duration::from_millis(500));
            continue;
        }
        say(&format!("Robotiq 2F-85 on {path} (slave {}) is active", cfg.slave));
        let clear_at_start = wanted.clear_seq;
        let mut sent: Option<u8> = None;
        let mut move_started: Option<(u8, Instant)> = None;
        let mut failures = 0u32;
        let mut next = Instant::now();
        loop {
            if process::stop_requested() {
                return Ok(stats);
            }
            anyhow::ensure!(!control.lost(), "r2g-control of instance '{instance}' stopped; r2g-robotiq stops too");
            std::thread::sleep(next.saturating_duration_since(Instant::now()));
            next += poll;
            if next < Instant::now() {
                next = Instant::now() + poll;
            }
            wanted.update(&ports);
            out.finger_max_m = wanted.finger_max_m.unwrap_or(0.0);
            let t = Instant::now();
            let status = match l.status() {
                Ok(s) => {
                    failures = 0;
                    s
                }
                Err(e) => {
                    failures += 1;
                    if e.text.contains("CRC") {
                        stats.crc_errors += 1;
                    } else if e.text.contains("no answer") {
                        stats.timeouts += 1;
                    }
                    if e.fatal || failures >= MAX_FAILURES {
                        let lost_reason =
                            if e.fatal { e.text } else { format!("{} ({failures} times in a row)", e.text) };
                        say(&lost_reason);
                        publish(&mut out, GRIPPER_LINK_LOST, &lost_reason);
                        stats.link_losses += 1;
                        link = None;
                        continue 'session;
                    }
                    continue;
                }
            };
            let us = t.elapsed().as_micros().min(u128::from(u32::MAX)) as u32;
            stats.polls += 1;
            if stats.poll_us.len() < 1_000_000 {
                stats.poll_us.push(us);
            }
            out.poll_us = us;
            out.current_ma = f64::from(status.current_ma);
            out.grasp = status.grasp();
            out.finger_m = scale.fraction_open(status.position) * out.finger_max_m;
            if status.major_fault() || !status.activated {
                let text = if status.activated {
                    format!("Robotiq fault 0x{:02X}: {}", status.fault, robotiq::fault_name(status.fault))
                } else {
                    "the gripper was reset (not activated): reactivating".to_string()
                };
                say(&text);
                publish(&mut out, if status.activated { u32::from(status.fault) } else { GRIPPER_NOT_READY }, &text);
                // A fault that stops the gripper needs the operator (`r2g clear`); a reset one
                // reactivates at once.
                if !status.activated || wanted.clear_seq != clear_at_start {
                    stats.reactivations += 1;
                    reset = status.activated;
                    continue 'session;
                }
                continue;
            }
            publish(&mut out, 0, "");
            if let Some((pos, t0)) = move_started {
                if status.requested == pos && status.object != 0 {
                    stats.moves.push((pos, t0.elapsed().as_micros() as u64, status.object));
                    move_started = None;
                }
            }
            // The target: the runtime's command, as a fraction of its robot model's range.
            let (Some(max), Some(f)) = (wanted.finger_max_m, wanted.finger_m) else { continue };
            let pos = scale.position(f / max);
            if sent.is_none_or(|s| s.abs_diff(pos) > 1) {
                let c = Command { activate: true, go: true, position: pos, speed: cfg.speed, force: cfg.force };
                match l.write(&c) {
                    Ok(()) => {
                        stats.writes += 1;
                        sent = Some(pos);
                        move_started = Some((pos, Instant::now()));
                    }
                    Err(e) => {
                        failures += 1;
                        say(&e.text);
                        if e.fatal || failures >= MAX_FAILURES {
                            publish(&mut out, GRIPPER_LINK_LOST, &e.text);
                            stats.link_losses += 1;
                            link = None;
                            continue 'session;
                        }
                    }
                }
            }
        }
    }
}

/// Activates the gripper (rACT 0 then 1) and waits for it to report ready, publishing
/// "activating" meanwhile. A gripper that is active already and without a fault is left as it
/// is unless `reset` (a reconnect must not reset a gripper holding an object: the reset releases
/// its grip).
fn activate(
    l: &mut Link,
    reset: bool,
    out: &mut GripperState,
    publish: &mut impl FnMut(&mut GripperState, u32, &str),
    stats: &mut Stats,
) -> Result<(), LinkError> {
    let s = l.status()?;
    if s.ready() && !s.major_fault() && !reset {
        return Ok(());
    }
    let text = "activating the gripper (its fingers open and close once)";
    publish(out, GRIPPER_NOT_READY, text);
    l.write(&Command::default())?;
    l.write(&Command { activate: true, ..Command::default() })?;
    let t0 = Instant::now();
    loop {
        let s = l.status()?;
        stats.polls += 1;
        if s.ready() {
            return Ok(());
        }
        if s.major_fault() {
            return Err(LinkError {
                text: format!("activation failed: Robotiq fault 0x{:02X}: {}", s.fault, robotiq::fault_name(s.fault)),
                fatal: false,
            });
        }
        if t0.elapsed() > ACTIVATION_TIMEOUT {
            return Err(LinkError {
                text: format!("the gripper did not finish its activation within {} s", ACTIVATION_TIMEOUT.as_secs()),
                fatal: false,
            });
        }
        publish(out, GRIPPER_NOT_READY, text);
        std::thread::sleep(Duration::from_millis(20));
    }
}
