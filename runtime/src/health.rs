//! What the tick loop shares with the threads beside it (the systemd notifier and the operator
//! socket): plain atomics the loop stores between ticks, so nothing on the tick path locks,
//! allocates or does I/O for them.

use std::sync::atomic::{AtomicBool, AtomicI32, AtomicI64, AtomicU32, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

/// Bits of [`Health::fault`].
pub const FAULT_OPERATOR: u32 = 1;
pub const FAULT_ROBOT_LOST: u32 = 2;

#[derive(Debug, Default)]
pub struct Health {
    /// Loop cycles completed (wall: ticks; lockstep: loop passes, busy or idle). The watchdog
    /// pings only while this advances.
    pub cycles: AtomicU64,
    /// Control ticks completed.
    pub ticks: AtomicU64,
    /// Deadlines missed (the loop skips them rather than bursting to catch up).
    pub overruns: AtomicU64,
    /// The largest wake-up latency of the last full second, ns.
    pub wake_max_ns: AtomicU64,
    /// CLOCK_MONOTONIC of the last state from the robot side, ns.
    pub last_state_ns: AtomicU64,
    /// [`FAULT_OPERATOR`] | [`FAULT_ROBOT_LOST`].
    pub fault: AtomicU32,
    pub agent_port_errors: AtomicU64,
    /// `ipc_schema::Mode` as u32.
    pub mode: AtomicU32,
    pub started_ns: AtomicU64,
    /// The watchdog interval systemd asked for, µs (0: none).
    pub watchdog_usec: AtomicU64,
    /// Operator fault resets: the socket thread bumps `clear_requested`; the loop, between
    /// ticks, clears, stores the outcome in `clear_result` (1 cleared, 0 nothing to clear) and
    /// then `clear_done` to the request's number.
    pub clear_requested: AtomicU64,
    pub clear_done: AtomicU64,
    pub clear_result: AtomicU32,
    /// Set when the loop has ended (STOPPING).
    pub stopping: AtomicBool,
    /// Commands found outside the limits (see `TickStats::limit_violations`).
    pub limit_violations: AtomicU64,
    /// What real-time setup achieved: SCHED_FIFO priority (0: refused or not asked), memory
    /// locked, the CPU the loop is pinned to (-1: none), and whether anything asked was refused.
    pub rt_fifo_priority: AtomicI32,
    pub rt_memory_locked: AtomicBool,
    pub rt_cpu: AtomicI64,
    pub rt_refused: AtomicBool,
}

impl Health {
    pub fn new(mode: u32) -> Arc<Self> {
        let h = Self::default();
        h.rt_cpu.store(-1, Relaxed);
        h.mode.store(mode, Relaxed);
        h.started_ns.store(ipc_schema::monotonic_ns(), Relaxed);
        Arc::new(h)
    }

    /// The number of a pending operator fault reset, if one waits (the loop calls this between
    /// ticks, clears, publishes the state that shows it, then calls [`Self::finish_clear`]).
    #[inline]
    pub fn take_clear(&self) -> Option<u64> {
        let asked = self.clear_requested.load(Relaxed);
        (asked != self.clear_done.load(Relaxed)).then_some(asked)
    }

    /// Answers reset `n`: whether there was a fault to clear.
    #[inline]
    pub fn finish_clear(&self, n: u64, cleared: bool) {
        self.clear_result.store(u32::from(cleared), Relaxed);
        self.clear_done.store(n, std::sync::atomic::Ordering::Release);
    }

    /// Records what real-time setup achieved (before the loop's first tick).
    pub fn set_realtime(&self, r: &crate::rt::RtReport) {
        self.rt_fifo_priority.store(r.fifo_priority.unwrap_or(0), Relaxed);
        self.rt_memory_locked.store(r.locked_memory, Relaxed);
        self.rt_cpu.store(r.pinned_cpu.map_or(-1, |c| c as i64), Relaxed);
        self.rt_refused.store(!r.problems.is_empty(), Relaxed);
    }

    /// "fifo 80, cpu 3, memory locked", with what was refused named.
    pub fn realtime_line(&self) -> String {
        let prio = self.rt_fifo_priority.load(Relaxed);
        let cpu = self.rt_cpu.load(Relaxed);
        format!(
            "{}{}, {}, {}",
            if self.rt_refused.load(Relaxed) { "NOT ALL GRANTED: " } else { "" },
            if prio > 0 { format!("fifo {prio}") } else { "no fifo".into() },
            if cpu >= 0 { format!("cpu {cpu}") } else { "not pinned".into() },
            if self.rt_memory_locked.load(Relaxed) { "memory locked" } else { "memory not locked" },
        )
    }

    /// One line for systemd's STATUS= and logs.
    pub fn status_line(&self) -> String {
        let fault = self.fault.load(Relaxed);
        format!(
            "ticks {} missed {} wake max {:.0} us (last s) robot side {} fault {} limit violations {} rt {}",
            self.ticks.load(Relaxed),
            self.overruns.load(Relaxed),
            self.wake_max_ns.load(Relaxed) as f64 / 1e3,
            if fault & FAULT_ROBOT_LOST != 0 { "LOST" } else { "ok" },
            if fault & FAULT_OPERATOR != 0 { "operator_required" } else { "none" },
            self.limit_violations.load(Relaxed),
            self.realtime_line(),
        )
    }

    /// Milliseconds since the last robot state.
    pub fn state_age_ms(&self) -> f64 {
        ipc_schema::monotonic_ns().saturating_sub(self.last_state_ns.load(Relaxed)) as f64 / 1e6
    }
}

/// The systemd notifier: `READY=1` once the first control cycle has completed, then every half
/// watchdog interval `WATCHDOG=1` if (and only if) the loop's cycle counter advanced since the
/// last ping, `STATUS=` with the tick figures every second, and `STOPPING=1` when the loop ends.
/// Does nothing without `$NOTIFY_SOCKET`. Start it before the loop thread raises itself to
/// SCHED_FIFO, so this thread keeps the normal scheduler.
pub fn spawn_notifier(health: Arc<Health>) -> Option<std::thread::JoinHandle<()>> {
    std::env::var_os("NOTIFY_SOCKET")?;
    let mut usec = 0u64;
    let watchdog = sd_notify::watchdog_enabled(false, &mut usec).then_some(usec);
    health.watchdog_usec.store(watchdog.unwrap_or(0), Relaxed);
    std::thread::Builder::new().name("sd-notify".into()).spawn(move || notifier(&health, watchdog)).ok()
}

fn notifier(health: &Health, watchdog_usec: Option<u64>) {
    use sd_notify::NotifyState;
    let send = |states: &[NotifyState]| {
        if let Err(e) = sd_notify::notify(false, states) {
            eprintln!("r2g-control: sd_notify: {e}");
        }
    };
    // Ready once a cycle has completed: the services exist and the robot side answered.
    while health.cycles.load(Relaxed) == 0 {
        if health.stopping.load(Relaxed) {
            send(&[NotifyState::Stopping]);
            return;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let ready = format!("first control cycle done; {}", health.status_line());
    send(&[NotifyState::Ready, NotifyState::Status(&ready)]);

    let ping_every = watchdog_usec.map_or(Duration::from_secs(1), |u| Duration::from_micros(u / 2));
    let status_every = Duration::from_secs(1);
    let mut last_cycles = health.cycles.load(Relaxed);
    let mut next_ping = std::time::Instant::now() + ping_every;
    let mut next_status = std::time::Instant::now() + status_every;
    loop {
        let now = std::time::Instant::now();
        let wake = next_ping.min(next_status);
        if wake > now {
            std::thread::sleep((wake - now).min(Duration::from_millis(20)));
        }
        if health.stopping.load(Relaxed) {
            send(&[NotifyState::Stopping, NotifyState::Status("stopping")]);
            return;
        }
        let now = std::time::Instant::now();
        if now >= next_ping {
            next_ping += ping_every;
            if next_ping < now {
                next_ping = now + ping_every;
            }
            let cycles = health.cycles.load(Relaxed);
            // A loop that stopped cycling (stalled, deadlocked, starved) gets no ping, and
            // systemd's watchdog acts after WatchdogSec.
            if watchdog_usec.is_some() && cycles != last_cycles {
                send(&[NotifyState::Watchdog]);
            }
            last_cycles = cycles;
        }
        if now >= next_status {
            next_status += status_every;
            if next_status < now {
                next_status = now + status_every;
            }
            send(&[NotifyState::Status(&health.status_line())]);
        }
    }
}
