//! r2g-control with a stall hook, for the watchdog test only (`cargo test` builds examples;
//! nothing installs this one). SIGUSR1 makes the loop thread alone sleep for
//! `$R2G_TEST_STALL_MS` (default 3000) after its current cycle, while the process's other
//! threads (the systemd notifier among them) keep running: SIGSTOP would stop them all and
//! prove nothing about the watchdog.

use std::sync::atomic::{AtomicBool, Ordering};

#[global_allocator]
static ALLOC: runtime::alloc_count::CountingAlloc = runtime::alloc_count::CountingAlloc;

static STALL: AtomicBool = AtomicBool::new(false);

extern "C" fn on_usr1(_: libc::c_int) {
    STALL.store(true, Ordering::SeqCst);
}

fn stall_if_asked() {
    if STALL.swap(false, Ordering::SeqCst) {
        let ms = std::env::var("R2G_TEST_STALL_MS").ok().and_then(|v| v.parse().ok()).unwrap_or(3000);
        std::thread::sleep(std::time::Duration::from_millis(ms));
    }
}

fn main() {
    // SAFETY: the handler only stores to an atomic.
    unsafe {
        libc::signal(libc::SIGUSR1, on_usr1 as *const () as libc::sighandler_t);
    }
    std::process::exit(runtime::control_main::main(Some(stall_if_asked)));
}
