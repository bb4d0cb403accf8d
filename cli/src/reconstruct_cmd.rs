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
    /// The robot's TCP link in its URDF (the scene's `tcp_link`). The URDF must have a chain of
    /// exactly 7 revolute joints from its base to this link, and `--joints` gives those 7 angles;
    /// a missing link is refused with the list of the URDF's links.
    #[arg(long, default_value = "hand_tcp")]
    pub tcp_link: String,
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
    /// Optional: ask a model for each fitted object's name, optionally a shape (box, cylinder,
    /// sphere, bowl or mesh imposed; disc, container or parts kept only where the frames gave
    /// them) and a material (mass and friction), sending the source images and the fitted
    /// objects as text. An endpoint TOML
    /// file (agent-host/endpoints/), "record:<toml>", "replay:<cassette.jsonl>" or
    /// "scripted:<answers.json>" (the scripted server on loopback: mechanics only). Off by
    /// default: without it, names and shapes come from the frames alone.
    #[arg(long)]
    pub llm: Option<String>,
    /// Wire format for `--llm scripted:…`: openai or anthropic.
    #[arg(long, default_value = "openai")]
    pub provider: String,
}

const MODEL_SYSTEM: &str = "You label the objects of a table-top scene that was reconstructed from camera \
frames for a robot simulator. You receive the camera images and a JSON list of the objects the reconstruction \
fitted, each with an id, a provisional name, the shape it was fitted as, its size, position (metres, robot \
base frame: x forward, y left, z up) and colour. For each listed object, say what it is, and optionally which \
shape represents it best for grasping and physics and what it is made of. Shapes you may impose (the object \
is fitted again as that shape, whatever the frames show): box, cylinder (upright), sphere, bowl (an open round \
container) or mesh (one convex hull of its points, which closes every hole and hollow). Shapes only the \
frames can give, which you may name to keep a fit that has them: disc (a flat round object standing on its \
edge), container (an open round body with its floor, walls and whatever sticks out, such as a mug's \
handle, or an open rectangular bin, kept as its floor and four walls) and parts (pieces cut wherever a camera saw through the object, such as a rack's slots or a hook's gap). \
Leave the shape out to keep the fit. A material, from the list given with the objects, sets the friction and \
the mass: its density times the volume of the fitted shape, which is solid except for bowls, containers and \
parts, within 20 g to 2 kg (static furniture keeps no mass). Leave the material out for a hollow object fitted \
as a solid shape, such as a can or a closed carton: it would come out far too heavy. Use only the ids you were given: never add an object, never \
merge or split objects. Answer with strict JSON only, no prose and no code fence: {\"objects\": [{\"id\": \
\"o1\", \"name\": \"lower_case_name\", \"primitive\": \"box\", \"material\": \"wood\"}]}, where \
primitive and material may be left out. Names are short lower-case identifiers (letters, digits, \
underscores), one per object, all different.";

/// The model's answer to the labelling request: asks the endpoint with the fitted objects and the
/// source images, and writes {text, model, source, provider, usage} to `to` for the fit step,
/// which checks and applies it.
fn ask_model(
    llm: &str,
    provider: &str,
    frames: &Path,
    fitted: &serde_json::Value,
    work: &Path,
    to: &Path,
) -> anyhow::Result<()> {
    use agent_host::llm::{Client, Message, Part, Role};
    let objects = serde_json::to_string_pretty(&fitted["for_model"])?;
    let materials: Vec<&str> =
        fitted["materials"].as_array().into_iter().flatten().filter_map(serde_json::Value::as_str).collect();
    let mut parts = vec![Part::Text(format!(
        "The fitted objects (ids o1..o{}):\n{objects}\n\nMaterials: {}.\n\nThe source images follow, one per camera.",
        fitted["for_model"].as_array().map(|a| a.len()).unwrap_or(0),
        materials.join(", ")
    ))];
    let mut pngs: Vec<PathBuf> = std::fs::read_dir(frames.join("rgb"))
        .with_context(|| format!("{}", frames.join("rgb").display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().and_then(|x| x.to_str()) == Some("png"))
        .collect();
    pngs.sort();
    for p in pngs.iter().take(4) {
        parts.push(Part::Text(format!("Image {}:", p.file_name().unwrap_or_default().to_string_lossy())));
        parts.push(Part::Png(std::fs::read(p).with_context(|| format!("{}", p.display()))?));
    }
    let (endpoint, _scripted, source) = agent_host::session::endpoint(llm, provider, "reconstruct", None, work)?;
    let client = Client::new(endpoint.clone())?;
    eprintln!(
        "r2g reconstruct: asking {} ({}, {source}) for names, shapes and materials",
        endpoint.model, endpoint.base_url
    );
    let c = client
        .complete(MODEL_SYSTEM, &[Message { role: Role::User, parts }])
        .with_context(|| format!("the call to the model endpoint {} failed", endpoint.base_url))?;
    let rec = json!({"text": c.text, "model": endpoint.model, "source": source, "provider": endpoint.provider,
                     "usage": {"input": c.usage.input, "output": c.usage.output}, "truncated": c.truncated,
                     "mechanics_only": source == "scripted"});
    std::fs::write(to, serde_json::to_vec(&rec)?)?;
    Ok(())
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
            // Not ours: one line, never a traceback (the Python side writes one under the work
            // folder when R2G_RECONSTRUCT_KEEP_WORK is set).
            None => bail!(
                "{} {} failed (exit {}): {}",
                py.display(),
                script.display(),
                out.status.code().map(|c| c.to_string()).unwrap_or_else(|| "by a signal".into()),
                err.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("no message").trim()
            ),
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

/// The demonstration copied into the gym (`demo.csv`), re-anchored when the fit step found a
/// `demonstration_scene`: every entity of that scene is paired with a reconstructed object (by
/// name, else the nearest; the `anchor` step), its move measured, and the demonstration adapted
/// by `real2sim::augment::reanchor` (the adaptation `r2g augment` uses). Returns the line to
/// print and the record for reconstruction.json.
fn demonstration(
    fitted: &serde_json::Value,
    stage: &Path,
    scene_path: &Path,
    work: &Path,
) -> anyhow::Result<(String, serde_json::Value)> {
    let Some(src) = fitted["demonstration_scene"].as_str() else {
        return Ok((
            "copied unchanged: the task file names no demonstration_scene (the scene it was recorded in), so it \
             is not re-anchored to the reconstructed objects; if they stand elsewhere than where it was recorded, it \
             will miss them"
                .into(),
            json!({"status": "copied", "reanchored": false,
                   "why": "the task file names no demonstration_scene to measure the objects' moves from"}),
        ));
    };
    let s = |p: &Path| p.display().to_string();
    let anchor = step(&["anchor".into(), "--out".into(), s(stage), "--source-scene".into(), src.into()])?;
    let (demo, _) = real2sim::augment::Demonstration::recorded_in(Path::new(src), &work.join("demonstration_gate"))
        .with_context(|| format!("re-anchoring the demonstration recorded in {src}"))?;
    let mut moves = std::collections::BTreeMap::new();
    for m in anchor["moves"].as_array().into_iter().flatten() {
        let v3 = |k: &str| -> anyhow::Result<[f64; 3]> {
            let a: Vec<f64> = m[k].as_array().into_iter().flatten().filter_map(|x| x.as_f64()).collect();
            a.try_into().map_err(|_| anyhow::anyhow!("anchor step: {k} of {} is not 3 numbers", m["entity"]))
        };
        let entity = m["entity"].as_str().unwrap_or_default().to_string();
        let yaw = m["yaw_deg"].as_f64().unwrap_or(0.0).to_radians();
        moves.insert(entity, real2sim::augment::planar_move(v3("from_m")?, v3("to_m")?, yaw));
    }
    let rows = if moves.is_empty() {
        demo.rows.clone()
    } else {
        real2sim::augment::reanchor(&demo, &moves, scene_path)
            .with_context(|| format!("re-anchoring the demonstration recorded in {src} to the reconstruction"))?
    };
    let re_solved = rows.iter().zip(&demo.rows).filter(|(a, b)| a != b).count();
    let tmp = stage.join(".demo.csv.tmp");
    lockstep::write_demo(&tmp, &rows)?;
    std::fs::rename(&tmp, stage.join("demo.csv"))?;
    let entities: Vec<&str> =
        anchor["moves"].as_array().into_iter().flatten().filter_map(|m| m["entity"].as_str()).collect();
    let note = if moves.is_empty() {
        format!(
            "recorded in {src}; every paired object stands where it stood there (within 1.5 mm, 1 deg): rows unchanged"
        )
    } else {
        format!(
            "re-anchored from {src}: {} moved ({}), {re_solved} of {} rows re-solved",
            entities.len(),
            entities.join(", "),
            rows.len()
        )
    };
    let record = json!({
        "status": if moves.is_empty() { "unchanged" } else { "re-anchored" },
        "reanchored": !moves.is_empty(),
        "source_scene": src,
        "moves": anchor["moves"],
        "unchanged": anchor["unchanged"],
        "unmatched": anchor["unmatched"],
        "unpaired_reconstructed": anchor["unpaired_reconstructed"],
        "anchors": demo.anchors.iter().map(|a| json!({"row": a.row, "entity": a.entity})).collect::<Vec<_>>(),
        "rows": rows.len(),
        "rows_re_solved": re_solved,
    });
    Ok((note, record))
}

pub fn run(a: ReconstructArgs) -> anyhow::Result<i32> {
    let started = Instant::now();
    // The robot, as `r2g kin` takes it: a name or a URDF file.
    let model = runtime::launch::robot_by_name(&a.robot, &a.tcp_link)
        .with_context(|| format!("--robot {} with --tcp-link {}", a.robot, a.tcp_link))?;
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
        "--tcp-link".into(),
        a.tcp_link.clone(),
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
    let mut fitted = step(&fit)?;
    if let Some(llm) = &a.llm {
        if llm.starts_with("scripted") {
            eprintln!(
                "r2g reconstruct: mechanics only: --llm {llm} answers with a synthetic answer written in advance"
            );
        }
        // Ask about the objects as fitted, then fit again from the frames with the answer applied
        // (the fit is deterministic: the same objects, the same ids).
        let answer = work.0.join("model_answer.json");
        ask_model(llm, &a.provider, &a.frames, &fitted, &work.0, &answer)?;
        for e in std::fs::read_dir(&staging.dir)?.flatten() {
            let p = e.path();
            if p.is_dir() {
                std::fs::remove_dir_all(&p)?
            } else {
                std::fs::remove_file(&p)?
            }
        }
        fit.extend(["--llm-answer".into(), s(&answer)]);
        fitted = step(&fit)?;
    }
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
    // The demonstration, re-anchored to the reconstructed objects when the task file says which
    // scene it was recorded in.
    let demo_note = if fitted["demonstration"].as_bool() == Some(true) {
        let (note, record) = demonstration(&fitted, &staging.dir, &scene_path, &work.0)?;
        rep["demonstration"] = record;
        Some(note)
    } else {
        None
    };
    rep["seconds"]["total"] = json!((started.elapsed().as_secs_f64() * 1e3).round() / 1e3);
    std::fs::write(&rep_path, serde_json::to_vec_pretty(&rep)?)?;
    // The gym as it will be used: it loads and runs.
    let scene = sim_host::Scene::load(&scene_path).with_context(|| format!("{}", scene_path.display()))?;
    lockstep::Episode::new(&scene_path, 0).context("the reconstructed scene does not compile")?;
    let task_empty = scene.task.success.is_empty();
    let out = staging.commit()?;
    for sus in rep["spurious_suspects"].as_array().into_iter().flatten() {
        println!(
            "suspect: {}: {}",
            sus["name"].as_str().unwrap_or("?"),
            sus["why"].as_str().unwrap_or("likely spurious")
        );
    }
    for w in fitted["warnings"].as_array().into_iter().flatten().filter_map(|w| w.as_str()) {
        if w.contains("kept static") {
            println!("static: {w}");
        }
    }
    if let Some(note) = &demo_note {
        println!("demonstration: {note}");
    }
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
            "demonstration": rep["demonstration"]["status"],
            "model": rep["model"]["names_applied"],
            "spurious_suspects": rep["spurious_suspects"],
            "seconds": (started.elapsed().as_secs_f64() * 1e3).round() / 1e3,
        })
    );
    Ok(0)
}
