#![doc = include_str!("../README.md")]

use std::collections::HashMap;
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};

use anyhow::{bail, Context};
use serde_json::{json, Value};

/// One job: the arguments of one `r2g` run that plays one episode and ends with one JSON line
/// (`episode ...`, `replay ...`; later `validate ...`, `episode --skills learn ...`).
#[derive(Debug, Clone)]
pub struct Job {
    pub id: usize,
    pub args: Vec<String>,
}

/// Where the jobs run.
#[derive(Debug, Clone, PartialEq)]
pub enum Backend {
    /// This many at once on this machine (no Ray).
    Local(usize),
    /// As Ray tasks: `address` is `auto` (the running cluster, else a local one for this batch)
    /// or a cluster's address; at most `max_concurrent` at once (None: as many as the cluster's
    /// `r2g_gym` resources allow).
    Ray { address: String, max_concurrent: Option<usize> },
}

impl Backend {
    /// `--ray ADDRESS` (with `--workers N`: at most N at once) or `--workers N` alone; neither:
    /// `None` (the caller's own sequential path).
    pub fn from_args(ray: Option<&str>, workers: Option<usize>) -> Option<Self> {
        match (ray, workers) {
            (Some(a), w) => Some(Self::Ray { address: a.to_string(), max_concurrent: w }),
            (None, Some(n)) => Some(Self::Local(n.max(1))),
            (None, None) => None,
        }
    }
}

/// The checkout the binaries run from.
fn root() -> PathBuf {
    runtime::launch::gyms_dir().parent().map(Path::to_path_buf).unwrap_or_default()
}

static DRIVERS: AtomicUsize = AtomicUsize::new(0);
static NODES: Mutex<std::collections::BTreeMap<String, usize>> = Mutex::new(std::collections::BTreeMap::new());

/// The Ray nodes (`"<node id>@<address>"`) that results of this process came from so far, with
/// how many each; empty off Ray.
pub fn nodes_seen() -> std::collections::BTreeMap<String, usize> {
    NODES.lock().unwrap_or_else(|e| e.into_inner()).clone()
}

/// How many fleet drivers (`r2g_fleet.py` processes; under Ray each one a `ray.init`) this
/// process has started so far.
pub fn drivers_started() -> usize {
    DRIVERS.load(Ordering::Relaxed)
}

/// Subcommands whose `--out` is a folder of the job's own (owned by one try at a time and
/// removed unless a try ends with its result, see [`run`]); other jobs (`replay`, `validate`) share or reuse
/// theirs.
const OWN_OUT: &[&str] = &["episode"];

/// The job's own output folder, if it has one ([`OWN_OUT`]).
fn own_out(job: &Job) -> Option<String> {
    if !OWN_OUT.contains(&job.args.first()?.as_str()) {
        return None;
    }
    let i = job.args.iter().position(|a| a == "--out")?;
    job.args.get(i + 1).filter(|o| Path::new(o).is_absolute()).cloned()
}

/// Whether a job's result is that of a try that ended by itself with its result (not killed by
/// a signal, its JSON line printed: `r2g episode` prints it once its folder is whole, and exits
/// 1 for an episode that did not achieve its task): the only tries whose own folder is kept.
fn succeeded(r: &Value) -> bool {
    r["rc"].as_i64().is_some_and(|rc| rc >= 0) && r["value"].is_object()
}

/// Removes the own output folders of `jobs` (what their last tries, cut short with their
/// worker or node, left): renamed aside in one step, then deleted, as the driver's `discard`
/// does. Called only once no try of these jobs can still run.
fn discard_outs<'a>(jobs: impl IntoIterator<Item = &'a Job>) {
    for out in jobs.into_iter().filter_map(own_out) {
        let out = Path::new(&out);
        let (Some(parent), Some(name)) = (out.parent(), out.file_name()) else { continue };
        let aside = parent.join(format!(".{}.removed-driver-{}", name.to_string_lossy(), std::process::id()));
        if std::fs::rename(out, &aside).is_ok() {
            let _ = match std::fs::symlink_metadata(&aside) {
                Ok(m) if m.is_dir() => std::fs::remove_dir_all(&aside),
                _ => std::fs::remove_file(&aside),
            };
        }
    }
}

/// The job as the driver reads it.
fn job_json(j: &Job, cwd: &Path) -> Value {
    json!({"id": j.id, "args": j.args, "cwd": cwd, "out": own_out(j)})
}

/// Whether the Ray head at `address` (host:port) answers at all.
fn head_answers(address: &str) -> bool {
    use std::net::ToSocketAddrs;
    address
        .to_socket_addrs()
        .ok()
        .and_then(|mut a| a.next())
        .is_some_and(|a| std::net::TcpStream::connect_timeout(&a, std::time::Duration::from_secs(3)).is_ok())
}

/// A driver that has exited with `status`: why, in words naming the head when it is gone.
fn driver_failed(backend: &Backend, status: std::process::ExitStatus, results: usize, jobs: usize) -> anyhow::Error {
    match backend {
        Backend::Ray { address, .. } if address != "auto" && !head_answers(address) => anyhow::anyhow!(
            "the Ray head at {address} does not answer (lost): the fleet driver stopped ({status}) after \
             {results} of {jobs} results (episodes still running on other nodes may yet finish; an episode \
             folder without result.json is not whole)"
        ),
        _ => anyhow::anyhow!(
            "the fleet driver failed ({status}) after {results} of {jobs} results; see its message above"
        ),
    }
}

/// The fleet driver's program: the venv's Python and `fleet/py/r2g_fleet.py`.
fn driver() -> anyhow::Result<(PathBuf, PathBuf)> {
    let root = root();
    let driver = root.join("fleet/py/r2g_fleet.py");
    if !driver.is_file() {
        bail!("{} is missing: run from a checkout (make build)", driver.display());
    }
    Ok((root.join(".venv/bin/python"), driver))
}

/// The driver dies with us.
fn die_with_parent(cmd: &mut Command) {
    // SAFETY: prctl in the child before exec; async-signal-safe.
    unsafe {
        use std::os::unix::process::CommandExt;
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM, 0, 0, 0);
            Ok(())
        });
    }
}

/// Where a job ran, as results name it: `{"host", "id" (the Ray node id), "ip" (the Ray
/// node's address)}`; id and address are null off Ray.
fn with_node(mut r: Value) -> Value {
    if let (Some(id), Some(ip)) = (r["node"]["id"].as_str(), r["node"]["ip"].as_str()) {
        *NODES.lock().unwrap_or_else(|e| e.into_inner()).entry(format!("{id}@{ip}")).or_default() += 1;
    }
    if let (Some(v), Some(node)) = (r.get("value").filter(|v| v.is_object()).cloned(), r.get("node").cloned()) {
        let mut v = v;
        v["node"] = node;
        r["value"] = v;
    }
    r
}

/// Runs `jobs` on `backend`, calling `on_result` with each job's result as it finishes (in the
/// order they finish): `{"id", "rc", "value" (the job's JSON line, with `"node"` added, or
/// null), "stderr_tail", "node" (see [`with_node`]), "worker", "wall_s"}`, or `{"id",
/// "error"}` for a job that failed on every try. `work_dir` keeps the job list. The driver is
/// `fleet/py/r2g_fleet.py` in the project venv; it imports Ray only for [`Backend::Ray`]. A job
/// of [`OWN_OUT`] writes its `--out` folder in place; a try that does not end with its result
/// (killed, or failed before it printed its JSON line) removes it, a retry first removes what a
/// dead try left, and when the driver has ended well (or was a local one, whose tries die with
/// it) the folders of jobs that failed on every try are removed: after `run`, such a folder
/// exists only for a job whose try ended with its result. After a Ray
/// driver that failed (its head lost), tries may still run on the workers: their folders are
/// left to them (whole once `result.json` is there). When the driver fails on a Ray head that
/// no longer answers, the error names the head.
pub fn run(jobs: &[Job], backend: &Backend, work_dir: &Path, mut on_result: impl FnMut(Value)) -> anyhow::Result<()> {
    let (python, driver) = driver()?;
    std::fs::create_dir_all(work_dir).with_context(|| format!("creating {}", work_dir.display()))?;
    let list = work_dir.join(format!(".fleet-jobs-{}.json", std::process::id()));
    // Jobs run in this working directory wherever it exists (a relative path in their arguments
    // means the same there as here; see MULTINODE.md for other nodes).
    let cwd = std::env::current_dir().context("the working directory")?;
    let body: Vec<Value> = jobs.iter().map(|j| job_json(j, &cwd)).collect();
    std::fs::write(&list, serde_json::to_vec(&body)?)?;
    let r2g = std::env::current_exe().context("locating r2g")?;
    let mut cmd = Command::new(&python);
    cmd.arg(&driver).args(["run", "--jobs"]).arg(&list).arg("--r2g").arg(&r2g);
    match backend {
        Backend::Local(n) => cmd.args(["--local", &n.to_string()]),
        Backend::Ray { address, max_concurrent } => {
            cmd.args(["--ray", address]);
            if let Some(n) = max_concurrent {
                cmd.args(["--max-concurrent", &n.to_string()]);
            }
            &mut cmd
        }
    };
    die_with_parent(&mut cmd);
    let mut child = cmd.stdout(Stdio::piped()).stdin(Stdio::null()).spawn().context("starting the fleet driver")?;
    DRIVERS.fetch_add(1, Ordering::Relaxed);
    let out = child.stdout.take().context("driver stdout")?;
    let mut results = 0;
    let mut done = std::collections::HashSet::new();
    for line in std::io::BufReader::new(out).lines() {
        let Ok(line) = line else { break };
        match serde_json::from_str::<Value>(&line) {
            Ok(v) => {
                results += 1;
                if succeeded(&v) {
                    done.extend(v["id"].as_u64());
                }
                on_result(with_node(v))
            }
            Err(_) => eprintln!("{line}"),
        }
    }
    let status = child.wait()?;
    let _ = std::fs::remove_file(&list);
    if status.success() || matches!(backend, Backend::Local(_)) {
        discard_outs(jobs.iter().filter(|j| !done.contains(&(j.id as u64))));
    }
    if !status.success() {
        return Err(driver_failed(backend, status, results, jobs.len()));
    }
    Ok(())
}

/// The jobs of a [`Pool`] waiting for their results, and whether the driver's output has ended
/// (then no result comes any more, for them or for a job submitted later).
#[derive(Default)]
struct Waiting {
    closed: bool,
    jobs: HashMap<usize, mpsc::Sender<Value>>,
}

/// One Ray driver for jobs submitted one by one, from any thread, over its lifetime
/// (`r2g_fleet.py serve`): it joins the cluster once, and every job submitted while others run
/// runs beside them as a task of its own. [`Pool::run`] blocks until that job's result.
pub struct Pool {
    backend: Backend,
    stdin: Mutex<Option<ChildStdin>>,
    child: Mutex<Child>,
    waiting: Arc<Mutex<Waiting>>,
    next: AtomicUsize,
    cwd: PathBuf,
}

impl Pool {
    /// Starts the driver on a [`Backend::Ray`] (it joins the cluster before the first job).
    pub fn new(backend: &Backend) -> anyhow::Result<Self> {
        let Backend::Ray { address, .. } = backend else { bail!("a fleet pool runs on Ray only") };
        let (python, driver) = driver()?;
        let r2g = std::env::current_exe().context("locating r2g")?;
        let mut cmd = Command::new(&python);
        cmd.arg(&driver).args(["serve", "--ray", address, "--r2g"]).arg(&r2g);
        die_with_parent(&mut cmd);
        cmd.stdout(Stdio::piped()).stdin(Stdio::piped());
        let waiting: Arc<Mutex<Waiting>> = Arc::default();
        let w = waiting.clone();
        // The driver is started by the thread that reads its results, which lives as long as
        // it does: PR_SET_PDEATHSIG fires when the thread that started a child ends, and the
        // first caller may be a short-lived worker thread.
        let (started_tx, started_rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut child = match cmd.spawn() {
                Ok(c) => c,
                Err(e) => {
                    let _ = started_tx.send(Err(e));
                    return;
                }
            };
            let Some(out) = child.stdout.take() else { return };
            let _ = started_tx.send(Ok(child));
            for line in std::io::BufReader::new(out).lines() {
                let Ok(line) = line else { break };
                match serde_json::from_str::<Value>(&line) {
                    Ok(v) => {
                        let id = v["id"].as_u64().unwrap_or(u64::MAX) as usize;
                        if let Some(tx) = w.lock().unwrap_or_else(|e| e.into_inner()).jobs.remove(&id) {
                            let _ = tx.send(with_node(v));
                        }
                    }
                    Err(_) => eprintln!("{line}"),
                }
            }
            // The driver is gone: whoever still waits hears it (their senders drop), and so does
            // whoever comes later (closed, under the same lock).
            let mut w = w.lock().unwrap_or_else(|e| e.into_inner());
            w.closed = true;
            w.jobs.clear();
        });
        let mut child = started_rx.recv().context("starting the fleet driver")?.context("starting the fleet driver")?;
        DRIVERS.fetch_add(1, Ordering::Relaxed);
        let stdin = child.stdin.take();
        Ok(Self {
            backend: backend.clone(),
            stdin: Mutex::new(stdin),
            child: Mutex::new(child),
            waiting,
            next: AtomicUsize::new(0),
            cwd: std::env::current_dir().context("the working directory")?,
        })
    }

    /// Runs `args` as one job and returns its result (as [`run`] reports it).
    pub fn run(&self, args: Vec<String>) -> anyhow::Result<Value> {
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let job = Job { id, args };
        let (tx, rx) = mpsc::channel();
        {
            let mut w = self.waiting.lock().unwrap_or_else(|e| e.into_inner());
            if w.closed {
                drop(w);
                return Err(self.failed().context(format!(
                    "job {id} ({}) submitted after the fleet driver's output had ended: it cannot run",
                    job.args.first().map_or("", String::as_str)
                )));
            }
            w.jobs.insert(id, tx);
        }
        {
            let mut stdin = self.stdin.lock().unwrap_or_else(|e| e.into_inner());
            let sent = stdin
                .as_mut()
                .map(|s| writeln!(s, "{}", job_json(&job, &self.cwd)).and_then(|_| s.flush()))
                .transpose();
            if !matches!(sent, Ok(Some(()))) {
                self.waiting.lock().unwrap_or_else(|e| e.into_inner()).jobs.remove(&id);
                return Err(self.failed());
            }
        }
        let r = rx.recv().map_err(|_| self.failed())?;
        if !succeeded(&r) {
            // The job's last try is over: what it left of its own folder goes.
            discard_outs([&job]);
        }
        Ok(r)
    }

    /// Why the driver is gone.
    fn failed(&self) -> anyhow::Error {
        let mut child = self.child.lock().unwrap_or_else(|e| e.into_inner());
        match child.wait() {
            Ok(status) => driver_failed(&self.backend, status, 0, 1),
            Err(e) => anyhow::anyhow!("the fleet driver: {e}"),
        }
    }
}

impl Drop for Pool {
    fn drop(&mut self) {
        // End of input: the driver finishes what runs and exits.
        self.stdin.lock().unwrap_or_else(|e| e.into_inner()).take();
        let _ = self.child.lock().unwrap_or_else(|e| e.into_inner()).wait();
    }
}

/// Replays of the gyms' demonstrations, `seeds` seeds each (0, 1, ...), as jobs on `backend`;
/// traces and verdicts under `out`. Returns the summary: success rate per gym and overall.
pub fn replays(gyms: &[String], seeds: u64, backend: &Backend, out: &Path) -> anyhow::Result<Value> {
    // Absolute: each job runs wherever a worker is, in whatever directory it has.
    let out = &std::path::absolute(out)?;
    let mut jobs = Vec::new();
    for g in gyms {
        for s in 0..seeds.max(1) {
            let args = vec![
                "replay".into(),
                g.clone(),
                "--seed".into(),
                s.to_string(),
                "--out".into(),
                out.display().to_string(),
            ];
            jobs.push(Job { id: jobs.len(), args });
        }
    }
    let mut rows: Vec<Value> = Vec::new();
    run(&jobs, backend, out, |r| {
        let id = r["id"].as_u64().unwrap_or(0) as usize;
        let (gym, seed) = (&jobs[id].args[1], &jobs[id].args[3]);
        let success = r["value"]["success"].as_bool().unwrap_or(false);
        eprintln!("r2g replay: {gym} seed {seed}: success {success}");
        rows.push(json!({"gym": gym, "seed": seed.parse::<u64>().unwrap_or(0), "success": success,
            "error": r.get("error").cloned().unwrap_or(Value::Null), "node": r["node"], "wall_s": r["wall_s"]}));
    })?;
    rows.sort_by_key(|r| (r["gym"].as_str().unwrap_or("").to_string(), r["seed"].as_u64()));
    let mut per_gym = serde_json::Map::new();
    for g in gyms {
        let mine: Vec<&Value> = rows.iter().filter(|r| r["gym"] == g.as_str()).collect();
        let ok = mine.iter().filter(|r| r["success"] == true).count();
        per_gym
            .insert(g.clone(), json!({"episodes": mine.len(), "success_rate": ok as f64 / mine.len().max(1) as f64}));
    }
    let ok = rows.iter().filter(|r| r["success"] == true).count();
    Ok(json!({"episodes": rows.len(), "success_rate": ok as f64 / rows.len().max(1) as f64,
        "per_gym": per_gym, "per_episode": rows}))
}
