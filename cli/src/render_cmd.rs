//! `r2g render`: a gym rendered by the sim-host's MuJoCo renderer into a BOP scene folder
//! (`sim_host::bop`): the scene at rest after reset, or the states of a native trace at given
//! times, from the scene's cameras or from the cameras of a BOP `scene_camera.json`.

use std::path::PathBuf;

use anyhow::{bail, Context};
use sim_host::bop::{self, Shooter};
use sim_host::trace::Trace;
use sim_host::Sim;

#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    /// Gym name, gym folder, or scene file.
    pub gym: String,
    /// The folder to write (BOP scene layout); written whole or not at all.
    #[arg(long)]
    pub out: PathBuf,
    /// A scene camera to render (repeatable; default: every camera of the scene).
    #[arg(long = "camera")]
    pub cameras: Vec<String>,
    /// Render from the cameras of this BOP scene_camera.json instead (per image: cam_K,
    /// cam_R_w2c, cam_t_w2c in mm with the robot base as the world, and "width", "height").
    #[arg(long = "cameras", value_name = "SCENE_CAMERA_JSON")]
    pub cameras_file: Option<PathBuf>,
    /// A native trace of this gym (`r2g replay`, `r2g validate --keep-trace`); with --at.
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// Times to render from the trace, seconds of simulated time (the nearest sample each).
    #[arg(long, value_delimiter = ',')]
    pub at: Vec<f64>,
    #[command(flatten)]
    pub placement: crate::PlacementArgs,
}

/// Half the trace's sample period: how far outside the recorded span a time may ask.
const TRACE_SLACK_S: f64 = 0.005;

pub fn run(a: RenderArgs) -> anyhow::Result<i32> {
    a.placement.check()?;
    let scene_path = runtime::launch::resolve_scene(&a.gym)?;
    let trace = match (&a.trace, a.at.is_empty()) {
        (Some(p), false) => {
            if a.placement.seed != 0 || a.placement.perturb.is_some() {
                bail!("--seed and --perturb place the objects at rest; a trace holds its own placement: give one or the other");
            }
            let text = std::fs::read_to_string(p).with_context(|| format!("cannot read --trace {}", p.display()))?;
            let t: Trace = serde_json::from_str(&text)
                .map_err(|e| anyhow::anyhow!("--trace {}: not a native trace: {e}", p.display()))?;
            Some(t)
        }
        (Some(_), true) => bail!("--trace needs --at T[,T...]: the times to render, seconds of simulated time"),
        (None, false) => bail!("--at needs --trace: the times are times of a native trace"),
        (None, true) => None,
    };
    if a.cameras_file.is_some() && !a.cameras.is_empty() {
        bail!("--camera picks scene cameras; with --cameras FILE every image of the file is rendered: give one or the other");
    }
    let mut sim = Sim::load(&scene_path).with_context(|| format!("compiling {}", scene_path.display()))?;
    // The cameras: the scene's (all, or those named), or the file's compiled into the scene.
    let (cameras, labels): (Vec<usize>, Option<Vec<String>>) = match &a.cameras_file {
        Some(file) => {
            let bop = bop::read_scene_camera(file).map_err(|e| anyhow::anyhow!(e))?;
            let world_from_base = sim.world_from_base();
            let mut scene = sim.scene.clone();
            scene.cameras = bop
                .iter()
                .map(|c| bop::camera_spec(c, world_from_base))
                .collect::<Result<_, _>>()
                .map_err(|e| anyhow::anyhow!(e))?;
            sim = Sim::from_scene(scene).with_context(|| {
                format!("compiling {} with the cameras of {}", scene_path.display(), file.display())
            })?;
            ((0..bop.len()).collect(), Some(bop.iter().map(|c| c.id.clone()).collect()))
        }
        None if a.cameras.is_empty() => ((0..sim.scene.cameras.len()).collect(), None),
        None => {
            let names: Vec<&str> = sim.scene.cameras.iter().map(|c| c.name.as_str()).collect();
            let mut picked = Vec::new();
            for n in &a.cameras {
                match names.iter().position(|c| c == n) {
                    Some(i) => picked.push(i),
                    None => bail!(
                        "--camera {n}: scene '{}' has no such camera (it has {})",
                        sim.scene.name,
                        names.join(", ")
                    ),
                }
            }
            (picked, None)
        }
    };
    if cameras.is_empty() {
        bail!("scene '{}' has no cameras to render", sim.scene.name);
    }
    let mut shooter = Shooter::new(&sim);
    let mut images = Vec::new();
    match &trace {
        None => {
            sim.seed = a.placement.seed;
            sim.set_perturbation(a.placement.perturb.clone()).map_err(|e| anyhow::anyhow!("--perturb: {e}"))?;
            if let Some(note) = sim.placed.as_ref().and_then(|p| p.note.clone()) {
                eprintln!("note: {note}");
            }
            images.extend(shooter.shoot(&sim, &cameras, labels.as_deref())?);
        }
        Some(t) => {
            let at =
                |what: String| anyhow::anyhow!("--trace {}: {what}", a.trace.clone().unwrap_or_default().display());
            if t.gym != sim.scene.name {
                bail!(at(format!("recorded in gym '{}', not in '{}'", t.gym, sim.scene.name)));
            }
            let (Some(first), Some(last)) = (t.samples.first(), t.samples.last()) else {
                bail!(at("has no samples".into()))
            };
            for &when in &a.at {
                if !when.is_finite() || when < first.t_s - TRACE_SLACK_S || when > last.t_s + TRACE_SLACK_S {
                    bail!(at(format!(
                        "--at {when}: outside the trace, which spans {:.3} to {:.3} s",
                        first.t_s, last.t_s
                    )));
                }
                let nearest = t
                    .samples
                    .iter()
                    .min_by(|x, y| (x.t_s - when).abs().total_cmp(&(y.t_s - when).abs()))
                    .unwrap_or(first);
                sim.set_state_from_sample(nearest).map_err(&at)?;
                images.extend(shooter.shoot(&sim, &cameras, labels.as_deref())?);
            }
        }
    }
    let names: Vec<String> = sim.scene.objects.iter().map(|o| o.name.clone()).collect();
    bop::write(&a.out, &names, &images)?;
    println!(
        "{}",
        serde_json::json!({
            "out": a.out,
            "gym": sim.scene.name,
            "images": images.len(),
            "cameras": images.iter().map(|i| i.camera.clone()).collect::<std::collections::BTreeSet<_>>(),
            "objects": names,
        })
    );
    Ok(0)
}
