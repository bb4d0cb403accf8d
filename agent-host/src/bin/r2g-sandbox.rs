//! r2g-sandbox: confines itself (see `agent_host::sandbox`) and then executes the worker.
//!
//! `r2g-sandbox POLICY_JSON STATUS_FD PROGRAM [ARGS...]`. Writes one JSON line saying what was
//! enforced to STATUS_FD (then closes it), or `{"error": ...}` and exits 126 when confinement
//! failed; nothing unconfined is ever executed. Started by the agent host, not by hand.

use std::io::Write;
use std::os::fd::FromRawFd;
use std::os::unix::process::CommandExt;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        eprintln!("usage: r2g-sandbox POLICY_JSON STATUS_FD PROGRAM [ARGS...]");
        std::process::exit(2);
    }
    let Ok(fd) = args[2].parse::<i32>() else {
        eprintln!("r2g-sandbox: STATUS_FD must be a number");
        std::process::exit(2);
    };
    if fd < 3 {
        eprintln!("r2g-sandbox: STATUS_FD must be 3 or above");
        std::process::exit(2);
    }
    // SAFETY: the host hands us this descriptor open for writing; we own it from here.
    let mut status = unsafe { std::fs::File::from_raw_fd(fd) };
    let result = serde_json::from_str::<agent_host::sandbox::Policy>(&args[1])
        .map_err(anyhow::Error::from)
        .and_then(|p| agent_host::sandbox::confine(&p));
    match result {
        Ok(enforced) => {
            let _ = writeln!(status, "{}", serde_json::json!({ "enforced": enforced }));
            drop(status);
            let err = std::process::Command::new(&args[3]).args(&args[4..]).exec();
            eprintln!("r2g-sandbox: cannot execute {}: {err}", args[3]);
            std::process::exit(127);
        }
        Err(e) => {
            let _ = writeln!(status, "{}", serde_json::json!({ "error": format!("{e:#}") }));
            std::process::exit(126);
        }
    }
}
