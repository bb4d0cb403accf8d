//! Calls into the host-side Python geometry (`agent-host/py/skill_tools.py`): perception and
//! rule binding live in Python (robo_perception, robo_skills), next to what stage programs use,
//! so a rule extracted here binds exactly as it will when it runs.

use std::io::Write as _;
use std::path::Path;
use std::process::{Command, Stdio};

use anyhow::{bail, Context};
use serde_json::Value;

/// Runs `skill_tools.py <cmd>` with `request` on stdin; its JSON answer, or its error.
pub fn call(root: &Path, cmd: &str, request: &Value) -> anyhow::Result<Value> {
    let py = root.join(".venv/bin/python");
    let script = root.join("agent-host/py/skill_tools.py");
    let mut child = Command::new(&py)
        .arg(&script)
        .arg(cmd)
        .env("MUJOCO_GL", "egl")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .with_context(|| format!("starting {} {}", py.display(), script.display()))?;
    child.stdin.take().context("stdin")?.write_all(request.to_string().as_bytes())?;
    let out = child.wait_with_output()?;
    let text = String::from_utf8_lossy(&out.stdout);
    let answer: Value = text.lines().last().and_then(|l| serde_json::from_str(l).ok()).with_context(|| {
        format!("skill_tools.py {cmd} gave no answer: {}", String::from_utf8_lossy(&out.stderr).trim())
    })?;
    if let Some(e) = answer.get("error") {
        bail!("skill_tools.py {cmd}: {}", e.as_str().unwrap_or_default());
    }
    Ok(answer)
}
