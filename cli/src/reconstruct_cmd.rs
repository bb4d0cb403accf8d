//! `r2g reconstruct`: a gym folder from RGB-D frames in the BOP scene layout.
//!
//! The geometry is `real2sim/py/r2g_reconstruct.py` (run with the checkout's `.venv` Python, as
//! the HDF5 reader is): `fit` reads the frames, removes the robot's pixels, segments and fits the
//! objects and writes `scene.toml` into a staging folder; this command then lets physics settle
//! the objects (`lockstep::Episode`, the arm held at the capture pose) and writes the settled
//! poses, and `gate` renders the reconstruction from every source camera (`r2g render`),
//! compares it object by object with the source and corrects it, a bounded number of rounds.
//! The staging folder is renamed to `--out` only once every step passed and the scene compiles,
//! so the gym appears whole or not at all.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context};
use serde_json::json;

#[derive(clap::Args, Debug)]
pub struct ReconstructArgs {
    /// Folder of frames in the BOP scene layout: scene_camera.json (per image cam_K, cam_R_w2c,
    /// cam_t_w2c in mm with the robot base as the world, depth_scale), rgb/<id>.png and
    /// depth/<id>.png (uint16; value x depth_scale = mm along the optical axis).
    pub frames: PathBuf,
    /// The robot: panda, fr3 (the Panda URDF with that limit profile) or the path of a URDF, as
    /// `r2g kin` takes it.
    #[arg(long, default_value = "panda")]
    pub robot: String,
    /// The arm's pose at capture: "q1,...,q7" (rad; an 8th value is the gripper, -1 open .. +1
    /// closed) for every image, or a JSON file per image id ({"<id>": {"joints_rad": [7],
    /// "finger_m": f}}, as `r2g render` writes joints.json).
    #[arg(long)]
    pub joints: String,
    /// The gym folder to write; must not exist or be empty.
    #[arg(long)]
    pub out: PathBuf,
    /// A TOML file with a [task] table (instruction, success rules, demonstration, as in
    /// scene.toml) and optionally [names]: new name = "colour shape" prompt or [x, y] of the
    /// object it names. Without it (and without --instruction) the task is left empty.
    #[arg(long)]
    pub task: Option<PathBuf>,
    /// The task's instruction (replaces the task file's).
    #[arg(long)]
    pub instruction: Option<String>,
    /// For frames without depth/: an HTTP service answering depth for an RGB image
    /// (real2sim/RECONSTRUCT.md has the wire format).
    #[arg(long)]
    pub geometry_url: Option<String>,
    /// Correction rounds of the reprojection gate (each followed by settling and a new render);
    /// one more round only measures.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
    /// Smallest per-object mask IoU at which the gate stops correcting.
    #[arg(long, default_value_t = 0.9)]
    pub iou_goal: f64,
    /// Simulated seconds of gravity settling before each render.
    #[arg(long, default_value_t = 1.0)]
    pub settle_s: f64,
}

/// The interpreter: `$R2G_PYTHON`, else the checkout's `.venv/bin/python`.
fn python() -> PathBuf {
    std::env::var_os("R2G_PYTHON").map(PathBuf::from).unwrap_or_else(|| checkout().join(".venv/bin/python"))
}

fn checkout() -> PathBuf {
    runtime::launch::gyms_dir().parent().map(Path::to_path_buf).unwrap_or_default()
}

/// A work folder for renders and the state between steps, removed however the command ends.
struct Work(PathBuf);

impl Drop for Work {
    fn drop(&mut self) {
        if std::env::var_os("R2G_RECONSTRUCT_KEEP_WORK").is_none() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// Runs one step of the Python side; its last stdout line is JSON. An input problem comes back
/// as "error: ..." on stderr and becomes this command's error, word for word.
fn step(args: &[String]) -> anyhow::Result<serde_json::Value> {
    let script = checkout().join("real2sim/py/r2g_reconstruct.py");
    let py = python();
    let out = Command::new(&py).arg(&script).args(args).output().with_context(|| {
        format!("cannot run {} {} (build the venv first: make robo)", py.display(), script.display())
    })?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let line = err.lines().rev().find(|l| l.starts_with("error: ")).map(|l| l["error: ".len()..].to_string());
        match line {
            Some(l) => bail!("{l}"),
            None => bail!("{} {} failed: {}", py.display(), script.display(), err.trim()),
        }
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let last = text.lines().rev().find(|l| l.trim_start().starts_with('{')).unwrap_or("{}");
    serde_json::from_str(last).with_context(|| format!("reconstruction step answered {last:?}"))
}

fn arr(v: &[f64]) -> toml::Value {
    toml::Value::Array(v.iter().map(|x| toml::Value::Float((x * 1e6).round() / 1e6)).collect())
}

/// Lets physics run `seconds` with the arm held at its initial pose and writes every object's
/// final pose into the scene file. Returns how far each object moved, m.
fn settle(scene_path: &Path, seconds: f64) -> anyhow::Result<Vec<(String, f64)>> {
    let mut ep = lockstep::Episode::new(scene_path, 0)
        .with_context(|| format!("the reconstructed scene does not compile: {}", scene_path.display()))?;
    ep.hold(seconds);
    let (Some(first), Some(last)) = (ep.trace.samples.first(), ep.trace.samples.last()) else {
        return Ok(Vec::new());
    };
    let text = std::fs::read_to_string(scene_path)?;
    let header: String = text.lines().take_while(|l| l.starts_with('#')).map(|l| format!("{l}\n")).collect();
    let mut t: toml::Table = text.parse().with_context(|| format!("{}", scene_path.display()))?;
    let mut moved = Vec::new();
    if let Some(objs) = t.get_mut("objects").and_then(|v| v.as_array_mut()) {
        for (i, name) in ep.trace.objects.iter().enumerate() {
            let Some(o) = objs
                .iter_mut()
                .filter_map(|o| o.as_table_mut())
                .find(|o| o.get("name").and_then(|n| n.as_str()) == Some(name))
            else {
                continue;
            };
            let (a, b) = (first.objects[i], last.objects[i]);
            if b.iter().any(|v| !v.is_finite()) {
                bail!("object '{name}' left the simulation while settling (non-finite pose)");
            }
            moved.push((name.clone(), ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()));
            o.insert("position_m".into(), arr(&b[..3]));
            o.insert("quat_wxyz".into(), arr(&b[3..7]));
        }
    }
    let body = toml::to_string(&t).context("writing the settled scene")?;
    let tmp = scene_path.with_extension("toml.tmp");
    std::fs::write(&tmp, format!("{header}{body}"))?;
    std::fs::rename(&tmp, scene_path)?;
    Ok(moved)
}

pub fn run(a: ReconstructArgs) -> anyhow::Result<i32> {
    let started = Instant::now();
    // The robot, as `r2g kin` takes it: a name or a URDF file.
    let model = runtime::launch::robot_by_name(&a.robot, "hand_tcp").with_context(|| format!("--robot {}", a.robot))?;
    let panda_urdf = runtime::launch::robots_dir().join("panda").join("panda.urdf");
    let (urdf, limits) = match controllers::Profile::from_name(&a.robot) {
        Some(_) => (panda_urdf.clone(), a.robot.clone()),
        None => (PathBuf::from(&a.robot), "panda".to_string()),
    };
    let urdf = urdf.canonicalize().with_context(|| format!("--robot {}", urdf.display()))?;
    let is_panda = panda_urdf.canonicalize().map(|p| p == urdf).unwrap_or(false);
    if !a.frames.is_dir() {
        bail!("frames folder {} does not exist", a.frames.display());
    }
    if !(0.0..=10.0).contains(&a.settle_s) || !(0.0..=1.0).contains(&a.iou_goal) || a.rounds > 10 {
        bail!("--settle-s takes 0..10 s, --iou-goal 0..1, --rounds at most 10");
    }
    let staging = real2sim::gym::Staging::new(&a.out)?;
    let work = Work(std::env::temp_dir().join(format!("r2g-reconstruct-{}", std::process::id())));
    let _ = std::fs::remove_dir_all(&work.0);
    std::fs::create_dir_all(&work.0)?;
    let exe = std::env::current_exe().context("locating this r2g binary")?;
    let s = |p: &Path| p.display().to_string();
    let name = a.out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "reconstructed".into());
    let mut fit = vec![
        "fit".into(),
        "--frames".into(),
        s(&a.frames),
        "--urdf".into(),
        s(&urdf),
        "--limits".into(),
        limits,
        "--joints".into(),
        a.joints.clone(),
        "--out".into(),
        s(&staging.dir),
        "--work".into(),
        s(&work.0),
        "--r2g".into(),
        s(&exe),
        "--name".into(),
        name,
    ];
    if is_panda {
        fit.push("--panda".into());
    }
    if let Some(t) = &a.task {
        fit.extend(["--task".into(), s(t)]);
    }
    if let Some(i) = &a.instruction {
        fit.extend(["--instruction".into(), i.clone()]);
    }
    if let Some(u) = &a.geometry_url {
        fit.extend(["--geometry-url".into(), u.clone()]);
    }
    let fitted = step(&fit)?;
    let scene_path = staging.dir.join("scene.toml");
    // The capture pose must be one the robot can take.
    let scene = sim_host::Scene::load(&scene_path).with_context(|| format!("{}", scene_path.display()))?;
    for (j, q) in scene.robot.initial_joints_rad.iter().enumerate() {
        let lim = &model.joints[j];
        if !(lim.q_min_rad..=lim.q_max_rad).contains(q) {
            bail!(
                "--joints: joint {} = {q:.4} rad is outside the robot's limits [{:.4}, {:.4}]",
                j + 1,
                lim.q_min_rad,
                lim.q_max_rad
            );
        }
    }
    // Settle, render, compare, correct.
    let mut last_round = json!(null);
    let mut settling = Vec::new();
    for round in 0..=a.rounds {
        let moved = settle(&scene_path, a.settle_s)?;
        settling.push(json!({"round": round, "moved_m": moved.iter().map(|(n, d)| json!({"name": n, "m": (d * 1e5).round() / 1e5})).collect::<Vec<_>>()}));
        let mut g = vec![
            "gate".into(),
            "--out".into(),
            s(&staging.dir),
            "--work".into(),
            s(&work.0),
            "--r2g".into(),
            s(&exe),
            "--round".into(),
            round.to_string(),
            "--iou-goal".into(),
            a.iou_goal.to_string(),
        ];
        if round == a.rounds {
            g.push("--last".into());
        }
        last_round = step(&g)?;
        if last_round["converged"].as_bool() == Some(true) {
            break;
        }
    }
    // The settling figures beside the gate's.
    let rep_path = staging.dir.join("reconstruction.json");
    let mut rep: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&rep_path)?)?;
    rep["settling"] = json!(settling);
    rep["seconds"]["total"] = json!((started.elapsed().as_secs_f64() * 1e3).round() / 1e3);
    std::fs::write(&rep_path, serde_json::to_vec_pretty(&rep)?)?;
    // The gym as it will be used: it loads and runs.
    let scene = sim_host::Scene::load(&scene_path).with_context(|| format!("{}", scene_path.display()))?;
    lockstep::Episode::new(&scene_path, 0).context("the reconstructed scene does not compile")?;
    let task_empty = scene.task.success.is_empty();
    let out = staging.commit()?;
    if task_empty {
        println!(
            "task: empty: no success rules were given (--task FILE with [task] success rules); the gym has {} and cannot be judged until rules are added",
            if scene.task.instruction.is_empty() { "no instruction either".to_string() } else { format!("the instruction {:?}", scene.task.instruction) }
        );
    }
    println!(
        "{}",
        json!({
            "gym": out.display().to_string(),
            "objects": fitted["objects"],
            "kinds": fitted["kinds"],
            "rounds": rep["rounds"].as_array().map(|r| r.len()).unwrap_or(0),
            "mean_iou": last_round["mean_iou"],
            "min_iou": last_round["min_iou"],
            "task_empty": task_empty,
            "warnings": fitted["warnings"],
            "seconds": (started.elapsed().as_secs_f64() * 1e3).round() / 1e3,
        })
    );
    Ok(0)
}
