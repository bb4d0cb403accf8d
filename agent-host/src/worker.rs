//! The host side of sandboxed execution: each stage program runs in a fresh confined Python
//! process with its own trusted `robo` proxy, in the episode's scratch folder. The host waits for
//! the process to exit under the wall clock (killing the whole process group), a scratch-disk
//! quota and the worker's own kernel limits, and reads its output as it comes; whatever the
//! program does, the run ends with an [`ExecResult`] and the host carries on.

use std::collections::BTreeMap;
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
    /// The project's root (for `.venv`, `agent-host/py`, `robot-skill`).
    pub root: PathBuf,
    pub limits: Limits,
    /// Where the host builds the read-only `robot-skill/` the worker sees (as
    /// `<scratch>/robot-skill`): the documents, the configuration in force and the memory
    /// folder's records ([`Worker::refresh_view`]). Never inside `scratch`.
    pub view_dir: PathBuf,
    /// The memory folder whose records `robot-skill/memory/` shows (None: only its README).
    pub memory_dir: Option<PathBuf>,
    /// The robot configuration file in force, shown as `robot-skill/config/robot.json` (None:
    /// the one `r2g up` uses without `--robot-config`, `runtime::launch::default_robot_config`).
    pub robot_config: Option<PathBuf>,
}

impl WorkerConfig {
    /// A worker for `instance` writing in `scratch`, its logs in `log_dir` and its view beside
    /// them (`<log_dir>/../view`), without memory, on the shipped robot configuration.
    pub fn new(instance: &str, scratch: &Path, log_dir: &Path, root: &Path, limits: Limits) -> Self {
        Self {
            instance: instance.into(),
            scratch: scratch.to_path_buf(),
            log_dir: log_dir.to_path_buf(),
            root: root.to_path_buf(),
            limits,
            view_dir: log_dir.parent().unwrap_or(log_dir).join("view"),
            memory_dir: None,
            robot_config: None,
        }
    }
}

/// The documents of `robot-skill/` a stage program reads as they are in the checkout (linked
/// into its view); everything else there is made per run (`config/`, the memory records).
pub const SHARED_DOCS: [&str; 5] = ["SKILL.md", "api", "examples", "skills/README.md", "memory/README.md"];

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
    /// The host's own part of running it, outside `wall_s`: starting the program's proxy and
    /// confined worker before, and ending them after, s.
    #[serde(default)]
    pub host_s: f64,
    /// Waypoints posted, robot calls made and calls refused by the budget.
    pub control_steps: u64,
    pub robot_calls: u64,
    pub budget_refusals: u64,
    /// Robot calls refused because the turn is observation-only.
    pub observe_refusals: u64,
    /// The program's chunks by outcome (`executed`, `failed`, `rejected`: refused by the
    /// runtime, the budget or robo before anything moved) and its resets (`done`, `refused`).
    pub chunks: BTreeMap<String, u64>,
    pub resets: BTreeMap<String, u64>,
    /// The program's own last `reset`/`post_actions`: `fn`, `status`, `reason`, `executed`
    /// (None: it made neither).
    pub last_call: Option<serde_json::Value>,
    /// Output written straight to the worker's descriptors (bypassing sys.stdout), tail only.
    pub raw_output: String,
    /// The program's reset/post_actions calls as the proxy logged them (targets, reply,
    /// feedback, robot time before and after); the run record keeps them in `calls.json`.
    #[serde(skip)]
    pub calls: Vec<serde_json::Value>,
}

/// The trusted proxy: a Python process holding the real `robo` connection.
struct Proxy {
    child: Child,
    input: ChildStdin,
    output: BufReader<ChildStdout>,
}

impl Proxy {
    /// A JSON command and its one-line answer, within `timeout`.
    fn cmd(&mut self, v: &serde_json::Value, timeout: Duration) -> anyhow::Result<serde_json::Value> {
        writeln!(self.input, "{v}")?;
        self.input.flush()?;
        let line = read_line_within(&mut self.output, timeout)?;
        serde_json::from_str(&line).context("the robo proxy answered nonsense")
    }

    fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Reads one line, failing after `timeout` (a proxy stuck on its worker must not hang us).
fn read_line_within(r: &mut BufReader<ChildStdout>, timeout: Duration) -> anyhow::Result<String> {
    let deadline = Instant::now() + timeout;
    let mut line = Vec::new();
    loop {
        if let Some(i) = r.buffer().iter().position(|&b| b == b'\n') {
            line.extend_from_slice(&r.buffer()[..=i]);
            r.consume(i + 1);
            return Ok(String::from_utf8_lossy(&line).into_owned());
        }
        let buffered = r.buffer().to_vec();
        line.extend_from_slice(&buffered);
        r.consume(buffered.len());
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            bail!("the robo proxy did not answer within {:.0} s", timeout.as_secs_f64());
        }
        let mut pfd = libc::pollfd { fd: r.get_ref().as_raw_fd(), events: libc::POLLIN, revents: 0 };
        // SAFETY: one valid pollfd.
        let n = unsafe { libc::poll(&mut pfd, 1, left.as_millis().min(i32::MAX as u128) as i32) };
        if n > 0 && r.fill_buf()?.is_empty() {
            bail!("the robo proxy exited");
        }
    }
}

/// A program's proxy and confined worker, started and waiting for the program.
struct Launched {
    proxy: Proxy,
    ctl: UnixStream,
    worker: Option<Child>,
    cgroup: Option<PathBuf>,
    status_r: Option<std::io::PipeReader>,
    out_path: PathBuf,
    err_path: PathBuf,
}

impl Drop for Launched {
    /// One that no program used: its group and cgroup go (the proxy goes with `Proxy`'s drop).
    fn drop(&mut self) {
        if let Some(mut w) = self.worker.take() {
            // SAFETY: the worker's own process group, which we created.
            unsafe { libc::kill(-(w.id() as i32), libc::SIGKILL) };
            let _ = w.wait();
        }
        if let Some(cg) = self.cgroup.take() {
            for _ in 0..50 {
                if std::fs::remove_dir(&cg).is_ok() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
}

pub struct Worker {
    cfg: WorkerConfig,
    /// The proxy the host itself uses between programs (observations, resets).
    host: Option<Proxy>,
    /// The next program's proxy and worker, started ahead (see [`Self::launch`]).
    next: Option<Launched>,
    /// Start the next program's processes as soon as one ends (default); off, each starts when
    /// its program comes (`bench agent` measures both).
    pub prestart: bool,
    /// What the kernel enforced on the last worker.
    pub enforced: Option<Enforced>,
    pub starts: u32,
    /// The worker's `robot-skill/` view has been built ([`Self::build_view`]).
    view_built: bool,
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
            let mut top = 2;
            for (from, to) in &fds {
                if libc::dup2(from.as_raw_fd(), *to) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                top = top.max(*to);
            }
            // Nothing else we inherited reaches the child (close-on-exec, so that the standard
            // library's exec-error pipe keeps working until exec).
            libc::syscall(libc::SYS_close_range, (top + 1) as u32, u32::MAX, 4u32 /* CLOSE_RANGE_CLOEXEC */);
            Ok(())
        });
    }
}

fn send_frame(s: &mut UnixStream, v: &serde_json::Value) -> std::io::Result<()> {
    let data = serde_json::to_vec(v).map_err(std::io::Error::other)?;
    s.write_all(&(data.len() as u32).to_be_bytes())?;
    s.write_all(&data)
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
        // Leftovers of hosts killed before their teardown (the host's pid is the second-last
        // part of the name); rmdir only removes empty cgroups.
        if let Ok(rd) = std::fs::read_dir(b) {
            for e in rd.flatten() {
                let n = e.file_name().to_string_lossy().into_owned();
                let host: Option<u32> = n.rsplit('-').nth(1).and_then(|p| p.parse().ok());
                if n.starts_with("r2g-") && host.is_some_and(|p| !Path::new(&format!("/proc/{p}")).exists()) {
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
        // R2G_HOST_BASELINE=1: the host as it was, for `bench agent`'s comparison in one run.
        let prestart = !ipc_schema::process::host_baseline();
        Self { cfg, host: None, next: None, prestart, enforced: None, starts: 0, view_built: false }
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
        let mut read = vec![prefix.clone(), root.join(".venv"), root.join("agent-host/py"), self.cfg.view_dir.clone()];
        // What the view's links point to (landlock judges a link's target).
        read.extend(SHARED_DOCS.iter().map(|d| root.join("robot-skill").join(d)));
        read.extend([
            PathBuf::from("/usr/lib"),
            PathBuf::from("/usr/share/locale"),
            PathBuf::from("/etc/ld.so.cache"),
            PathBuf::from("/etc/localtime"),
            PathBuf::from("/sys/devices/system/cpu"),
            PathBuf::from("/proc/self"),
        ]);
        let exec = [prefix.join("bin"), prefix.join("lib"), PathBuf::from("/lib64"), PathBuf::from("/usr/lib")];
        Ok(Policy {
            scratch: self.cfg.scratch.clone(),
            read,
            exec: exec.to_vec(),
            cpu_s: l.cpu_s,
            mem_mb: l.mem_mb,
            fsize_mb: l.fsize_mb,
            nofile: l.nofile,
            cgroup,
        })
    }

    fn prepare(&mut self) -> anyhow::Result<()> {
        std::fs::create_dir_all(&self.cfg.scratch)?;
        std::fs::create_dir_all(&self.cfg.log_dir)?;
        // Landlock rules and the worker's working folder must not depend on our cwd.
        self.cfg.scratch = std::fs::canonicalize(&self.cfg.scratch)?;
        self.cfg.log_dir = std::fs::canonicalize(&self.cfg.log_dir)?;
        self.cfg.root = std::fs::canonicalize(&self.cfg.root)?;
        if !self.view_built {
            self.build_view()?;
            self.view_built = true;
        }
        Ok(())
    }

    /// Builds the read-only `robot-skill/` the worker sees at `<scratch>/robot-skill`: links to
    /// the shared documents, a copy of the configuration in force as `config/robot.json` (and of
    /// the perception configuration), and `memory/` with the memory folder's records. Whatever
    /// stood at `<scratch>/robot-skill` (a link of an earlier run, or something a program
    /// planted) is replaced, following no links.
    fn build_view(&mut self) -> anyhow::Result<()> {
        let view = self.cfg.view_dir.join("robot-skill");
        if std::fs::symlink_metadata(&view).is_ok() {
            std::fs::remove_dir_all(&view).with_context(|| format!("clearing {}", view.display()))?;
        }
        let docs = self.cfg.root.join("robot-skill");
        for d in ["config", "memory", "skills"] {
            std::fs::create_dir_all(view.join(d))?;
        }
        for d in SHARED_DOCS {
            std::os::unix::fs::symlink(docs.join(d), view.join(d))?;
        }
        let config = self.cfg.robot_config.clone().unwrap_or_else(runtime::launch::default_robot_config);
        std::fs::copy(&config, view.join("config/robot.json"))
            .with_context(|| format!("the robot configuration {}", config.display()))?;
        let perception = std::env::var_os("R2G_PERCEPTION_CONFIG")
            .map_or_else(|| docs.join("config/perception.json"), PathBuf::from);
        if perception.is_file() {
            std::fs::copy(&perception, view.join("config/perception.json"))?;
        }
        self.cfg.view_dir = std::fs::canonicalize(&self.cfg.view_dir)?;
        self.refresh_view()?;
        let link = self.cfg.scratch.join("robot-skill");
        match std::fs::symlink_metadata(&link) {
            Ok(m) if m.is_dir() => std::fs::remove_dir_all(&link)?,
            Ok(_) => std::fs::remove_file(&link)?,
            Err(_) => {}
        }
        std::os::unix::fs::symlink(self.cfg.view_dir.join("robot-skill"), &link)?;
        Ok(())
    }

    /// Copies the memory folder's records that the view does not show yet into
    /// `robot-skill/memory/` (records are append-only: a name shown once keeps its content).
    pub fn refresh_view(&self) -> anyhow::Result<()> {
        let Some(dir) = &self.cfg.memory_dir else { return Ok(()) };
        crate::memory::mirror(dir, &self.cfg.view_dir.join("robot-skill/memory"))
    }

    /// Starts a proxy serving `robo` over `robo_end` (fd 3 in the proxy).
    fn spawn_proxy(&self, robo_end: &UnixStream) -> anyhow::Result<Proxy> {
        let mut cmd = Command::new(self.python());
        cmd.args(["-I", "-B"])
            .arg(self.cfg.root.join("agent-host/py/robo_proxy.py"))
            .env_clear()
            .env("R2G_INSTANCE", &self.cfg.instance)
            .env("PATH", "/usr/bin:/bin")
            // Where the instance's shared memory is found (deploy/ moves it under /run/r2g).
            .envs(std::env::var_os("R2G_IPC_CONFIG").map(|v| ("R2G_IPC_CONFIG", v)))
            // Which perception services the proxy may call for the program (never the program's choice).
            .envs(std::env::var_os("R2G_PERCEPTION_CONFIG").map(|v| ("R2G_PERCEPTION_CONFIG", v)))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(std::fs::OpenOptions::new().create(true).append(true).open(self.cfg.log_dir.join("proxy.log"))?);
        pass_fds(&mut cmd, vec![(high(robo_end.as_raw_fd())?, 3)]);
        // SAFETY: prctl in the child before exec; async-signal-safe.
        unsafe {
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL, 0, 0, 0);
                Ok(())
            });
        }
        let mut child = cmd.spawn().context("starting the robo proxy")?;
        drop(cmd);
        let input = child.stdin.take().context("proxy stdin")?;
        let output = BufReader::new(child.stdout.take().context("proxy stdout")?);
        Ok(Proxy { child, input, output })
    }

    /// With `prestart`, starts the next program's processes now, so that they are up when it
    /// comes; one that cannot start now is started (and its error reported) by the next
    /// [`Self::run`].
    pub fn prestart_next(&mut self) {
        if self.prestart && self.next.is_none() {
            self.next = self.launch().ok();
        }
    }

    /// Waits until a proxy has started (it says `ready`).
    fn proxy_ready(&self, p: &mut Proxy) -> anyhow::Result<()> {
        let line = read_line_within(&mut p.output, Duration::from_secs(30));
        if !line.as_ref().is_ok_and(|l| l.contains("\"ready\"")) {
            bail!("the robo proxy did not start: {}", tail(&self.cfg.log_dir.join("proxy.log"), 600).trim());
        }
        Ok(())
    }

    /// Starts a program's proxy and confined worker without waiting for them: the next program's
    /// come up (two Python interpreters, the sandbox applied) while the current one runs, and
    /// [`Self::run`] takes them. On by default (`prestart`); a worker started this way that no
    /// program uses is stopped on drop.
    fn launch(&mut self) -> anyhow::Result<Launched> {
        self.prepare()?;
        self.starts += 1;
        let (robo_host, robo_worker) = UnixStream::pair()?;
        let (ctl, ctl_worker) = UnixStream::pair()?;
        let proxy = self.spawn_proxy(&robo_host)?;
        drop(robo_host);
        let name_cg = format!("{}-{}-{}", self.cfg.instance, std::process::id(), self.starts);
        let cgroup = make_cgroup(&name_cg, self.cfg.limits.pids);
        let policy = serde_json::to_string(&self.policy(cgroup.clone())?)?;
        let (status_r, status_w) = std::io::pipe()?;
        // One pair of files per worker: the next one starts while this one still writes.
        let out_path = self.cfg.log_dir.join(format!("worker-{}.out", self.starts));
        let err_path = self.cfg.log_dir.join(format!("worker-{}.err", self.starts));
        let mut cmd = Command::new(crate::sibling("r2g-sandbox")?);
        cmd.arg(policy)
            .arg("5")
            .arg(self.python())
            .args(["-I", "-B"])
            .arg(self.cfg.root.join("agent-host/py/runner.py"))
            .env_clear()
            .env("HOME", &self.cfg.scratch)
            .env("LANG", "C.UTF-8")
            .env("PATH", "/usr/bin:/bin")
            .env("OPENBLAS_NUM_THREADS", "1")
            .env("OMP_NUM_THREADS", "1")
            .env("MALLOC_ARENA_MAX", "2")
            // robo_perception keeps object identities for the whole episode in this file
            .env("R2G_PERCEPTION_TRACKS", self.cfg.scratch.join(".perception-tracks.json"))
            // Where iceoryx2 keeps the instance's files: no secret (the sandbox denies it), named
            // so the hostile-program suite probes the configured place, not only the default.
            .env("R2G_IPC_ROOT", ipc_root())
            .current_dir(&self.cfg.scratch)
            .stdin(Stdio::null())
            .stdout(std::fs::File::create(&out_path)?)
            .stderr(std::fs::File::create(&err_path)?)
            .process_group(0);
        pass_fds(
            &mut cmd,
            vec![
                (high(ctl_worker.as_raw_fd())?, 3),
                (high(robo_worker.as_raw_fd())?, 4),
                (high(status_w.as_raw_fd())?, 5),
            ],
        );
        let spawned = cmd.spawn();
        // Our copies of the worker's ends go now, so its exit closes them for good.
        drop((cmd, ctl_worker, robo_worker, status_w));
        let worker = spawned.context("starting r2g-sandbox")?;
        Ok(Launched { proxy, ctl, worker: Some(worker), cgroup, status_r: Some(status_r), out_path, err_path })
    }

    /// A command for the host's own proxy (`observe`, `reset`).
    pub fn host_cmd(&mut self, v: serde_json::Value) -> anyhow::Result<serde_json::Value> {
        if self.host.is_none() {
            self.prepare()?;
            let (ours, _unused) = UnixStream::pair()?;
            let mut p = self.spawn_proxy(&ours)?;
            self.proxy_ready(&mut p)?;
            self.host = Some(p);
        }
        let Some(p) = self.host.as_mut() else { bail!("no proxy") };
        match p.cmd(&v, Duration::from_secs(60)) {
            Ok(r) => Ok(r),
            Err(e) => {
                self.host = None;
                Err(e)
            }
        }
    }

    /// Runs one program in a fresh confined worker with its own proxy; never fails because of
    /// what the program does. The worker is gone when this returns.
    pub fn run(&mut self, code: &str, name: &str, budget: Budget) -> anyhow::Result<ExecResult> {
        let started = Instant::now();
        let limits = self.cfg.limits.clone();
        let mut launched = match self.next.take() {
            Some(l) => l,
            None => self.launch()?,
        };
        // The next program's processes come up while this one runs.
        self.prestart_next();
        self.proxy_ready(&mut launched.proxy)?;
        launched.proxy.cmd(
            &serde_json::json!({"cmd": "begin", "budget": budget.control_steps, "observe_only": budget.observe_only}),
            Duration::from_secs(30),
        )?;
        let (Some(mut worker), Some(status_r)) = (launched.worker.take(), launched.status_r.take()) else {
            bail!("a launched worker was used twice");
        };
        let cgroup = launched.cgroup.take();
        let (out_path, err_path) = (launched.out_path.clone(), launched.err_path.clone());
        let (proxy, ctl) = (&mut launched.proxy, &mut launched.ctl);
        let pgid = worker.id() as i32;
        let cleanup = |worker: &mut Child| {
            // SAFETY: the worker's own process group, which we created; it cannot leave it.
            unsafe { libc::kill(-pgid, libc::SIGKILL) };
            let _ = worker.wait();
            if let Some(cg) = &cgroup {
                for _ in 0..50 {
                    if std::fs::remove_dir(cg).is_ok() {
                        break;
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
            }
        };
        // What the kernel enforced (or why nothing ran).
        let status = read_status(status_r, Duration::from_secs(30));
        let enforced: Option<Enforced> = status.get("enforced").and_then(|e| serde_json::from_value(e.clone()).ok());
        let Some(enforced) = enforced else {
            cleanup(&mut worker);
            bail!(
                "the sandbox could not be applied, nothing ran: {}",
                status.get("error").and_then(|e| e.as_str()).unwrap_or("no status from r2g-sandbox")
            );
        };
        for w in &enforced.warnings {
            eprintln!("r2g sandbox WARNING: {w}");
        }
        self.enforced = Some(enforced);

        // Everything the worker sends is read as it comes, so it never blocks on us.
        let reader = {
            let mut r = ctl.try_clone()?;
            std::thread::spawn(move || {
                let mut all = Vec::new();
                let mut buf = [0u8; 65536];
                while all.len() < 32 << 20 {
                    match r.read(&mut buf) {
                        Ok(0) | Err(_) => break,
                        Ok(n) => all.extend_from_slice(&buf[..n]),
                    }
                }
                all
            })
        };
        let t0 = Instant::now();
        let sent = send_frame(ctl, &serde_json::json!({"code": code, "name": name}));
        let mut killed_for: Option<String> = sent.err().map(|e| format!("the worker did not take the program: {e}"));
        let status = loop {
            if killed_for.is_some() {
                cleanup(&mut worker);
                break None;
            }
            if let Some(st) = worker.try_wait()? {
                break Some(st);
            }
            let (bytes, files) = usage(&self.cfg.scratch, limits.scratch_files);
            if t0.elapsed().as_secs_f64() > limits.wall_s {
                killed_for = Some(format!("wall-clock limit: the program ran longer than {:.0} s", limits.wall_s));
            } else if bytes > limits.scratch_mb << 20 {
                killed_for = Some(format!("disk quota: the scratch folder grew past {} MiB", limits.scratch_mb));
            } else if files > limits.scratch_files {
                killed_for =
                    Some(format!("disk quota: more than {} files in the scratch folder", limits.scratch_files));
            } else {
                std::thread::sleep(Duration::from_millis(20));
            }
        };
        let wall_s = t0.elapsed().as_secs_f64();
        cleanup(&mut worker);
        let _ = ctl.shutdown(std::net::Shutdown::Both);
        let bytes = reader.join().unwrap_or_default();
        // The runner's reply is the last whole frame.
        let reply = last_frame(&bytes);
        let clean_exit = status.is_some_and(|s| s.success());
        let mut r = match (reply, clean_exit) {
            (Some(v), true) => {
                let mut r: ExecResult = serde_json::from_value(v.clone()).unwrap_or_else(|e| ExecResult {
                    exit: "exception".into(),
                    exception: Some(format!("the worker's reply was not understood: {e}")),
                    ..ExecResult::default()
                });
                r.exit_code = v.get("code").and_then(|c| c.as_i64());
                r
            }
            _ => {
                let violation = killed_for.unwrap_or_else(|| match status.and_then(|s| s.signal()) {
                    Some(libc::SIGSYS) => "forbidden system call: the sandbox's seccomp filter killed the worker \
                                           (sockets, new processes, ptrace, mounts and the like are not allowed)"
                        .into(),
                    Some(libc::SIGXCPU) | Some(libc::SIGKILL) => {
                        format!("CPU time limit: the worker used more than {} s of CPU", limits.cpu_s)
                    }
                    Some(libc::SIGXFSZ) => format!("file size limit: a file grew past {} MiB", limits.fsize_mb),
                    Some(s) => format!("the worker died from signal {s}"),
                    None => format!(
                        "the worker ended without a result (exit code {})",
                        status.and_then(|s| s.code()).unwrap_or(-1)
                    ),
                });
                ExecResult { exit: "killed".into(), violation: Some(violation), ..ExecResult::default() }
            }
        };
        r.wall_s = wall_s;
        r.host_s = (started.elapsed().as_secs_f64() - wall_s).max(0.0);
        // Cap what goes back into prompts, whatever the worker claimed.
        for t in [&mut r.stdout, &mut r.stderr] {
            cap_text(t, 64 * 1024);
        }
        if let Some(e) = r.exception.as_mut() {
            cap_text(e, 16 * 1024);
        }
        match proxy.cmd(&serde_json::json!({"cmd": "end"}), Duration::from_secs(5)) {
            Ok(v) => Self::take_stats(&mut r, &v),
            Err(_) => {
                if r.violation.is_none() {
                    r.violation = Some("the program jammed its robot connection; it was cut".into());
                }
            }
        }
        drop(launched);
        if r.violation.is_none() {
            r.violation = classify(&r, &limits);
        }
        let raw = format!("{}{}", tail(&out_path, 2000), tail(&err_path, 2000));
        r.raw_output = raw;
        Ok(r)
    }

    fn take_stats(r: &mut ExecResult, v: &serde_json::Value) {
        let n = |k: &str| v.get(k).and_then(|x| x.as_u64()).unwrap_or(0);
        r.control_steps = n("steps");
        r.robot_calls = n("calls");
        r.budget_refusals = n("refused");
        r.observe_refusals = n("observe_refused");
        let counts = |k: &str| -> BTreeMap<String, u64> {
            v.get(k).and_then(|c| serde_json::from_value(c.clone()).ok()).unwrap_or_default()
        };
        r.chunks = counts("chunks");
        r.resets = counts("resets");
        r.last_call = v.get("last").filter(|l| l.is_object()).cloned();
        r.calls = v.get("log").and_then(|l| l.as_array()).cloned().unwrap_or_default();
    }
}

/// Cuts a text to at most `max` bytes at a character boundary, saying so.
fn cap_text(t: &mut String, max: usize) {
    if t.len() > max {
        let mut cut = max;
        while !t.is_char_boundary(cut) {
            cut -= 1;
        }
        t.truncate(cut);
        t.push_str("\n[... cut]");
    }
}

/// The last complete length-prefixed JSON frame in `bytes`.
fn last_frame(bytes: &[u8]) -> Option<serde_json::Value> {
    let (mut at, mut last) = (0usize, None);
    while at + 4 <= bytes.len() {
        let n = u32::from_be_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]) as usize;
        let Some(body) = bytes.get(at + 4..at + 4 + n) else { break };
        if let Ok(v) = serde_json::from_slice::<serde_json::Value>(body) {
            last = Some(v);
        }
        at += 4 + n;
    }
    last
}

/// The sandbox's one status line, or an error object after `timeout`.
fn read_status(pipe: std::io::PipeReader, timeout: Duration) -> serde_json::Value {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(pipe).read_line(&mut line);
        let _ = tx.send(line);
    });
    match rx.recv_timeout(timeout) {
        Ok(line) => serde_json::from_str(line.trim()).unwrap_or(serde_json::Value::Null),
        Err(_) => serde_json::json!({"error": "r2g-sandbox gave no status in time"}),
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

/// The iceoryx2 root path this process uses (see `ipc_schema::ipc_config`).
fn ipc_root() -> String {
    ipc_schema::ipc_config().map(|c| c.global.root_path().to_string()).unwrap_or_default()
}
