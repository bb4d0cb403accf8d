//! r2g-control's command line: arguments, checks, and the run.

use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};
use ipc_schema::process;
use ipc_schema::Mode;

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ModeArg {
    /// 1 kHz on the wall clock (absolute deadlines on CLOCK_MONOTONIC).
    Wall,
    /// Advance with the simulator on simulated time, as fast as the machine allows, and only
    /// while a request is executing.
    Lockstep,
}

/// Control process: turns agents' action chunks into a limited 1 kHz joint command stream
/// for r2g-sim (or a real arm). Normally started by `r2g up`, not by hand.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Scene file of the gym; its [robot] table names the URDF and TCP link.
    scene: PathBuf,
    #[arg(long, default_value = "default")]
    instance: String,
    #[arg(long, value_enum, default_value_t = ModeArg::Wall)]
    mode: ModeArg,
    /// Tick period in microseconds.
    #[arg(long, default_value_t = 1000)]
    period_us: u64,
    /// Busy-wait this many microseconds before each deadline to cut wake-up jitter.
    #[arg(long, default_value_t = 0)]
    spin_us: u64,
    /// SCHED_FIFO priority for the tick thread (0 keeps the normal scheduler).
    #[arg(long, default_value_t = 80)]
    fifo_priority: i32,
    /// CPU to pin the tick thread to (default: the last one).
    #[arg(long)]
    cpu: Option<usize>,
    /// Stop after this many seconds (default: run until SIGINT/SIGTERM).
    #[arg(long)]
    duration_s: Option<f64>,
    /// Profile and limits (`robot-skill/config/robot.json`); without it, the shipped defaults
    /// (simulation profile).
    #[arg(long)]
    robot_config: Option<PathBuf>,
    /// Write the tick statistics as JSON here on exit.
    #[arg(long)]
    stats_out: Option<PathBuf>,
    /// Wall mode: the robot side counts as lost after this many milliseconds without state;
    /// the arm holds, requests are refused with the reason, and the loop keeps cycling.
    #[arg(long, default_value_t = 100)]
    state_timeout_ms: u64,
    /// Members of this group may clear faults (`r2g clear`), besides root and this process's
    /// own user.
    #[arg(long)]
    operator_group: Option<String>,
}

/// The whole of r2g-control (its `main`); `after_cycle` is for test builds only (see
/// [`crate::RunConfig::after_cycle`]). Returns the exit code.
pub fn main(after_cycle: Option<fn()>) -> i32 {
    let args = Args::parse();
    if !(100..=10_000).contains(&args.period_us) || args.spin_us >= args.period_us {
        eprintln!("r2g-control: --period-us must be 100..=10000 and --spin-us below it");
        return 2;
    }
    if args.duration_s.is_some_and(|d| !(d.is_finite() && d > 0.0 && d < 1e7)) {
        eprintln!("r2g-control: --duration-s must be a positive number of seconds");
        return 2;
    }
    if std::env::var_os("R2G_ABORT_ON_TICK_ALLOC").is_some_and(|v| v == "1") {
        crate::alloc_count::ABORT_ON_SYSTEM_ALLOC.store(true, std::sync::atomic::Ordering::Relaxed);
    }
    if !(1..=60_000).contains(&args.state_timeout_ms) {
        eprintln!("r2g-control: --state-timeout-ms must be 1..=60000");
        return 2;
    }
    if let Err(e) = ipc_schema::ipc_config() {
        eprintln!("r2g-control: error: {e}");
        return 2;
    }
    let robot = match &args.robot_config {
        Some(p) => match crate::RobotConfig::load(p) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("r2g-control: error: {e:#}");
                return 2;
            }
        },
        None => crate::RobotConfig::default(),
    };
    let calibration = match crate::calibration::Calibration::load(&robot.calibration) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("r2g-control: error: {e:#}");
            return 2;
        }
    };
    // The bytes the configuration was read from (a second read: the file is small and read once).
    let config_bytes = match args.robot_config.as_ref().map(std::fs::read).transpose() {
        Ok(b) => b,
        Err(e) => {
            eprintln!("r2g-control: error: reading the robot config again: {e}");
            return 2;
        }
    };
    let setup = crate::setup_report(&args.scene, config_bytes.as_deref());
    process::install_stop_signals();
    process::die_with_parent();
    let cfg = crate::RunConfig {
        instance: args.instance.clone(),
        mode: match args.mode {
            ModeArg::Wall => Mode::Wall,
            ModeArg::Lockstep => Mode::Lockstep,
        },
        scene: args.scene.clone(),
        period_ns: args.period_us * 1000,
        spin_ns: args.spin_us * 1000,
        fifo_priority: (args.fifo_priority > 0).then_some(args.fifo_priority),
        cpu: args.cpu.or_else(crate::rt::last_cpu),
        duration: args.duration_s.map(Duration::from_secs_f64),
        state_timeout: Duration::from_millis(args.state_timeout_ms),
        operator_group: args.operator_group.clone(),
        after_cycle,
        robot,
        calibration,
        setup,
    };
    match crate::run(&cfg) {
        Ok(stats) => {
            if let Some(p) = &args.stats_out {
                let tmp = p.with_extension("json.tmp");
                if let Err(e) = std::fs::write(&tmp, stats.to_json().to_string()).and_then(|_| std::fs::rename(&tmp, p))
                {
                    eprintln!("r2g-control: cannot write {}: {e}", p.display());
                }
            }
        }
        Err(e) => {
            eprintln!("r2g-control: error: {e:#}");
            return 1;
        }
    }
    0
}
