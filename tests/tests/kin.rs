//! `r2g kin` end to end: the real binary, JSON lines in and out.

use std::io::Write;
use std::process::{Command, Stdio};

use serde_json::Value;

/// Runs `r2g kin <args>` with `input` on stdin; returns its stdout lines as JSON.
fn kin(args: &[&str], input: &str) -> Vec<Value> {
    let mut child = Command::new(integration_tests::r2g())
        .arg("kin")
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn r2g kin");
    child.stdin.take().expect("stdin").write_all(input.as_bytes()).expect("write stdin");
    let out = child.wait_with_output().expect("r2g kin");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().unwrap_or_else(|| panic!("not an array: {v}")).iter().map(|x| x.as_f64().expect("number")).collect()
}

#[test]
fn fk_of_the_zero_configuration_is_the_published_tcp() {
    let out = kin(&["fk", "--robot", "panda"], "{\"q\":[0,0,0,0,0,0,0]}\n");
    assert_eq!(out.len(), 1);
    let p = floats(&out[0]["position"]);
    for (got, want) in p.iter().zip([0.088, 0.0, 0.8226]) {
        assert!((got - want).abs() < 1e-9, "{p:?}");
    }
    let q = floats(&out[0]["quaternion"]);
    // xyzw (0.92388, 0.38268, 0, 0), up to sign.
    let s = q[0].signum();
    for (got, want) in q.iter().zip([0.92388, 0.38268, 0.0, 0.0]) {
        assert!((s * got - want).abs() < 1e-5, "{q:?}");
    }
    let flange = kin(&["fk", "--frame", "flange"], "{\"q\":[0,0,0,0,0,0,0]}\n");
    assert!((floats(&flange[0]["position"])[2] - 0.926).abs() < 1e-9, "{flange:?}");
}

#[test]
fn ik_round_trip_and_errors_per_line() {
    let q = [0.4, -0.3, 0.2, -2.1, 0.3, 1.9, -0.5];
    let fk = kin(&["fk", "--robot", "fr3"], &format!("{{\"q\":{q:?}}}\n"));
    let input = format!(
        "{{\"position\":{},\"quaternion\":{},\"seed\":[0,-0.785,0,-2.356,0,1.571,0.785]}}\nnot json\n{{\"position\":[1,2]}}\n{{\"position\":[3,0,0.5],\"quaternion\":[0,0,0,1],\"seed\":[0,-0.785,0,-2.356,0,1.571,0.785]}}\n",
        fk[0]["position"], fk[0]["quaternion"]
    );
    let out = kin(&["ik", "--robot", "fr3"], &input);
    assert_eq!(out.len(), 4, "{out:?}");
    assert_eq!(out[0]["ok"], true, "{}", out[0]);
    assert!(out[0]["position_error"].as_f64().is_some_and(|e| e <= 1e-5), "{}", out[0]);
    assert!(out[0]["rotation_error"].as_f64().is_some_and(|e| e <= 1e-5), "{}", out[0]);
    // The answer, put back through fk, lands on the same pose.
    let back = kin(&["fk", "--robot", "fr3"], &format!("{{\"q\":{}}}\n", out[0]["q"]));
    for (a, b) in floats(&back[0]["position"]).iter().zip(floats(&fk[0]["position"])) {
        assert!((a - b).abs() <= 1e-5, "{back:?} vs {fk:?}");
    }
    // FR3 limits: J6 stays at or above 0.4398.
    assert!(floats(&out[0]["q"])[5] >= 0.4398, "{}", out[0]);
    assert!(out[1]["error"].as_str().is_some_and(|e| e.starts_with("not JSON")), "{}", out[1]);
    assert!(
        out[2]["error"].as_str().is_some_and(|e| e.contains("\"position\" must have 3 numbers, got 2")),
        "{}",
        out[2]
    );
    assert_eq!(out[3]["ok"], false, "{}", out[3]);
    assert!(out[3]["position_error"].as_f64().is_some_and(|e| e.is_finite() && e > 1.0), "{}", out[3]);
}

#[test]
fn unknown_robot_is_a_clear_failure() {
    let out = Command::new(integration_tests::r2g())
        .args(["kin", "fk", "--robot", "no_such_robot"])
        .stdin(Stdio::null())
        .output()
        .expect("run");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no robot 'no_such_robot'"), "{err}");
}
