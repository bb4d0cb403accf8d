//! `r2g-robotiq`: a Robotiq 2F-85 as an instance's gripper (see this crate's README).

use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;

#[derive(Parser, Debug)]
#[command(name = "r2g-robotiq", about = "Drives a Robotiq 2F-85 over Modbus RTU as the gripper of an r2g instance")]
struct Args {
    #[arg(long, default_value = "default")]
    instance: String,
    /// config/robot.json: its "gripper" table names the port and the settings.
    #[arg(long)]
    robot_config: PathBuf,
    /// Status poll period, ms, 2 to 100 (each poll is one Modbus exchange of about 2 ms at
    /// 115200 baud; the runtime holds the arm after 250 ms without a word from this driver).
    #[arg(long, default_value_t = 10)]
    poll_ms: u64,
    /// Write the run's figures here as JSON: when it ends, and within a second of a line error
    /// or a lost link while it runs. Without it, the environment's R2G_ROBOTIQ_STATS_OUT (how
    /// tests and benches reach the driver `r2g up` starts).
    #[arg(long)]
    stats_out: Option<PathBuf>,
}

fn main() {
    if let Err(e) = run() {
        eprintln!("r2g-robotiq: error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    let a = Args::parse();
    ipc_schema::process::install_stop_signals();
    ipc_schema::process::die_with_parent();
    let max_ms = gripper::MAX_POLL.as_millis() as u64;
    anyhow::ensure!((2..=max_ms).contains(&a.poll_ms), "--poll-ms must be within 2..={max_ms}, got {}", a.poll_ms);
    let stats_out = a.stats_out.or_else(|| std::env::var_os("R2G_ROBOTIQ_STATS_OUT").map(PathBuf::from));
    let config = runtime::RobotConfig::load(&a.robot_config)?;
    let runtime::robot_config::Gripper::Robotiq2f85(cfg) = &config.gripper else {
        anyhow::bail!(
            "{} names the gripper \"{}\", not robotiq_2f85: nothing for r2g-robotiq to drive",
            a.robot_config.display(),
            config.gripper.driver()
        );
    };
    let stats = gripper::run(&a.instance, cfg, Duration::from_millis(a.poll_ms), stats_out.as_deref())?;
    // One line with the run's figures (journal, `r2g up`'s log, `bench/py/rig_bench.py`).
    eprintln!("r2g-robotiq: stats {}", stats.to_json());
    if let Some(p) = stats_out {
        stats.write(&p)?;
    }
    Ok(())
}
