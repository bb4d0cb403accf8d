//! What the model is told: the system prompt (the robot-skill documents, the answer format, the
//! configuration in force, the skills section), the first message (the run's backend, mode,
//! limits, budgets and memory before the model needs them) and the feedback after each program
//! (the program's own robot calls, its output, the state before and after, what it showed).
//!
//! Every sentence here must be true of the run it is sent in: a text that names a document or a
//! helper is matched by a file the program can read or a module it can import (the tests check
//! both), and numbers come from the run, never from defaults.

use std::path::Path;

use serde_json::Value;

use crate::worker::{Budget, ExecResult, Limits};

/// Documents given whole in the system prompt, in this order (the profile document is chosen by
/// the backend and follows `api/README.md`). Chosen by measurement (agent-host/README.md,
/// "What the model is told"): every one is needed by every episode, and inlined they are part
/// of the prefix a provider caches.
const INLINE: [&str; 4] = ["SKILL.md", "api/README.md", "api/PERCEPTION.md", "memory/README.md"];

/// Files a stage program reads when it needs them (`robot-skill/<path>` from its scratch folder),
/// with what each holds. `skills/README.md` is given whole instead when skills are offered.
pub const READABLE: [(&str, &str); 6] = [
    (
        "examples/pick_object.py",
        "a whole pick with robo_perception (pre-grasp, look again, descend, close, lift, verify)",
    ),
    ("examples/place_object.py", "a whole pick and place onto another object with robo_perception.place_poses"),
    ("examples/close_door.py", "a hinged door pushed shut round its hinge (robo_perception.measure_hinged)"),
    ("examples/push_past_line.py", "an object pushed with the closed fingers until all of it is past a line"),
    ("skills/README.md", "the format of skill files and how to run one with robo_skills"),
    ("config/perception.json", "whether perception runs locally or through the operator's services (robo_services)"),
];

/// Modules a stage program may import; anything else outside the standard library fails with
/// ImportError (agent-host/py/runner.py enforces the same list).
pub const MODULES: &str =
    "robo, robo_perception, robo_skills, robo_services, robo_memory, numpy and the Python standard library";

fn read_doc(root: &Path, rel: &str) -> String {
    std::fs::read_to_string(root.join("robot-skill").join(rel)).unwrap_or_else(|_| format!("({rel} is missing)"))
}

fn profile_doc(profile: &str) -> &'static str {
    if profile == "franka" {
        "api/FRANKA.md"
    } else {
        "api/SIMULATION.md"
    }
}

/// The system prompt. Its static part comes first (documents, the list of readable files, the
/// answer format) so that providers' prompt caches hold it across requests and episodes; then
/// the configuration in force (`robot_config`: the file's text) and the skills section.
pub fn system_prompt(root: &Path, profile: &str, robot_config: &str, skills: &str) -> String {
    let mut s = String::from(
        "You control a robot arm by writing Python stage programs. Your instructions are the documents of the \
         robot-skill folder. The ones below are given whole; the others are listed after them and a stage program \
         can read them (read-only) at the path shown, relative to its current folder (your observation-only first \
         program may read them too).\n\n",
    );
    let mut docs: Vec<&str> = INLINE.to_vec();
    docs.insert(2, profile_doc(profile));
    if !skills.is_empty() {
        docs.push("skills/README.md");
    }
    for doc in &docs {
        s.push_str(&format!("===== robot-skill/{doc} =====\n{}\n\n", read_doc(root, doc)));
    }
    s.push_str("===== Readable files (not included above) =====\n");
    for (path, what) in READABLE.iter().filter(|(p, _)| !docs.contains(p)) {
        s.push_str(&format!("- robot-skill/{path}: {what}\n"));
    }
    let other = profile_doc(if profile == "franka" { "simulation" } else { "franka" });
    s.push_str(&format!(
        "- robot-skill/{other}: the other profile (not in force here)\n\
         - robot-skill/memory/: the memory records kept so far (list the folder; memory/README.md above says which to use)\n\n"
    ));
    s.push_str(&DECISION_FORMAT.replace("{modules}", MODULES));
    s.push_str(&format!(
        "\n===== robot-skill/config/robot.json (the configuration in force) =====\n{}\n\n",
        robot_config.trim_end()
    ));
    s.push_str(&format!(
        "===== Skills =====\n{}\n",
        if skills.is_empty() { "(none offered in this episode)" } else { skills }
    ));
    s
}

const DECISION_FORMAT: &str = "===== How to answer =====
Every reply is one decision in this form:
<observation>what the latest images and measured state show</observation>
<plan>what this stage does, its entry conditions and how you will know it worked</plan>
<code>
one complete Python program for this stage
</code>
<expected>the visible effect you expect once it ran</expected>
When the task is done (or cannot be done), reply with <observation>...</observation> and
<stop>why you stop</stop> instead of code.

The program runs in a fresh Python process in a sandbox. Its current folder is a scratch folder
kept for the whole episode: files it saves there stay for later programs (a module you save there can
be imported by them). robot-skill/ in that folder is these documents (read-only); memory/ is where
new memory records go. A program may import {modules}, its own modules
and the examples (after sys.path.insert(0, \"robot-skill/examples\")); any other import fails with
ImportError. No network, no
subprocesses, no files outside the scratch folder and robot-skill/. The first message gives the
budgets (control steps and time per program, decisions per episode).

After each program you get: how it ended, its chunks executed / failed / rejected and resets, the
status and reason of its own last robot call, the time it used (simulated time in lockstep mode,
wall-clock time in wall mode), its stdout and stderr, the
measured state before and after it, fresh images of every camera, and the images it handed over with
robo_perception.show() (api/PERCEPTION.md, \"Showing images\").
";

/// One line of numeric state.
pub fn state_line(s: &Value) -> String {
    let r = |v: &Value| -> String {
        v.as_array()
            .map(|a| a.iter().map(|x| format!("{:.4}", x.as_f64().unwrap_or(f64::NAN))).collect::<Vec<_>>().join(", "))
            .unwrap_or_default()
    };
    format!(
        "joint [{}]; ee_pose [{}]; gripper [{}]; external_force_n [{}]; timestamp {:.3}; control_type {}; fault {}",
        r(&s["joint"]),
        r(&s["ee_pose"]),
        r(&s["gripper"]),
        r(&s["external_force_n"]),
        s["timestamp"].as_f64().unwrap_or(0.0),
        s["control_type"],
        s["fault"],
    )
}

/// The memory fingerprint of the setup `state` comes from, as robot-skill/memory/README.md
/// defines it (and `robo_memory.fingerprint()` computes it in a program).
pub fn memory_fingerprint(state: &Value) -> Value {
    serde_json::json!({
        "gym": state["setup"]["gym"],
        "robot_config_sha256": state["setup"]["robot_config_sha256"],
        "backend": state["backend"],
    })
}

/// How many records the memory folder `dir` holds, and how many of them carry `fingerprint`.
pub fn memory_counts(dir: Option<&Path>, fingerprint: &Value) -> (usize, usize) {
    let Some(rd) = dir.and_then(|d| std::fs::read_dir(d).ok()) else { return (0, 0) };
    let (mut all, mut matching) = (0, 0);
    for e in rd.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if !crate::memory::is_record_name(&name) {
            continue;
        }
        all += 1;
        let Ok(text) = std::fs::read_to_string(e.path()) else { continue };
        if serde_json::from_str::<Value>(&text).is_ok_and(|r| &r["fingerprint"] == fingerprint) {
            matching += 1;
        }
    }
    (all, matching)
}

/// What the first message says about the run before anything else.
pub struct RunFacts<'a> {
    pub profile: &'a str,
    pub max_decisions: u32,
    pub budget: Budget,
    pub limits: &'a Limits,
    pub memory: (usize, usize),
}

/// The first message: the run's facts, the state now, and what to do in this turn.
pub fn first_message(state: &Value, f: &RunFacts, cameras: &[String]) -> String {
    let mode = match state["mode"].as_str() {
        Some("lockstep") => "lockstep (simulated time advances only while reset() or post_actions() runs)",
        Some("wall") => "wall (real time: the world moves between your calls too)",
        _ => "unknown",
    };
    let safety = serde_json::to_string(&state["effective_safety"]).unwrap_or_default();
    let fingerprint = memory_fingerprint(state);
    format!(
        "First, observation only.\n\n\
         This run: backend {backend}, mode {mode}; the profile document in force is robot-skill/{doc}.\n\
         Budgets: {decisions} decisions in this episode (this reply is the first); each program may post at most \
         {steps} waypoints in all (control steps; more are refused) and runs for at most {wall:.0} s of wall-clock time \
         and {cpu} s of CPU time (then the sandbox stops it).\n\
         Limits in force (effective_safety): {safety}\n\
         Memory: the fingerprint of this setup (robot-skill/memory/README.md) is {fingerprint}; robot-skill/memory/ \
         holds {records} record(s), {matching} with this fingerprint.\n\
         get_state() now: {line}. Attached: the images of {cams}.\n\n\
         Report the measured joints, TCP pose, gripper, what each camera shows, and the frame conventions and limits \
         that apply. Do not move the robot in this turn: reset() and post_actions() are refused. You may include a \
         <code> program that only observes (it may read the documents and memory records). Then wait for the task.",
        backend = state["backend"].as_str().unwrap_or("unknown"),
        doc = profile_doc(f.profile),
        decisions = f.max_decisions,
        steps = f.budget.control_steps,
        wall = f.limits.wall_s,
        cpu = f.limits.cpu_s,
        records = f.memory.0,
        matching = f.memory.1,
        line = state_line(state),
        cams = cameras.join(" and "),
    )
}

/// Simulated time a program used, s: from the state before it to the state after it, across
/// its resets (each restarts the clock at 0), never negative. `calls` is its calls.json log.
pub fn simulated_s(before: &Value, after: &Value, calls: &[Value]) -> f64 {
    let t = |v: &Value| v.as_f64().filter(|x| x.is_finite());
    let mut cursor = t(&before["timestamp"]).unwrap_or(0.0);
    let mut total = 0.0;
    for c in calls {
        let (t0, t1) = (t(&c["t_before"]), t(&c["t_after"]));
        if c["fn"] == "reset" {
            total += (t0.unwrap_or(cursor) - cursor).max(0.0);
            cursor = 0.0;
        } else if let Some(t0) = t0 {
            total += (t0 - cursor).max(0.0);
            cursor = t0;
        }
        if let Some(t1) = t1 {
            total += (t1 - cursor).max(0.0);
            cursor = t1;
        }
    }
    total + (t(&after["timestamp"]).unwrap_or(cursor) - cursor).max(0.0)
}

/// An image a program handed over (`show/`), or why one was not shown.
pub enum Shown {
    Image { name: String, width: u32, height: u32 },
    Refused { name: String, why: String },
}

/// The text after a program ran.
pub struct Feedback<'a> {
    pub n: u32,
    pub result: &'a ExecResult,
    pub before: &'a Value,
    pub after: &'a Value,
    pub budget: Budget,
    pub decisions_left: u32,
    pub max_decisions: u32,
    pub lockstep: bool,
    pub shown: &'a [Shown],
    pub cameras: &'a [String],
}

/// Refused hand-over files named one by one in the feedback; the rest are counted.
const MAX_REFUSED_LINES: usize = 8;

fn count(m: &std::collections::BTreeMap<String, u64>, k: &str) -> u64 {
    m.get(k).copied().unwrap_or(0)
}

pub fn feedback_text(f: &Feedback) -> String {
    let r = f.result;
    // In lockstep the wall clock says nothing about the robot and would make each request
    // differ from run to run (a replayed cassette needs the same requests): simulated time.
    let took = if f.lockstep {
        format!("{:.3} s of simulated time", simulated_s(&f.before["state"], &f.after["state"], &r.calls))
    } else {
        format!("{:.1} s of wall-clock time", r.wall_s)
    };
    let steps = if f.budget.observe_only {
        "no control steps (observation only)".to_string()
    } else {
        format!("control steps used {} of {}", r.control_steps, f.budget.control_steps)
    };
    let mut t = format!(
        "Stage program {} ended: {}{}; {took}; {steps}; robot calls {}.\n",
        f.n,
        r.exit,
        r.exit_code.map(|c| format!(" (exit code {c})")).unwrap_or_default(),
        r.robot_calls,
    );
    t.push_str(&format!(
        "Its chunks: {} executed, {} failed, {} rejected; resets: {} done, {} refused.\n",
        count(&r.chunks, "executed"),
        count(&r.chunks, "failed"),
        count(&r.chunks, "rejected"),
        count(&r.resets, "done"),
        count(&r.resets, "refused"),
    ));
    match &r.last_call {
        Some(c) => {
            let mut executed = match c["executed"].as_u64() {
                Some(n) if c["fn"] == "post_actions" => format!(", {n} waypoint(s) executed"),
                _ => String::new(),
            };
            let contact = &c["contact"];
            if let (Some(peak), Some(mean)) = (contact["peak_n"].as_f64(), contact["mean_n"].as_f64()) {
                let at = match contact["peak_waypoint"].as_u64() {
                    Some(w) => format!(" (heading for waypoint {w})"),
                    None => String::new(),
                };
                let start = match contact["start_n"].as_f64() {
                    Some(s) => format!(", {s:.2} N at its start"),
                    None => String::new(),
                };
                executed.push_str(&format!(
                    "; contact force over the chunk: peak {peak:.2} N{at}, mean {mean:.2} N{start}"
                ));
            }
            t.push_str(&format!(
                "Its last robot call: {}() → {} — {}{executed}.\n",
                c["fn"].as_str().unwrap_or("?"),
                c["status"],
                c["reason"],
            ));
        }
        None => t.push_str("Its last robot call: none (it sent no reset() or post_actions()).\n"),
    }
    if let Some(v) = &r.violation {
        t.push_str(&format!("SANDBOX: {v}\n"));
    }
    if r.budget_refusals > 0 {
        t.push_str(&format!("{} robot call(s) were refused by the control-step budget.\n", r.budget_refusals));
    }
    if r.observe_refusals > 0 {
        t.push_str(&format!("{} robot call(s) were refused: this turn is observation-only.\n", r.observe_refusals));
    }
    for (name, body) in [("stdout", &r.stdout), ("stderr", &r.stderr)] {
        t.push_str(&format!("--- {name} ---\n{}\n", if body.is_empty() { "(empty)" } else { body.trim_end() }));
    }
    if let Some(e) = &r.exception {
        t.push_str(&format!("--- exception ---\n{}\n", e.trim_end()));
    }
    t.push_str(&format!(
        "State before: {}\nState after:  {}\n",
        state_line(&f.before["state"]),
        state_line(&f.after["state"])
    ));
    let shown: Vec<String> = f
        .shown
        .iter()
        .filter_map(|s| match s {
            Shown::Image { name, width, height } => Some(format!("{} ({width}x{height})", name.escape_debug())),
            Shown::Refused { .. } => None,
        })
        .collect();
    t.push_str(&format!("Attached: fresh images of {} after the program", f.cameras.join(" and ")));
    if shown.is_empty() {
        t.push_str(".\n");
    } else {
        t.push_str(&format!(", then the images it showed: {}.\n", shown.join(", ")));
    }
    let refused: Vec<_> = f
        .shown
        .iter()
        .filter_map(|s| match s {
            Shown::Refused { name, why } => Some((name, why)),
            Shown::Image { .. } => None,
        })
        .collect();
    for (name, why) in refused.iter().take(MAX_REFUSED_LINES) {
        t.push_str(&format!("Not shown: {}: {why}\n", name.escape_debug()));
    }
    if refused.len() > MAX_REFUSED_LINES {
        t.push_str(&format!("Not shown either: {} more file(s) in show/.\n", refused.len() - MAX_REFUSED_LINES));
    }
    t.push_str(&format!("Decisions left: {} of {}.\n", f.decisions_left, f.max_decisions));
    t
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn py(rel: &str) -> String {
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)).expect("a file of the crate")
    }

    /// The Python sides state the same lists and limits as the texts the model reads.
    #[test]
    fn the_modules_and_hand_over_limits_agree_with_the_python_that_enforces_them() {
        let runner = py("py/runner.py");
        let line = runner.lines().find(|l| l.starts_with("SUPPORTED = (")).expect("SUPPORTED in runner.py");
        let mut enforced: Vec<&str> = line.split('"').skip(1).step_by(2).collect();
        enforced.sort_unstable();
        let told = MODULES.trim_end_matches(" and the Python standard library");
        let mut told: Vec<&str> = told.split(", ").collect();
        told.sort_unstable();
        assert_eq!(enforced, told);
        let images = py("py/lib/robo_perception/images.py");
        for (name, value) in [
            ("MAX_SHOWN", crate::episode::MAX_SHOWN as u64),
            ("MAX_SHOWN_SIDE", u64::from(crate::episode::MAX_SHOWN_SIDE)),
            ("MAX_SHOWN_BYTES", crate::episode::MAX_SHOWN_BYTES),
        ] {
            let line = images.lines().find(|l| l.starts_with(&format!("{name} = "))).expect(name);
            let v = line.split('=').nth(1).unwrap_or_default().trim();
            let v: u64 = match v.split_once(" << ") {
                Some((a, b)) => a.parse::<u64>().unwrap_or(0) << b.parse::<u32>().unwrap_or(0),
                None => v.parse().unwrap_or(0),
            };
            assert_eq!(v, value, "{name} in images.py");
        }
    }

    #[test]
    fn simulated_time_counts_across_a_reset_and_is_never_negative() {
        let before = json!({"timestamp": 10.883});
        let after = json!({"timestamp": 2.5});
        let calls = [
            json!({"fn": "post_actions", "t_before": 10.883, "t_after": 12.0}),
            json!({"fn": "reset", "t_before": 12.0, "t_after": 0.0}),
            json!({"fn": "post_actions", "t_before": 0.0, "t_after": 2.5}),
        ];
        assert!((simulated_s(&before, &after, &calls) - 3.617).abs() < 1e-9);
        // An old record's reset without t_before, and no calls at all.
        let calls = [json!({"fn": "reset", "t_after": 0.0}), json!({"fn": "post_actions", "t_after": 1.0})];
        assert!((simulated_s(&before, &json!({"timestamp": 1.0}), &calls) - 1.0).abs() < 1e-9);
        assert_eq!(simulated_s(&json!({"timestamp": 3.0}), &json!({"timestamp": 0.0}), &[]), 0.0);
    }
}
