#![doc = include_str!("../README.md")]

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

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

/// Runs `jobs` on `backend`, calling `on_result` with each job's result as it finishes (in the
/// order they finish): `{"id", "rc", "value" (the job's JSON line or null), "stderr_tail",
/// "node", "worker", "wall_s"}`, or `{"id", "error"}` for a job that failed on every try.
/// `work_dir` keeps the job list. The driver is `fleet/py/r2g_fleet.py` in the project venv; it
/// imports Ray only for [`Backend::Ray`].
pub fn run(jobs: &[Job], backend: &Backend, work_dir: &Path, mut on_result: impl FnMut(Value)) -> anyhow::Result<()> {
    let root = root();
    let python = root.join(".venv/bin/python");
    let driver = root.join("fleet/py/r2g_fleet.py");
    if !driver.is_file() {
        bail!("{} is missing: run from a checkout (make build)", driver.display());
    }
    std::fs::create_dir_all(work_dir).with_context(|| format!("creating {}", work_dir.display()))?;
    let list = work_dir.join(format!(".fleet-jobs-{}.json", std::process::id()));
    // Jobs run in this working directory wherever it exists (a relative path in their arguments
    // means the same there as here; see MULTINODE.md for other nodes).
    let cwd = std::env::current_dir().context("the working directory")?;
    let body: Vec<Value> = jobs.iter().map(|j| json!({"id": j.id, "args": j.args, "cwd": cwd})).collect();
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
    // SAFETY: prctl in the child before exec; async-signal-safe.
    unsafe {
        use std::os::unix::process::CommandExt;
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM, 0, 0, 0);
            Ok(())
        });
    }
    let mut child = cmd.stdout(Stdio::piped()).stdin(Stdio::null()).spawn().context("starting the fleet driver")?;
    let out = child.stdout.take().context("driver stdout")?;
    for line in std::io::BufReader::new(out).lines() {
        let line = line?;
        match serde_json::from_str::<Value>(&line) {
            Ok(v) => on_result(v),
            Err(_) => eprintln!("{line}"),
        }
    }
    let status = child.wait()?;
    let _ = std::fs::remove_file(&list);
    if !status.success() {
        bail!("the fleet driver failed ({status}); see its message above");
    }
    Ok(())
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
