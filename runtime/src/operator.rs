//! The operator channel of a running instance: a Unix stream socket at
//! `<run dir>/operator.sock` (see [`ipc_schema::process::run_dir`]) served by a thread of
//! r2g-control beside the tick loop. Anyone who can connect may ask for `status` (tick health);
//! `clear` (the fault reset) is taken only from a peer the kernel vouches for (`SO_PEERCRED`,
//! `SO_PEERGROUPS`): root, the runtime's own user, or a member of the operator group. Every
//! refused attempt is logged with the peer's uid and pid. Deliberately not part of `robo`, and
//! the agent channel refuses fault resets: generated code can never clear a fault.

use std::io::{BufRead, BufReader, Write};
use std::os::fd::AsRawFd;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::PathBuf;
use std::sync::atomic::Ordering::{Acquire, Relaxed};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use serde_json::json;

use crate::health::{Health, FAULT_OPERATOR, FAULT_ROBOT_LOST};

/// The operator socket of `instance`.
pub fn socket_path(instance: &str) -> PathBuf {
    ipc_schema::process::run_dir(instance).join("operator.sock")
}

/// Who the kernel says is on the other end of a Unix socket.
#[derive(Debug, Clone)]
pub struct Peer {
    pub pid: i32,
    pub uid: u32,
    pub gid: u32,
    /// Supplementary groups (`SO_PEERGROUPS`).
    pub groups: Vec<u32>,
}

/// Reads the peer's credentials of a connected Unix socket.
pub fn peer_of(stream: &UnixStream) -> std::io::Result<Peer> {
    let fd = stream.as_raw_fd();
    let mut cred = libc::ucred { pid: 0, uid: 0, gid: 0 };
    let mut len = std::mem::size_of::<libc::ucred>() as libc::socklen_t;
    // SAFETY: getsockopt writes at most `len` bytes into `cred`, a valid ucred.
    let r = unsafe {
        libc::getsockopt(fd, libc::SOL_SOCKET, libc::SO_PEERCRED, (&mut cred as *mut libc::ucred).cast(), &mut len)
    };
    if r != 0 {
        return Err(std::io::Error::last_os_error());
    }
    /// `SO_PEERGROUPS` (Linux 4.13); not in every libc release.
    const SO_PEERGROUPS: libc::c_int = 59;
    let mut groups = vec![0 as libc::gid_t; 256];
    let mut glen = (groups.len() * std::mem::size_of::<libc::gid_t>()) as libc::socklen_t;
    // SAFETY: getsockopt writes at most `glen` bytes into the buffer.
    let r = unsafe { libc::getsockopt(fd, libc::SOL_SOCKET, SO_PEERGROUPS, groups.as_mut_ptr().cast(), &mut glen) };
    // A peer in more groups than fit (ERANGE) is judged by its uid and primary group alone.
    let n = if r == 0 { glen as usize / std::mem::size_of::<libc::gid_t>() } else { 0 };
    groups.truncate(n);
    Ok(Peer { pid: cred.pid, uid: cred.uid, gid: cred.gid, groups })
}

/// Who may clear faults.
#[derive(Debug, Clone)]
pub struct Policy {
    /// The runtime's own user.
    pub own_uid: u32,
    /// The operator group, by name and gid.
    pub operator_group: Option<(String, u32)>,
}

impl Policy {
    /// The policy for this process; `operator_group` must name an existing group.
    pub fn new(operator_group: Option<&str>) -> anyhow::Result<Self> {
        let group = match operator_group {
            None => None,
            Some(name) => Some((name.to_string(), gid_of(name)?)),
        };
        // SAFETY: geteuid cannot fail.
        Ok(Self { own_uid: unsafe { libc::geteuid() }, operator_group: group })
    }

    /// None when `peer` may clear faults, else why not.
    pub fn refuses(&self, peer: &Peer) -> Option<String> {
        if peer.uid == 0 || peer.uid == self.own_uid {
            return None;
        }
        if let Some((_, gid)) = &self.operator_group {
            if peer.gid == *gid || peer.groups.contains(gid) {
                return None;
            }
        }
        Some(format!(
            "uid {} is not root, not the runtime's user (uid {}){}",
            peer.uid,
            self.own_uid,
            match &self.operator_group {
                Some((name, gid)) => format!(" and not in the operator group {name} (gid {gid})"),
                None => " and no operator group is configured (r2g-control --operator-group)".into(),
            }
        ))
    }
}

/// The gid of a group name (getgrnam_r).
pub fn gid_of(name: &str) -> anyhow::Result<u32> {
    let c = std::ffi::CString::new(name).context("group name holds a NUL byte")?;
    let mut grp: libc::group = unsafe { std::mem::zeroed() };
    let mut buf = vec![0 as libc::c_char; 16384];
    let mut out: *mut libc::group = std::ptr::null_mut();
    // SAFETY: every pointer is valid for the call; buf outlives it.
    let r = unsafe { libc::getgrnam_r(c.as_ptr(), &mut grp, buf.as_mut_ptr(), buf.len(), &mut out) };
    if r != 0 || out.is_null() {
        bail!("no group named '{name}' on this machine (create it, e.g. with deploy/sysusers.d)");
    }
    Ok(grp.gr_gid)
}

/// The running operator socket; dropping it stops the thread and removes the socket file.
pub struct Server {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let _ = std::fs::remove_file(&self.path);
        if let Some(dir) = self.path.parent() {
            let _ = std::fs::remove_dir(dir); // only if empty
        }
    }
}

/// Binds the instance's operator socket and serves it from a thread (normal scheduler: start it
/// before the loop thread raises itself to SCHED_FIFO).
pub fn serve(instance: &str, health: Arc<Health>, policy: Policy) -> anyhow::Result<Server> {
    let path = socket_path(instance);
    let dir = path.parent().context("socket path has no folder")?;
    // A folder someone else made could hold a socket that answers in our name.
    if let Some(base) = dir.parent().filter(|b| b.exists()) {
        use std::os::unix::fs::MetadataExt;
        // SAFETY: geteuid cannot fail.
        let (meta, me) = (std::fs::metadata(base)?, unsafe { libc::geteuid() });
        if meta.uid() != me && meta.uid() != 0 {
            bail!(
                "{} belongs to uid {}, not to this user (uid {me}) or root: refusing to serve there",
                base.display(),
                meta.uid()
            );
        }
    }
    if !dir.is_dir() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        // Reachable by other users (they are then told no, and logged), listable by none.
        std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o711))
            .with_context(|| format!("setting the mode of {}", dir.display()))?;
    }
    if path.exists() {
        if UnixStream::connect(&path).is_ok() {
            bail!("another runtime of instance '{instance}' serves {} already", path.display());
        }
        std::fs::remove_file(&path).with_context(|| format!("removing the stale socket {}", path.display()))?;
    }
    let listener = UnixListener::bind(&path).with_context(|| format!("binding {}", path.display()))?;
    // Connecting is open to every local user: the credentials decide, and refusals are logged.
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o666))
        .with_context(|| format!("setting the mode of {}", path.display()))?;
    listener.set_nonblocking(true)?;
    let stop = Arc::new(AtomicBool::new(false));
    let (st, inst) = (stop.clone(), instance.to_string());
    let thread = std::thread::Builder::new()
        .name("operator".into())
        .spawn(move || {
            let busy = Arc::new(std::sync::atomic::AtomicUsize::new(0));
            while !st.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((stream, _)) => {
                        // One short-lived thread per connection, a few at most, so a client
                        // that connects and says nothing cannot keep the operator out.
                        if busy.load(Ordering::Relaxed) >= MAX_CONNECTIONS {
                            let _ = (&stream).write_all(b"{\"ok\":false,\"error\":\"busy: try again\"}\n");
                            continue;
                        }
                        busy.fetch_add(1, Ordering::Relaxed);
                        let (b, i, h, p) = (busy.clone(), inst.clone(), health.clone(), policy.clone());
                        let spawned = std::thread::Builder::new().name("operator-conn".into()).spawn(move || {
                            if let Err(e) = handle(stream, &i, &h, &p) {
                                eprintln!("r2g-control: operator socket: {e:#}");
                            }
                            b.fetch_sub(1, Ordering::Relaxed);
                        });
                        if spawned.is_err() {
                            busy.fetch_sub(1, Ordering::Relaxed);
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        std::thread::sleep(Duration::from_millis(20));
                    }
                    Err(e) => {
                        eprintln!("r2g-control: operator socket: accept: {e}");
                        std::thread::sleep(Duration::from_millis(200));
                    }
                }
            }
        })
        .context("starting the operator thread")?;
    Ok(Server { path, stop, thread: Some(thread) })
}

/// Longest line a client may send.
const MAX_LINE: usize = 64;
/// Connections served at once.
const MAX_CONNECTIONS: usize = 8;
/// How long a client may take to send its request.
const READ_TIMEOUT: Duration = Duration::from_millis(500);
/// How long a fault reset may wait for the loop: longer than the longest wait of the lockstep
/// loop (10 s for its simulator), so a reset that was answered "not taken" is never applied.
const CLEAR_TIMEOUT: Duration = Duration::from_secs(15);

fn handle(stream: UnixStream, instance: &str, health: &Health, policy: &Policy) -> anyhow::Result<()> {
    stream.set_nonblocking(false)?;
    stream.set_read_timeout(Some(READ_TIMEOUT))?;
    stream.set_write_timeout(Some(Duration::from_secs(2)))?;
    let peer = peer_of(&stream).context("reading the peer's credentials")?;
    let mut line = String::new();
    BufReader::new(std::io::Read::take(&stream, MAX_LINE as u64))
        .read_line(&mut line)
        .context("reading the request")?;
    let answer = match line.trim() {
        "status" => status_json(instance, health),
        "clear" => match policy.refuses(&peer) {
            Some(why) => {
                eprintln!(
                    "r2g-control: refused operator request 'clear' from uid {} pid {}: {why}",
                    peer.uid, peer.pid
                );
                json!({"ok": false, "error": format!("refused: only an operator may clear faults; {why}")})
            }
            None => {
                eprintln!("r2g-control: operator request 'clear' from uid {} pid {}", peer.uid, peer.pid);
                clear(health)
            }
        },
        other => {
            let shown: String = other.chars().take(MAX_LINE).collect();
            json!({"ok": false, "error": format!("unknown request {shown:?}: send \"status\" or \"clear\"")})
        }
    };
    (&stream).write_all(format!("{answer}\n").as_bytes()).context("answering")?;
    Ok(())
}

fn clear(health: &Health) -> serde_json::Value {
    let n = health.clear_requested.fetch_add(1, Relaxed) + 1;
    let t0 = Instant::now();
    while health.clear_done.load(Acquire) < n {
        if t0.elapsed() > CLEAR_TIMEOUT {
            return json!({"ok": false, "error": "the control loop did not take the request within 15 s: is it stalled?"});
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    if health.clear_result.load(Relaxed) == 1 {
        json!({"ok": true, "cleared": true, "reason": "fault cleared by the operator: the arm accepts commands again"})
    } else {
        json!({"ok": true, "cleared": false, "reason": "there was no fault to clear"})
    }
}

fn status_json(instance: &str, h: &Health) -> serde_json::Value {
    let fault = h.fault.load(Relaxed);
    json!({
        "ok": true,
        "instance": instance,
        "pid": std::process::id(),
        "mode": if h.mode.load(Relaxed) == ipc_schema::Mode::Lockstep as u32 { "lockstep" } else { "wall" },
        "ticks": h.ticks.load(Relaxed),
        "cycles": h.cycles.load(Relaxed),
        "overruns": h.overruns.load(Relaxed),
        "wake_max_us": h.wake_max_ns.load(Relaxed) as f64 / 1e3,
        "state_age_ms": h.state_age_ms(),
        "robot_lost": fault & FAULT_ROBOT_LOST != 0,
        "fault": if fault & FAULT_OPERATOR != 0 { "operator_required" } else { "none" },
        "agent_port_errors": h.agent_port_errors.load(Relaxed),
        "uptime_s": ipc_schema::monotonic_ns().saturating_sub(h.started_ns.load(Relaxed)) as f64 / 1e9,
        "watchdog_usec": h.watchdog_usec.load(Relaxed),
        "limit_violations": h.limit_violations.load(Relaxed),
        "realtime": {
            "fifo_priority": h.rt_fifo_priority.load(Relaxed),
            "cpu": h.rt_cpu.load(Relaxed),
            "memory_locked": h.rt_memory_locked.load(Relaxed),
            "all_granted": !h.rt_refused.load(Relaxed),
            "summary": h.realtime_line(),
        },
    })
}

/// Sends one request line to the instance's operator socket and returns the JSON answer.
fn ask(instance: &str, request: &str) -> anyhow::Result<serde_json::Value> {
    let path = socket_path(instance);
    let stream = match UnixStream::connect(&path) {
        Ok(s) => s,
        Err(e) if e.kind() == std::io::ErrorKind::PermissionDenied => {
            bail!("cannot reach the operator socket {} of instance '{instance}': {e}", path.display())
        }
        Err(e) => bail!("no r2g instance '{instance}' is running here (cannot connect to {}: {e})", path.display()),
    };
    stream.set_read_timeout(Some(CLEAR_TIMEOUT + Duration::from_secs(5)))?;
    (&stream).write_all(format!("{request}\n").as_bytes())?;
    let mut line = String::new();
    BufReader::new(&stream).read_line(&mut line).context("reading the runtime's answer")?;
    serde_json::from_str(&line).with_context(|| format!("the runtime answered something unreadable: {line:?}"))
}

/// Asks the runtime of `instance` to clear an `operator_required` fault; returns whether it did
/// and the runtime's reason. Fails when this process's user is not an operator.
pub fn clear_fault(instance: &str) -> anyhow::Result<(bool, String)> {
    let v = ask(instance, "clear")?;
    if v["ok"] != true {
        bail!("{}", v["error"].as_str().unwrap_or("the runtime refused"));
    }
    Ok((v["cleared"] == true, v["reason"].as_str().unwrap_or_default().to_string()))
}

/// The tick health of the runtime of `instance`: ticks, overruns (missed deadlines), the
/// largest wake-up latency of the last second, the age of the last robot state, faults.
pub fn status(instance: &str) -> anyhow::Result<serde_json::Value> {
    let v = ask(instance, "status")?;
    if v["ok"] != true {
        bail!("{}", v["error"].as_str().unwrap_or("the runtime refused"));
    }
    Ok(v)
}
