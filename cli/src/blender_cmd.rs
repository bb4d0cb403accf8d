//! `r2g blender`: arguments and printing. The export of the compiled scene (drawn geoms,
//! cameras, lights, per-sample body poses), the demonstration replayed for a trace, Blender's run
//! and its renders are `real2sim::blender`.

use std::path::PathBuf;

use anyhow::{bail, Context};
use real2sim::blender;
use serde_json::json;
use sim_host::Sim;

#[derive(clap::Args, Debug)]
pub struct BlenderArgs {
    /// Gym name, gym folder, or scene file.
    pub gym: String,
    /// A native trace of this gym (`r2g replay` writes `<gym>-seed<N>.trace.json`; `r2g
    /// validate --keep-trace` writes trace.json). Without it the gym's demonstration is replayed
    /// in lockstep (seed 0), or the scene is shown at rest when it has none.
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// The .blend file to write.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub render: RenderArgs,
}

#[derive(clap::Args, Debug, Clone)]
pub struct RenderArgs {
    /// Also render with Cycles (CPU) into this folder (BOP scene layout: scene_camera.json,
    /// rgb/, mask_visib/ from flat per-object colours, timing.json).
    #[arg(long)]
    pub render: Option<PathBuf>,
    /// Cameras to render (default: every camera of the scene).
    #[arg(long = "camera")]
    pub cameras: Vec<String>,
    /// Use the cameras of this BOP scene_camera.json instead of the scene's (per image: cam_K,
    /// cam_R_w2c, cam_t_w2c in mm with the robot base as the world, and "width", "height"; as
    /// `r2g render --cameras`). Each image id becomes a camera named bop_<id>, and with --render
    /// every one is rendered at every --at instant.
    #[arg(long = "cameras", value_name = "SCENE_CAMERA_JSON")]
    pub cameras_file: Option<PathBuf>,
    /// Instants to render, seconds of simulated time (the nearest trace sample each).
    #[arg(long, value_delimiter = ',')]
    pub at: Vec<f64>,
    /// Cycles samples per pixel of the RGB images.
    #[arg(long, default_value_t = 16)]
    pub samples: u32,
    /// Image size as a percentage of each camera's resolution (intrinsics scale with it).
    #[arg(long, default_value_t = 50)]
    pub percent: u32,
}

pub fn run(a: BlenderArgs) -> anyhow::Result<i32> {
    if a.out.extension().and_then(|e| e.to_str()) != Some("blend") {
        bail!("--out {}: name a .blend file", a.out.display());
    }
    if a.render.render.is_none() && (!a.render.cameras.is_empty() || !a.render.at.is_empty()) {
        bail!("--camera and --at choose what --render renders: give --render <dir> with them");
    }
    if a.render.cameras_file.is_some() && !a.render.cameras.is_empty() {
        bail!("--camera picks scene cameras; with --cameras FILE every image of the file is rendered: give one or the other");
    }
    let scene_path = runtime::launch::resolve_scene(&a.gym)?;
    let mut sim = Sim::load(&scene_path).with_context(|| format!("compiling {}", scene_path.display()))?;
    // The camera file is read (and refused) before anything is replayed or written.
    let labels = match &a.render.cameras_file {
        Some(file) => {
            let (s, labels) = blender::with_bop_cameras(&sim, file)?;
            sim = s;
            Some(labels)
        }
        None => None,
    };
    if let Some(parent) = a.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    let motion = blender::motion(&sim, &scene_path, a.trace.as_deref())?;
    let mut doc = blender::export(&mut sim, &motion)?;
    if let Some(l) = &labels {
        blender::label_cameras(&mut doc, l)?;
    }
    let r = &a.render;
    let summary = match &r.render {
        Some(dir) => {
            blender::render_to(&doc, Some(&a.out), motion.states(), &r.cameras, &r.at, r.samples, r.percent, dir)?
        }
        None => blender::run_blender(&doc, Some(&a.out), None)?,
    };
    println!(
        "{}",
        json!({
            "blend": a.out,
            "gym": sim.scene.name,
            "source": motion.source,
            "frames": motion.states().len(),
            "sim_time_s": motion.states().last().map(|s| s.t_s),
            "geoms": doc["geoms"].as_array().map(Vec::len),
            "meshes": doc["meshes"].as_array().map(Vec::len),
            "bodies": doc["bodies"].as_array().map(Vec::len),
            "cameras": doc["cameras"].as_array().map(Vec::len),
            "camera_file": r.cameras_file,
            "render": r.render,
            "blender": summary,
        })
    );
    Ok(0)
}
