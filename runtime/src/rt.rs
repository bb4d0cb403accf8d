//! Real-time setup and the absolute-deadline clock.

/// What real-time setup achieved.
#[derive(Debug, Default, Clone)]
pub struct RtReport {
    pub locked_memory: bool,
    pub fifo_priority: Option<i32>,
    pub pinned_cpu: Option<usize>,
    pub problems: Vec<String>,
}

impl RtReport {
    /// One line naming everything that was not granted, or None when all was.
    pub fn warning(&self) -> Option<String> {
        if self.problems.is_empty() {
            None
        } else {
            Some(format!("warning: running without full real-time setup: {}", self.problems.join("; ")))
        }
    }
}

/// Locks memory, switches the calling thread to SCHED_FIFO and pins it, as far as permitted.
pub fn setup(fifo_priority: Option<i32>, cpu: Option<usize>) -> RtReport {
    let mut r = RtReport::default();
    // SAFETY: plain syscalls with valid arguments.
    unsafe {
        if libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) == 0 {
            r.locked_memory = true;
        } else {
            r.problems.push(format!("mlockall failed ({})", std::io::Error::last_os_error()));
        }
        if let Some(prio) = fifo_priority {
            let param = libc::sched_param { sched_priority: prio };
            if libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) == 0 {
                r.fifo_priority = Some(prio);
            } else {
                r.problems.push(format!("SCHED_FIFO {prio} refused ({})", std::io::Error::last_os_error()));
            }
        }
    }
    if let Some(cpu) = cpu {
        let ids = core_affinity::get_core_ids().unwrap_or_default();
        match ids.into_iter().find(|c| c.id == cpu) {
            Some(core) if core_affinity::set_for_current(core) => r.pinned_cpu = Some(cpu),
            _ => r.problems.push(format!("cannot pin to CPU {cpu}")),
        }
    }
    r
}

/// The highest-numbered CPU this process may run on (a good default for the tick thread).
pub fn last_cpu() -> Option<usize> {
    core_affinity::get_core_ids().and_then(|ids| ids.iter().map(|c| c.id).max())
}

pub fn now_ns() -> u64 {
    ipc_schema::monotonic_ns()
}

/// Sleeps until an absolute CLOCK_MONOTONIC deadline; optionally spins the last `spin_ns`.
#[inline]
pub fn sleep_until(deadline_ns: u64, spin_ns: u64) {
    let sleep_to = deadline_ns.saturating_sub(spin_ns);
    let ts = libc::timespec {
        tv_sec: (sleep_to / 1_000_000_000) as libc::time_t,
        tv_nsec: (sleep_to % 1_000_000_000) as libc::c_long,
    };
    // SAFETY: valid timespec; EINTR just returns early and the loop below or the caller copes.
    unsafe {
        while libc::clock_nanosleep(libc::CLOCK_MONOTONIC, libc::TIMER_ABSTIME, &ts, std::ptr::null_mut())
            == libc::EINTR
        {}
    }
    while spin_ns > 0 && now_ns() < deadline_ns {
        std::hint::spin_loop();
    }
}
