//! `r2g-fci`: a real Franka arm as an instance's robot side (see this crate's README).

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;

#[derive(Parser, Debug)]
#[command(name = "r2g-fci", about = "Serves a Franka arm over FCI as the robot side of an r2g instance")]
struct Args {
    /// Scene file (its [robot] table: URDF and TCP link for the reported TCP pose).
    scene: PathBuf,
    #[arg(long, default_value = "default")]
    instance: String,
    /// The robot's FCI address: host or host:port.
    #[arg(long)]
    robot: String,
    /// config/robot.json: collision thresholds and the reflex window (its "franka" table).
    #[arg(long)]
    robot_config: Option<PathBuf>,
    /// How long after a robot state the runtime's command may arrive and still be sent, µs
    /// (100..=900: within the robot's 1 ms cycle, before its next state).
    #[arg(long, default_value_t = 700)]
    reply_budget_us: u64,
    /// Robot cycles in a row without the runtime's answer before the motion is finished.
    #[arg(long, default_value_t = 10)]
    max_missed: u32,
    /// Also drive the Franka Hand (port 1338 of the same host); the robot config's
    /// `"gripper": {"driver": "franka_hand"}` does the same.
    #[arg(long)]
    gripper: bool,
    /// Require a real-time kernel.
    #[arg(long)]
    realtime: bool,
    /// The FCI version the robot must speak (5: Panda, 10: FR3); by default what it announces.
    #[arg(long)]
    fci_version: Option<u16>,
    /// Write the run's figures here as JSON when it ends.
    #[arg(long)]
    stats_out: Option<PathBuf>,
}

fn main() {
    if let Err(e) = run() {
        eprintln!("r2g-fci: error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    let a = Args::parse();
    ipc_schema::process::install_stop_signals();
    ipc_schema::process::die_with_parent();
    anyhow::ensure!(
        (100..=900).contains(&a.reply_budget_us),
        "--reply-budget-us must be within 100..=900 (an answer must leave before the robot's next state, 1 ms later)"
    );
    anyhow::ensure!(
        (1..=19).contains(&a.max_missed),
        "--max-missed must be within 1..=19 (the robot's own limit is 20)"
    );
    let config = match &a.robot_config {
        Some(p) => runtime::RobotConfig::load(p)?,
        None => runtime::RobotConfig::default(),
    };
    if let (true, runtime::robot_config::Gripper::Robotiq2f85(r)) = (a.gripper, &config.gripper) {
        anyhow::bail!(
            "--gripper drives a Franka Hand, but the robot config names a Robotiq 2F-85 on {} (r2g-robotiq drives \
             it): drop --gripper, or name \"franka_hand\" in the config",
            r.port.display()
        );
    }
    let opts = fci::Options {
        instance: a.instance,
        scene: a.scene,
        address: a.robot,
        reflexes: config.reflexes,
        reply_budget_us: a.reply_budget_us,
        max_missed: a.max_missed,
        gripper: a.gripper || config.gripper == runtime::robot_config::Gripper::FrankaHand,
        cameras: config.cameras.iter().map(|c| c.name.clone()).collect(),
        realtime: a.realtime,
        fci_version: a.fci_version,
    };
    let stats = fci::run(&opts)?;
    let json = stats.to_json();
    eprintln!("r2g-fci: {json}");
    if let Some(p) = a.stats_out {
        let tmp = p.with_extension("tmp");
        std::fs::write(&tmp, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, &p).with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}
