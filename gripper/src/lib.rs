//! `r2g-robotiq`: a Robotiq 2F-85 on a serial port as the gripper of an instance (see this
//! crate's README). All serial I/O happens here, in its own process: the runtime's tick only
//! reads the newest [`GripperState`] and writes its finger target into the command it publishes
//! anyway; this driver polls the gripper, publishes what it reads, and sends a new position
//! request when the target changes.

pub mod robotiq;

use std::io::{Read, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::Context;
use ipc_schema::process::{self, PeerWatch};
use ipc_schema::{GripperState, JointCommand, Qos, RuntimeInfo, Services, GRIPPER_LINK_LOST, GRIPPER_NOT_READY};
use robotiq::{Command, FaultClass, Frames, Scale, Status};
use runtime::robot_config::Robotiq;

type Pub<T> = iceoryx2::port::publisher::Publisher<iceoryx2::prelude::ipc::Service, T, ()>;
type Sub<T> = iceoryx2::port::subscriber::Subscriber<iceoryx2::prelude::ipc::Service, T, ()>;

/// How long the start of an answer, and then its rest, may take before the request counts as
/// unanswered.
const ANSWER_TIMEOUT: Duration = Duration::from_millis(100);
/// The longest one read of the port blocks, so that the wait for an answer still publishes.
const READ_SLICE: Duration = Duration::from_millis(20);
/// The longest the driver goes without publishing, whatever it waits for (an answer, a
/// reconnect, an activation): well inside the runtime's 250 ms watchdog, so that the runtime
/// hears the driver's own words for a silent gripper, never "the driver published nothing".
pub const HEARTBEAT: Duration = Duration::from_millis(40);
/// The longest poll period `--poll-ms` accepts (the runtime's watchdog is 250 ms).
pub const MAX_POLL: Duration = Duration::from_millis(100);
/// Unanswered or broken exchanges in a row before the link counts as lost.
const MAX_FAILURES: u32 = 3;
/// How long the activation may take.
const ACTIVATION_TIMEOUT: Duration = Duration::from_secs(15);
/// How often a port that is gone is tried again.
const REOPEN_EVERY: Duration = Duration::from_millis(500);

/// The process's node name for an instance.
pub fn node_name(instance: &str) -> String {
    format!("r2g-robotiq-{instance}")
}

/// What went wrong on the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkErrorKind {
    /// The port vanished or broke (unplugged, EIO, end of file): reopen it.
    Gone,
    /// No (whole) answer in time ([`ANSWER_TIMEOUT`]).
    Timeout,
    /// An answer whose CRC does not match.
    Crc,
    /// An answer that is not one to this request (another slave or function, an exception, a
    /// short frame).
    Bad,
}

/// What went wrong on the line, and in words (without the port: [`LinkError::on`] puts it last,
/// so that a long `/dev/serial/by-id/...` name is what a short text field cuts).
#[derive(Debug)]
pub struct LinkError {
    pub kind: LinkErrorKind,
    pub text: String,
}

impl LinkError {
    fn new(kind: LinkErrorKind, text: impl Into<String>) -> Self {
        Self { kind, text: text.into() }
    }

    /// The port itself is gone (not just one bad answer).
    pub fn fatal(&self) -> bool {
        self.kind == LinkErrorKind::Gone
    }

    /// The words for the published state and the log: the reason, then the port.
    pub fn on(&self, port: &str) -> String {
        format!("{}: {port}", self.text)
    }
}

fn io_error(e: &std::io::Error) -> LinkError {
    use std::io::ErrorKind as K;
    if matches!(e.kind(), K::TimedOut | K::WouldBlock | K::Interrupted) {
        LinkError::new(
            LinkErrorKind::Timeout,
            format!("no answer from the gripper within {} ms", ANSWER_TIMEOUT.as_millis()),
        )
    } else {
        LinkError::new(LinkErrorKind::Gone, format!("serial port failed ({e}): the device vanished or was unplugged"))
    }
}

/// What the driver publishes: its newest reading and fault, sent again whenever nothing was
/// published for [`HEARTBEAT`] (see [`GripperState::published_ns`]).
struct Out<'p> {
    publisher: &'p Pub<GripperState>,
    state: GripperState,
    last: Instant,
    said: String,
}

impl<'p> Out<'p> {
    fn new(publisher: &'p Pub<GripperState>) -> Self {
        Self { publisher, state: GripperState::default(), last: Instant::now(), said: String::new() }
    }

    /// Publishes the newest reading with this fault (0: none; `clears_itself`: see
    /// [`GripperState::clears_itself`]).
    fn publish(&mut self, fault: u32, clears_itself: bool, text: &str) {
        self.state.fault = fault;
        self.state.clears_itself = u32::from(clears_itself);
        self.state.set_fault_text(text);
        self.send();
    }

    fn send(&mut self) {
        self.state.seq += 1;
        self.state.published_ns = ipc_schema::monotonic_ns();
        let _ = self.publisher.send_copy(self.state);
        self.last = Instant::now();
    }

    /// Publishes the newest state again if nothing went out for [`HEARTBEAT`].
    fn beat(&mut self) {
        if self.last.elapsed() >= HEARTBEAT {
            self.send();
        }
    }

    /// Sleeps, beating.
    fn sleep(&mut self, d: Duration) {
        let end = Instant::now() + d;
        loop {
            self.beat();
            let now = Instant::now();
            if now >= end {
                return;
            }
            std::thread::sleep((end - now).min(HEARTBEAT / 2));
        }
    }

    /// Logs a line once per change of what there is to say.
    fn say(&mut self, text: &str) {
        if self.said != text {
            eprintln!("r2g-robotiq: {text}");
            self.said = text.to_string();
        }
    }
}

/// One Modbus RTU link to the gripper.
pub struct Link {
    port: Box<dyn serialport::SerialPort>,
    frames: Frames,
}

impl Link {
    pub fn open(path: &str, baud: u32, slave: u8) -> Result<Self, LinkError> {
        let port = serialport::new(path, baud)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(serialport::FlowControl::None)
            .timeout(READ_SLICE)
            .open()
            .map_err(|e| {
                let text = if std::path::Path::new(path).exists() {
                    format!("cannot open the serial port ({e})")
                } else {
                    "serial port vanished (unplugged, or no such device)".to_string()
                };
                LinkError::new(LinkErrorKind::Gone, text)
            })?;
        Ok(Self { port, frames: Frames::new(slave) })
    }

    /// Sends `frame` and reads its whole answer, beating meanwhile.
    fn exchange(&mut self, frame: &[u8], out: &mut Out) -> Result<Vec<u8>, LinkError> {
        // Bytes left over from an earlier, late answer would be taken for this one.
        let _ = self.port.clear(serialport::ClearBuffer::Input);
        self.port.write_all(frame).map_err(|e| io_error(&e))?;
        let mut answer = vec![0u8; 3];
        self.read_exact(&mut answer, Instant::now() + ANSWER_TIMEOUT, out)?;
        let len = robotiq::answer_len(&answer).map_err(|e| {
            LinkError::new(
                LinkErrorKind::Bad,
                format!("the gripper sent a frame that is not an answer: {}", robotiq::describe(e)),
            )
        })?;
        if len < 3 {
            return Err(LinkError::new(LinkErrorKind::Bad, "the gripper sent a short frame"));
        }
        answer.resize(len, 0);
        self.read_exact(&mut answer[3..], Instant::now() + ANSWER_TIMEOUT, out)?;
        Ok(answer)
    }

    fn read_exact(&mut self, buf: &mut [u8], deadline: Instant, out: &mut Out) -> Result<(), LinkError> {
        use std::io::ErrorKind as K;
        let mut got = 0;
        while got < buf.len() {
            out.beat();
            if Instant::now() > deadline {
                return Err(io_error(&std::io::Error::from(K::TimedOut)));
            }
            match self.port.read(&mut buf[got..]) {
                // A pty whose other end closed reads 0 bytes: the device is gone.
                Ok(0) => {
                    return Err(LinkError::new(
                        LinkErrorKind::Gone,
                        "serial port closed (end of file): the device vanished",
                    ))
                }
                Ok(n) => got += n,
                Err(e) if matches!(e.kind(), K::TimedOut | K::WouldBlock | K::Interrupted) => {}
                Err(e) => return Err(io_error(&e)),
            }
        }
        Ok(())
    }

    fn write(&mut self, c: &Command, out: &mut Out) -> Result<(), LinkError> {
        let (req, frame) = self.frames.write(c);
        let answer = self.exchange(&frame, out)?;
        robotiq::parse_write(&req, &answer).map_err(bad)
    }

    fn status(&mut self, out: &mut Out) -> Result<Status, LinkError> {
        let (req, frame) = self.frames.read_status(3);
        let answer = self.exchange(&frame, out)?;
        robotiq::parse_status(&req, &answer).map_err(bad)
    }
}

fn bad(e: rmodbus::ErrorKind) -> LinkError {
    let kind = if e == rmodbus::ErrorKind::FrameCRCError { LinkErrorKind::Crc } else { LinkErrorKind::Bad };
    LinkError::new(kind, robotiq::describe(e))
}

/// One exchange, tried again at once after a bad answer or none, up to [`MAX_FAILURES`] times
/// in a row (each counted in `stats`); a port that is gone fails at once.
fn retried<T>(
    l: &mut Link,
    out: &mut Out,
    stats: &mut Stats,
    mut f: impl FnMut(&mut Link, &mut Out) -> Result<T, LinkError>,
) -> Result<T, LinkError> {
    let mut tries = 0;
    loop {
        match f(l, out) {
            Ok(v) => return Ok(v),
            Err(e) => {
                tries += 1;
                match e.kind {
                    LinkErrorKind::Crc => stats.crc_errors += 1,
                    LinkErrorKind::Timeout => stats.timeouts += 1,
                    LinkErrorKind::Bad => stats.bad_answers += 1,
                    LinkErrorKind::Gone => return Err(e),
                }
                if tries >= MAX_FAILURES {
                    return Err(LinkError::new(e.kind, format!("{} ({tries} times in a row)", e.text)));
                }
            }
        }
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
    /// Answers that were not answers to the request (another slave, an exception, too short).
    pub bad_answers: u64,
    pub link_losses: u64,
    /// Resets (after an operator's clear) and activations of a gripper found reset.
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
            "timeouts": self.timeouts, "bad_answers": self.bad_answers, "link_losses": self.link_losses,
            "reactivations": self.reactivations,
            "poll_us": quantiles(self.poll_us.iter().map(|&u| u64::from(u)).collect()),
            "move_to_target_us": moves(3),
            "move_to_object_us": moves(2),
        })
    }

    /// The line faults and losses leave in the counters: what [`StatsFile`] watches.
    fn errors(&self) -> [u64; 5] {
        [self.crc_errors, self.timeouts, self.bad_answers, self.link_losses, self.reactivations]
    }

    /// Writes the figures as JSON to a temporary name, then renames it into place.
    pub fn write(&self, path: &Path) -> anyhow::Result<()> {
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, serde_json::to_string_pretty(&self.to_json())?)
            .with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
    }
}

/// `--stats-out`: written at the end, and while running within a second of an error counter
/// changing, so that a bad line shows there before the process ends.
struct StatsFile<'a> {
    path: Option<&'a Path>,
    written: [u64; 5],
    at: Instant,
}

impl StatsFile<'_> {
    fn update(&mut self, stats: &Stats) {
        let Some(path) = self.path else { return };
        if stats.errors() != self.written && self.at.elapsed() >= Duration::from_secs(1) {
            if let Err(e) = stats.write(path) {
                eprintln!("r2g-robotiq: {e:#}");
            }
            (self.written, self.at) = (stats.errors(), Instant::now());
        }
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
    /// The finger target; None until the runtime sends one (it sends none, a NaN, until it has
    /// taken this gripper's first reading as its target).
    finger_m: Option<f64>,
    /// The operator's fault resets counted so far (`JointCommand::clear_seq`); None before the
    /// first command.
    clear_seq: Option<u64>,
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
            self.clear_seq = Some(self.clear_seq.unwrap_or(0).max(c.clear_seq));
        }
    }
}

/// How an activation ended.
enum Activation {
    Ready,
    /// A stop was requested or the runtime is gone: the caller ends.
    Interrupted,
    /// The gripper did not become ready: why.
    Failed(String),
}

/// Runs the driver until SIGINT/SIGTERM or the runtime stopping; `stats_out` receives the
/// figures (see [`StatsFile`]).
pub fn run(instance: &str, cfg: &Robotiq, poll: Duration, stats_out: Option<&Path>) -> anyhow::Result<Stats> {
    let control = PeerWatch::spawn(process::control_node(instance), Duration::from_secs(30));
    ipc_schema::cleanup_dead_nodes();
    let ports = Ports::open(instance)?;
    let path = cfg.port.display().to_string();
    let scale = Scale { closed: cfg.closed_count };
    let mut stats = Stats::default();
    let mut file = StatsFile { path: stats_out, written: [0; 5], at: Instant::now() };
    let mut wanted = Wanted::default();
    let mut out = Out::new(&ports.state);
    let mut link: Option<Link> = None;
    // Reset the gripper before activating it (ends a major fault; drops what it holds).
    let mut reset = false;
    // The operator's count of resets when the current major fault was first seen: only a larger
    // one (a clear made after the fault began) resets the gripper. It outlives reconnects.
    let mut fault_clear_seq: Option<u64> = None;
    let lost = |out: &mut Out, stats: &mut Stats, e: &LinkError| {
        let text = e.on(&path);
        out.say(&text);
        out.publish(GRIPPER_LINK_LOST, false, &text);
        stats.link_losses += 1;
    };
    'session: loop {
        if process::stop_requested() {
            return Ok(stats);
        }
        anyhow::ensure!(!control.lost(), "r2g-control of instance '{instance}' stopped; r2g-robotiq stops too");
        file.update(&stats);
        wanted.update(&ports);
        out.state.finger_max_m = wanted.finger_max_m.unwrap_or(0.0);
        // Connect and activate.
        let Some(l) = link.as_mut() else {
            match Link::open(&path, cfg.baud, cfg.slave) {
                Ok(l) => link = Some(l),
                Err(e) => {
                    let text = e.on(&path);
                    out.say(&text);
                    out.publish(GRIPPER_LINK_LOST, false, &text);
                    out.sleep(REOPEN_EVERY);
                }
            }
            continue;
        };
        match activate(l, std::mem::take(&mut reset), &mut out, &mut stats, &control) {
            Ok(Activation::Ready) => {}
            Ok(Activation::Interrupted) => continue,
            Ok(Activation::Failed(why)) => {
                out.say(&why);
                out.publish(GRIPPER_NOT_READY, true, &why);
                out.sleep(REOPEN_EVERY);
                continue;
            }
            Err(e) => {
                lost(&mut out, &mut stats, &e);
                link = None;
                out.sleep(REOPEN_EVERY);
                continue;
            }
        }
        let mut sent: Option<u8> = None;
        let mut move_started: Option<(u8, Instant)> = None;
        let mut next = Instant::now();
        loop {
            if process::stop_requested() {
                return Ok(stats);
            }
            anyhow::ensure!(!control.lost(), "r2g-control of instance '{instance}' stopped; r2g-robotiq stops too");
            file.update(&stats);
            out.sleep(next.saturating_duration_since(Instant::now()));
            next += poll;
            if next < Instant::now() {
                next = Instant::now() + poll;
            }
            wanted.update(&ports);
            out.state.finger_max_m = wanted.finger_max_m.unwrap_or(0.0);
            let t = Instant::now();
            let status = match retried(l, &mut out, &mut stats, |l, o| l.status(o)) {
                Ok(s) => s,
                Err(e) => {
                    lost(&mut out, &mut stats, &e);
                    link = None;
                    continue 'session;
                }
            };
            let us = t.elapsed().as_micros().min(u128::from(u32::MAX)) as u32;
            stats.polls += 1;
            if stats.poll_us.len() < 1_000_000 {
                stats.poll_us.push(us);
            }
            out.state.poll_us = us;
            out.state.current_ma = f64::from(status.current_ma);
            out.state.grasp = status.grasp();
            out.state.finger_m = scale.fraction_open(status.position) * out.state.finger_max_m;
            if !status.activated {
                // Reset under our feet (a power cut): it holds nothing any more; activate it.
                let text = "the gripper was reset (not activated): reactivating";
                out.say(text);
                out.publish(GRIPPER_NOT_READY, true, text);
                stats.reactivations += 1;
                continue 'session;
            }
            match status.fault_class() {
                FaultClass::Major => {
                    let text = status.fault_text();
                    out.say(&text);
                    out.publish(u32::from(status.fault_code()), false, &text);
                    // It needs a reset, which drops what it holds: only after the operator's
                    // clear (`r2g clear`) made since the fault began.
                    if fault_clear_seq.is_none() {
                        fault_clear_seq = wanted.clear_seq;
                    }
                    if let (Some(at), Some(now)) = (fault_clear_seq, wanted.clear_seq) {
                        if now > at {
                            fault_clear_seq = None;
                            stats.reactivations += 1;
                            reset = true;
                            continue 'session;
                        }
                    }
                    continue;
                }
                FaultClass::Minor => {
                    // Ends by itself (cooled down, requests arriving again): hold meanwhile.
                    fault_clear_seq = None;
                    let text = status.fault_text();
                    out.say(&text);
                    out.publish(u32::from(status.fault_code()), true, &text);
                    continue;
                }
                FaultClass::None => fault_clear_seq = None,
            }
            let Some(max) = wanted.finger_max_m else {
                // Its readings mean nothing to the runtime without its finger range.
                out.publish(GRIPPER_NOT_READY, true, "waiting for the runtime's robot model (its finger range)");
                continue;
            };
            out.say(&format!("Robotiq 2F-85 on {path} (slave {}) is active", cfg.slave));
            out.publish(0, false, "");
            if let Some((pos, t0)) = move_started {
                if status.requested == pos && status.object != 0 {
                    stats.moves.push((pos, t0.elapsed().as_micros() as u64, status.object));
                    move_started = None;
                }
            }
            // The target: the runtime's command, as a fraction of its robot model's range.
            let Some(f) = wanted.finger_m else { continue };
            let pos = scale.position(f / max);
            if sent.is_none_or(|s| s.abs_diff(pos) > 1) {
                let c = Command { activate: true, go: true, position: pos, speed: cfg.speed, force: cfg.force };
                match retried(l, &mut out, &mut stats, |l, o| l.write(&c, o)) {
                    Ok(()) => {
                        stats.writes += 1;
                        sent = Some(pos);
                        move_started = Some((pos, Instant::now()));
                    }
                    Err(e) => {
                        lost(&mut out, &mut stats, &e);
                        link = None;
                        continue 'session;
                    }
                }
            }
        }
    }
}

/// Activates the gripper (rACT 0 then 1) when it is not active, or when `reset`, and waits for
/// it to report ready, publishing "activating" meanwhile. A gripper that is active is left as it
/// is (a reconnect must not reset a gripper holding an object: the reset releases its grip),
/// even with a major fault: that waits for the operator's clear in the poll loop.
fn activate(
    l: &mut Link,
    reset: bool,
    out: &mut Out,
    stats: &mut Stats,
    control: &PeerWatch,
) -> Result<Activation, LinkError> {
    let s = retried(l, out, stats, |l, o| l.status(o))?;
    if !reset && s.activated && (s.ready() || s.fault_class() == FaultClass::Major) {
        return Ok(Activation::Ready);
    }
    let text = if reset {
        "resetting and activating the gripper (its fingers open and close once; what it held drops)"
    } else {
        "activating the gripper (its fingers open and close once)"
    };
    out.say(text);
    out.publish(GRIPPER_NOT_READY, true, text);
    // An activation already under way (gACT set, not ready yet) is waited for, not restarted.
    if reset || !s.activated {
        retried(l, out, stats, |l, o| l.write(&Command::default(), o))?;
        retried(l, out, stats, |l, o| l.write(&Command { activate: true, ..Command::default() }, o))?;
    }
    let t0 = Instant::now();
    loop {
        if process::stop_requested() || control.lost() {
            return Ok(Activation::Interrupted);
        }
        let s = retried(l, out, stats, |l, o| l.status(o))?;
        stats.polls += 1;
        if s.ready() {
            return Ok(Activation::Ready);
        }
        if s.fault_class() == FaultClass::Major {
            return Ok(Activation::Failed(format!("activation failed: {}", s.fault_text())));
        }
        if t0.elapsed() > ACTIVATION_TIMEOUT {
            return Ok(Activation::Failed(format!(
                "the gripper did not finish its activation within {} s",
                ACTIVATION_TIMEOUT.as_secs()
            )));
        }
        out.publish(GRIPPER_NOT_READY, true, text);
        out.sleep(Duration::from_millis(20));
    }
}
