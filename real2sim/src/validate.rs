//! The validation gate: a gym executed natively from its inputs (in-process lockstep, no shared
//! memory, no rendering), judged by physics, with every input hashed.
//!
//! [`validate`] is a pure unit of work over one gym folder: it reads the folder, runs two
//! lockstep episodes and writes `evidence.json` (and the trace, on request) into `out`; it
//! shares no state with other calls, so candidates can be validated on threads, processes or
//! other machines (`r2g validate <dir>`).
//!
//! Checks (all must pass):
//! - `initial_penetration`: at the first sample no two things overlap deeper than the task's
//!   `max_penetration_m`;
//! - `settles_at_rest`: left alone for `settle_s`, no free object drifts more than
//!   `settle_drift_m` or still moves faster than `rest_speed_m_s` over the last 0.1 s;
//! - `waypoints_reachable`: every row is within the robot's joint limits and passes the scene's
//!   collision and workspace checks, and every chunk of the replay executed;
//! - `event_timing`: each grasp the source commands is matched by a native grasp within
//!   `timing_tolerance_s` (onset and release), and the grasps, robot contacts and containments
//!   recorded in `events.json` recur within it;
//! - `task_success`: the evaluator's verdict on the trace;
//! - `worst_penetration`: the deepest overlap at any sample stays under `max_transient_penetration_m`;
//! - `final_stability`: over the final `final_window_s`, every free object moves slower than
//!   `rest_speed_m_s` and turns slower than `rest_angular_rad_s`, every fixture joint slower than
//!   `rest_speed_m_s` (slides) or `rest_joint_deg_s` (hinges).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use lockstep::Episode;
use serde::Serialize;
use serde_json::json;
use sim_host::scene::JointKind;
use sim_host::trace::{criteria_sha256, Check, Evaluation, Trace};
use sim_host::Scene;

use crate::events::{self, EventsFile};
use crate::{sha256_hex, Error, Result};

#[derive(Debug, Clone, Copy, Serialize)]
pub struct Thresholds {
    pub settle_s: f64,
    pub settle_drift_m: f64,
    pub rest_speed_m_s: f64,
    pub rest_angular_rad_s: f64,
    pub rest_joint_deg_s: f64,
    pub final_window_s: f64,
    pub max_transient_penetration_m: f64,
}

impl Default for Thresholds {
    fn default() -> Self {
        Self {
            settle_s: 0.5,
            settle_drift_m: 0.005,
            rest_speed_m_s: 0.02,
            rest_angular_rad_s: 0.2,
            rest_joint_deg_s: 2.0,
            final_window_s: 0.2,
            max_transient_penetration_m: 0.005,
        }
    }
}

#[derive(Debug, Clone)]
pub struct Options {
    pub seed: u64,
    /// Folder for `evidence.json` (and `trace.json`).
    pub out: PathBuf,
    pub keep_trace: bool,
    pub thresholds: Thresholds,
    pub events: events::Params,
}

impl Options {
    pub fn new(out: PathBuf) -> Self {
        Self { seed: 0, out, keep_trace: false, thresholds: Thresholds::default(), events: events::Params::default() }
    }
}

/// What the gate found; written as `evidence.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Evidence {
    pub gym: String,
    /// The scene file, relative to the evidence's folder (so it stays right when a gym built in a
    /// staging folder is renamed into place, or a pool is moved whole).
    pub scene: String,
    pub success: bool,
    pub checks: BTreeMap<String, Check>,
    /// sha256 of every input: the scene file, the robot description, meshes, the demonstration,
    /// the success criteria, the seed, the recorded events.
    pub inputs: BTreeMap<String, String>,
    /// sha256 over the sorted `name=hash` lines of `inputs`.
    pub inputs_sha256: String,
    pub seed: u64,
    pub trace_sha256: String,
    pub evaluation: Evaluation,
    pub thresholds: Thresholds,
    /// The native events of this run.
    pub native_events: Vec<events::Interval>,
    pub r2g_version: String,
    /// Not part of the verdict: how long the gate took.
    pub wall_s: f64,
}

impl Evidence {
    /// The one JSON line `r2g validate` ends with.
    pub fn line(&self, evidence_path: &Path) -> serde_json::Value {
        json!({
            "gym": self.gym,
            "success": self.success,
            "checks": self.checks,
            "trace_sha256": self.trace_sha256,
            "inputs_sha256": self.inputs_sha256,
            "evidence": evidence_path.display().to_string(),
        })
    }
}

fn hash_file(inputs: &mut BTreeMap<String, String>, key: String, path: &Path) -> Result<()> {
    let bytes = std::fs::read(path).map_err(Error::io(path))?;
    inputs.insert(key, sha256_hex(&bytes));
    Ok(())
}

/// The hashed inputs of a gym.
pub fn inputs(scene_path: &Path, scene: &Scene, seed: u64) -> Result<BTreeMap<String, String>> {
    let mut inputs = BTreeMap::new();
    hash_file(&mut inputs, "scene".into(), scene_path)?;
    hash_file(&mut inputs, "robot_urdf".into(), &scene.robot.urdf)?;
    let mut meshes: Vec<PathBuf> = Vec::new();
    for o in &scene.objects {
        meshes.extend(o.mesh.clone());
        meshes.extend(o.parts.iter().filter_map(|p| p.mesh.clone()));
    }
    for f in &scene.fixtures {
        meshes.extend(f.parts.iter().filter_map(|p| p.mesh.clone()));
        if let Some(j) = &f.joint {
            meshes.extend(j.parts.iter().filter_map(|p| p.mesh.clone()));
        }
    }
    meshes.sort();
    meshes.dedup();
    for m in meshes {
        let name = m.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        hash_file(&mut inputs, format!("mesh:{name}"), &m)?;
    }
    if let Some(d) = &scene.task.demonstration {
        hash_file(&mut inputs, "demonstration".into(), d)?;
    }
    inputs.insert("criteria".into(), criteria_sha256(scene));
    inputs.insert("seed".into(), sha256_hex(format!("seed={seed}").as_bytes()));
    let ev = scene_dir(scene_path).join("events.json");
    if ev.is_file() {
        hash_file(&mut inputs, "events".into(), &ev)?;
    }
    Ok(inputs)
}

pub fn scene_dir(scene_path: &Path) -> PathBuf {
    scene_path.parent().unwrap_or(Path::new(".")).to_path_buf()
}

fn check(value: serde_json::Value, pass: bool) -> Check {
    Check { value, pass }
}

fn r5(v: f64) -> f64 {
    (v * 1e5).round() / 1e5
}

/// Largest linear (m/s) and angular (rad/s) speed of each free object between consecutive
/// samples from `from_s` on.
fn speeds(scene: &Scene, trace: &Trace, from_s: f64) -> Vec<(String, f64, f64)> {
    let mut out = Vec::new();
    for (i, name) in trace.objects.iter().enumerate() {
        if !scene.objects.iter().any(|o| &o.name == name && o.free) {
            continue;
        }
        let (mut v, mut w) = (0.0f64, 0.0f64);
        for pair in trace.samples.windows(2).filter(|p| p[0].t_s >= from_s - 1e-9) {
            let dt = (pair[1].t_s - pair[0].t_s).max(1e-9);
            let (a, b) = (pair[0].objects[i], pair[1].objects[i]);
            v = v.max(((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) + (b[2] - a[2]).powi(2)).sqrt() / dt);
            let qa = crate::gym::pose_wxyz([0.0; 3], [a[3], a[4], a[5], a[6]]).rotation;
            let qb = crate::gym::pose_wxyz([0.0; 3], [b[3], b[4], b[5], b[6]]).rotation;
            w = w.max(qa.angle_to(&qb) / dt);
        }
        out.push((name.clone(), v, w));
    }
    out
}

/// Runs the gate on the gym whose scene file is `scene_path` and writes the evidence.
pub fn validate(scene_path: &Path, o: &Options) -> Result<(Evidence, PathBuf)> {
    validate_native(scene_path, o).map(|(e, p, _)| (e, p))
}

/// As [`validate`], also handing back the native run (its trace and row times).
pub fn validate_native(scene_path: &Path, o: &Options) -> Result<(Evidence, PathBuf, crate::replay::Native)> {
    let started = Instant::now();
    let th = o.thresholds;
    let scene = Scene::load(scene_path).map_err(|e| Error::Episode(anyhow::Error::from(e)))?;
    let inputs = inputs(scene_path, &scene, o.seed)?;
    let lines: String = inputs.iter().map(|(k, v)| format!("{k}={v}\n")).collect();
    let inputs_sha256 = sha256_hex(lines.as_bytes());
    let demo_path = scene.task.demonstration.clone().ok_or_else(|| {
        Error::Episode(anyhow::anyhow!("scene {} has no task.demonstration to validate", scene_path.display()))
    })?;
    let rows = lockstep::read_demo(&demo_path)?;
    let hz = scene.task.demonstration_hz;
    let recorded: Option<EventsFile> = {
        let p = scene_dir(scene_path).join("events.json");
        if p.is_file() {
            let text = std::fs::read_to_string(&p).map_err(Error::io(&p))?;
            Some(
                serde_json::from_str(&text)
                    .map_err(|e| Error::input(&p.display().to_string(), "(file)", None, e.to_string()))?,
            )
        } else {
            None
        }
    };
    let mut checks = BTreeMap::new();

    // At rest before anything moves.
    let mut rest = Episode::new(scene_path, o.seed)?;
    rest.hold(th.settle_s);
    let first = rest.trace.samples.first().cloned();
    let last = rest.trace.samples.last().cloned();
    let mut drift = Vec::new();
    if let (Some(a), Some(b)) = (&first, &last) {
        for (i, name) in rest.trace.objects.iter().enumerate() {
            let (p, q) = (a.objects[i], b.objects[i]);
            let d = ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt();
            drift.push((name.clone(), d));
        }
    }
    let moving = speeds(&scene, &rest.trace, th.settle_s - 0.1);
    let worst_drift = drift.iter().cloned().fold(("".to_string(), 0.0f64), |a, b| if b.1 > a.1 { b } else { a });
    let worst_speed = moving.iter().map(|m| m.1).fold(0.0f64, f64::max);
    checks.insert(
        "settles_at_rest".into(),
        check(
            json!({"settle_s": th.settle_s, "worst_drift_m": r5(worst_drift.1), "object": worst_drift.0,
                   "max_speed_last_0.1s_m_s": r5(worst_speed)}),
            worst_drift.1 <= th.settle_drift_m && worst_speed <= th.rest_speed_m_s,
        ),
    );

    // Waypoints: limits and the scene's checks, row by row.
    let (robot, safety) = runtime::scene_robot(scene_path)?;
    let mut unreachable = None;
    for (k, r) in rows.iter().enumerate() {
        let q: [f64; 7] = std::array::from_fn(|j| r[j]);
        if let Some(j) = (0..7).find(|&j| !(robot.joints[j].q_min_rad..=robot.joints[j].q_max_rad).contains(&q[j])) {
            unreachable = Some(json!({"row": k, "why": format!("joint {} = {:.4} outside its limits", j + 1, q[j])}));
            break;
        }
        if let Err(v) = safety.check(&q) {
            unreachable = Some(json!({"row": k, "why": v.to_string()}));
            break;
        }
    }

    // The demonstration, natively.
    let native_run = crate::replay::play(scene_path, o.seed, &rows, hz, scene.task.settle_s)?;
    let ep = &native_run.episode;
    let initial = ep.trace.samples.first().cloned();
    let failed: Vec<serde_json::Value> =
        native_run.failures.iter().map(|(row, why)| json!({"first_row": row, "why": why})).collect();
    let evaluation = ep.evaluate();
    let trace = &ep.trace;
    checks.insert(
        "waypoints_reachable".into(),
        check(
            json!({"rows": rows.len(), "first_unreachable": unreachable, "chunks_not_executed": failed}),
            unreachable.is_none() && failed.is_empty(),
        ),
    );
    let name = |i: u16| trace.owners.get(i as usize).cloned().unwrap_or_default();
    let (p0, pair0) = initial.map(|s| (s.penetration_m, s.penetration_pair)).unwrap_or((0.0, [u16::MAX; 2]));
    checks.insert(
        "initial_penetration".into(),
        check(
            json!({"deepest_m": r5(p0), "between": if p0 > 0.0 { json!([name(pair0[0]), name(pair0[1])]) } else { json!(null) },
                   "limit_m": scene.task.max_penetration_m}),
            p0 <= scene.task.max_penetration_m,
        ),
    );
    let worst = trace.samples.iter().max_by(|a, b| a.penetration_m.total_cmp(&b.penetration_m));
    let (pw, pair_w, tw) =
        worst.map(|s| (s.penetration_m, s.penetration_pair, s.t_s)).unwrap_or((0.0, [u16::MAX; 2], 0.0));
    checks.insert(
        "worst_penetration".into(),
        check(
            json!({"deepest_m": r5(pw), "at_s": r5(tw),
                   "between": if pw > 0.0 { json!([name(pair_w[0]), name(pair_w[1])]) } else { json!(null) },
                   "limit_m": th.max_transient_penetration_m}),
            pw <= th.max_transient_penetration_m,
        ),
    );
    let failing: Vec<&String> = evaluation.checks.iter().filter(|(_, c)| !c.pass).map(|(k, _)| k).collect();
    checks.insert("task_success".into(), check(json!({"failed_rules": failing}), evaluation.success));

    // Final stability.
    let end = trace.samples.last().map(|s| s.t_s).unwrap_or(0.0);
    let from = end - th.final_window_s;
    let obj = speeds(&scene, trace, from);
    let (mut v, mut w, mut who) = (0.0f64, 0.0f64, String::new());
    for (n, a, b) in &obj {
        if *a > v || *b > w {
            who = n.clone();
        }
        v = v.max(*a);
        w = w.max(*b);
    }
    let mut joint_ok = true;
    let mut joints = serde_json::Map::new();
    let specs: Vec<_> =
        scene.fixtures.iter().filter_map(|f| f.joint.as_ref().map(|j| (f.name.clone(), j.kind))).collect();
    for (j, (fname, kind)) in specs.iter().enumerate() {
        let mut top = 0.0f64;
        for pair in trace.samples.windows(2).filter(|p| p[0].t_s >= from - 1e-9) {
            let dt = (pair[1].t_s - pair[0].t_s).max(1e-9);
            top = top.max((pair[1].joints[j] - pair[0].joints[j]).abs() / dt);
        }
        let limit = if *kind == JointKind::Slide { th.rest_speed_m_s } else { th.rest_joint_deg_s };
        joint_ok &= top <= limit;
        joints.insert(fname.clone(), json!(r5(top)));
    }
    checks.insert(
        "final_stability".into(),
        check(
            json!({"window_s": th.final_window_s, "max_speed_m_s": r5(v), "max_angular_rad_s": r5(w), "object": who,
                   "fixture_joint_speed": joints}),
            v <= th.rest_speed_m_s && w <= th.rest_angular_rad_s && joint_ok,
        ),
    );

    // Events against the source.
    let row_at = |t: f64| native_run.row_at(t);
    let native = events::from_trace(&scene, trace, &row_at, o.events);
    let (source, source_kind) = match &recorded {
        Some(r) => (r.source.clone(), r.source_kind.clone()),
        None => (events::source_grasps(&rows, hz), "demonstration gripper column".to_string()),
    };
    let to_native = |t: f64| native_run.time_of_row(t * hz);
    let timing = events::timing(
        &source,
        &native,
        recorded.as_ref().map(|r| r.native.as_slice()),
        trace,
        &to_native,
        o.events.timing_tolerance_s,
    );
    let missing =
        recorded.as_ref().map(|r| events::missing(&r.native, &native, o.events.timing_tolerance_s)).unwrap_or_default();
    checks.insert(
        "event_timing".into(),
        check(
            json!({"source": source_kind, "source_grasps": source.len(), "native_grasps":
                   native.iter().filter(|e| e.kind == events::Kind::Grasp).count(),
                   "max_abs_error_s": r5(timing.max_abs_error_s), "tolerance_s": timing.tolerance_s,
                   "close_source_native_error_s": timing.close, "open_source_native_error_s": timing.open,
                   "closed_on_nothing_s": timing.closed_on_nothing, "recorded_events_missing": missing}),
            timing.pass && missing.is_empty(),
        ),
    );

    let success = checks.values().all(|c| c.pass);
    std::fs::create_dir_all(&o.out).map_err(Error::io(&o.out))?;
    let evidence = Evidence {
        gym: scene.name.clone(),
        scene: crate::gym::relative_to(scene_path, &o.out).display().to_string(),
        success,
        checks,
        inputs,
        inputs_sha256,
        seed: o.seed,
        trace_sha256: evaluation.trace_sha256.clone(),
        evaluation,
        thresholds: th,
        native_events: native,
        r2g_version: env!("CARGO_PKG_VERSION").into(),
        wall_s: started.elapsed().as_secs_f64(),
    };
    let path = o.out.join("evidence.json");
    lockstep::demo::write_atomic(&path, &serde_json::to_vec_pretty(&evidence).map_err(|e| Error::Episode(e.into()))?)?;
    if o.keep_trace {
        lockstep::demo::write_atomic(
            &o.out.join("trace.json"),
            &serde_json::to_vec(&ep.trace).map_err(|e| Error::Episode(e.into()))?,
        )?;
    }
    Ok((evidence, path, native_run))
}
