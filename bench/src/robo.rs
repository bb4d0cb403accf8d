//! `r2g bench robo`: Python round-trip latency of `robo.get_state` (numeric state only, with two
//! PNGs, raw arrays with depth) and `post_actions` submission → acceptance → first motion,
//! against a live wall-mode instance, beside a Unix-socket baseline shipping the same state and
//! images between two Python processes in the same run (`bench/py/robo_bench.py`).

use std::time::Duration;

use anyhow::{bail, Context};
use ipc_schema::Mode;
use runtime::launch::{self, Instance, UpOptions};
use serde_json::Value;

pub fn run(gym: &str, samples: usize) -> anyhow::Result<Value> {
    if !(100..=1_000_000).contains(&samples) {
        bail!("--samples must be in 100..=1000000");
    }
    let (python, script) = crate::tick::python_script("robo_bench.py")?;
    let opts = UpOptions {
        scene: launch::resolve_scene(gym)?,
        instance: format!("benchrobo{}", std::process::id()),
        mode: Mode::Wall,
        render_hz: 10.0,
        control_args: Vec::new(),
        sim_args: Vec::new(),
        robot_config: None,
        ready_timeout: Duration::from_secs(60),
    };
    let mut inst = Instance::up(&opts)?;
    let out = crate::tick::python_command(&python, &script)
        .arg(samples.to_string())
        .env("R2G_INSTANCE", &inst.name)
        .stderr(std::process::Stdio::inherit())
        .output()
        .context("running bench/py/robo_bench.py");
    inst.stop();
    let out = out?;
    crate::tick::script_figures(&out, "robo_bench.py")
}
