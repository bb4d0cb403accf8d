//! Killing any one process stops the others cleanly, leaves no orphan, and leaves nothing that
//! blocks the next `r2g up` of the same instance.

use std::time::Duration;

use integration_tests::{become_subreaper, instance, running, sigkill, wait_gone, Up};

const GYM: &str = "pick_block_plate";

fn killing_a_child_stops_the_instance(victim: &str, other: &str, tag: &str) {
    become_subreaper();
    let name = instance(tag);
    let mut up = Up::start(GYM, &name, &[]);
    let victim_pid = up.child_pid(victim);
    let other_pid = up.child_pid(other);
    sigkill(victim_pid);
    let code = up.wait_exit(Duration::from_secs(20)).expect("r2g up must stop after its child was killed");
    assert_eq!(code, Some(1), "r2g up exits 1 when a child dies");
    let log = up.stderr_lines.join("\n");
    assert!(log.contains(&format!("{victim} (pid {victim_pid}) was killed by signal 9")), "{log}");
    assert!(wait_gone(other_pid, Duration::from_secs(10)), "{other} (pid {other_pid}) still running");
    assert!(!running(victim_pid));
    drop(up);
    // The same instance starts again: nothing stale blocks it.
    let again = Up::start(GYM, &name, &[]);
    drop(again);
}

#[test]
fn sigkill_of_the_sim_host_stops_the_runtime_and_up_restarts() {
    killing_a_child_stops_the_instance("r2g-sim", "r2g-control", "ks");
}

#[test]
fn sigkill_of_the_runtime_stops_the_sim_host_and_up_restarts() {
    killing_a_child_stops_the_instance("r2g-control", "r2g-sim", "kc");
}

#[test]
fn sigkill_of_the_supervisor_leaves_no_orphans_and_up_restarts() {
    become_subreaper();
    let name = instance("ku");
    let up = Up::start(GYM, &name, &[]);
    let sim = up.child_pid("r2g-sim");
    let control = up.child_pid("r2g-control");
    sigkill(up.child.id() as i32);
    assert!(wait_gone(sim, Duration::from_secs(10)), "r2g-sim outlived its supervisor");
    assert!(wait_gone(control, Duration::from_secs(10)), "r2g-control outlived its supervisor");
    drop(up);
    let again = Up::start(GYM, &name, &[]);
    drop(again);
}

#[test]
fn a_second_up_of_a_running_instance_is_refused_clearly() {
    let name = instance("dup");
    let _first = Up::start(GYM, &name, &[]);
    let out = std::process::Command::new(integration_tests::r2g())
        .args(["up", GYM, "--instance", &name])
        .output()
        .expect("run r2g up");
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("already running"), "{err}");
}

#[test]
fn bad_input_to_up_is_a_clear_error() {
    let out = std::process::Command::new(integration_tests::r2g()).args(["up", "no_such_gym"]).output().expect("run");
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no gym 'no_such_gym'") && err.contains("pick_block_plate"), "{err}");
    let out = std::process::Command::new(integration_tests::r2g())
        .args(["up", GYM, "--instance", "a/b"])
        .output()
        .expect("run");
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("instance name"));
}

#[test]
fn a_malformed_scene_is_refused_with_its_problem() {
    let dir = std::env::temp_dir().join(format!("r2g-bad-scene-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp dir");
    let scene = dir.join("scene.toml");
    let good = std::fs::read_to_string(integration_tests::root().join("gyms/pick_block_plate/scene.toml"))
        .expect("scene")
        .replace("../../robots", &integration_tests::root().join("robots").display().to_string());
    // A short joint list, an unknown limit profile and a half-given workspace are each named.
    for (text, expect) in [
        (
            "name = \"x\"\n[robot]\nurdf = \"nope.urdf\"\ninitial_joints_rad = [0, 0, 0]\n".to_string(),
            "initial_joints_rad",
        ),
        (good.replace("tcp_link = \"hand_tcp\"", "tcp_link = \"hand_tcp\"\nlimits = \"ur5\""), "limits = \"ur5\""),
        (format!("{good}\n[safety]\nworkspace_min_m = [0, 0, 0]\n"), "workspace_max_m"),
    ] {
        std::fs::write(&scene, text).expect("write");
        let out = std::process::Command::new(integration_tests::r2g())
            .args(["up", scene.to_str().expect("utf8"), "--instance", &instance("bad")])
            .output()
            .expect("run");
        assert_eq!(out.status.code(), Some(1));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expect), "{err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn down_returns_once_up_has_exited_with_its_last_verdict_written() {
    let name = instance("dn");
    let traces = std::env::temp_dir().join(format!("r2g-down-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&traces);
    let mut up = Up::start(GYM, &name, &["--mode", "lockstep", "--trace-dir", traces.to_str().expect("utf-8")]);
    let pid_file = ipc_schema::process::run_dir(&name).join("up.pid");
    let pid: u32 = std::fs::read_to_string(&pid_file).expect("r2g up writes its pid").trim().parse().expect("a pid");
    assert_eq!(pid, up.child.id());
    let down = |name: &str| {
        std::process::Command::new(integration_tests::r2g())
            .args(["down", "--instance", name])
            .output()
            .expect("run r2g down")
    };
    let out = down(&name);
    assert_eq!(out.status.code(), Some(0), "{}", String::from_utf8_lossy(&out.stderr));
    // Returned only after `r2g up` exited (0: stopped on request) and the episode was judged.
    assert_eq!(up.wait_exit(Duration::from_millis(200)), Some(Some(0)), "r2g up still runs after r2g down");
    assert!(traces.join("episode-1.eval.json").is_file(), "the last verdict is written before down returns");
    assert!(!pid_file.exists(), "the pid file goes with the instance");
    // Nothing runs any more: a clear refusal, nothing signalled.
    let out = down(&name);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no `r2g up` of instance"));
    // A stale file naming a process that is not this instance's `r2g up` (this test): refused.
    std::fs::create_dir_all(pid_file.parent().expect("run folder")).expect("run folder");
    std::fs::write(&pid_file, format!("{}\n", std::process::id())).expect("plant a stale pid file");
    let out = down(&name);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("nothing was signalled"));
    let _ = std::fs::remove_file(&pid_file);
    let _ = std::fs::remove_dir_all(&traces);
}
