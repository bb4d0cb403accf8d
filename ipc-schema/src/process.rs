//! Process plumbing every r2g process shares: stop on SIGINT/SIGTERM, and notice when a peer
//! process has died (its iceoryx2 node is gone or dead) without waiting on it.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_stop_signal(_: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

/// Makes SIGINT and SIGTERM set a flag that [`stop_requested`] reads.
pub fn install_stop_signals() {
    // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
    unsafe {
        libc::signal(libc::SIGINT, on_stop_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_stop_signal as *const () as libc::sighandler_t);
    }
}

pub fn stop_requested() -> bool {
    STOP.load(Ordering::Relaxed)
}

/// Asks the kernel to send SIGTERM to this process when its parent dies, so that a killed
/// supervisor never leaves orphans behind.
pub fn die_with_parent() {
    // SAFETY: prctl with PR_SET_PDEATHSIG takes a signal number and has no memory effects.
    unsafe {
        libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
    }
}

/// Whether a node of this name is alive: `Some(true)` alive, `Some(false)` dead (crashed),
/// `None` not registered at all.
pub fn node_alive(name: &str) -> Option<bool> {
    let mut found = None;
    let Ok(config) = crate::ipc_config() else { return None };
    let _ = Node::<ipc::Service>::list(config, |state| {
        let (alive, details) = match &state {
            NodeState::<ipc::Service>::Alive(v) => (true, v.details()),
            NodeState::<ipc::Service>::Dead(v) => (false, v.details()),
            _ => return CallbackProgression::Continue,
        };
        if let Some(d) = details {
            if d.name().as_str() == name {
                // Several entries can share a name briefly (a dead one next to its successor).
                found = Some(found.unwrap_or(false) || alive);
            }
        }
        CallbackProgression::Continue
    });
    found
}

/// Watches a peer node from a background thread; the owner reads one atomic, so the check
/// costs nothing on a real-time path.
pub struct PeerWatch {
    lost: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
}

impl PeerWatch {
    /// The peer counts as lost once it was seen alive and then is dead or gone, or when it
    /// never appears within `grace`.
    pub fn spawn(peer: String, grace: Duration) -> Self {
        let lost = Arc::new(AtomicBool::new(false));
        let stop = Arc::new(AtomicBool::new(false));
        let (l, s) = (lost.clone(), stop.clone());
        let started = Instant::now();
        let _ = std::thread::Builder::new().name("peer-watch".into()).spawn(move || {
            let mut seen = false;
            while !s.load(Ordering::Relaxed) {
                match node_alive(&peer) {
                    Some(true) => seen = true,
                    Some(false) => l.store(true, Ordering::Relaxed),
                    None if seen || started.elapsed() > grace => l.store(true, Ordering::Relaxed),
                    None => {}
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        });
        Self { lost, stop }
    }

    pub fn lost(&self) -> bool {
        self.lost.load(Ordering::Relaxed)
    }
}

impl Drop for PeerWatch {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// The folder of one instance's local files (the operator socket): `$R2G_RUN_DIR/<instance>`
/// (deploy/'s units set `/run/r2g`), else `/run/r2g/<instance>` when it exists (an installed
/// instance, so an operator's shell needs no variable), else `$XDG_RUNTIME_DIR/r2g/<instance>`,
/// else `/tmp/r2g-<uid>/<instance>`.
pub fn run_dir(instance: &str) -> std::path::PathBuf {
    let installed = std::path::Path::new("/run/r2g").join(instance);
    let base = match (std::env::var_os("R2G_RUN_DIR"), std::env::var_os("XDG_RUNTIME_DIR")) {
        (Some(d), _) => std::path::PathBuf::from(d),
        _ if installed.is_dir() => return installed,
        (None, Some(x)) => std::path::Path::new(&x).join("r2g"),
        // SAFETY: getuid cannot fail.
        (None, None) => std::path::PathBuf::from(format!("/tmp/r2g-{}", unsafe { libc::getuid() })),
    };
    base.join(instance)
}

/// `R2G_HOST_BASELINE=1`: the agent host's path as it was before its start-up work was
/// overlapped (no programs started ahead, a new episode's first frame and the info for new
/// agents waiting for their periodic slot), so that `r2g bench agent` measures both in one run.
/// Read when asked (the benchmark switches it between episodes of one process), off the tick;
/// never set outside that benchmark.
pub fn host_baseline() -> bool {
    std::env::var_os("R2G_HOST_BASELINE").is_some_and(|v| v == "1")
}

/// Node names of the processes of one instance.
pub fn sim_node(instance: &str) -> String {
    format!("r2g-sim-{instance}")
}
pub fn control_node(instance: &str) -> String {
    format!("r2g-control-{instance}")
}
