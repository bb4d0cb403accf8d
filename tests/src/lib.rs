//! Harness for multi-process tests: starts the real `r2g up`, finds its children through
//! /proc, and always stops what it started, by pid, even when a test fails.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// target/<profile>/ of this build (test binaries live in target/<profile>/deps/).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let deps = exe.parent().expect("deps folder");
    deps.parent().expect("profile folder").to_path_buf()
}

/// The checkout this crate lives in.
pub fn root() -> PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

pub fn r2g() -> PathBuf {
    let p = bin_dir().join("r2g");
    assert!(p.is_file(), "{} missing: build the workspace first (make build)", p.display());
    p
}

/// Makes this test process adopt orphaned descendants, so that a killed `r2g up`'s children are
/// reaped here and can be checked, instead of lingering under init.
pub fn become_subreaper() {
    // SAFETY: prctl with PR_SET_CHILD_SUBREAPER has no memory effects.
    unsafe {
        libc::prctl(libc::PR_SET_CHILD_SUBREAPER, 1);
    }
}

/// A unique instance name per test and process.
pub fn instance(tag: &str) -> String {
    format!("t{}{}", std::process::id(), tag)
}

pub struct Up {
    pub child: Child,
    pub instance: String,
    stderr: mpsc::Receiver<String>,
    pub stderr_lines: Vec<String>,
}

impl Up {
    /// Starts `r2g up <gym>` and waits for its READY line.
    pub fn start(gym: &str, instance: &str, extra: &[&str]) -> Self {
        let mut child = Command::new(r2g())
            .args(["up", gym, "--instance", instance, "--render-hz", "5"])
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn r2g up");
        let (tx, rx) = mpsc::channel();
        let stdout = child.stdout.take().expect("stdout");
        let ready_tx = tx.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let _ = ready_tx.send(format!("OUT {line}"));
            }
        });
        let stderr = child.stderr.take().expect("stderr");
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let mut up = Self { child, instance: instance.into(), stderr: rx, stderr_lines: Vec::new() };
        let t0 = Instant::now();
        loop {
            match up.stderr.recv_timeout(Duration::from_millis(100)) {
                Ok(l) if l == format!("OUT READY {instance}") => return up,
                Ok(l) => up.stderr_lines.push(l),
                Err(_) => {}
            }
            if let Ok(Some(s)) = up.child.try_wait() {
                panic!("r2g up exited early ({s}): {:?}", up.stderr_lines);
            }
            assert!(t0.elapsed() < Duration::from_secs(90), "not READY within 90 s: {:?}", up.stderr_lines);
        }
    }

    pub fn drain(&mut self) {
        while let Ok(l) = self.stderr.try_recv() {
            self.stderr_lines.push(l);
        }
    }

    /// Pid of the child process with this executable name (r2g-sim, r2g-control).
    pub fn child_pid(&self, comm: &str) -> i32 {
        children_of(self.child.id() as i32)
            .into_iter()
            .find(|&p| comm_of(p).as_deref() == Some(comm))
            .unwrap_or_else(|| panic!("no {comm} child of r2g up"))
    }

    /// Waits up to `timeout` for r2g up to exit; returns its exit code (or None on signal).
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<Option<i32>> {
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            if let Ok(Some(s)) = self.child.try_wait() {
                std::thread::sleep(Duration::from_millis(100));
                self.drain();
                return Some(s.code());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }
}

impl Drop for Up {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            // SAFETY: signals the child this harness started, by pid.
            unsafe {
                libc::kill(self.child.id() as i32, libc::SIGTERM);
            }
            let t0 = Instant::now();
            while matches!(self.child.try_wait(), Ok(None)) && t0.elapsed() < Duration::from_secs(10) {
                std::thread::sleep(Duration::from_millis(20));
            }
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

pub fn children_of(pid: i32) -> Vec<i32> {
    std::fs::read_to_string(format!("/proc/{pid}/task/{pid}/children"))
        .unwrap_or_default()
        .split_whitespace()
        .filter_map(|s| s.parse().ok())
        .collect()
}

pub fn comm_of(pid: i32) -> Option<String> {
    std::fs::read_to_string(format!("/proc/{pid}/comm")).ok().map(|s| s.trim().to_string())
}

/// True while the process exists and is not a zombie.
pub fn running(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => {
            let state = stat.rsplit(')').next().and_then(|rest| rest.split_whitespace().next()).unwrap_or("X");
            state != "Z" && state != "X"
        }
        Err(_) => false,
    }
}

/// Waits until `pid` is gone (reaping it if it was re-parented to us); false on timeout.
pub fn wait_gone(pid: i32, timeout: Duration) -> bool {
    let t0 = Instant::now();
    while t0.elapsed() < timeout {
        // SAFETY: reaps our own adopted child if it is one; harmless otherwise.
        unsafe {
            libc::waitpid(pid, std::ptr::null_mut(), libc::WNOHANG);
        }
        if !running(pid) {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    false
}

pub fn sigkill(pid: i32) {
    // SAFETY: pid is a process this test started (directly or through r2g up).
    unsafe {
        libc::kill(pid, libc::SIGKILL);
    }
}
