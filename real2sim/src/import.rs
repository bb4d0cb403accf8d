//! `r2g import droid|egodex <episode> --scene <scene.toml> --out <gym>`: a source episode into a
//! gym folder like the shipped ones: `scene.toml` (the given scene, paths rebased, the
//! demonstration pointed at `demo.csv`; for DROID the robot starts where the episode does),
//! `demo.csv` (joint + gripper rows at the scene's rate), `record.json` (the demonstration
//! record), `events.json` (source grasps, native events with before/onset/after keyframes, the
//! motion's anchors) and `import.json` (what the import measured). The folder appears whole or
//! not at all.

use std::path::{Path, PathBuf};

use serde_json::json;
use sim_host::Scene;

use crate::events::{self, EventsFile};
use crate::gym::{self, Staging};
use crate::record::Record;
use crate::retarget::{self, HandParams};
use crate::{droid, egodex, resample, Error, Result};

/// What an import wrote.
#[derive(Debug, Clone)]
pub struct Imported {
    pub dir: PathBuf,
    pub rows: usize,
    pub report: serde_json::Value,
}

/// The given scene, only read: one naming a demonstration that is not there (we write our own)
/// is loaded from a copy without it in the staging folder, never beside the user's file.
fn load(
    scene_path: &Path,
    staging: &Staging,
) -> Result<(Scene, controllers::RobotModel, controllers::safety::SafetyChecks)> {
    let scene = Scene::load(scene_path).or_else(|e| {
        if !e.to_string().contains("demonstration") {
            return Err(Error::Episode(e.into()));
        }
        let mut t = gym::rebased_scene(scene_path, &staging.dir)?;
        if let Some(task) = t.get_mut("task").and_then(|v| v.as_table_mut()) {
            task.remove("demonstration");
        }
        let copy =
            staging.write("scene.toml", toml::to_string(&t).map_err(|e| Error::Episode(e.into()))?.as_bytes())?;
        Scene::load(&copy).map_err(|e| Error::Episode(e.into()))
    })?;
    let (robot, safety) = runtime::scene_robot(scene_path)?;
    Ok((scene, robot, safety))
}

/// Writes the gym: files, then a native replay inside the staging folder for the events.
#[allow(clippy::too_many_arguments)]
fn write_gym(
    scene_path: &Path,
    staging: Staging,
    record: &Record,
    rows: &[[f64; 8]],
    start: Option<([f64; 7], f64)>,
    source: Vec<events::SourceGrasp>,
    source_kind: &str,
    mut report: serde_json::Value,
) -> Result<Imported> {
    let mut table = gym::rebased_scene(scene_path, &staging.dir)?;
    if let Some((q, g)) = start {
        if let Some(robot) = table.get_mut("robot").and_then(|r| r.as_table_mut()) {
            robot.insert(
                "initial_joints_rad".into(),
                toml::Value::Array(q.iter().map(|v| toml::Value::Float(*v)).collect()),
            );
            robot.insert("initial_gripper".into(), toml::Value::Float(g));
        }
    }
    let text = format!(
        "# Imported by `r2g import {}` from {} (see import.json, record.json).\n{}",
        record.source.kind,
        record.source.files.first().cloned().unwrap_or_default(),
        toml::to_string(&table).map_err(|e| Error::Episode(e.into()))?
    );
    let scene_file = staging.write("scene.toml", text.as_bytes())?;
    let demo = staging.dir.join("demo.csv");
    lockstep::write_demo(&demo, rows)?;
    // From here on the rows as written (6 decimals): the events must be those of the gym on disk.
    let rows = &lockstep::read_demo(&demo)?;
    staging.write("record.json", &serde_json::to_vec(record).map_err(|e| Error::Episode(e.into()))?)?;
    // The native events, from a replay of what we just wrote.
    let scene = Scene::load(&scene_file).map_err(|e| Error::Episode(e.into()))?;
    let hz = scene.task.demonstration_hz;
    let native_run = crate::replay::play(&scene_file, 0, rows, hz, scene.task.settle_s)?;
    let params = events::Params::default();
    let row_at = |t: f64| native_run.row_at(t);
    let native = events::from_trace(&scene, &native_run.episode.trace, &row_at, params);
    let anchors = events::anchors(&native, &row_at);
    let file = EventsFile { params, source_kind: source_kind.into(), source, native, anchors };
    staging.write("events.json", &serde_json::to_vec_pretty(&file).map_err(|e| Error::Episode(e.into()))?)?;
    report["native_replay_success"] = json!(native_run.episode.evaluate().success);
    report["native_events"] = json!(file.native.len());
    report["rows"] = json!(rows.len());
    staging.write("import.json", &serde_json::to_vec_pretty(&report).map_err(|e| Error::Episode(e.into()))?)?;
    let dir = staging.commit()?;
    Ok(Imported { dir, rows: rows.len(), report })
}

/// Imports a DROID episode folder.
pub fn droid(episode: &Path, scene_path: &Path, out: &Path, gate: droid::FkGate) -> Result<Imported> {
    let staging = Staging::new(out)?;
    let (scene, robot, safety) = load(scene_path, &staging)?;
    let (record, fk) = droid::read(episode, &robot, &safety, gate)?;
    let Some(track) = &record.robot else { return Err(Error::Episode(anyhow::anyhow!("DROID record without robot"))) };
    let hz = scene.task.demonstration_hz;
    // Switch times from the source: a command is closed above 0.75 and open again below 0.5
    // (the demonstrations' +0.5 / 0 on the -1..1 scale); a measured opening stops at the object,
    // so there a rise above 0.3 closes and a fall below 0.15 opens.
    let commanded = track.gripper_source.starts_with("action/");
    let (on, off) = if commanded { (0.75, 0.5) } else { (0.3, 0.15) };
    let closed = resample::hysteresis(&track.gripper_closed, on, off);
    let plan = resample::plan(&record.t_s, &closed, hz);
    // A command is replayed as it is. A measured opening is not a command: closed on an object
    // it reads the object's width, and commanding that width would squeeze nothing; so over
    // its closed intervals the gripper is commanded shut (+1), elsewhere it follows the opening.
    let grip = |c: f64, shut: bool| if shut && !commanded { 1.0 } else { 2.0 * c - 1.0 };
    let frames: Vec<[f64; 8]> = track
        .joints_rad
        .iter()
        .zip(&track.gripper_closed)
        .zip(&closed)
        .map(|((q, c), shut)| [q[0], q[1], q[2], q[3], q[4], q[5], q[6], grip(*c, *shut)])
        .collect();
    let rows = resample::apply(&plan, &frames);
    let source = events::grasps_of(&closed, &record.t_s);
    let first = rows[0];
    let report = json!({
        "source": "droid",
        "files": record.source.files,
        "task": record.source.task,
        "frames": record.t_s.len(),
        "duration_s": record.t_s.last(),
        "source_rate_hz": (record.t_s.len() - 1) as f64 / record.t_s.last().copied().unwrap_or(1.0).max(1e-9),
        "demo_rate_hz": hz,
        "fk_gate": {"against": "observation/robot_state/cartesian_position = panda_link8 (flange) in panda_link0",
                    "position_m": gate.position_m, "rotation_rad": gate.rotation_rad, "measured": fk},
        "gripper_from": track.gripper_source,
        "gripper_switches_s": resample::switches(&closed, &record.t_s),
        "scene": scene_path.display().to_string(),
        "start_joints_from_frame_0": true,
    });
    write_gym(
        scene_path,
        staging,
        &record,
        &rows,
        Some(([first[0], first[1], first[2], first[3], first[4], first[5], first[6]], first[7])),
        source,
        &format!("droid {} (closed above {on}, open below {off})", track.gripper_source),
        report,
    )
}

/// Reads `--registration FILE`: JSON `{"base_from_world": [[4 numbers] x 4]}` (row-major).
pub fn read_registration(path: &Path) -> Result<nalgebra::Isometry3<f64>> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(Error::io(path))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| Error::input(&file, "(file)", None, format!("not JSON: {e}")))?;
    let m: [[f64; 4]; 4] = serde_json::from_value(v.get("base_from_world").cloned().unwrap_or_default())
        .map_err(|_| Error::input(&file, "base_from_world", None, "missing or not a 4x4 array of numbers"))?;
    crate::record::iso_of(&m).map_err(|why| Error::input(&file, "base_from_world", None, why))
}

/// Imports an EgoDex episode file.
pub fn egodex(
    episode: &Path,
    scene_path: &Path,
    out: &Path,
    side: &str,
    registration: Option<&Path>,
    params: HandParams,
) -> Result<Imported> {
    let staging = Staging::new(out)?;
    let (scene, robot, safety) = load(scene_path, &staging)?;
    let given = registration.map(read_registration).transpose()?;
    let hand = egodex::read(episode, side, params.min_confidence)?;
    let hz = scene.task.demonstration_hz;
    let r = retarget::retarget(&hand, &scene, &robot, &safety, given, params, hz)?;
    let closed: Vec<bool> = r.report.switches_s.iter().map(|s| s.1).collect();
    let times: Vec<f64> = r.report.switches_s.iter().map(|s| s.0).collect();
    // Grasps from the switches: a leading `false` state is implied before the first close.
    let mut source = Vec::new();
    for (t, c) in times.iter().zip(&closed) {
        if *c {
            source.push(events::SourceGrasp { close_s: *t, open_s: None });
        } else if let Some(last) = source.last_mut().filter(|g: &&mut events::SourceGrasp| g.open_s.is_none()) {
            last.open_s = Some(*t);
        }
    }
    let report = json!({
        "source": "egodex",
        "files": r.record.source.files,
        "task": r.record.source.task,
        "hand": r.report,
        "registration": r.record.source.registration,
        "demo_rate_hz": hz,
        "demo_offset_s": r.offset_s,
        "scene": scene_path.display().to_string(),
    });
    write_gym(scene_path, staging, &r.record, &r.rows, None, source, "egodex hand aperture (hysteresis)", report)
}
