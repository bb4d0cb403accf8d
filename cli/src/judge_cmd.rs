//! `r2g judge`: arguments, and the two things `real2sim::judge` is handed: the renderers (this
//! binary's own `r2g render` and `r2g blender`, run as child processes) and the endpoint call
//! (`agent_host::llm`).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use agent_host::llm::{Client, Message, Part, Role};
use agent_host::session;
use anyhow::{bail, Context};
use real2sim::judge::{self, Engine, RenderRequest, Reply};
use serde_json::json;

#[derive(clap::Args, Debug)]
pub struct JudgeArgs {
    /// Gym name, gym folder, or scene file.
    pub gym: String,
    /// An endpoint TOML file (agent-host/endpoints/), "record:<toml>", "replay:<cassette.jsonl>",
    /// or "scripted[:<answers.json>]": the scripted server on loopback answering with a synthetic
    /// answer written in advance (default: real2sim/judge/scripted/<gym>.json). "scripted" is the
    /// default, as for `r2g episode` and `r2g skills extract`: r2g has no configured endpoint of
    /// its own, so a real grade needs an endpoint file named here. Scores from the scripted
    /// endpoint test the mechanics only; they are not measurements, and the output says so first.
    #[arg(long, default_value = "scripted")]
    pub llm: String,
    /// Wire format for `--llm scripted`: openai or anthropic.
    #[arg(long, default_value = "openai")]
    pub provider: String,
    /// Folder for judge.json, the evidence and the raw answer (must not exist, or be empty;
    /// default: runs/judge/<gym>-<unix seconds>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Source frames in the BOP layout (default: the gym's frames/, else the folder its
    /// reconstruction.json names; without any, the scene file is the reference).
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// Source frames sent at most (spread over the image ids).
    #[arg(long, default_value_t = 3)]
    pub max_frames: usize,
    /// A native verdict already computed: `r2g validate`'s evidence.json or JSON line, or the
    /// evaluation `r2g replay` prints (saved to a file). Default: `r2g validate` runs here.
    #[arg(long)]
    pub verdict: Option<PathBuf>,
    /// The native trace of --verdict (default: trace.json beside the evidence).
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// Scene camera the execution is rendered from (default: the first fixed camera).
    #[arg(long)]
    pub camera: Option<String>,
    /// Instants of the execution to render, s (default: start, grasps, releases, end).
    #[arg(long, value_delimiter = ',')]
    pub at: Option<Vec<f64>>,
    /// Send no Blender images (the request says they were not requested).
    #[arg(long)]
    pub no_blender: bool,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Runs `r2g render` or `r2g blender` of this binary into `out` (BOP layout).
fn render(engine: Engine, scene: &Path, req: &RenderRequest, out: &Path) -> anyhow::Result<()> {
    let exe = std::env::current_exe().context("the path of this r2g")?;
    // A binary rebuilt while this one runs leaves /proc/self/exe naming "<path> (deleted)"; the
    // path itself then holds the new build.
    let exe = exe.to_str().and_then(|s| s.strip_suffix(" (deleted)")).map_or(exe.clone(), PathBuf::from);
    let mut cmd = Command::new(&exe);
    let at: Vec<String> = req.at.iter().map(|t| format!("{t}")).collect();
    match engine {
        Engine::Mujoco => {
            cmd.arg("render").arg(scene).arg("--out").arg(out);
            if let Some(c) = &req.cameras {
                cmd.arg("--cameras").arg(c);
            }
        }
        Engine::Blender => {
            cmd.arg("blender").arg(scene).arg("--out").arg(out.with_extension("blend")).arg("--render").arg(out);
            if let Some(c) = &req.cameras {
                cmd.arg("--cameras").arg(c);
            }
        }
    }
    for c in &req.camera {
        cmd.arg("--camera").arg(c);
    }
    if let Some(t) = &req.trace {
        cmd.arg("--trace").arg(t);
    }
    match (engine, at.is_empty()) {
        (_, false) => {
            cmd.arg("--at").arg(at.join(","));
        }
        // Blender at rest: the first instant.
        (Engine::Blender, true) => {
            cmd.args(["--at", "0"]);
        }
        (Engine::Mujoco, true) => {}
    }
    let shown = format!("r2g {}", cmd.get_args().map(|a| a.to_string_lossy()).collect::<Vec<_>>().join(" "));
    eprintln!("r2g judge: {shown}");
    let o = cmd.stdin(Stdio::null()).output().with_context(|| format!("starting {shown}"))?;
    if !o.status.success() {
        let err = String::from_utf8_lossy(&o.stderr);
        let tail: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
        bail!("{shown} failed ({}): {}", o.status, tail[tail.len().saturating_sub(3)..].join(" | "));
    }
    Ok(())
}

pub fn run(a: JudgeArgs) -> anyhow::Result<i32> {
    let scene = runtime::launch::resolve_scene(&a.gym)?;
    let name = scene.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let out = std::path::absolute(a.out.clone().unwrap_or_else(|| judge::default_out(&name)))?;
    let mut o = judge::Options::new(out.clone());
    o.frames = a.frames.as_deref().map(std::path::absolute).transpose()?;
    o.verdict = a.verdict.as_deref().map(std::path::absolute).transpose()?;
    o.trace = a.trace.as_deref().map(std::path::absolute).transpose()?;
    o.camera = a.camera.clone();
    o.at = a.at.clone();
    if let Some(at) = &o.at {
        if let Some(t) = at.iter().find(|t| !(t.is_finite() && **t >= 0.0)) {
            bail!("--at: {t} is not a time (seconds, >= 0)");
        }
    }
    o.max_frames = a.max_frames;
    o.blender = !a.no_blender;
    o.seed = a.seed;

    let scripted = a.llm == "scripted" || a.llm.starts_with("scripted:");
    if scripted {
        eprintln!(
            "r2g judge: mechanics only: --llm {} answers with a synthetic answer written in advance; the scores are not measurements",
            a.llm
        );
    }
    // The scripted default is this gym's synthetic judge answer; it grades Blender images, so a
    // run without them takes the variant that leaves that part ungraded.
    let suffix = if a.no_blender { "-no-blender" } else { "" };
    let default_script = session::root().join("real2sim/judge/scripted").join(format!("{name}{suffix}.json"));
    if a.llm == "scripted" && !default_script.is_file() {
        bail!(
            "--llm scripted: no synthetic judge answer for gym '{name}' ({} is missing); give scripted:<answers.json> or an endpoint file",
            default_script.display()
        );
    }
    // The endpoint is set up only once the evidence is gathered and the request is ready.
    let ask = |system: &str, parts: &[judge::Part]| -> anyhow::Result<Reply> {
        // The scripted server logs into <out>/llm-log; `record:` keeps <out>/cassette.jsonl.
        let (endpoint, _scripted, source) = session::endpoint(&a.llm, &a.provider, &name, Some(&default_script), &out)?;
        let client = Client::new(endpoint.clone())?;
        let parts: Vec<Part> = parts
            .iter()
            .map(|p| match p {
                judge::Part::Text(t) => Part::Text(t.clone()),
                judge::Part::Png(b) => Part::Png(b.clone()),
            })
            .collect();
        eprintln!("r2g judge: asking {} ({}, {source})", endpoint.model, endpoint.base_url);
        let c = client.complete(system, &[Message { role: Role::User, parts }])?;
        Ok(Reply {
            text: c.text,
            model: endpoint.model.clone(),
            source: source.to_string(),
            provider: endpoint.provider.clone(),
            usage: json!({"input": c.usage.input, "cached": c.usage.cached, "output": c.usage.output,
                          "reasoning": c.usage.reasoning}),
            attempts: c.attempts,
            wall_s: c.wall_s,
            truncated: c.truncated,
        })
    };
    let r = judge::run(&scene, &o, &render, &ask)?;
    let v = &r.record;
    for m in v["request"]["missing_evidence"].as_array().into_iter().flatten() {
        eprintln!("r2g judge: missing evidence: {}", m.as_str().unwrap_or_default());
    }
    eprintln!("r2g judge: {}", v["label"].as_str().unwrap_or_default());
    let s = &v["scores"];
    for k in ["content_alignment", "viewpoint_alignment", "action_fidelity", "task_completion", "simulation_success"] {
        eprintln!("  {k:<20} {}", s[k]);
        if k == "content_alignment" && s["content_alignment_partial"] == true {
            eprintln!(
                "    (partial: MuJoCo part {}, Blender part {}; {})",
                s["content_alignment_mujoco"],
                s["content_alignment_blender"],
                s["content_alignment_basis"].as_str().unwrap_or_default()
            );
        }
        if k == "action_fidelity" && !s["action_fidelity_rule"].is_null() {
            eprintln!("    ({})", s["action_fidelity_rule"].as_str().unwrap_or_default());
        }
    }
    if v["override"]["applied"] == true {
        eprintln!("  physical-failure override applied: {}", v["override"]["reasons"]);
    }
    println!(
        "{}",
        json!({"gym": v["gym"], "judge": r.path.display().to_string(), "measurement": v["measurement"],
               "label": v["label"],
               "scores": {"content_alignment": s["content_alignment"],
                          "content_alignment_mujoco": s["content_alignment_mujoco"],
                          "content_alignment_blender": s["content_alignment_blender"],
                          "viewpoint_alignment": s["viewpoint_alignment"],
                          "action_fidelity": s["action_fidelity"], "task_completion": s["task_completion"],
                          "simulation_success": s["simulation_success"]},
               "override": v["override"]["applied"], "model": v["llm"]["model"], "tokens": v["llm"]["usage"]})
    );
    Ok(0)
}
