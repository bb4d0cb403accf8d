//! `r2g kin fk|ik`: forward and inverse kinematics over JSON lines, one answer per input line.
//!
//! This stays in the CLI: it is the command's wire format (parse a request line, call
//! `controllers`' FK or IK, print an answer line) and holds no kinematics of its own.

use std::io::{BufRead, Write};

use anyhow::Context;
use controllers::kinematics::{from_arrays, to_arrays};
use controllers::{FrameId, IkConfig, IkSolver, RobotModel, N};
use serde_json::{json, Map, Value};

/// The frame `--frame` names, or the TCP.
pub fn frame(robot: &RobotModel, name: Option<&str>) -> anyhow::Result<FrameId> {
    match name {
        None => Ok(robot.kin.tcp),
        Some(n) => robot.kin.frame(n).with_context(|| {
            let known: Vec<&str> = robot.kin.frames().iter().map(|f| f.name.as_str()).collect();
            format!("no frame '{n}' (frames: {}, tcp, flange)", known.join(", "))
        }),
    }
}

/// One request's fields, checked against the keys it may have.
fn object<'a>(v: &'a Value, allowed: &[&str]) -> Result<&'a Map<String, Value>, String> {
    let o = v.as_object().ok_or_else(|| format!("expected a JSON object, got {}", kind(v)))?;
    if let Some(k) = o.keys().find(|k| !allowed.contains(&k.as_str())) {
        return Err(format!("unknown key \"{k}\" (expected {})", allowed.join(", ")));
    }
    Ok(o)
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// `o[key]` as exactly `L` finite numbers.
fn numbers<const L: usize>(o: &Map<String, Value>, key: &str) -> Result<Option<[f64; L]>, String> {
    let Some(v) = o.get(key) else { return Ok(None) };
    let a = v.as_array().ok_or_else(|| format!("\"{key}\" must be an array of {L} numbers, got {}", kind(v)))?;
    if a.len() != L {
        return Err(format!("\"{key}\" must have {L} numbers, got {}", a.len()));
    }
    let mut out = [0.0; L];
    for (i, x) in a.iter().enumerate() {
        out[i] = x.as_f64().ok_or_else(|| format!("\"{key}\"[{i}] must be a number, got {}", kind(x)))?;
    }
    Ok(Some(out))
}

fn required<const L: usize>(o: &Map<String, Value>, key: &str) -> Result<[f64; L], String> {
    numbers::<L>(o, key)?.ok_or_else(|| format!("missing \"{key}\" ({L} numbers)"))
}

/// Answers one fk request.
pub fn fk_line(robot: &RobotModel, frame: FrameId, line: &str) -> Value {
    let r = (|| {
        let v: Value = serde_json::from_str(line).map_err(|e| format!("not JSON: {e}"))?;
        let o = object(&v, &["q"])?;
        let q: [f64; N] = required(o, "q")?;
        let (p, quat) = to_arrays(&robot.kin.fk(&q, frame));
        Ok::<_, String>(json!({ "position": p, "quaternion": quat }))
    })();
    r.unwrap_or_else(|e| json!({ "error": e }))
}

/// Answers one ik request. Without a seed the solver starts from the middle of the joint box.
pub fn ik_line(solver: &IkSolver, line: &str) -> Value {
    let r = (|| {
        let v: Value = serde_json::from_str(line).map_err(|e| format!("not JSON: {e}"))?;
        let o = object(&v, &["position", "quaternion", "seed"])?;
        let p: [f64; 3] = required(o, "position")?;
        let quat: [f64; 4] = required(o, "quaternion")?;
        let norm = quat.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm <= 1e-9 {
            return Err("\"quaternion\" has zero length: give [x, y, z, w] of a rotation".to_string());
        }
        let (lo, hi) = solver.bounds();
        let seed = match numbers::<N>(o, "seed")? {
            Some(s) => s,
            None => std::array::from_fn(|j| 0.5 * (lo[j] + hi[j])),
        };
        let s = solver.solve(&from_arrays(p, quat), &seed).map_err(|e| e.to_string())?;
        Ok(json!({
            "ok": s.ok,
            "q": s.q,
            "position_error": s.position_error_m,
            "rotation_error": s.rotation_error_rad,
            "iterations": s.iterations,
            "restarts": s.restarts,
        }))
    })();
    r.unwrap_or_else(|e| json!({ "error": e }))
}

/// Reads requests from stdin until it closes; blank lines are skipped.
pub fn run(ik: bool, robot: &str, tcp: &str, frame_name: Option<&str>) -> anyhow::Result<i32> {
    let model = runtime::launch::robot_by_name(robot, tcp)?;
    let frame = frame(&model, frame_name)?;
    let mut solver = IkSolver::new(&model, IkConfig::default())?;
    solver.set_frame(frame)?;
    let stdin = std::io::stdin();
    let mut out = std::io::stdout().lock();
    for line in stdin.lock().lines() {
        let line = line.context("reading stdin")?;
        if line.trim().is_empty() {
            continue;
        }
        let answer = if ik { ik_line(&solver, &line) } else { fk_line(&model, frame, &line) };
        writeln!(out, "{answer}")?;
        out.flush()?;
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use controllers::Profile;

    fn panda() -> RobotModel {
        let xml =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
        RobotModel::from_urdf_str(&xml, "hand_tcp", Profile::Panda).expect("model")
    }

    #[test]
    fn malformed_requests_say_what_is_wrong() {
        let r = panda();
        let s = IkSolver::new(&r, IkConfig::default()).expect("solver");
        let err = |v: Value| v["error"].as_str().unwrap_or_default().to_string();
        assert!(err(fk_line(&r, r.kin.tcp, "{\"q\":[1,2]}")).contains("must have 7 numbers, got 2"));
        assert!(err(fk_line(&r, r.kin.tcp, "{\"q\":[0,0,0,\"a\",0,0,0]}")).contains("\"q\"[3] must be a number"));
        assert!(err(fk_line(&r, r.kin.tcp, "[1]")).contains("expected a JSON object"));
        assert!(err(fk_line(&r, r.kin.tcp, "{\"q\":")).starts_with("not JSON"));
        assert!(err(fk_line(&r, r.kin.tcp, "{\"qq\":[]}")).contains("unknown key \"qq\""));
        assert!(err(ik_line(&s, "{\"position\":[0.3,0,0.5]}")).contains("missing \"quaternion\""));
        assert!(err(ik_line(&s, "{\"position\":[0.3,0,0.5],\"quaternion\":[0,0,0,0]}")).contains("zero length"));
        let ok = ik_line(&s, "{\"position\":[0.30689,0,0.48688],\"quaternion\":[1,0,0,0]}");
        assert_eq!(ok["ok"], true, "{ok}");
    }
}
