//! `r2g-robotiq`: a Robotiq 2F-85 as an instance's gripper (see this crate's README).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;

#[derive(Parser, Debug)]
#[command(name = "r2g-robotiq", about = "Drives a Robotiq 2F-85 over Modbus RTU as the gripper of an r2g instance")]
struct Args {
    #[arg(long, default_value = "default")]
    instance: String,
    /// config/robot.json: its "gripper" table names the port and the settings.
    #[arg(long)]
    robot_config: PathBuf,
    /// Status poll period, ms (each poll is one Modbus exchange of about 2 ms at 115200 baud).
    #[arg(long, default_value_t = 10)]
    poll_ms: u64,
    /// Write the run's figures here as JSON when it ends.
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
    anyhow::ensure!((2..=1000).contains(&a.poll_ms), "--poll-ms must be within 2..=1000");
    let config = runtime::RobotConfig::load(&a.robot_config)?;
    let runtime::robot_config::Gripper::Robotiq2f85(cfg) = &config.gripper else {
        anyhow::bail!(
            "{} names the gripper \"{}\", not robotiq_2f85: nothing for r2g-robotiq to drive",
            a.robot_config.display(),
            config.gripper.driver()
        );
    };
    let stats = gripper::run(&a.instance, cfg, Duration::from_millis(a.poll_ms))?;
    let json = stats.to_json();
    // One line with the run's figures (journal, `r2g up`'s log, `bench/py/robotiq_bench.py`).
    eprintln!("r2g-robotiq: stats {json}");
    if let Some(p) = a.stats_out {
        let tmp = p.with_extension("tmp");
        std::fs::write(&tmp, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, &p).with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}
