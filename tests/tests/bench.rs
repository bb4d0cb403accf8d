//! The benchmarks run end to end and print their figures as the last line. Timing is not
//! asserted here: that belongs to `r2g bench`, whose figures go in the issue notes.

use std::process::Command;
use std::sync::Mutex;

/// Benchmarks busy-poll both cores: never two at once, or they measure each other.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn last_json_line(out: &[u8]) -> serde_json::Value {
    let text = String::from_utf8_lossy(out);
    let line = text.lines().last().unwrap_or_default();
    serde_json::from_str(line).unwrap_or_else(|e| panic!("last line is not JSON ({e}): {text}"))
}

#[test]
fn bench_ipc_measures_every_message_it_sends() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let out = Command::new(integration_tests::r2g())
        .args(["bench", "ipc", "--only", "iceoryx2:state"])
        .output()
        .expect("run");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v = last_json_line(&out.stdout);
    assert_eq!(v["bench"], "ipc");
    assert!(v["iceoryx2"]["state_p50_us"].as_f64().is_some_and(|x| x > 0.0), "{v}");
    assert!(v["iceoryx2"]["state_msgs_per_s"].as_f64().is_some_and(|x| x > 100.0), "{v}");
}

#[test]
fn bench_tick_reports_both_loops() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let out = Command::new(integration_tests::r2g()).args(["bench", "tick", "--seconds", "1"]).output().expect("run");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v = last_json_line(&out.stdout);
    for k in ["p50_us", "p999_us", "compute_p99_us"] {
        assert!(v["runtime"][k].as_f64().is_some(), "runtime.{k} missing: {v}");
    }
    for k in ["p50_us", "p999_us"] {
        assert!(v["baseline"][k].as_f64().is_some(), "baseline.{k} missing: {v}");
    }
    assert_eq!(v["runtime"]["tick_allocations"], 0, "{v}");
    assert!(v["runtime"]["ticks"].as_u64().is_some_and(|t| t > 500), "{v}");
}

#[test]
fn bench_ik_reports_solver_and_baselines() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let out = Command::new(integration_tests::r2g()).args(["bench", "ik", "--count", "300"]).output().expect("run");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v = last_json_line(&out.stdout);
    assert_eq!(v["bench"], "ik");
    assert_eq!(v["targets"], 300, "{v}");
    assert!(v["success_rate"].as_f64().is_some_and(|r| r >= 0.99), "{v}");
    for k in ["median_us", "p99_us", "max_us", "fk_us"] {
        assert!(v[k].as_f64().is_some_and(|x| x > 0.0), "{k} missing: {v}");
    }
    assert!(v["naive_pinv"]["success_rate"].as_f64().is_some(), "{v}");
    assert!(v["home_seed"]["success_rate"].as_f64().is_some(), "{v}");
    // Either measured or explicitly absent with the reason.
    assert!(v["pinocchio"]["median_us"].as_f64().is_some() || v["pinocchio_note"].is_string(), "{v}");
}
