//! `r2g judge`: a model grades a gym against its reference with our rubric
//! (`judge/rubric.md`, written after the paper's appendix), from evidence gathered here: the
//! source frames when the gym came from frames, MuJoCo and Blender images of the same instants,
//! the demonstration and its native execution summarised as text, and the native verdict.
//!
//! This module gathers the evidence, builds the request, checks the answer and computes the
//! scores; it neither renders nor talks to a network. Rendering ([`RenderFn`]) and the endpoint
//! call ([`AskFn`]) are handed in by the caller (`cli`: `r2g render`, `r2g blender`, and
//! `agent_host::llm`), so this crate keeps its layer.
//!
//! Viewpoint evidence is the gym's own cameras rendered at rest, each shown after the source frame
//! it stands for (a camera `cam_<id>`, as `r2g reconstruct` names them, or the camera name a frame
//! records); without such a correspondence the gym's cameras are sent unpaired and the request
//! says so.
//!
//! Scores we compute rather than take from the model ([`scores`]): content alignment (the MuJoCo
//! part plus the Blender part; none, with the part given alone, when one engine's images are
//! missing), action fidelity (six parts, then the `wrong_goal` / `non_equivalent` rules), task
//! completion (three parts), simulation success = action fidelity × task completion / 100, and
//! the physical-failure override (0 when the native verdict measured initial or persistent
//! penetration, or the model reports a confirmed failure).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context};
use serde_json::{json, Map, Value};
use sim_host::Scene;

use crate::events::Kind;
use crate::sha256_hex;

/// The rubric, the system prompt of every request.
pub const RUBRIC: &str = include_str!("../judge/rubric.md");
/// Bumped whenever the rubric or the answer's shape changes.
pub const RUBRIC_VERSION: u32 = 2;

/// A piece of the user message.
#[derive(Debug, Clone)]
pub enum Part {
    Text(String),
    /// PNG bytes.
    Png(Vec<u8>),
}

/// The endpoint's answer, as the caller's client reports it.
#[derive(Debug, Clone)]
pub struct Reply {
    pub text: String,
    /// The model the endpoint configuration names.
    pub model: String,
    /// `live`, `scripted` or `replayed`.
    pub source: String,
    pub provider: String,
    /// Normalised usage: `input`, `cached`, `output`, `reasoning`.
    pub usage: Value,
    pub attempts: u32,
    pub wall_s: f64,
    /// The endpoint stopped the answer at its token limit.
    pub truncated: bool,
}

/// The renderer an image set comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Engine {
    Mujoco,
    Blender,
}

impl Engine {
    pub fn name(self) -> &'static str {
        match self {
            Engine::Mujoco => "MuJoCo",
            Engine::Blender => "Blender",
        }
    }
    fn key(self) -> &'static str {
        match self {
            Engine::Mujoco => "mujoco",
            Engine::Blender => "blender",
        }
    }
}

/// What to render: the scene at rest from the cameras of a BOP `scene_camera.json`, or the
/// native trace at instants from scene cameras named here (all of them when empty).
#[derive(Debug, Clone, Default)]
pub struct RenderRequest {
    pub cameras: Option<PathBuf>,
    pub camera: Vec<String>,
    pub trace: Option<PathBuf>,
    pub at: Vec<f64>,
}

/// Renders `scene` with an engine into `out` (a folder that does not exist yet), in the BOP
/// layout (`scene_camera.json` with `r2g_camera` and `r2g_t_s`, `rgb/<id:06>.png`).
pub type RenderFn<'a> = &'a dyn Fn(Engine, &Path, &RenderRequest, &Path) -> anyhow::Result<()>;
/// Sends the system prompt and one user message to the endpoint.
pub type AskFn<'a> = &'a dyn Fn(&str, &[Part]) -> anyhow::Result<Reply>;

#[derive(Debug, Clone)]
pub struct Options {
    /// The folder judge.json and the evidence go to (must not exist, or be empty).
    pub out: PathBuf,
    /// Source frames in the BOP layout (default: `<gym>/frames`, else the folder the gym's
    /// `reconstruction.json` names).
    pub frames: Option<PathBuf>,
    /// A native verdict already computed: `r2g validate`'s evidence.json (or its JSON line),
    /// or `r2g replay`'s evaluation. Default: the gate is run here.
    pub verdict: Option<PathBuf>,
    /// The native trace of that verdict (default: trace.json beside an evidence.json).
    pub trace: Option<PathBuf>,
    /// Scene camera for the instants along the trace (default: the first fixed camera).
    pub camera: Option<String>,
    /// Instants along the trace, s (default: chosen from the native events).
    pub at: Option<Vec<f64>>,
    /// Source frames used at most.
    pub max_frames: usize,
    /// Ask for Blender images (false: they are reported as not requested).
    pub blender: bool,
    pub seed: u64,
}

impl Options {
    pub fn new(out: PathBuf) -> Self {
        Self {
            out,
            frames: None,
            verdict: None,
            trace: None,
            camera: None,
            at: None,
            max_frames: 3,
            blender: true,
            seed: 0,
        }
    }
}

/// One image of the request.
#[derive(Debug, Clone)]
struct Image {
    label: String,
    png: Vec<u8>,
    file: PathBuf,
    /// The source image id, for source frames.
    id: Option<u64>,
    /// The camera that took it (`r2g_camera`), when recorded.
    camera: Option<String>,
}

/// A set of images, or why there is none.
type ImageSet = Result<Vec<Image>, String>;

/// The native verdict and where it came from.
struct Verdict {
    kind: &'static str,
    path: PathBuf,
    value: Value,
    trace: Option<PathBuf>,
}

/// What `run` produced.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub path: PathBuf,
    pub record: Value,
}

fn r2(v: f64) -> f64 {
    (v * 100.0).round() / 100.0
}

fn now_s() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

/// Grades the gym whose scene file is `scene_path`: gathers the evidence, asks, checks the
/// answer and writes `<out>/judge.json` (write, then rename). A malformed answer is an error that
/// names what is wrong; the answer is kept in `<out>/answer.raw.txt` either way.
pub fn run(scene_path: &Path, o: &Options, render: RenderFn, ask: AskFn) -> anyhow::Result<Outcome> {
    let scene = Scene::load(scene_path).with_context(|| format!("scene {}", scene_path.display()))?;
    let gym_dir = crate::validate::scene_dir(scene_path);
    if o.out.exists() && std::fs::read_dir(&o.out).map(|mut d| d.next().is_some()).unwrap_or(true) {
        bail!("the output folder {} exists and is not empty: give a new one", o.out.display());
    }
    std::fs::create_dir_all(o.out.join("evidence")).with_context(|| format!("creating {}", o.out.display()))?;
    let verdict = native_verdict(scene_path, o)?;
    let native_failures = physical_failures(&verdict.value);

    let source = source_frames(&gym_dir, o);
    let mut missing: Vec<String> = Vec::new();
    let source_images: ImageSet = source
        .as_ref()
        .map_err(Clone::clone)
        .and_then(|s| s.frames.iter().map(|f| s.image(f)).collect::<Result<Vec<_>, String>>());
    if let Err(why) = &source_images {
        missing.push(format!("source frames: {why}"));
    }

    // The viewpoint evidence: the gym's own cameras at rest, each paired with the source frame it
    // stands for where that is known. The source cameras are not rendered: the question is
    // whether the gym's cameras see what the reference cameras saw.
    let gym_cameras: Vec<String> = scene.cameras.iter().map(|c| c.name.clone()).collect();
    let viewpoints = source.as_ref().ok().map(|s| {
        let frames: Vec<(u64, String, Option<String>)> = s
            .frames
            .iter()
            .map(|(id, key)| (*id, key.clone(), s.cameras[key]["r2g_camera"].as_str().map(str::to_string)))
            .collect();
        pair_viewpoints(&gym_cameras, &frames, o.max_frames)
    });
    // The trace at instants.
    let camera = trace_camera(&scene, o.camera.as_deref())?;
    let instants = match (&o.at, &verdict.trace) {
        (Some(at), _) => at.clone(),
        (None, Some(_)) => instants(&verdict.value),
        (None, None) => Vec::new(),
    };
    let mut rest: Vec<(Engine, ImageSet)> = Vec::new();
    let mut sets: Vec<(String, Engine, ImageSet)> = Vec::new();
    for engine in [Engine::Mujoco, Engine::Blender] {
        let skip = (engine == Engine::Blender && !o.blender).then(|| "not requested (--no-blender)".to_string());
        if let Some(vp) = &viewpoints {
            let dir = o.out.join("evidence").join(format!("{}-rest", engine.key()));
            let req = RenderRequest { camera: vp.cameras(), ..Default::default() };
            let set = match &skip {
                Some(why) => Err(why.clone()),
                None => render_set(render, engine, scene_path, &req, &dir).map(|set| label_rest(engine, set, vp)),
            };
            if let Err(why) = &set {
                missing.push(format!("{} images at rest from the gym's own cameras: {why}", engine.name()));
            }
            rest.push((engine, set));
        }
        let dir = o.out.join("evidence").join(format!("{}-trace", engine.key()));
        let (what, req) = match &verdict.trace {
            Some(t) if !instants.is_empty() => (
                format!("along the native execution, camera {camera}"),
                RenderRequest {
                    camera: vec![camera.clone()],
                    trace: Some(t.clone()),
                    at: instants.clone(),
                    cameras: None,
                },
            ),
            _ => (
                format!("at rest (no native trace to follow), camera {camera}"),
                RenderRequest { camera: vec![camera.clone()], ..Default::default() },
            ),
        };
        let set = match &skip {
            Some(why) => Err(why.clone()),
            None => render_set(render, engine, scene_path, &req, &dir),
        };
        if let Err(why) = &set {
            missing.push(format!("{} images {what}: {why}", engine.name()));
        }
        sets.push((what, engine, set));
    }

    // Items that cannot be graded from what is here.
    let has = |e: Engine| {
        sets.iter().any(|(_, en, s)| *en == e && s.as_ref().is_ok_and(|v| !v.is_empty()))
            || rest.iter().any(|(en, s)| *en == e && s.as_ref().is_ok_and(|v| !v.is_empty()))
    };
    let mut nullable = BTreeSet::new();
    if !has(Engine::Mujoco) {
        nullable.insert("content_alignment.mujoco".to_string());
    }
    if !has(Engine::Blender) {
        nullable.insert("content_alignment.blender".to_string());
    }
    let any_rest = rest.iter().any(|(_, s)| s.as_ref().is_ok_and(|v| !v.is_empty()));
    if source_images.as_ref().map_or(true, Vec::is_empty) || !any_rest {
        nullable.insert("viewpoint_alignment".to_string());
    }

    // The request.
    let mut parts: Vec<Part> = Vec::new();
    let mut images: Vec<Value> = Vec::new();
    let mut push_image = |parts: &mut Vec<Part>, im: &Image| {
        parts.push(Part::Text(im.label.clone()));
        images.push(json!({"label": im.label, "file": im.file.display().to_string(),
                           "png_sha256": sha256_hex(&im.png), "bytes": im.png.len()}));
        parts.push(Part::Png(im.png.clone()));
    };
    parts.push(Part::Text(header(&scene, &source, &missing, &nullable)));
    parts.push(Part::Text(scene_text(&scene)));
    if let (Ok(s), Some(vp)) = (&source_images, &viewpoints) {
        let rest_images: Vec<&Image> = rest.iter().filter_map(|(_, set)| set.as_ref().ok()).flatten().collect();
        if vp.pairs.is_empty() {
            parts.push(Part::Text(format!("## Reference: {} source frame(s)", s.len())));
            for im in s {
                push_image(&mut parts, im);
            }
            parts.push(Part::Text(format!(
                "## The gym's own cameras at rest, NOT paired with the source frames: {} image(s)\n{}",
                rest_images.len(),
                vp.basis
            )));
            for im in &rest_images {
                push_image(&mut parts, im);
            }
        } else {
            parts.push(Part::Text(format!(
                "## Reference and viewpoints: {} source frame(s), each followed by the gym's own camera that \
                 corresponds to it, rendered at rest\n{}",
                s.len(),
                vp.basis
            )));
            let mut sent: BTreeSet<PathBuf> = BTreeSet::new();
            for im in s {
                push_image(&mut parts, im);
                let Some(cam) = vp.pairs.iter().find(|p| Some(p.1) == im.id).map(|p| &p.0) else {
                    parts.push(Part::Text(format!(
                        "(The gym has no camera that corresponds to source frame {}.)",
                        im.id.unwrap_or_default()
                    )));
                    continue;
                };
                for r in rest_images.iter().filter(|r| r.camera.as_ref() == Some(cam)) {
                    if sent.insert(r.file.clone()) {
                        push_image(&mut parts, r);
                    } else {
                        parts.push(Part::Text(format!("(Compare with the image of {cam} shown above: {}.)", r.label)));
                    }
                }
            }
        }
    }
    for (what, engine, set) in &sets {
        if let Ok(s) = set {
            parts.push(Part::Text(format!("## {} images {what}: {} image(s)", engine.name(), s.len())));
            for im in s {
                push_image(&mut parts, im);
            }
        }
    }
    parts.push(Part::Text(demonstration_text(&scene, scene_path, &verdict)));
    parts.push(Part::Text(verdict_text(&verdict, &native_failures)));
    parts.push(Part::Text(
        "Grade now. Answer with the one JSON object the instructions describe, and nothing else.".into(),
    ));
    let texts: Vec<&str> =
        parts.iter().filter_map(|p| if let Part::Text(t) = p { Some(t.as_str()) } else { None }).collect();
    write_atomic(&o.out.join("request.md"), texts.join("\n\n").as_bytes())?;

    let reply = ask(RUBRIC, &parts).context("the judge's call to the LLM endpoint failed")?;
    let raw_path = o.out.join("answer.raw.txt");
    write_atomic(&raw_path, reply.text.as_bytes())?;
    if reply.truncated {
        bail!(
            "the endpoint cut the answer off at its token limit (max_tokens); raise it in the endpoint file. The answer is in {}",
            raw_path.display()
        );
    }
    let answer = parse_answer(&reply.text, &nullable).map_err(|why| {
        anyhow::anyhow!("the judge's answer is not valid: {why}. The raw answer is in {}", raw_path.display())
    })?;

    // Scores: ours, from the parts.
    let sc = scores(&answer, !native_failures.is_empty());
    let mut reasons: Vec<Value> = native_failures.iter().map(|r| json!({"from": "native verdict", "why": r})).collect();
    if answer.physical_failure {
        reasons.push(json!({"from": "judge", "why": answer.physical_failure_why}));
    }

    let scripted = reply.source == "scripted";
    let record = json!({
        "r2g_judge": 1,
        "rubric_version": RUBRIC_VERSION,
        "gym": scene.name,
        "scene": scene_path.display().to_string(),
        "measurement": !scripted,
        "label": if scripted {
            "mechanics only: the scripted endpoint's answer was written by us in advance (synthetic); these scores are not measurements"
        } else {
            "scores from the model named in llm.model"
        },
        "scores": {
            "content_alignment": sc.content_alignment.map(r2),
            "content_alignment_mujoco": answer.ca_mujoco.map(r2),
            "content_alignment_blender": answer.ca_blender.map(r2),
            "content_alignment_partial": sc.content_alignment_partial,
            "content_alignment_basis": sc.content_alignment_basis,
            "viewpoint_alignment": answer.viewpoint.map(r2),
            "action_fidelity": r2(sc.action_fidelity),
            "action_fidelity_parts_sum": r2(sc.action_fidelity_parts_sum),
            "action_fidelity_rule": sc.action_fidelity_rule,
            "task_completion": r2(sc.task_completion),
            "simulation_success": r2(sc.simulation_success),
            "simulation_success_before_override": r2(sc.simulation_success_before_override),
        },
        "override": {"applied": sc.overridden, "reasons": reasons},
        "answer": answer.value,
        "llm": {
            "source": reply.source, "model": reply.model, "provider": reply.provider,
            "usage": reply.usage, "attempts": reply.attempts, "wall_s": r2(reply.wall_s),
        },
        "request": {
            "system_sha256": sha256_hex(RUBRIC.as_bytes()),
            "texts": texts.len(),
            "text_chars": texts.iter().map(|t| t.chars().count()).sum::<usize>(),
            "text_file": "request.md",
            "images": images,
            "missing_evidence": missing,
            "not_gradable": nullable,
            "viewpoints": viewpoints.as_ref().map(|vp| json!({
                "paired": !vp.pairs.is_empty(),
                "pairs": vp.pairs.iter().map(|(c, id)| json!({"gym_camera": c, "source_id": id})).collect::<Vec<_>>(),
                "unpaired_gym_cameras": vp.unpaired_cameras,
                "unpaired_source_ids": vp.unpaired_frames,
                "basis": vp.basis,
            })),
            "instants_s": instants,
            "trace_camera": camera,
        },
        "native_verdict": {
            "kind": verdict.kind,
            "path": verdict.path.display().to_string(),
            "success": verdict.value["success"],
            "failed_checks": failed_checks(&verdict.value),
            "physical_failures": native_failures,
        },
        "source_frames": source.as_ref().map(|s| json!(s.dir.display().to_string())).unwrap_or(Value::Null),
        "answer_file": "answer.raw.txt",
    });
    let path = o.out.join("judge.json");
    write_atomic(&path, &serde_json::to_vec_pretty(&record)?)?;
    Ok(Outcome { path, record })
}

// ---------------------------------------------------------------- scores

/// The figures we compute from a checked answer.
#[derive(Debug, Clone, PartialEq)]
pub struct Scores {
    /// MuJoCo part + Blender part; `None` unless both parts were graded.
    pub content_alignment: Option<f64>,
    /// Only one engine's part was graded (it is reported alone, not scaled up).
    pub content_alignment_partial: bool,
    pub content_alignment_basis: &'static str,
    /// The six parts added up, before the two rules.
    pub action_fidelity_parts_sum: f64,
    pub action_fidelity: f64,
    /// `wrong_goal` (0) or `non_equivalent` (at most 40), when one applied.
    pub action_fidelity_rule: Option<&'static str>,
    pub task_completion: f64,
    pub simulation_success_before_override: f64,
    pub simulation_success: f64,
    /// The physical-failure override zeroed simulation success.
    pub overridden: bool,
}

/// The arithmetic of the rubric, and nothing else: content alignment = the two engine parts
/// added (absent when either is); action fidelity = the six parts added, 0 when `wrong_goal`,
/// at most 40 when `non_equivalent`; task completion = its three parts added; simulation success
/// = action fidelity × task completion / 100, and 0 when a physical failure is confirmed (by the
/// native checks, `native_physical_failure`, or by the model's own report).
pub fn scores(a: &Answer, native_physical_failure: bool) -> Scores {
    let (content_alignment, content_alignment_partial, content_alignment_basis) = match (a.ca_mujoco, a.ca_blender) {
        (Some(m), Some(b)) => (Some(m + b), false, "MuJoCo part + Blender part"),
        (Some(_), None) => (
            None,
            true,
            "partial: no Blender images were graded, so there is no total; the MuJoCo part (0-50) stands alone",
        ),
        (None, Some(_)) => (
            None,
            true,
            "partial: no MuJoCo images were graded, so there is no total; the Blender part (0-50) stands alone",
        ),
        (None, None) => (None, false, "not graded: no rendered images"),
    };
    let sum: f64 = a.af_parts.iter().sum();
    let (action_fidelity, action_fidelity_rule) = if a.wrong_goal {
        (0.0, Some("wrong_goal: action fidelity is 0"))
    } else if a.non_equivalent {
        (sum.min(40.0), Some("non_equivalent: action fidelity is capped at 40"))
    } else {
        (sum, None)
    };
    let task_completion: f64 = a.tc_parts.iter().sum();
    let before = action_fidelity * task_completion / 100.0;
    let overridden = native_physical_failure || a.physical_failure;
    Scores {
        content_alignment,
        content_alignment_partial,
        content_alignment_basis,
        action_fidelity_parts_sum: sum,
        action_fidelity,
        action_fidelity_rule,
        task_completion,
        simulation_success_before_override: before,
        simulation_success: if overridden { 0.0 } else { before },
        overridden,
    }
}

// ---------------------------------------------------------------- viewpoints

/// Which of the gym's own cameras stands for which source frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Viewpoints {
    /// (gym camera, source image id), in source-frame order.
    pub pairs: Vec<(String, u64)>,
    /// The gym's cameras rendered with no known source frame (only when nothing pairs).
    pub unpaired_cameras: Vec<String>,
    /// Source frames no camera of the gym stands for.
    pub unpaired_frames: Vec<u64>,
    /// How the pairs were found, or why there are none, for the request.
    pub basis: String,
}

impl Viewpoints {
    /// The gym cameras to render at rest, each once.
    pub fn cameras(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for c in self.pairs.iter().map(|p| &p.0).chain(&self.unpaired_cameras) {
            if !out.contains(c) {
                out.push(c.clone());
            }
        }
        out
    }
}

/// Pairs the gym's cameras (`gym`, in scene order) with source frames (`frames`: image id, its
/// key in scene_camera.json, the camera name the frame records as `r2g_camera`). A gym camera
/// stands for a frame when it is named `cam_<id>` (the name `r2g reconstruct` gives the camera
/// it makes from that frame), or else when it has the name the frame records. When nothing
/// pairs, the first `max` gym cameras are sent unpaired.
pub fn pair_viewpoints(gym: &[String], frames: &[(u64, String, Option<String>)], max: usize) -> Viewpoints {
    let mut pairs = Vec::new();
    let mut unpaired_frames = Vec::new();
    let (mut by_reconstruct, mut by_record) = (false, false);
    for (id, key, recorded) in frames {
        let named = [format!("cam_{key}"), format!("cam_{id}")];
        if let Some(c) = gym.iter().find(|c| named.contains(c)) {
            pairs.push((c.clone(), *id));
            by_reconstruct = true;
        } else if let Some(c) = recorded.as_ref().and_then(|r| gym.iter().find(|c| *c == r)) {
            pairs.push((c.clone(), *id));
            by_record = true;
        } else {
            unpaired_frames.push(*id);
        }
    }
    let mut basis = Vec::new();
    if by_reconstruct {
        basis.push("a camera named cam_<id> is the one r2g reconstruct built from source frame <id>");
    }
    if by_record {
        basis.push("a source frame records the name of the camera that took it (r2g_camera), and the gym has a camera of that name");
    }
    let unpaired_cameras = if pairs.is_empty() { gym.iter().take(max.max(1)).cloned().collect() } else { Vec::new() };
    let basis = if pairs.is_empty() {
        "Which gym camera corresponds to which source frame is not known: no camera of the gym is named after a \
         source frame (cam_<id>, as r2g reconstruct names them) or carries the camera name a frame records. The \
         gym's cameras are shown unpaired; judge the viewpoint from the best match you can see and say which \
         pairing you used."
            .to_string()
    } else {
        let mut b = format!("Paired because {}.", basis.join("; and "));
        if !unpaired_frames.is_empty() {
            b += &format!(
                " The gym has no camera for source frame(s) {}.",
                unpaired_frames.iter().map(u64::to_string).collect::<Vec<_>>().join(", ")
            );
        }
        b
    };
    Viewpoints { pairs, unpaired_cameras, unpaired_frames, basis }
}

/// Relabels the at-rest images of the gym's own cameras with the source frame each stands for.
fn label_rest(engine: Engine, set: Vec<Image>, vp: &Viewpoints) -> Vec<Image> {
    set.into_iter()
        .map(|mut im| {
            let cam = im.camera.clone().unwrap_or_else(|| "(unnamed)".into());
            let ids: Vec<String> = vp.pairs.iter().filter(|p| p.0 == cam).map(|p| p.1.to_string()).collect();
            im.label = format!(
                "{} image of the gym's own camera {cam} at rest, {}",
                engine.name(),
                if ids.is_empty() {
                    "not paired with a source frame".to_string()
                } else {
                    format!("the view of source frame {}", ids.join(", "))
                }
            );
            im
        })
        .collect()
}

fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    lockstep::demo::write_atomic(path, bytes).with_context(|| format!("writing {}", path.display()))
}

// ---------------------------------------------------------------- the native verdict

fn native_verdict(scene_path: &Path, o: &Options) -> anyhow::Result<Verdict> {
    let Some(path) = &o.verdict else {
        let mut vo = crate::validate::Options::new(o.out.join("native"));
        vo.seed = o.seed;
        vo.keep_trace = true;
        let (_, path) = crate::validate::validate(scene_path, &vo).context("the native gate (r2g validate)")?;
        let value: Value = serde_json::from_slice(&std::fs::read(&path)?)?;
        return Ok(Verdict { kind: "validate", trace: Some(o.out.join("native/trace.json")), path, value });
    };
    let read = |p: &Path| -> anyhow::Result<Value> {
        let text = std::fs::read_to_string(p).with_context(|| format!("the verdict {}", p.display()))?;
        // `r2g replay` and `r2g validate` print lines before their JSON; the last line counts.
        let last = text.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("");
        serde_json::from_str(&text)
            .or_else(|_| serde_json::from_str(last))
            .with_context(|| format!("the verdict {} is not JSON", p.display()))
    };
    let mut path = path.clone();
    let mut value = read(&path)?;
    // `r2g validate`'s line names its evidence.json: read that.
    if let (Some(ev), None) = (value["evidence"].as_str(), value.get("evaluation")) {
        path = PathBuf::from(ev);
        value = read(&path)?;
    }
    let kind = if value.get("evaluation").is_some() && value.get("inputs_sha256").is_some() {
        "validate"
    } else if value.get("criteria_sha256").is_some() && value.get("checks").is_some() {
        "replay"
    } else {
        bail!(
            "{} is neither r2g validate's evidence.json nor r2g replay's evaluation (no 'evaluation'/'inputs_sha256' or 'criteria_sha256'/'checks')",
            path.display()
        );
    };
    if !value["checks"].is_object() || !value["success"].is_boolean() {
        bail!("{}: the verdict has no 'checks' object or no boolean 'success'", path.display());
    }
    let trace = match &o.trace {
        Some(t) if t.is_file() => Some(t.clone()),
        Some(t) => bail!("the trace {} does not exist", t.display()),
        None => path.parent().map(|d| d.join("trace.json")).filter(|t| t.is_file()),
    };
    Ok(Verdict { kind, path, value, trace })
}

/// The checks of a verdict that failed, by name (the gate's and the evaluator's).
fn failed_checks(v: &Value) -> Vec<String> {
    let mut out = Vec::new();
    for (prefix, checks) in [("", &v["checks"]), ("evaluation.", &v["evaluation"]["checks"])] {
        if let Some(m) = checks.as_object() {
            out.extend(m.iter().filter(|(_, c)| c["pass"] == false).map(|(k, _)| format!("{prefix}{k}")));
        }
    }
    out
}

/// Physical failures the native verdict measured, as the paper's override means them: things
/// inside each other beyond the task's limit at the start (`initial_penetration`) or for longer
/// than a contact lasts (the evaluator's `no_persistent_penetration`). A brief overlap
/// (`worst_penetration`) or an object still drifting (`settles_at_rest`) fails the gate but is
/// not, on its own, a confirmed failure that breaks the execution; the model sees those checks
/// and may report one as such.
pub fn physical_failures(v: &Value) -> Vec<String> {
    let mut out = Vec::new();
    let checks = [("", &v["checks"]), ("evaluation.", &v["evaluation"]["checks"])];
    for (prefix, checks) in checks {
        let Some(m) = checks.as_object() else { continue };
        for (k, c) in m {
            let physical = k == "initial_penetration" || k.starts_with("no_persistent_penetration");
            if physical && c["pass"] == false {
                out.push(format!("{prefix}{k} failed: {}", c["value"]));
            }
        }
    }
    out
}

/// Instants worth seeing along the native execution: the start, each grasp's onset, middle and
/// release (robot contacts when nothing is grasped), and the end; at most 6, 0.2 s apart.
fn instants(v: &Value) -> Vec<f64> {
    let end = v["evaluation"]["sim_time_s"].as_f64().or(v["sim_time_s"].as_f64()).unwrap_or(0.0);
    let events: Vec<crate::events::Interval> = serde_json::from_value(v["native_events"].clone()).unwrap_or_default();
    let mut pick: Vec<f64> = Vec::new();
    let grasps: Vec<_> = events.iter().filter(|e| e.kind == Kind::Grasp).collect();
    let chosen: Vec<_> = if grasps.is_empty() {
        events.iter().filter(|e| e.kind == Kind::Contact && e.subject == "robot").collect()
    } else {
        grasps
    };
    for e in chosen {
        pick.extend([e.onset_s, 0.5 * (e.onset_s + e.offset_s), e.offset_s]);
    }
    if end <= 0.0 {
        return vec![0.0];
    }
    if pick.is_empty() {
        pick.extend([end / 3.0, 2.0 * end / 3.0]);
    }
    pick.truncate(4);
    let mut out = vec![0.0];
    out.extend(pick.into_iter().map(|t| t.clamp(0.0, end)));
    out.push(end);
    out.sort_by(f64::total_cmp);
    out.dedup_by(|a, b| (*a - *b).abs() < 0.2);
    out.iter().map(|t| (t * 1000.0).round() / 1000.0).collect()
}

// ---------------------------------------------------------------- evidence

struct SourceFrames {
    dir: PathBuf,
    /// The chosen images: id, and its key in scene_camera.json.
    frames: Vec<(u64, String)>,
    /// The chosen images' entries of scene_camera.json, by key.
    cameras: Map<String, Value>,
}

impl SourceFrames {
    fn image(&self, (id, key): &(u64, String)) -> Result<Image, String> {
        let file = self.dir.join("rgb").join(format!("{id:06}.png"));
        let png = std::fs::read(&file).map_err(|e| format!("{}: {e}", file.display()))?;
        if !png.starts_with(b"\x89PNG\r\n\x1a\n") {
            return Err(format!("{} is not a PNG", file.display()));
        }
        let cam = &self.cameras[key];
        Ok(Image {
            label: format!("Source frame {id} ({})", camera_words(cam)),
            png,
            file,
            id: Some(*id),
            camera: cam["r2g_camera"].as_str().map(str::to_string),
        })
    }
}

fn camera_words(cam: &Value) -> String {
    let mut w = Vec::new();
    if let Some(n) = cam["r2g_camera"].as_str() {
        w.push(format!("camera {n}"));
    }
    if let (Some(wd), Some(h)) = (cam["width"].as_u64(), cam["height"].as_u64()) {
        w.push(format!("{wd}x{h}"));
    }
    if let Some(t) = cam["r2g_t_s"].as_f64() {
        w.push(format!("t = {t:.2} s"));
    }
    if w.is_empty() {
        "no camera name recorded".into()
    } else {
        w.join(", ")
    }
}

/// The folder of source frames, or why there is none.
fn source_dir(gym_dir: &Path, o: &Options) -> Result<PathBuf, String> {
    if let Some(f) = &o.frames {
        return Ok(f.clone());
    }
    let local = gym_dir.join("frames");
    if local.join("scene_camera.json").is_file() {
        return Ok(local);
    }
    let rec = gym_dir.join("reconstruction.json");
    if !rec.is_file() {
        return Err(
            "the gym was not reconstructed from frames (it has no frames/ folder and no reconstruction.json); \
                    the reference is the scene as specified, described in text"
                .into(),
        );
    }
    let v: Value = std::fs::read_to_string(&rec)
        .map_err(|e| e.to_string())
        .and_then(|t| serde_json::from_str(&t).map_err(|e| e.to_string()))
        .map_err(|e| format!("{}: {e}", rec.display()))?;
    let named = ["frames", "frames_dir", "source_frames", "source", "input"]
        .iter()
        .find_map(|k| v[*k].as_str().or(v[*k]["path"].as_str()).or(v[*k]["dir"].as_str()))
        .ok_or_else(|| format!("{} names no frames folder (keys frames / source)", rec.display()))?;
    let p = PathBuf::from(named);
    Ok(if p.is_absolute() { p } else { gym_dir.join(p) })
}

fn source_frames(gym_dir: &Path, o: &Options) -> Result<SourceFrames, String> {
    let dir = source_dir(gym_dir, o)?;
    let file = dir.join("scene_camera.json");
    let text = std::fs::read_to_string(&file)
        .map_err(|e| format!("the source frames {}: {}: {e}", dir.display(), file.display()))?;
    let all: Map<String, Value> = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", file.display()))?;
    let mut ids: Vec<(u64, String)> = all
        .keys()
        .map(|k| {
            k.parse::<u64>()
                .map(|id| (id, k.clone()))
                .map_err(|_| format!("{}: image id '{k}' is not a number", file.display()))
        })
        .collect::<Result<_, _>>()?;
    ids.sort_unstable();
    if ids.is_empty() {
        return Err(format!("{} holds no images", file.display()));
    }
    // Evenly spread over the ids, the first and the last included.
    let n = o.max_frames.clamp(1, ids.len());
    let chosen: Vec<(u64, String)> = if n == 1 {
        vec![ids[0].clone()]
    } else {
        let mut c: Vec<(u64, String)> = (0..n).map(|i| ids[i * (ids.len() - 1) / (n - 1)].clone()).collect();
        c.dedup();
        c
    };
    let cameras: Map<String, Value> = chosen.iter().map(|(_, k)| (k.clone(), all[k].clone())).collect();
    Ok(SourceFrames { dir, frames: chosen, cameras })
}

/// Renders one set and reads its images back, or says why there are none.
fn render_set(render: RenderFn, engine: Engine, scene: &Path, req: &RenderRequest, out: &Path) -> ImageSet {
    render(engine, scene, req, out).map_err(|e| format!("{e:#}"))?;
    read_bop(engine, out)
}

/// The RGB images of a BOP folder, in image-id order, labelled with camera and instant.
fn read_bop(engine: Engine, dir: &Path) -> ImageSet {
    let file = dir.join("scene_camera.json");
    let text = std::fs::read_to_string(&file).map_err(|e| format!("{}: {e}", file.display()))?;
    let cams: Map<String, Value> = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", file.display()))?;
    let mut ids: Vec<(u64, Value)> = cams
        .into_iter()
        .map(|(k, v)| k.parse::<u64>().map(|id| (id, v)).map_err(|_| format!("{}: image id '{k}'", file.display())))
        .collect::<Result<_, _>>()?;
    ids.sort_by_key(|(id, _)| *id);
    let mut out = Vec::new();
    for (id, cam) in ids {
        let f = dir.join("rgb").join(format!("{id:06}.png"));
        let png = std::fs::read(&f).map_err(|e| format!("{}: {e}", f.display()))?;
        if !png.starts_with(b"\x89PNG\r\n\x1a\n") {
            return Err(format!("{} is not a PNG", f.display()));
        }
        out.push(Image {
            label: format!("{} image {id} ({})", engine.name(), camera_words(&cam)),
            png,
            file: f,
            id: None,
            camera: cam["r2g_camera"].as_str().map(str::to_string),
        });
    }
    if out.is_empty() {
        return Err(format!("{} lists no images", file.display()));
    }
    Ok(out)
}

fn trace_camera(scene: &Scene, named: Option<&str>) -> anyhow::Result<String> {
    if let Some(n) = named {
        if !scene.cameras.iter().any(|c| c.name == n) {
            bail!(
                "--camera {n}: the scene has no such camera (it has: {})",
                scene.cameras.iter().map(|c| c.name.as_str()).collect::<Vec<_>>().join(", ")
            );
        }
        return Ok(n.to_string());
    }
    scene
        .cameras
        .iter()
        .find(|c| c.link.is_none())
        .or(scene.cameras.first())
        .map(|c| c.name.clone())
        .ok_or_else(|| anyhow::anyhow!("the scene has no camera to render the execution from"))
}

// ---------------------------------------------------------------- text

fn header(
    scene: &Scene,
    source: &Result<SourceFrames, String>,
    missing: &[String],
    nullable: &BTreeSet<String>,
) -> String {
    let mut t = format!("# Gym `{}`\n\nTask: {}\n\n", scene.name, scene.task.instruction);
    t += match source {
        Ok(s) => format!(
            "Reference: {} frame(s) of the scene the gym should reproduce (BOP layout, {}).\n",
            s.frames.len(),
            s.dir.display()
        ),
        Err(_) => "Reference: no source frames. The scene specification below is the reference; the rendered \
                   images show what the gym builds from it.\n"
            .into(),
    }
    .as_str();
    if missing.is_empty() {
        t += "\nAll evidence is present.\n";
    } else {
        t += "\nMissing evidence (grade without it; do not guess what it would show):\n";
        for m in missing {
            t += &format!("- {m}\n");
        }
    }
    if nullable.is_empty() {
        t += "\nEvery item can be graded: give no null.\n";
    } else {
        t += &format!(
            "\nThese items cannot be graded from this evidence; give exactly them `\"score\": null` (and say why): {}\n",
            nullable.iter().cloned().collect::<Vec<_>>().join(", ")
        );
    }
    t
}

fn v3(v: &[f64]) -> String {
    format!("[{}]", v.iter().map(|x| format!("{x:.3}")).collect::<Vec<_>>().join(", "))
}

fn scene_text(scene: &Scene) -> String {
    let mut t = String::from("## The scene as the gym specifies it (robot base frame, metres)\n");
    if let Some(tb) = &scene.table {
        t += &format!("- table: top centre {}, size {}\n", v3(&tb.top_center_m), v3(&tb.size_m));
    }
    for ob in &scene.objects {
        let shape = ob.shape.map(|s| format!("{s:?}").to_lowercase()).unwrap_or_else(|| "compound".into());
        t += &format!(
            "- object `{}`: {shape}{}, size {}, at {}, colour rgba {}{}\n",
            ob.name,
            if ob.parts.is_empty() { String::new() } else { format!(" of {} parts", ob.parts.len()) },
            v3(&ob.size_m),
            v3(&ob.position_m),
            v3(&ob.rgba),
            if ob.free { ", free" } else { ", fixed" }
        );
    }
    for f in &scene.fixtures {
        t += &format!(
            "- fixture `{}`: {} part(s) at {}{}\n",
            f.name,
            f.parts.len(),
            v3(&f.position_m),
            f.joint.as_ref().map(|j| format!(", with a {:?} joint", j.kind).to_lowercase()).unwrap_or_default()
        );
    }
    for c in &scene.cameras {
        t += &format!(
            "- camera `{}`: {}{} looking at {}, {}, {}x{}\n",
            c.name,
            c.link.as_ref().map(|l| format!("on link {l}, ")).unwrap_or_default(),
            v3(&c.position_m),
            v3(&c.look_at_m),
            match (c.fovy_deg, c.fx, c.fy) {
                (_, Some(fx), Some(fy)) => format!("focal lengths {fx:.1}, {fy:.1} px"),
                (Some(f), _, _) => format!("vertical field of view {f:.1} deg"),
                _ => "the default field of view".into(),
            },
            c.width,
            c.height
        );
    }
    t
}

fn demonstration_text(scene: &Scene, scene_path: &Path, verdict: &Verdict) -> String {
    let dir = crate::validate::scene_dir(scene_path);
    let mut t = String::from("## The demonstration\n");
    match &scene.task.demonstration {
        Some(d) => match lockstep::read_demo(d) {
            Ok(rows) => {
                let hz = scene.task.demonstration_hz;
                t += &format!(
                    "Joint-space demonstration `{}`: {} rows at {hz} Hz ({:.1} s).\n",
                    d.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
                    rows.len(),
                    rows.len() as f64 / hz
                );
                let mut last: Option<bool> = None;
                for (k, r) in rows.iter().enumerate() {
                    let closed = r[7] > 0.0;
                    if last.is_some_and(|l| l != closed) {
                        t += &format!(
                            "- gripper {} at row {k} (t = {:.2} s of the demonstration)\n",
                            if closed { "closes" } else { "opens" },
                            k as f64 / hz
                        );
                    }
                    last = Some(closed);
                }
            }
            Err(e) => t += &format!("The demonstration file could not be read: {e:#}\n"),
        },
        None => t += "The gym has no demonstration.\n",
    }
    // The author's keyframes, when the demonstration was written from them.
    if let Ok(text) = std::fs::read_to_string(dir.join("keyframes.toml")) {
        if let Ok(v) = text.parse::<toml::Table>() {
            if let Some(kf) = v.get("keyframes").and_then(|k| k.as_array()) {
                t += "Keyframes the demonstration was authored from:\n";
                for (i, k) in kf.iter().enumerate() {
                    let note = k.get("note").and_then(|n| n.as_str()).unwrap_or("-");
                    let mut extra = Vec::new();
                    if let Some(p) = k.get("position_m") {
                        extra.push(format!("TCP to {p}"));
                    }
                    if let Some(g) = k.get("gripper").and_then(|g| g.as_float().or(g.as_integer().map(|i| i as f64))) {
                        extra.push(if g > 0.0 { "gripper closed".into() } else { "gripper open".to_string() });
                    }
                    if let Some(d) = k.get("duration_s") {
                        extra.push(format!("over {d} s"));
                    }
                    t += &format!("{}. {note} ({})\n", i + 1, extra.join(", "));
                }
            }
        }
    }
    // An imported demonstration's source events.
    if let Ok(text) = std::fs::read_to_string(dir.join("events.json")) {
        if let Ok(ev) = serde_json::from_str::<crate::events::EventsFile>(&text) {
            t += &format!("Source grasps ({}):\n", ev.source_kind);
            for g in &ev.source {
                t += &format!(
                    "- close at {:.2} s, open at {}\n",
                    g.close_s,
                    g.open_s.map(|o| format!("{o:.2} s")).unwrap_or_else(|| "never".into())
                );
            }
        }
    }
    t += "\n## What happened when it was executed natively (MuJoCo, in lockstep)\n";
    let events: Vec<crate::events::Interval> =
        serde_json::from_value(verdict.value["native_events"].clone()).unwrap_or_default();
    if events.is_empty() {
        t += "No interaction events were recorded with this verdict.\n";
    }
    for e in &events {
        let kind = format!("{:?}", e.kind).to_lowercase();
        t += &format!("- {kind}: {} with {} from {:.2} s to {:.2} s", e.subject, e.other, e.onset_s, e.offset_s);
        let pose = e.keyframes.iter().find(|k| k.at == "after").and_then(|k| k.subject_pose);
        if let (Some(after), false) = (pose, e.kind == Kind::Contact) {
            t += &format!(" ({} at {} just after)", e.subject, v3(&after[..3]));
        }
        t += "\n";
    }
    t
}

fn verdict_text(v: &Verdict, failures: &[String]) -> String {
    let mut t = format!(
        "## The native verdict (`r2g {}`): {}\n",
        v.kind,
        if v.value["success"] == true { "success" } else { "failure" }
    );
    for (prefix, checks) in [("", &v.value["checks"]), ("evaluator: ", &v.value["evaluation"]["checks"])] {
        if let Some(m) = checks.as_object() {
            for (k, c) in m {
                t += &format!("- {prefix}{} {k}: {}\n", if c["pass"] == true { "pass" } else { "FAIL" }, c["value"]);
            }
        }
    }
    if failures.is_empty() {
        t += "The native checks measured no physical failure.\n";
    } else {
        t += "The native checks measured a physical failure; simulation success will be 0 whatever you grade:\n";
        for f in failures {
            t += &format!("- {f}\n");
        }
    }
    t
}

// ---------------------------------------------------------------- the answer

/// A checked answer: the parts we add up, and the answer itself.
#[derive(Debug, Clone)]
pub struct Answer {
    pub ca_mujoco: Option<f64>,
    pub ca_blender: Option<f64>,
    pub viewpoint: Option<f64>,
    pub af_parts: Vec<f64>,
    pub wrong_goal: bool,
    pub non_equivalent: bool,
    pub tc_parts: Vec<f64>,
    pub physical_failure: bool,
    pub physical_failure_why: String,
    pub value: Value,
}

const AF_PARTS: [(&str, f64); 6] = [
    ("goals_objects", 10.0),
    ("actions_order", 20.0),
    ("contacts_mode", 25.0),
    ("paths_poses", 25.0),
    ("timing", 10.0),
    ("initial_final_states", 10.0),
];
const TC_PARTS: [(&str, f64); 3] = [("steps", 40.0), ("final_state", 40.0), ("physical_execution", 20.0)];

/// The JSON of an answer: the whole text, or the inside of one ```json fence around it.
fn answer_json(text: &str) -> Result<Value, String> {
    let t = text.trim();
    let inner = match t.strip_prefix("```") {
        Some(rest) => {
            let rest = rest.strip_prefix("json").unwrap_or(rest);
            rest.strip_suffix("```").ok_or("the answer opens a ``` fence and does not close it")?.trim()
        }
        None => t,
    };
    if inner.is_empty() {
        return Err("the answer is empty".into());
    }
    serde_json::from_str(inner).map_err(|e| {
        let shown: String = inner.chars().take(80).collect();
        format!("the answer is not one JSON object ({e}; it begins {shown:?})")
    })
}

/// Checks an answer against the rubric's shape: every key there, nothing else, every score a
/// number in its range (or null where `nullable` allows), every justification a non-empty string.
/// All problems are reported at once.
pub fn parse_answer(text: &str, nullable: &BTreeSet<String>) -> Result<Answer, String> {
    let v = answer_json(text)?;
    let mut errs: Vec<String> = Vec::new();
    if !v.is_object() {
        return Err("the answer is JSON but not an object".into());
    }
    let keys = |at: &Value, path: &str, want: &[&str], errs: &mut Vec<String>| match at.as_object() {
        None => errs.push(format!("{path} must be an object")),
        Some(m) => {
            for k in want {
                if !m.contains_key(*k) {
                    errs.push(format!("{path}.{k} is missing"));
                }
            }
            for k in m.keys() {
                if !want.contains(&k.as_str()) {
                    errs.push(format!("{path}.{k} is not part of the answer's shape"));
                }
            }
        }
    };
    let why = |at: &Value, path: &str, errs: &mut Vec<String>| match at.as_str() {
        Some(s) if !s.trim().is_empty() => s.to_string(),
        Some(_) => {
            errs.push(format!("{path} is empty: every score needs a justification"));
            String::new()
        }
        None => {
            errs.push(format!("{path} must be a string"));
            String::new()
        }
    };
    let score = |at: &Value, path: &str, max: f64, errs: &mut Vec<String>| -> Option<f64> {
        keys(at, path, &["score", "justification"], errs);
        why(&at["justification"], &format!("{path}.justification"), errs);
        let s = &at["score"];
        at.get("score")?;
        if s.is_null() {
            if !nullable.contains(path) {
                errs.push(format!(
                    "{path}.score is null, but its evidence was there: it must be a number in [0, {max}]"
                ));
            }
            return None;
        }
        match s.as_f64() {
            Some(x) if x.is_finite() && (0.0..=max).contains(&x) => {
                if nullable.contains(path) {
                    errs.push(format!("{path}.score is {x}, but its evidence is absent: it must be null"));
                }
                Some(x)
            }
            Some(x) => {
                errs.push(format!("{path}.score = {x} is outside [0, {max}]"));
                None
            }
            None => {
                errs.push(format!("{path}.score must be a number in [0, {max}], not {s}"));
                None
            }
        }
    };
    let flag = |at: &Value, path: &str, errs: &mut Vec<String>| -> bool {
        at.as_bool().unwrap_or_else(|| {
            errs.push(format!("{path} must be true or false, not {at}"));
            false
        })
    };
    keys(
        &v,
        "answer",
        &["content_alignment", "viewpoint_alignment", "action_fidelity", "task_completion", "physical_failure"],
        &mut errs,
    );
    let ca = &v["content_alignment"];
    keys(ca, "content_alignment", &["mujoco", "blender"], &mut errs);
    let ca_mujoco = score(&ca["mujoco"], "content_alignment.mujoco", 50.0, &mut errs);
    let ca_blender = score(&ca["blender"], "content_alignment.blender", 50.0, &mut errs);
    let viewpoint = score(&v["viewpoint_alignment"], "viewpoint_alignment", 100.0, &mut errs);
    let af = &v["action_fidelity"];
    let mut af_keys: Vec<&str> = AF_PARTS.iter().map(|p| p.0).collect();
    af_keys.extend(["wrong_goal", "non_equivalent", "justification"]);
    keys(af, "action_fidelity", &af_keys, &mut errs);
    let af_parts: Vec<f64> = AF_PARTS
        .iter()
        .map(|(k, max)| score(&af[*k], &format!("action_fidelity.{k}"), *max, &mut errs).unwrap_or(0.0))
        .collect();
    let wrong_goal = flag(&af["wrong_goal"], "action_fidelity.wrong_goal", &mut errs);
    let non_equivalent = flag(&af["non_equivalent"], "action_fidelity.non_equivalent", &mut errs);
    why(&af["justification"], "action_fidelity.justification", &mut errs);
    let tc = &v["task_completion"];
    keys(tc, "task_completion", &TC_PARTS.map(|p| p.0), &mut errs);
    let tc_parts: Vec<f64> = TC_PARTS
        .iter()
        .map(|(k, max)| score(&tc[*k], &format!("task_completion.{k}"), *max, &mut errs).unwrap_or(0.0))
        .collect();
    let pf = &v["physical_failure"];
    keys(pf, "physical_failure", &["observed", "justification"], &mut errs);
    let physical_failure = flag(&pf["observed"], "physical_failure.observed", &mut errs);
    let physical_failure_why = why(&pf["justification"], "physical_failure.justification", &mut errs);
    if !errs.is_empty() {
        return Err(errs.join("; "));
    }
    Ok(Answer {
        ca_mujoco,
        ca_blender,
        viewpoint,
        af_parts,
        wrong_goal,
        non_equivalent,
        tc_parts,
        physical_failure,
        physical_failure_why,
        value: v,
    })
}

/// A default output folder: `runs/judge/<gym>-<unix seconds>`.
pub fn default_out(gym: &str) -> PathBuf {
    PathBuf::from("runs/judge").join(format!("{gym}-{}", now_s()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part(s: f64) -> Value {
        json!({"score": s, "justification": "seen in the images"})
    }

    fn answer(ca_b: Value) -> Value {
        json!({
            "content_alignment": {"mujoco": part(40.0), "blender": ca_b},
            "viewpoint_alignment": {"score": null, "justification": "no source frames"},
            "action_fidelity": {"goals_objects": part(10.0), "actions_order": part(20.0), "contacts_mode": part(20.0),
                "paths_poses": part(20.0), "timing": part(8.0), "initial_final_states": part(10.0),
                "wrong_goal": false, "non_equivalent": false, "justification": "the same pick and place"},
            "task_completion": {"steps": part(40.0), "final_state": part(40.0), "physical_execution": part(15.0)},
            "physical_failure": {"observed": false, "justification": "nothing passes through anything"}
        })
    }

    fn nullable(items: &[&str]) -> BTreeSet<String> {
        items.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_valid_answer_is_added_up_by_us() {
        let a = parse_answer(&answer(part(30.0)).to_string(), &nullable(&["viewpoint_alignment"])).unwrap();
        assert_eq!(a.af_parts.iter().sum::<f64>(), 88.0);
        assert_eq!(a.tc_parts.iter().sum::<f64>(), 95.0);
        assert_eq!((a.ca_mujoco, a.ca_blender, a.viewpoint), (Some(40.0), Some(30.0), None));
        // A fenced answer is the same answer.
        let fenced = format!("```json\n{}\n```", answer(part(30.0)));
        assert!(parse_answer(&fenced, &nullable(&["viewpoint_alignment"])).is_ok());
    }

    #[test]
    fn every_fault_is_named() {
        let n = nullable(&["viewpoint_alignment"]);
        let e = parse_answer(&answer(part(60.0)).to_string(), &n).unwrap_err();
        assert!(e.contains("content_alignment.blender.score = 60 is outside [0, 50]"), "{e}");
        let e = parse_answer(&answer(json!({"score": 30, "justification": " "})).to_string(), &n).unwrap_err();
        assert!(e.contains("content_alignment.blender.justification is empty"), "{e}");
        let e = parse_answer(&answer(json!({"score": null, "justification": "x"})).to_string(), &n).unwrap_err();
        assert!(e.contains("content_alignment.blender.score is null, but its evidence was there"), "{e}");
        let e = parse_answer(&answer(part(30.0)).to_string(), &nullable(&[])).unwrap_err();
        assert!(e.contains("viewpoint_alignment.score is null"), "{e}");
        let mut extra = answer(part(30.0));
        extra["overall"] = json!(90);
        let e = parse_answer(&extra.to_string(), &n).unwrap_err();
        assert!(e.contains("answer.overall is not part of the answer's shape"), "{e}");
        let e = parse_answer("Scores: content 80, viewpoint 70.", &n).unwrap_err();
        assert!(e.starts_with("the answer is not one JSON object"), "{e}");
        assert!(parse_answer("", &n).unwrap_err().contains("empty"));
        let e = parse_answer(&answer(json!({"score": "30", "justification": "x"})).to_string(), &n).unwrap_err();
        assert!(e.contains("must be a number"), "{e}");
    }

    #[test]
    fn only_initial_and_persistent_penetration_are_native_physical_failures() {
        let v = json!({"checks": {"worst_penetration": {"pass": false, "value": {"deepest_m": 0.01}},
                                  "initial_penetration": {"pass": false, "value": {"deepest_m": 0.008}},
                                  "task_success": {"pass": false, "value": {}},
                                  "settles_at_rest": {"pass": false, "value": {}}},
                       "evaluation": {"checks": {"no_persistent_penetration": {"pass": false, "value": {}}}}});
        let f = physical_failures(&v);
        assert_eq!(f.len(), 2, "{f:?}");
        assert!(f[0].starts_with("initial_penetration failed"), "{f:?}");
        assert!(f[1].starts_with("evaluation.no_persistent_penetration failed"), "{f:?}");
        // A brief overlap or drift alone fails the gate but does not trigger the override.
        let v = json!({"checks": {"worst_penetration": {"pass": false}, "settles_at_rest": {"pass": false},
                                  "initial_penetration": {"pass": true}}});
        assert!(physical_failures(&v).is_empty());
        assert!(physical_failures(&json!({"checks": {"task_success": {"pass": false}}})).is_empty());
    }

    fn graded(af: [f64; 6], tc: [f64; 3]) -> Answer {
        Answer {
            ca_mujoco: Some(40.0),
            ca_blender: Some(35.0),
            viewpoint: Some(80.0),
            af_parts: af.to_vec(),
            wrong_goal: false,
            non_equivalent: false,
            tc_parts: tc.to_vec(),
            physical_failure: false,
            physical_failure_why: "none seen".into(),
            value: Value::Null,
        }
    }

    #[test]
    fn the_scores_follow_every_rule() {
        let a = graded([10.0, 20.0, 20.0, 15.0, 8.0, 10.0], [40.0, 30.0, 15.0]);
        let s = scores(&a, false);
        assert_eq!(s.content_alignment, Some(75.0));
        assert!(!s.content_alignment_partial);
        assert_eq!((s.action_fidelity_parts_sum, s.action_fidelity, s.action_fidelity_rule), (83.0, 83.0, None));
        assert_eq!(s.task_completion, 85.0);
        assert!((s.simulation_success - 83.0 * 85.0 / 100.0).abs() < 1e-9);
        assert_eq!(s.simulation_success, s.simulation_success_before_override);
        assert!(!s.overridden);

        // wrong_goal: action fidelity 0, and so simulation success, whatever the parts say.
        let s = scores(&Answer { wrong_goal: true, non_equivalent: true, ..a.clone() }, false);
        assert_eq!((s.action_fidelity_parts_sum, s.action_fidelity), (83.0, 0.0));
        assert!(s.action_fidelity_rule.unwrap().starts_with("wrong_goal"));
        assert_eq!((s.simulation_success, s.task_completion), (0.0, 85.0));

        // non_equivalent: capped at 40 when above, left alone when below.
        let s = scores(&Answer { non_equivalent: true, ..a.clone() }, false);
        assert_eq!(s.action_fidelity, 40.0);
        assert!(s.action_fidelity_rule.unwrap().starts_with("non_equivalent"));
        assert!((s.simulation_success - 40.0 * 85.0 / 100.0).abs() < 1e-9);
        let low = graded([5.0, 10.0, 5.0, 5.0, 2.0, 5.0], [40.0, 40.0, 20.0]);
        let s = scores(&Answer { non_equivalent: true, ..low }, false);
        assert_eq!((s.action_fidelity, s.simulation_success), (32.0, 32.0));

        // The override: from the native checks, or from the model; the figures before it stay.
        for (native, model) in [(true, false), (false, true), (true, true)] {
            let s = scores(&Answer { physical_failure: model, ..a.clone() }, native);
            assert!(s.overridden);
            assert_eq!(s.simulation_success, 0.0);
            assert!((s.simulation_success_before_override - 70.55).abs() < 1e-9);
            assert_eq!((s.action_fidelity, s.task_completion), (83.0, 85.0));
        }

        // One engine's part alone is reported as partial, with no total (and never doubled).
        let s = scores(&Answer { ca_blender: None, ..a.clone() }, false);
        assert_eq!((s.content_alignment, s.content_alignment_partial), (None, true));
        assert!(s.content_alignment_basis.contains("MuJoCo part (0-50) stands alone"));
        let s = scores(&Answer { ca_mujoco: None, ..a.clone() }, false);
        assert_eq!((s.content_alignment, s.content_alignment_partial), (None, true));
        assert!(s.content_alignment_basis.contains("Blender part (0-50) stands alone"));
        let s = scores(&Answer { ca_mujoco: None, ca_blender: None, ..a }, false);
        assert_eq!((s.content_alignment, s.content_alignment_partial), (None, false));
    }

    #[test]
    fn gym_cameras_pair_with_the_source_frames_they_stand_for() {
        let names = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let frame = |id: u64, cam: Option<&str>| (id, id.to_string(), cam.map(str::to_string));
        // A reconstructed gym: cam_<id> for each frame, whatever the frames record.
        let vp = pair_viewpoints(
            &names(&["cam_0", "cam_4", "cam_9"]),
            &[frame(0, Some("agentview")), frame(4, None), frame(7, None)],
            3,
        );
        assert_eq!(vp.pairs, vec![("cam_0".to_string(), 0), ("cam_4".to_string(), 4)]);
        assert_eq!(vp.unpaired_frames, vec![7]);
        assert!(vp.unpaired_cameras.is_empty());
        assert_eq!(vp.cameras(), names(&["cam_0", "cam_4"]));
        assert!(vp.basis.contains("r2g reconstruct") && vp.basis.contains("no camera for source frame(s) 7"));
        // A key written with leading zeros still pairs with cam_<id>.
        let vp = pair_viewpoints(&names(&["cam_3"]), &[(3, "000003".into(), None)], 3);
        assert_eq!(vp.pairs, vec![("cam_3".to_string(), 3)]);
        // Frames that record their camera's name pair with the gym camera of that name.
        let vp = pair_viewpoints(
            &names(&["agentview", "wrist"]),
            &[frame(0, Some("agentview")), frame(1, Some("agentview")), frame(2, Some("wrist"))],
            3,
        );
        assert_eq!(vp.pairs.len(), 3);
        assert_eq!(vp.cameras(), names(&["agentview", "wrist"]));
        assert!(vp.basis.contains("r2g_camera"));
        // Nothing corresponds: the gym's cameras go unpaired (at most `max`), and the basis says so.
        let vp = pair_viewpoints(&names(&["front", "side", "top"]), &[frame(0, Some("agentview")), frame(1, None)], 2);
        assert!(vp.pairs.is_empty());
        assert_eq!(vp.unpaired_cameras, names(&["front", "side"]));
        assert_eq!(vp.unpaired_frames, vec![0, 1]);
        assert!(vp.basis.contains("not known") && vp.basis.contains("unpaired"));
    }

    #[test]
    fn instants_follow_the_grasps() {
        let v = json!({"evaluation": {"sim_time_s": 20.0}, "native_events": [
            {"kind": "grasp", "subject": "block", "other": "robot", "onset_s": 8.0, "offset_s": 16.0, "keyframes": []}]});
        assert_eq!(instants(&v), vec![0.0, 8.0, 12.0, 16.0, 20.0]);
        assert_eq!(instants(&json!({"sim_time_s": 9.0})), vec![0.0, 3.0, 6.0, 9.0]);
    }
}
