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

#[test]
fn bench_ipc_measures_zeromq_too() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let out =
        Command::new(integration_tests::r2g()).args(["bench", "ipc", "--only", "zmq:command"]).output().expect("run");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v = last_json_line(&out.stdout);
    assert!(v["zmq"]["command_p50_us"].as_f64().is_some_and(|x| x > 0.0), "{v}");
    assert!(v["zmq"]["command_msgs_per_s"].as_f64().is_some_and(|x| x > 100.0), "{v}");
}

#[test]
fn bench_all_writes_a_report_with_plots() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = std::env::temp_dir().join(format!("r2g-bench-report-{}", std::process::id()));
    let out = Command::new(integration_tests::r2g())
        .args(["bench", "all", "--quick", "--jitter-seconds", "3", "--out", dir.to_str().expect("utf8")])
        .output()
        .expect("run");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v = last_json_line(&out.stdout);
    for k in ["iceoryx2.frame_p50_us", "uds.frame_p50_us", "zmq.frame_p50_us", "runtime.p999_us", "baseline.p999_us"] {
        assert!(v[k].as_f64().is_some_and(|x| x > 0.0), "{k} missing: {v}");
    }
    assert!(v["runtime.overruns"].is_u64(), "{v}");
    let summary = std::fs::read_to_string(dir.join("summary.md")).expect("summary.md");
    assert!(summary.contains("| iceoryx2 | frame |") && summary.contains("| runtime |"), "{summary}");
    // The Python agent really ran during the jitter run.
    let jitter: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("jitter.json")).expect("jitter.json")).expect("json");
    assert!(jitter["agent_load"]["get_state_numeric"].as_u64().is_some_and(|n| n > 0), "{jitter}");
    for png in ["ipc_frame_cdf.png", "jitter_wake_cdf.png", "jitter_wake_hist.png"] {
        let bytes = std::fs::read(dir.join(png)).unwrap_or_else(|e| panic!("{png}: {e}"));
        assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 5000, "{png} is not a drawn PNG");
    }
    for name in ["ipc", "jitter", "tick", "tick_compute", "ik", "limiter_fuzz", "sim"] {
        let j: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join(format!("{name}.json"))).expect("json"))
                .expect("valid JSON");
        assert!(j.get("error").is_none(), "{name} failed: {j}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bench_soak_reports_ticks_stall_memory_and_shared_memory() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let out = Command::new(integration_tests::r2g())
        .args(["bench", "soak", "--minutes", "0.3", "--stall-s", "2", "--sample-s", "1"])
        .output()
        .expect("run");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v = last_json_line(&out.stdout);
    assert_eq!(v["bench"], "soak");
    for k in ["/ticks", "/missed_ticks", "/wake_p999_us", "/baseline_wake_p999_us", "/ratio", "/agent_chunks"] {
        assert!(v.pointer(k).and_then(|x| x.as_f64()).is_some_and(f64::is_finite), "{k} missing: {v}");
    }
    for k in ["seconds", "missed_ticks", "wake_max_us", "before_missed_ticks"] {
        assert!(v["stall"][k].as_f64().is_some_and(f64::is_finite), "stall.{k} missing: {v}");
    }
    for p in ["r2g-sim", "r2g-control", "agent", "r2g-bench"] {
        for k in ["start", "end", "growth"] {
            assert!(v["rss_kib"][p][k].as_f64().is_some_and(f64::is_finite), "rss_kib.{p}.{k} missing: {v}");
        }
    }
    assert!(v["shm_files"]["before"].is_u64() && v["shm_files"]["after"].is_u64(), "{v}");
    assert!(v["shm_files"]["left_over"].is_array(), "{v}");
    assert!(v["agent_chunks"].as_u64().is_some_and(|n| n > 0), "the agent posted nothing: {v}");
}
