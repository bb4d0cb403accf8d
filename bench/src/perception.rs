//! `r2g bench perception`: the local perception library over the pack's graspable objects at
//! 640×480: segmentation IoU against MuJoCo's own segmentation of the same model and state, lift
//! rate of the worked example program judged from the sim-host's native trace, and segmentation
//! and grasp-proposal times beside a back-projection baseline; robot parts reported as objects;
//! and what it says about objects the hand acts on, against MuJoCo's truth: a held block lifted
//! (box bottom), a block put on the plate (plate top, block bottom, `on` against the judge), a
//! block pushed by part-open fingers (`held`), the cabinet door from the wrist camera up close (one
//! panel, no stolen track ids), and a tape line's markings (`bench/py/perception_bench.py`).

use anyhow::Context;
use runtime::launch;
use serde_json::Value;

pub fn run(gyms: &[String], lift: bool) -> anyhow::Result<Value> {
    let (python, script) = crate::tick::python_script("perception_bench.py")?;
    let mut cmd = crate::tick::python_command(&python, &script);
    if !gyms.is_empty() {
        cmd.arg("--gyms").arg(gyms.join(","));
    }
    if !lift {
        cmd.arg("--no-lift");
    }
    let exe = std::env::current_exe().context("locating r2g")?;
    let out = cmd
        .env("R2G_BIN", exe)
        .env("R2G_GYMS", launch::gyms_dir())
        .stderr(std::process::Stdio::inherit())
        .output()
        .context("running bench/py/perception_bench.py")?;
    crate::tick::script_figures(&out, "perception_bench.py")
}
