//! `r2g compare`: arguments and printing; the comparison (renders, silhouette IoU, the sheet) is
//! `real2sim::compare`. MuJoCo's renders come from this binary's own `r2g render`, run as a
//! child process.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context};

#[derive(clap::Args, Debug)]
pub struct CompareArgs {
    /// Gym name, gym folder, or scene file.
    pub gym: String,
    /// Instants to compare, seconds of simulated time (each the nearest trace sample). With
    /// --frames, the instant of every source image that does not carry its own (`r2g_t_s`);
    /// default 0.
    #[arg(long, value_delimiter = ',')]
    pub at: Vec<f64>,
    /// Cameras of the scene to compare (default: every camera). Not with --frames, whose
    /// images bring their own cameras.
    #[arg(long = "camera")]
    pub cameras: Vec<String>,
    /// A native trace of this gym (default: its demonstration replayed in lockstep, or the
    /// scene at rest without one).
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// Source frames in the BOP scene layout (scene_camera.json, rgb/): each image is compared
    /// with both renders from its own camera (intrinsics and pose).
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// The sheet to write (PNG). Beside it: `<stem>.json` (layout, IoU, times) and
    /// `<stem>.renders/` (both renderers' BOP folders).
    #[arg(long)]
    pub out: PathBuf,
    /// Cycles samples per pixel of Blender's images (the masks always take one, at each pixel's
    /// centre).
    #[arg(long, default_value_t = 8)]
    pub samples: u32,
    /// Blender's image size as a percentage of the camera's. IoU is computed at that size, with
    /// MuJoCo's masks resampled to it; below 100 the resampling alone costs small objects a few
    /// points of IoU.
    #[arg(long, default_value_t = 100)]
    pub percent: u32,
}

/// Runs `r2g render` (this binary) and returns its output folder.
fn mujoco_render(
    gym: &str,
    trace: &Path,
    at: &[f64],
    cameras: &[String],
    bop: Option<&Path>,
    out: &Path,
) -> anyhow::Result<()> {
    let exe = std::env::current_exe().context("finding the r2g binary")?;
    let mut cmd = Command::new(&exe);
    cmd.arg("render").arg(gym).arg("--out").arg(out).arg("--trace").arg(trace);
    cmd.arg("--at").arg(at.iter().map(|t| format!("{t}")).collect::<Vec<_>>().join(","));
    for c in cameras {
        cmd.arg("--camera").arg(c);
    }
    if let Some(b) = bop {
        cmd.arg("--cameras").arg(b);
    }
    let o = cmd.output().with_context(|| format!("running {} render", exe.display()))?;
    if !o.status.success() {
        bail!("r2g render failed ({}): {}", o.status, String::from_utf8_lossy(&o.stderr).trim());
    }
    Ok(())
}

pub fn run(a: CompareArgs) -> anyhow::Result<i32> {
    let o = real2sim::compare::Options {
        gym: a.gym,
        at: a.at,
        cameras: a.cameras,
        trace: a.trace,
        frames: a.frames,
        out: a.out,
        samples: a.samples,
        percent: a.percent,
    };
    let report = real2sim::compare::run(&o, &mujoco_render)?;
    println!("{}", serde_json::to_string(&report)?);
    Ok(0)
}
