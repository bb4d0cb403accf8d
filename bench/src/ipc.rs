//! `r2g bench ipc`: one-way publish→receive latency between two processes, for the payloads
//! the runtime moves, through iceoryx2 (zero-copy) and through the copying alternatives a lab
//! would otherwise use: a Unix domain socket, TCP on loopback, and ZeroMQ PUSH/PULL over its
//! `ipc://` transport (deoxys' choice; libzmq itself, built from source).
//!
//! Method: the sender stamps CLOCK_MONOTONIC into the message just before handing it over; the
//! receiver, in another process on the other core, busy-polls and records `now − stamp` once
//! the whole message is in hand. For iceoryx2 the payload already lives in shared memory (as a
//! rendered frame does) and only ownership moves; the sockets must copy every byte through the
//! kernel. Both ends are pinned, one per core.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::os::unix::net::{UnixListener, UnixStream};
use std::os::unix::process::CommandExt;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use iceoryx2::prelude::ZeroCopySend;
use ipc_schema::{monotonic_ns, CameraFrame, JointCommand, Qos, RobotState};
use runtime::Histogram;
use serde_json::{json, Value};

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Transport {
    Iceoryx2,
    Uds,
    Tcp,
    Zmq,
}

impl Transport {
    pub const ALL: [Transport; 4] = [Transport::Iceoryx2, Transport::Uds, Transport::Tcp, Transport::Zmq];
    pub fn name(self) -> &'static str {
        match self {
            Self::Iceoryx2 => "iceoryx2",
            Self::Uds => "uds",
            Self::Tcp => "tcp",
            Self::Zmq => "zmq",
        }
    }
    pub fn parse(s: &str) -> anyhow::Result<Self> {
        Self::ALL.into_iter().find(|t| t.name() == s).with_context(|| format!("unknown transport '{s}'"))
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Payload {
    /// A robot state sample (~200 B).
    State,
    /// A joint command (what the runtime sends the simulator or arm every tick).
    Command,
    /// A 640×480 RGB frame.
    Frame,
    /// A 640×480 RGB frame with float depth.
    Rgbd,
    /// 640×480 RGB frames sent back to back, unpaced: throughput (latency then includes queueing).
    FrameBurst,
}

impl Payload {
    pub const ALL: [Payload; 5] =
        [Payload::State, Payload::Command, Payload::Frame, Payload::Rgbd, Payload::FrameBurst];
    pub fn name(self) -> &'static str {
        match self {
            Self::State => "state",
            Self::Command => "command",
            Self::Frame => "frame",
            Self::Rgbd => "rgbd",
            Self::FrameBurst => "frame_burst",
        }
    }
    pub fn parse(s: &str) -> anyhow::Result<Self> {
        Self::ALL.into_iter().find(|p| p.name() == s).with_context(|| format!("unknown payload '{s}'"))
    }
    /// Bytes a copying transport must move.
    pub fn bytes(self) -> usize {
        let px = ipc_schema::MAX_IMAGE_WIDTH * ipc_schema::MAX_IMAGE_HEIGHT;
        match self {
            Self::State => core::mem::size_of::<RobotState>(),
            Self::Command => core::mem::size_of::<JointCommand>(),
            Self::Frame | Self::FrameBurst => 128 + px * 3,
            Self::Rgbd => 128 + px * 3 + px * 4,
        }
    }
    fn count_and_gap(self) -> (usize, Duration) {
        match self {
            Self::State | Self::Command => (20_000, Duration::from_micros(200)),
            Self::Frame => (2_000, Duration::from_millis(2)),
            Self::Rgbd => (1_000, Duration::from_millis(4)),
            Self::FrameBurst => (2_000, Duration::ZERO),
        }
    }
}

/// Pins the calling thread to one CPU. Set directly: a child inherits its parent's mask, so
/// asking which CPUs are "available" would only offer the parent's.
fn pin(cpu: usize) {
    // SAFETY: a zeroed cpu_set_t with one bit set is a valid mask for sched_setaffinity.
    unsafe {
        let mut set: libc::cpu_set_t = core::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        libc::sched_setaffinity(0, core::mem::size_of::<libc::cpu_set_t>(), &set);
    }
}

/// CPUs for the sender and the receiver: two different ones when the machine has them.
/// Decided once, before anything is pinned (the count reads this process's own mask).
fn cpus() -> (usize, usize) {
    static CPUS: std::sync::OnceLock<(usize, usize)> = std::sync::OnceLock::new();
    *CPUS.get_or_init(|| {
        let n = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        if n > 1 {
            (0, 1)
        } else {
            (0, 0)
        }
    })
}

struct Recorder {
    lat: Histogram,
    got: usize,
    first_ns: u64,
    last_ns: u64,
}

impl Recorder {
    fn record(&mut self, stamp_ns: u64) {
        let now = monotonic_ns();
        self.lat.record(now.saturating_sub(stamp_ns));
        if self.got == 0 {
            self.first_ns = now;
        }
        self.last_ns = now;
        self.got += 1;
    }
}

/// A small fixed-size payload the benchmark can stamp with a send time.
trait Stamped: core::fmt::Debug + ZeroCopySend + Default + 'static {
    fn stamped(seq: u64, now_ns: u64) -> Self;
    fn stamp(&self) -> u64;
}

impl Stamped for RobotState {
    fn stamped(seq: u64, now_ns: u64) -> Self {
        Self { seq, published_ns: now_ns, ..Default::default() }
    }
    fn stamp(&self) -> u64 {
        self.published_ns
    }
}

impl Stamped for JointCommand {
    /// The command has no time field: the benchmark stamps it into `state_seq`.
    fn stamped(seq: u64, now_ns: u64) -> Self {
        Self { seq, state_seq: now_ns, ..Default::default() }
    }
    fn stamp(&self) -> u64 {
        self.state_seq
    }
}

type IpcNode = iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>;

fn receive_small<T: Stamped>(
    node: &IpcNode,
    addr: &str,
    qos: Qos,
    count: usize,
    deadline: Instant,
    rec: &mut Recorder,
) -> anyhow::Result<()> {
    let sub = ipc_schema::open_or_create_pubsub::<T>(node, addr, qos)?.subscriber_builder().create()?;
    println!("READY {addr}");
    std::io::stdout().flush()?;
    let mut last_seen = Instant::now();
    while rec.got < count && Instant::now() < deadline && !(rec.got > 0 && last_seen.elapsed() > QUIET) {
        if let Some(s) = sub.receive()? {
            rec.record(s.stamp());
            last_seen = Instant::now();
        }
    }
    Ok(())
}

fn send_small<T: Stamped>(
    node: &IpcNode,
    target: &str,
    qos: Qos,
    count: usize,
    pace: &dyn Fn(usize, Instant),
) -> anyhow::Result<()> {
    let publisher = ipc_schema::open_or_create_pubsub::<T>(node, target, qos)?.publisher_builder().create()?;
    // Give the peer's subscriber a moment to be seen by the publisher.
    std::thread::sleep(Duration::from_millis(50));
    let start = Instant::now();
    for i in 0..count {
        pace(i, start);
        publisher.loan_uninit()?.write_payload(T::stamped(i as u64, monotonic_ns())).send()?;
    }
    Ok(())
}

/// A receiver stops once the sender has been silent this long (drops must not stall a run).
const QUIET: Duration = Duration::from_secs(2);

/// The receiving side, run as `r2g bench ipc-peer` in its own process. Prints `READY <addr>`,
/// then, after the sender finished, one JSON line of latency figures.
pub fn peer(transport: Transport, payload: Payload, addr: &str, cpu: usize) -> anyhow::Result<()> {
    pin(cpu);
    let (count, _) = payload.count_and_gap();
    let mut rec = Recorder { lat: Histogram::new(), got: 0, first_ns: 0, last_ns: 0 };
    let deadline = Instant::now() + Duration::from_secs(120);
    // Stop when the sender has gone quiet (a dropped message must not stall the run).
    let mut last_seen = Instant::now();
    let quiet = |got: usize, last_seen: Instant| got > 0 && last_seen.elapsed() > QUIET;
    match transport {
        Transport::Iceoryx2 => {
            let node = ipc_schema::node(&format!("bench-ipc-peer-{}", std::process::id()))?;
            let qos = Qos { history: 0, buffer: 4, max_publishers: 1, max_subscribers: 2, borrowed: 2 };
            if payload == Payload::Command {
                receive_small::<JointCommand>(&node, addr, qos, count, deadline, &mut rec)?;
            } else if payload == Payload::State {
                receive_small::<RobotState>(&node, addr, qos, count, deadline, &mut rec)?;
            } else {
                let sub = ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, addr, qos)?
                    .subscriber_builder()
                    .create()?;
                println!("READY {addr}");
                std::io::stdout().flush()?;
                while rec.got < count && Instant::now() < deadline && !quiet(rec.got, last_seen) {
                    if let Some(s) = sub.receive()? {
                        // Read in place: a header field, no copy of the pixels.
                        rec.record(s.rendered_ns);
                        last_seen = Instant::now();
                    }
                }
            }
        }
        Transport::Zmq => {
            let ctx = zmq::Context::new();
            let sock = ctx.socket(zmq::PULL)?;
            sock.bind(addr).with_context(|| format!("binding {addr}"))?;
            println!("READY {addr}");
            std::io::stdout().flush()?;
            let mut msg = zmq::Message::new();
            while rec.got < count && Instant::now() < deadline && !quiet(rec.got, last_seen) {
                // Busy-poll, as the other receivers do.
                match sock.recv(&mut msg, zmq::DONTWAIT) {
                    Ok(()) => {
                        if msg.len() != payload.bytes() {
                            bail!("zmq message of {} bytes, expected {}", msg.len(), payload.bytes());
                        }
                        rec.record(u64::from_ne_bytes(msg[..8].try_into().unwrap_or([0; 8])));
                        last_seen = Instant::now();
                    }
                    Err(zmq::Error::EAGAIN) => std::hint::spin_loop(),
                    Err(e) => return Err(e.into()),
                }
            }
        }
        Transport::Uds | Transport::Tcp => {
            let mut stream: Box<dyn Read> = if transport == Transport::Uds {
                let listener = UnixListener::bind(addr).with_context(|| format!("binding {addr}"))?;
                println!("READY {addr}");
                std::io::stdout().flush()?;
                let (s, _) = listener.accept()?;
                s.set_nonblocking(true)?;
                Box::new(s)
            } else {
                let listener = TcpListener::bind("127.0.0.1:0")?;
                println!("READY {}", listener.local_addr()?);
                std::io::stdout().flush()?;
                let (s, _) = listener.accept()?;
                s.set_nodelay(true)?;
                s.set_nonblocking(true)?;
                Box::new(s)
            };
            let mut buf = vec![0u8; payload.bytes()];
            while rec.got < count && Instant::now() < deadline {
                // Busy-poll until one whole message is in.
                let mut filled = 0;
                while filled < buf.len() {
                    match stream.read(&mut buf[filled..]) {
                        Ok(0) => bail!("sender closed the connection after {} messages", rec.got),
                        Ok(n) => filled += n,
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => std::hint::spin_loop(),
                        Err(e) => return Err(e.into()),
                    }
                }
                let stamp = u64::from_ne_bytes(buf[..8].try_into().unwrap_or([0; 8]));
                rec.record(stamp);
            }
        }
    }
    let span_s = (rec.last_ns.saturating_sub(rec.first_ns)) as f64 * 1e-9;
    let mut out = rec.lat.summary();
    out["received"] = json!(rec.got);
    out["msgs_per_s"] = json!(if span_s > 0.0 { (rec.got.saturating_sub(1)) as f64 / span_s } else { 0.0 });
    println!("{out}");
    Ok(())
}

/// One sender run against a fresh peer process; returns the peer's figures.
fn run_pair(transport: Transport, payload: Payload) -> anyhow::Result<Value> {
    let exe = std::env::current_exe()?;
    let addr = match transport {
        Transport::Iceoryx2 => format!("r2g/benchipc{}/{}", std::process::id(), payload.name()),
        Transport::Uds => std::env::temp_dir()
            .join(format!("r2g-bench-{}-{}.sock", std::process::id(), payload.name()))
            .display()
            .to_string(),
        Transport::Tcp => "127.0.0.1:0".into(),
        Transport::Zmq => format!(
            "ipc://{}",
            std::env::temp_dir().join(format!("r2g-bench-{}-{}.zmq", std::process::id(), payload.name())).display()
        ),
    };
    let _ = std::fs::remove_file(&addr);
    let _ = std::fs::remove_file(addr.trim_start_matches("ipc://"));
    let mut cmd = Command::new(exe);
    // SAFETY: prctl is async-signal-safe; the peer must not outlive this process.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    let mut child = cmd
        .args(["bench", "ipc-peer", "--transport", transport.name(), "--payload", payload.name(), "--addr", &addr])
        .args(["--cpu", &cpus().1.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .spawn()
        .context("starting the receiving peer")?;
    let stdout = child.stdout.take().context("peer stdout")?;
    let mut lines = BufReader::new(stdout).lines();
    let ready = lines.next().context("peer ended before READY")??;
    let target = ready.strip_prefix("READY ").context("peer did not say READY")?.to_string();
    let result = send(transport, payload, &target);
    let figures = match result {
        Ok(()) => lines.next().context("peer printed no figures")??,
        Err(e) => {
            // SAFETY: signals the peer this function started, by pid.
            unsafe {
                libc::kill(child.id() as i32, libc::SIGKILL);
            }
            let _ = child.wait();
            return Err(e);
        }
    };
    let _ = child.wait();
    let _ = std::fs::remove_file(addr.trim_start_matches("ipc://"));
    Ok(serde_json::from_str(&figures)?)
}

fn send(transport: Transport, payload: Payload, target: &str) -> anyhow::Result<()> {
    pin(cpus().0);
    let (count, gap) = payload.count_and_gap();
    let pace = |i: usize, start: Instant| {
        let due = start + gap * (i as u32 + 1);
        while Instant::now() < due {
            std::hint::spin_loop();
        }
    };
    match transport {
        Transport::Iceoryx2 => {
            let node = ipc_schema::node(&format!("bench-ipc-send-{}", std::process::id()))?;
            let qos = Qos { history: 0, buffer: 4, max_publishers: 1, max_subscribers: 2, borrowed: 2 };
            // Give the peer's subscriber a moment to be seen by the publisher.
            if payload == Payload::Command {
                send_small::<JointCommand>(&node, target, qos, count, &pace)?;
            } else if payload == Payload::State {
                send_small::<RobotState>(&node, target, qos, count, &pace)?;
            } else {
                let publisher = ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, target, qos)?
                    .publisher_builder()
                    .max_loaned_samples(1)
                    .create()?;
                std::thread::sleep(Duration::from_millis(50));
                let start = Instant::now();
                for i in 0..count {
                    pace(i, start);
                    let mut s = publisher.loan_uninit()?;
                    let p = s.payload_mut().as_mut_ptr();
                    // SAFETY: the sample is ours; pixels are left as the renderer would have
                    // written them in place (shared memory is initialised), only the header
                    // fields the reader uses are set, then ownership moves.
                    let s = unsafe {
                        (*p).seq = i as u64;
                        (*p).rendered_ns = monotonic_ns();
                        s.assume_init()
                    };
                    s.send()?;
                }
            }
        }
        Transport::Zmq => {
            let ctx = zmq::Context::new();
            let sock = ctx.socket(zmq::PUSH)?;
            sock.connect(target)?;
            std::thread::sleep(Duration::from_millis(50));
            let mut buf = vec![7u8; payload.bytes()];
            let start = Instant::now();
            for i in 0..count {
                pace(i, start);
                buf[..8].copy_from_slice(&monotonic_ns().to_ne_bytes());
                sock.send(&buf[..], 0)?;
            }
            // Let the queue drain before the context closes.
            std::thread::sleep(Duration::from_millis(200));
        }
        Transport::Uds | Transport::Tcp => {
            let mut stream: Box<dyn Write> = if transport == Transport::Uds {
                Box::new(UnixStream::connect(target)?)
            } else {
                let s = TcpStream::connect(target)?;
                s.set_nodelay(true)?;
                Box::new(s)
            };
            let mut buf = vec![7u8; payload.bytes()];
            let start = Instant::now();
            for i in 0..count {
                pace(i, start);
                buf[..8].copy_from_slice(&monotonic_ns().to_ne_bytes());
                stream.write_all(&buf)?;
            }
            stream.flush()?;
        }
    }
    Ok(())
}

/// Runs every transport × payload pair, or only those whose `transport:payload` name contains
/// `only`.
pub fn run(only: Option<&str>) -> anyhow::Result<Value> {
    let _ = cpus();
    let mut figures = serde_json::Map::new();
    let mut cdfs = serde_json::Map::new();
    let mut rows = Vec::new();
    for transport in Transport::ALL {
        let mut t = serde_json::Map::new();
        for payload in Payload::ALL {
            if only.is_some_and(|o| !format!("{}:{}", transport.name(), payload.name()).contains(o)) {
                continue;
            }
            eprintln!("bench ipc: {} {} ...", transport.name(), payload.name());
            let f = run_pair(transport, payload).with_context(|| format!("{} {}", transport.name(), payload.name()))?;
            let get = |k: &str| f[k].as_f64().unwrap_or(f64::NAN);
            for k in ["p50_us", "p99_us", "p999_us", "max_us"] {
                t.insert(format!("{}_{k}", payload.name()), json!(get(k)));
            }
            t.insert(format!("{}_msgs_per_s", payload.name()), json!(get("msgs_per_s")));
            t.insert(format!("{}_received", payload.name()), f["received"].clone());
            cdfs.insert(format!("{}.{}", transport.name(), payload.name()), f["cdf"].clone());
            rows.push(vec![
                transport.name().to_string(),
                payload.name().to_string(),
                format!("{}", payload.bytes()),
                format!("{}", f["received"]),
                format!("{:.2}", get("p50_us")),
                format!("{:.2}", get("p99_us")),
                format!("{:.2}", get("p999_us")),
                format!("{:.1}", get("max_us")),
            ]);
        }
        if !t.is_empty() {
            figures.insert(transport.name().into(), Value::Object(t));
        }
    }
    crate::print_table(&["transport", "payload", "bytes", "received", "p50 µs", "p99", "p99.9", "max"], &rows);
    let f = |t: &str, k: &str| figures.get(t).and_then(|v| v[k].as_f64()).unwrap_or(f64::NAN);
    let mut out = json!({ "bench": "ipc" });
    for (k, v) in &figures {
        out[k] = v.clone();
    }
    out["uds_over_iceoryx2_frame_p50"] = json!(f("uds", "frame_p50_us") / f("iceoryx2", "frame_p50_us"));
    out["uds_over_iceoryx2_rgbd_p50"] = json!(f("uds", "rgbd_p50_us") / f("iceoryx2", "rgbd_p50_us"));
    out["zmq_over_iceoryx2_frame_p50"] = json!(f("zmq", "frame_p50_us") / f("iceoryx2", "frame_p50_us"));
    println!("{out}");
    // The distributions (for plots) go to the caller, not onto the summary line.
    out["cdf"] = Value::Object(cdfs);
    Ok(out)
}
