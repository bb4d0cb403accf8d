//! The host side of a sandboxed worker: one confined Python process per episode that runs
//! stage programs one after another, plus the trusted `robo` proxy it talks to. Every run is
//! bounded by the wall clock (the whole process group is killed), a scratch-disk quota and the
//! worker's own kernel limits; whatever happens, a run ends with an [`ExecResult`] and the host
//! carries on (a killed worker is restarted for the next program).

use std::io::{BufRead, BufReader, Read, Write};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::os::unix::net::UnixStream;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use serde::{Deserialize, Serialize};

use crate::sandbox::{Enforced, Policy};

/// How much of the machine one worker may use.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Limits {
    pub cpu_s: u64,
    pub mem_mb: u64,
    pub fsize_mb: u64,
    pub nofile: u64,
    /// Processes and threads (pids cgroup).
    pub pids: u64,
    /// Wall clock per program, s.
    pub wall_s: f64,
    /// Total size of the scratch folder, MiB.
    pub scratch_mb: u64,
    /// Files in the scratch folder.
    pub scratch_files: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            cpu_s: 120,
            mem_mb: 4096,
            fsize_mb: 64,
            nofile: 64,
            pids: 64,
            wall_s: 120.0,
            scratch_mb: 256,
            scratch_files: 2000,
        }
    }
}

/// Where things are.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    pub instance: String,
    /// The worker's working folder, the only place it may write.
    pub scratch: PathBuf,
    /// Host-only folder for the worker's raw output and the proxy's log.
    pub log_dir: PathBuf,
    /// The project's root (for `.venv`, `agent/py`, `robot-skill`).
    pub root: PathBuf,
    pub limits: Limits,
}

/// What a program run gets within its run.
#[derive(Debug, Clone, Copy)]
pub struct Budget {
    /// Waypoints the program may post in all.
    pub control_steps: u64,
    /// Refuse reset and post_actions (the observation-only first turn).
    pub observe_only: bool,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct ExecResult {
    pub stdout: String,
    pub stderr: String,
    /// "ok", "exit", "exception" or "killed".
    pub exit: String,
    pub exit_code: Option<i64>,
    pub exception: Option<String>,
    pub exc_type: Option<String>,
    /// Set when the sandbox stopped or refused something, in words the model can act on.
    pub violation: Option<String>,
    pub wall_s: f64,
    /// Waypoints posted, robot calls made and calls refused by the budget.
    pub control_steps: u64,
    pub robot_calls: u64,
    pub budget_refusals: u64,
    /// Output written straight to the worker's descriptors (bypassing sys.stdout), tail only.
    pub raw_output: String,
}

struct Live {
    worker: Child,
    pgid: i32,
    ctl: UnixStream,
    proxy: Child,
    proxy_in: ChildStdin,
    proxy_out: BufReader<ChildStdout>,
    cgroup: Option<PathBuf>,
}

pub struct Worker {
    cfg: WorkerConfig,
    live: Option<Live>,
    /// What the kernel enforced on the current worker.
    pub enforced: Option<Enforced>,
    pub starts: u32,
}

/// Moves a descriptor above the range children use, close-on-exec.
fn high(fd: RawFd) -> anyhow::Result<OwnedFd> {
    // SAFETY: F_DUPFD_CLOEXEC returns a new descriptor we then own.
    let n = unsafe { libc::fcntl(fd, libc::F_DUPFD_CLOEXEC, 100) };
    if n < 0 {
        bail!("fcntl: {}", std::io::Error::last_os_error());
    }
    // SAFETY: n is a fresh descriptor.
    Ok(unsafe { OwnedFd::from_raw_fd(n) })
}

/// Makes `from` appear as `to` in the child (dup2 clears close-on-exec on the copy).
fn pass_fds(cmd: &mut Command, fds: Vec<(OwnedFd, RawFd)>) {
    // SAFETY: dup2 is async-signal-safe; the descriptors stay open until spawn returns.
    unsafe {
        cmd.pre_exec(move || {
            for (from, to) in &fds {
                if libc::dup2(from.as_raw_fd(), *to) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
            }
            Ok(())
        });
    }
}

fn send_frame(s: &mut UnixStream, v: &serde_json::Value) -> std::io::Result<()> {
    let data = serde_json::to_vec(v).map_err(std::io::Error::other)?;
    s.write_all(&(data.len() as u32).to_be_bytes())?;
    s.write_all(&data)
}

fn recv_frame(s: &mut UnixStream) -> std::io::Result<serde_json::Value> {
    let mut head = [0u8; 4];
    s.read_exact(&mut head)?;
    let n = u32::from_be_bytes(head) as usize;
    if n > 16 << 20 {
        return Err(std::io::Error::other("oversized reply from the worker"));
    }
    let mut body = vec![0u8; n];
    s.read_exact(&mut body)?;
    serde_json::from_slice(&body).map_err(std::io::Error::other)
}

/// Size and file count of a folder tree, stopping early past the limits.
fn usage(dir: &Path, max_files: u64) -> (u64, u64) {
    let (mut bytes, mut files) = (0u64, 0u64);
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            files += 1;
            if files > max_files {
                return (bytes, files);
            }
            match e.metadata() {
                Ok(m) if m.is_dir() => todo.push(e.path()),
                Ok(m) => bytes += m.len(),
                Err(_) => {}
            }
        }
    }
    (bytes, files)
}

fn tail(path: &Path, n: usize) -> String {
    let text = std::fs::read(path).unwrap_or_default();
    let start = text.len().saturating_sub(n);
    String::from_utf8_lossy(&text[start..]).into_owned()
}

/// A pids cgroup for one worker, when this machine lets us make one (v2 or v1 layout).
fn make_cgroup(name: &str, pids: u64) -> Option<PathBuf> {
    for base in ["/sys/fs/cgroup/pids", "/sys/fs/cgroup"] {
        let b = Path::new(base);
        if !b.join("cgroup.procs").exists() {
            continue;
        }
        // Leftovers of hosts killed before their teardown: rmdir only removes empty cgroups.
        if let Ok(rd) = std::fs::read_dir(b) {
            for e in rd.flatten() {
                if e.file_name().to_string_lossy().starts_with("r2g-") {
                    let _ = std::fs::remove_dir(e.path());
                }
            }
        }
        let dir = b.join(format!("r2g-{name}"));
        if std::fs::create_dir(&dir).is_ok() || dir.is_dir() {
            if std::fs::write(dir.join("pids.max"), pids.to_string()).is_ok() {
                return Some(dir);
            }
            let _ = std::fs::remove_dir(&dir);
        }
    }
    None
}

impl Worker {
    pub fn new(cfg: WorkerConfig) -> Self {
        Self { cfg, live: None, enforced: None, starts: 0 }
    }

    fn python(&self) -> PathBuf {
        self.cfg.root.join(".venv/bin/python")
    }

    fn policy(&self, cgroup: Option<PathBuf>) -> anyhow::Result<Policy> {
        let python = self.python();
        let real = std::fs::canonicalize(&python).with_context(|| format!("{} (run `make robo`)", python.display()))?;
        // .../versions/3.11.7/bin/python3.11 -> .../versions/3.11.7
        let prefix = real.parent().and_then(Path::parent).context("interpreter prefix")?.to_path_buf();
        let root = &self.cfg.root;
        let l = &self.cfg.limits;
        let read = [
            prefix.clone(),
            root.join(".venv"),
            root.join("agent/py"),
            root.join("robot-skill/SKILL.md"),
            root.join("robot-skill/api"),
            root.join("robot-skill/config"),
            root.join("robot-skill/memory/README.md"),
            PathBuf::from("/usr/lib"),
            PathBuf::from("/usr/share/locale"),
            PathBuf::from("/etc/ld.so.cache"),
            PathBuf::from("/etc/localtime"),
            PathBuf::from("/sys/devices/system/cpu"),
            PathBuf::from("/proc/self"),
        ];
        let exec = [prefix.join("bin"), prefix.join("lib"), PathBuf::from("/lib64"), PathBuf::from("/usr/lib")];
        Ok(Policy {
            scratch: self.cfg.scratch.clone(),
            read: read.to_vec(),
            exec: exec.to_vec(),
            cpu_s: l.cpu_s,
            mem_mb: l.mem_mb,
            fsize_mb: l.fsize_mb,
            nofile: l.nofile,
            cgroup,
        })
    }

    fn start(&mut self) -> anyhow::Result<()> {
        std::fs::create_dir_all(&self.cfg.scratch)?;
        std::fs::create_dir_all(&self.cfg.log_dir)?;
        // Landlock rules and the worker's working folder must not depend on our cwd.
        self.cfg.scratch = std::fs::canonicalize(&self.cfg.scratch)?;
        self.cfg.log_dir = std::fs::canonicalize(&self.cfg.log_dir)?;
        self.cfg.root = std::fs::canonicalize(&self.cfg.root)?;
        // The skill documents, readable from the scratch folder (landlock judges the target).
        let link = self.cfg.scratch.join("robot-skill");
        if std::fs::symlink_metadata(&link).is_err() {
            std::os::unix::fs::symlink(self.cfg.root.join("robot-skill"), &link)?;
        }
        std::fs::create_dir_all(&self.cfg.log_dir)?;
        self.starts += 1;
        let (robo_host, robo_worker) = UnixStream::pair()?;
        let (ctl_host, ctl_worker) = UnixStream::pair()?;
        // The proxy: trusted, but given nothing of the host's environment either.
        let mut proxy = Command::new(self.python());
        proxy
            .args(["-I", "-B"])
            .arg(self.cfg.root.join("agent/py/robo_proxy.py"))
            .env_clear()
            .env("R2G_INSTANCE", &self.cfg.instance)
            .env("PATH", "/usr/bin:/bin")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(self.cfg.log_dir.join("proxy.log"))?);
        pass_fds(&mut proxy, vec![(high(robo_host.as_raw_fd())?, 3)]);
        // SAFETY: prctl in the child before exec; async-signal-safe.
        unsafe {
            proxy.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL, 0, 0, 0);
                Ok(())
            });
        }
        let mut proxy = proxy.spawn().context("starting the robo proxy")?;
        drop(robo_host);
        let proxy_in = proxy.stdin.take().context("proxy stdin")?;
        let mut proxy_out = BufReader::new(proxy.stdout.take().context("proxy stdout")?);
        let mut line = String::new();
        proxy_out.read_line(&mut line)?;
        if !line.contains("\"ready\"") {
            let _ = proxy.kill();
            let _ = proxy.wait();
            bail!("the robo proxy did not start: {}", tail(&self.cfg.log_dir.join("proxy.log"), 600).trim());
        }

        let name = format!("{}-{}-{}", self.cfg.instance, std::process::id(), self.starts);
        let cgroup = make_cgroup(&name, self.cfg.limits.pids);
        let policy = serde_json::to_string(&self.policy(cgroup.clone())?)?;
        let (status_r, status_w) = std::io::pipe()?;
        let sandbox = crate::sibling("r2g-sandbox")?;
        let mut cmd = Command::new(sandbox);
        cmd.arg(policy)
            .arg("5")
            .arg(self.python())
            .args(["-I", "-B"])
            .arg(self.cfg.root.join("agent/py/runner.py"))
            .env_clear()
            .env("HOME", &self.cfg.scratch)
            .env("LANG", "C.UTF-8")
            .env("PATH", "/usr/bin:/bin")
            .env("OPENBLAS_NUM_THREADS", "1")
            .env("OMP_NUM_THREADS", "1")
            .env("MALLOC_ARENA_MAX", "2")
            .current_dir(&self.cfg.scratch)
            .stdin(Stdio::null())
            .stdout(std::fs::File::create(self.cfg.log_dir.join("worker.out"))?)
            .stderr(std::fs::File::create(self.cfg.log_dir.join("worker.err"))?)
            .process_group(0);
        pass_fds(
            &mut cmd,
            vec![
                (high(ctl_worker.as_raw_fd())?, 3),
                (high(robo_worker.as_raw_fd())?, 4),
                (high(status_w.as_raw_fd())?, 5),
            ],
        );
        let worker = cmd.spawn();
        drop((ctl_worker, robo_worker, status_w));
        let worker = match worker {
            Ok(w) => w,
            Err(e) => {
                let _ = proxy.kill();
                let _ = proxy.wait();
                return Err(e).context("starting r2g-sandbox");
            }
        };
        let pgid = worker.id() as i32;
        let mut status = String::new();
        BufReader::new(status_r).read_line(&mut status)?;
        let status: serde_json::Value = serde_json::from_str(status.trim()).unwrap_or(serde_json::Value::Null);
        let mut live = Live { worker, pgid, ctl: ctl_host, proxy, proxy_in, proxy_out, cgroup };
        let enforced: Option<Enforced> = status.get("enforced").and_then(|e| serde_json::from_value(e.clone()).ok());
        let Some(enforced) = enforced else {
            Self::teardown(&mut live);
            bail!(
                "the sandbox could not be applied, nothing ran: {}",
                status.get("error").and_then(|e| e.as_str()).unwrap_or("no status from r2g-sandbox")
            );
        };
        for w in &enforced.warnings {
            eprintln!("r2g sandbox WARNING: {w}");
        }
        live.ctl.set_read_timeout(Some(Duration::from_secs(30)))?;
        let hello = recv_frame(&mut live.ctl);
        if hello.is_err() {
            Self::teardown(&mut live);
            bail!("the sandboxed worker did not start: {}", tail(&self.cfg.log_dir.join("worker.err"), 800).trim());
        }
        self.enforced = Some(enforced);
        self.live = Some(live);
        Ok(())
    }

    fn teardown(live: &mut Live) {
        // SAFETY: signals the worker's own process group, which we created.
        unsafe { libc::kill(-live.pgid, libc::SIGKILL) };
        let _ = live.worker.wait();
        let _ = live.proxy.kill();
        let _ = live.proxy.wait();
        if let Some(cg) = &live.cgroup {
            // Emptied by the kill above; the kernel may take a moment to notice.
            for _ in 0..50 {
                if std::fs::remove_dir(cg).is_ok() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }

    fn proxy_cmd(live: &mut Live, v: serde_json::Value) -> anyhow::Result<serde_json::Value> {
        writeln!(live.proxy_in, "{v}")?;
        live.proxy_in.flush()?;
        let mut line = String::new();
        live.proxy_out.read_line(&mut line)?;
        serde_json::from_str(&line).context("the robo proxy stopped answering")
    }

    /// A command for the trusted proxy (`observe`, `reset`), starting the worker if needed.
    pub fn host_cmd(&mut self, v: serde_json::Value) -> anyhow::Result<serde_json::Value> {
        if self.live.is_none() {
            self.start()?;
        }
        let Some(live) = self.live.as_mut() else { bail!("no worker") };
        Self::proxy_cmd(live, v)
    }

    /// Runs one program; never fails because of what the program does.
    pub fn run(&mut self, code: &str, name: &str, budget: Budget) -> anyhow::Result<ExecResult> {
        if self.live.is_none() {
            self.start()?;
        }
        let limits = self.cfg.limits.clone();
        let scratch = self.cfg.scratch.clone();
        let log_dir = self.cfg.log_dir.clone();
        let begin =
            serde_json::json!({"cmd": "begin", "budget": budget.control_steps, "observe_only": budget.observe_only});
        let alive = self.live.as_mut().map(|l| Self::proxy_cmd(l, begin.clone()).is_ok());
        if alive == Some(false) {
            // The previous program left the worker or its proxy dead: start afresh.
            if let Some(mut live) = self.live.take() {
                Self::teardown(&mut live);
            }
            self.start()?;
            let Some(live) = self.live.as_mut() else { bail!("no worker") };
            Self::proxy_cmd(live, begin)?;
        }
        let Some(live) = self.live.as_mut() else { bail!("no worker") };
        let raw_before = std::fs::metadata(log_dir.join("worker.out")).map(|m| m.len()).unwrap_or(0)
            + std::fs::metadata(log_dir.join("worker.err")).map(|m| m.len()).unwrap_or(0);
        let t0 = Instant::now();
        send_frame(&mut live.ctl, &serde_json::json!({"code": code, "name": name}))?;
        live.ctl.set_read_timeout(Some(Duration::from_millis(200)))?;
        let mut killed_for: Option<String> = None;
        let reply = loop {
            match recv_frame(&mut live.ctl) {
                Ok(v) => break Some(v),
                Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
                Err(_) => break None,
            }
            let (bytes, files) = usage(&scratch, limits.scratch_files);
            if t0.elapsed().as_secs_f64() > limits.wall_s {
                killed_for = Some(format!("wall-clock limit: the program ran longer than {:.0} s", limits.wall_s));
            } else if bytes > limits.scratch_mb << 20 {
                killed_for = Some(format!("disk quota: the scratch folder grew past {} MiB", limits.scratch_mb));
            } else if files > limits.scratch_files {
                killed_for =
                    Some(format!("disk quota: more than {} files in the scratch folder", limits.scratch_files));
            }
            if killed_for.is_some() {
                // SAFETY: the worker's own process group, created by us; it cannot leave it.
                unsafe { libc::kill(-live.pgid, libc::SIGKILL) };
                break None;
            }
        };
        let wall_s = t0.elapsed().as_secs_f64();
        let mut r = match reply {
            Some(v) => serde_json::from_value::<ExecResult>(v.clone()).map(|mut r| {
                r.exit_code = v.get("code").and_then(|c| c.as_i64());
                r
            })?,
            None => {
                let status = live.worker.wait()?;
                let violation = killed_for.unwrap_or_else(|| match status.signal() {
                    Some(libc::SIGSYS) => "forbidden system call: the sandbox's seccomp filter killed the worker \
                                           (sockets, new processes, ptrace, mounts and the like are not allowed)"
                        .into(),
                    Some(libc::SIGXCPU) | Some(libc::SIGKILL) => {
                        format!("CPU time limit: the worker used more than {} s of CPU", limits.cpu_s)
                    }
                    Some(libc::SIGXFSZ) => format!("file size limit: a file grew past {} MiB", limits.fsize_mb),
                    Some(s) => format!("the worker died from signal {s}"),
                    None => format!("the worker exited with code {}", status.code().unwrap_or(-1)),
                });
                ExecResult { exit: "killed".into(), violation: Some(violation), ..ExecResult::default() }
            }
        };
        r.wall_s = wall_s;
        if r.exit == "killed" {
            let mut live = self.live.take().context("live worker")?;
            let _ = Self::proxy_cmd(&mut live, serde_json::json!({"cmd": "end"})).map(|v| Self::take_stats(&mut r, &v));
            Self::teardown(&mut live);
        } else {
            match Self::proxy_cmd(live, serde_json::json!({"cmd": "end"})) {
                Ok(v) => Self::take_stats(&mut r, &v),
                Err(_) => {
                    // The proxy refused to go on (a malformed or oversized frame from the
                    // program): the worker's robot connection is gone; both restart.
                    r.violation = Some("the program sent malformed data to the robot connection; it was cut".into());
                    if let Some(mut live) = self.live.take() {
                        Self::teardown(&mut live);
                    }
                }
            }
            if r.violation.is_none() {
                r.violation = classify(&r, &limits);
            }
        }
        let out_now = std::fs::metadata(log_dir.join("worker.out")).map(|m| m.len()).unwrap_or(0)
            + std::fs::metadata(log_dir.join("worker.err")).map(|m| m.len()).unwrap_or(0);
        if out_now > raw_before {
            r.raw_output =
                format!("{}{}", tail(&log_dir.join("worker.out"), 2000), tail(&log_dir.join("worker.err"), 2000));
        }
        Ok(r)
    }

    fn take_stats(r: &mut ExecResult, v: &serde_json::Value) {
        let n = |k: &str| v.get(k).and_then(|x| x.as_u64()).unwrap_or(0);
        r.control_steps = n("steps");
        r.robot_calls = n("calls");
        r.budget_refusals = n("refused");
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        if let Some(mut live) = self.live.take() {
            Self::teardown(&mut live);
        }
    }
}

/// A program that ended by itself may still have been stopped by the sandbox.
fn classify(r: &ExecResult, limits: &Limits) -> Option<String> {
    let exc = r.exception.as_deref().unwrap_or("");
    let last = exc.lines().last().unwrap_or("").trim();
    match r.exc_type.as_deref() {
        Some("MemoryError") => Some(format!("memory limit: the worker may use {} MiB of address space", limits.mem_mb)),
        Some("PermissionError") => Some(format!("denied by the sandbox: {last}")),
        _ if exc.contains("[Errno 1] Operation not permitted") || exc.contains("[Errno 13] Permission denied") => {
            Some(format!("denied by the sandbox: {last}"))
        }
        _ if exc.contains("File too large") => {
            Some(format!("file size limit: a file grew past {} MiB", limits.fsize_mb))
        }
        _ => None,
    }
}
