//! Reading a finished episode's run record (agent-host's `Recorder`: config.json,
//! transcript.jsonl, rounds/NNN/{stage.py, calls.json, obs.npz}, result.json, and the native
//! traces under episodes/) and labelling each code round's local effect.
//!
//! The label comes from what was measured, never from the model's words, and from the motion,
//! not from how the program ended: a round is **negative** when its motion failed — a chunk
//! refused or failed, an object that fell (dropped 5 cm while nothing held it) or toppled
//! (tilted 30° while free and ended lying on the table or floor), or fingers closed on nothing
//! in a round that had no physical effect at all; one that executed every chunk it sent without
//! that is **positive** — even when its program then raised or exited on its own check (its
//! executed motion is kept; the program's end is a note) and even when it closed the fingers
//! on purpose to push something; a round that sent nothing is **unknown** (a sandbox denial
//! included: no motion failed). Physical effects come from the trace: objects moved, lifted,
//! grasped, set down, a fixture's joint moved (a drawer opened, a door closed), what the robot
//! touched. The task checks passing before and after are reported beside, not judged.
//!
//! Everything before the episode's last `reset()` is **exploration** (warm-up probes, a first
//! try undone): those rounds, and a round's calls before its own reset, are labelled but kept
//! out of skills. The native trace is read here, after the episode: the policy never saw it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use serde::Serialize;
use serde_json::Value;
use sim_host::trace::{evaluate, Sample, Trace};
use sim_host::Scene;

use crate::format::Outcome;

/// Object displacement that counts as "moved", m; a rise that counts as "lifted", m.
const MOVED_M: f64 = 0.01;
const ROSE_M: f64 = 0.02;
/// A drop that counts as "fell" for an object nobody holds, m; a tilt that counts as "toppled".
const FELL_M: f64 = 0.05;
const TOPPLED_RAD: f64 = 0.52;
/// A fixture joint change that counts as moved: a slide, m; a hinge, degrees.
const SLIDE_M: f64 = 0.01;
const HINGE_DEG: f64 = 3.0;
/// Scene objects that still stand where the episode's first observation saw them, m.
const SAME_PLACE_M: f64 = 0.001;

#[derive(Debug, Clone)]
pub struct Round {
    pub n: u32,
    pub observe_only: bool,
    pub plan: String,
    pub code: Option<String>,
    pub exec: Option<Value>,
    pub state_before: Value,
    pub state_after: Value,
    pub obs_before: Option<PathBuf>,
    /// The observation after the round (the next round's `obs_before`).
    pub obs_after: Option<PathBuf>,
    pub calls: Vec<Value>,
    pub feedback: String,
}

impl Round {
    /// The posted chunks of this round (reset calls left out).
    pub fn chunks(&self) -> impl Iterator<Item = &Value> {
        self.calls.iter().filter(|c| c["fn"] == "post_actions")
    }

    pub fn resets(&self) -> usize {
        self.calls.iter().filter(|c| c["fn"] == "reset").count()
    }

    /// The calls split at each reset(): segment k runs in the k-th sim-host episode the round
    /// touched (resets left out).
    pub fn segments(&self) -> Vec<&[Value]> {
        self.calls.split(|c| c["fn"] == "reset").collect()
    }

    /// Which segment holds the round's motion: the last one that posted a chunk (the last
    /// segment when none did).
    pub fn motion_segment(&self) -> usize {
        let segs = self.segments();
        segs.iter().rposition(|s| s.iter().any(|c| c["fn"] == "post_actions")).unwrap_or(segs.len() - 1)
    }

    /// The calls that make the round's motion: those of its motion segment.
    pub fn motion_calls(&self) -> Vec<Value> {
        self.segments()[self.motion_segment()].to_vec()
    }
}

pub struct RunRecord {
    pub dir: PathBuf,
    /// The episode id evidence cites: the run folder's name and the instance that ran it.
    pub name: String,
    pub gym: String,
    pub task: String,
    pub scene: PathBuf,
    pub seed: u64,
    pub success: Option<bool>,
    pub rounds: Vec<Round>,
}

/// What physics says a round did (from the trace, after the episode).
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct Effects {
    /// Objects that moved (name, metres).
    pub moved: Vec<(String, f64)>,
    /// Objects that rose (name, metres).
    pub rose: Vec<(String, f64)>,
    /// Objects in the closed fingers when the round ended.
    pub grasped: Vec<String>,
    /// Objects resting on another object or fixture (not the table), released, at the end.
    pub rests_on: Vec<(String, String)>,
    /// Objects that fell while nobody held them (name, metres dropped).
    pub fell: Vec<(String, f64)>,
    /// Objects that tilted over while nobody held them (name, radians).
    pub toppled: Vec<(String, f64)>,
    /// Fixture joints that moved (a drawer opened, a door closed).
    pub joints: Vec<JointChange>,
    /// What the robot touched during the round besides the table and the floor (objects and
    /// fixtures), in order of first contact.
    pub touched: Vec<String>,
    /// The fingers ended (nearly) shut with nothing between them.
    pub closed_on_nothing: bool,
    /// Task checks passing at the round's start and end.
    pub checks_before: usize,
    pub checks_after: usize,
    pub checks_total: usize,
}

/// One fixture joint over a round, in the scene's units.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct JointChange {
    pub fixture: String,
    /// `slide` (m) or `hinge` (degrees).
    pub kind: String,
    pub from: f64,
    pub to: f64,
    /// Its travel in the scene (from, to), when the scene gives one.
    pub range: Option<[f64; 2]>,
}

impl JointChange {
    pub fn describe(&self) -> String {
        let unit = if self.kind == "slide" { " m" } else { " deg" };
        let toward = match self.range {
            Some([lo, hi]) if (self.to - lo).abs() < (self.to - hi).abs() => format!(", toward its {lo}{unit} end"),
            Some([_, hi]) => format!(", toward its {hi}{unit} end"),
            None => String::new(),
        };
        format!(
            "{}'s {} went from {:.3} to {:.3}{unit} ({:+.3}{unit}{toward})",
            self.fixture,
            self.kind,
            self.from,
            self.to,
            self.to - self.from
        )
    }
}

impl Effects {
    /// Whether physics shows the round did something to the world: moved, lifted or grasped an
    /// object, moved a fixture's joint, or touched something other than the table.
    pub fn physical(&self) -> bool {
        !(self.moved.is_empty()
            && self.rose.is_empty()
            && self.grasped.is_empty()
            && self.joints.is_empty()
            && self.touched.is_empty())
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Label {
    pub round: u32,
    pub outcome: Outcome,
    /// Why the outcome is what it is (for a negative round: the motion failures).
    pub reasons: Vec<String>,
    pub effects: Option<Effects>,
    /// Before the episode's last reset(): exploration, never a skill's evidence or procedure.
    pub exploration: bool,
    /// What was measured besides, deciding nothing: how the program ended, calls undone by a
    /// reset() within the round, fingers shut on purpose.
    pub notes: Vec<String>,
}

impl Label {
    pub fn new(round: u32, outcome: Outcome, reasons: Vec<String>, effects: Option<Effects>) -> Self {
        Self { round, outcome, reasons, effects, exploration: false, notes: Vec::new() }
    }

    /// A motion failure: what pairs with the round that corrected it.
    pub fn failed(&self) -> bool {
        self.outcome == Outcome::Negative && !self.exploration
    }

    /// A round whose motion may become a skill's procedure or evidence.
    pub fn usable(&self) -> bool {
        self.outcome == Outcome::Positive && !self.exploration
    }
}

fn read_json(p: &Path) -> anyhow::Result<Value> {
    let t = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
    serde_json::from_str(&t).with_context(|| format!("{} is not JSON", p.display()))
}

impl RunRecord {
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        let dir = std::fs::canonicalize(dir).with_context(|| format!("no run folder {}", dir.display()))?;
        let config = read_json(&dir.join("config.json")).context("a run record has config.json")?;
        let transcript = std::fs::read_to_string(dir.join("transcript.jsonl"))
            .with_context(|| format!("reading {}/transcript.jsonl", dir.display()))?;
        let mut rounds = Vec::new();
        for (i, line) in transcript.lines().enumerate() {
            let Ok(r) = serde_json::from_str::<Value>(line) else {
                bail!("{}/transcript.jsonl line {}: not JSON", dir.display(), i + 1);
            };
            let Some(n) = r["round"].as_u64() else { continue };
            let calls = match r["calls"].as_str() {
                Some(rel) => read_json(&dir.join(rel))?.as_array().cloned().unwrap_or_default(),
                None => Vec::new(),
            };
            rounds.push(Round {
                n: n as u32,
                observe_only: r["observe_only"].as_bool().unwrap_or(false),
                plan: r["decision"]["plan"].as_str().unwrap_or_default().to_string(),
                code: r["decision"]["code"].as_str().map(str::to_string),
                exec: r.get("exec").cloned().filter(|e| !e.is_null()),
                state_before: r["state_before"].clone(),
                state_after: r["state_after"].clone(),
                obs_before: r["obs_before"].as_str().map(|p| dir.join(p)),
                obs_after: r["obs_after"].as_str().map(|p| dir.join(p)),
                calls,
                feedback: r["feedback"].as_str().unwrap_or_default().to_string(),
            });
        }
        let result = read_json(&dir.join("result.json")).ok();
        // The run folder's name with the instance that ran it (`ep<pid>-<ms>-<n>`, unique on this
        // machine): folders named alike (`episode-000-without` of two batches) stay apart.
        let folder = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let name = match config["instance"].as_str() {
            Some(i) if !i.is_empty() => format!("{folder}@{i}"),
            _ => folder,
        };
        Ok(Self {
            name,
            gym: config["gym"].as_str().unwrap_or_default().to_string(),
            task: config["task"].as_str().unwrap_or_default().to_string(),
            scene: PathBuf::from(config["scene"].as_str().context("config.json names no scene")?),
            seed: config["seed"].as_u64().unwrap_or(0),
            success: result.as_ref().and_then(|r| r["success"].as_bool()),
            rounds,
            dir,
        })
    }

    /// The trace of the sim-host episode numbered `k` (1 ran from start to the host's reset).
    fn trace(&self, k: usize) -> Option<Trace> {
        let p = self.dir.join("episodes").join(format!("episode-{k}.trace.json"));
        let t: Trace = serde_json::from_str(&std::fs::read_to_string(p).ok()?).ok()?;
        // A trace whose samples do not all hold every object is not read (no indexing past them).
        t.samples.iter().all(|s| s.objects.len() == t.objects.len()).then_some(t)
    }

    /// Per round: the sim-host episode its motion ran in and the simulated times (s) of that
    /// motion's start and end there. Episode 1 ends at the host's reset before the first round;
    /// each reset a program sends ends one more. A round's motion is its last segment that
    /// posted chunks (see [`Round::motion_segment`]): one after a reset starts at 0 in the new
    /// episode; one followed by a reset ends at that reset (its `t_before`, or the last chunk's
    /// `t_after` in records written before resets carried it).
    pub fn windows(&self) -> Vec<(usize, f64, f64)> {
        let mut episode = 2usize;
        self.rounds
            .iter()
            .map(|r| {
                let segs = r.segments();
                let k = r.motion_segment();
                let e = episode + k;
                episode += segs.len() - 1;
                let t0 = if k == 0 { r.state_before["timestamp"].as_f64().unwrap_or(0.0) } else { 0.0 };
                let t1 = if k + 1 == segs.len() {
                    r.state_after["timestamp"].as_f64().unwrap_or(t0)
                } else {
                    let reset = r.calls.iter().filter(|c| c["fn"] == "reset").nth(k);
                    reset
                        .and_then(|c| c["t_before"].as_f64())
                        .or_else(|| segs[k].iter().filter_map(|c| c["t_after"].as_f64()).reduce(f64::max))
                        .unwrap_or(t0)
                };
                (e, t0, t1.max(t0))
            })
            .collect()
    }

    /// The round and call index of the episode's last reset() sent by a program, if any.
    pub fn last_reset(&self) -> Option<(u32, usize)> {
        self.rounds.iter().rev().find_map(|r| r.calls.iter().rposition(|c| c["fn"] == "reset").map(|i| (r.n, i)))
    }

    /// Whether a round's motion ran before the episode's last reset() (exploration).
    pub fn exploration(&self, round: u32) -> bool {
        let Some((last, _)) = self.last_reset() else { return false };
        match self.rounds.iter().find(|r| r.n == round) {
            Some(r) if r.n == last => r.motion_segment() + 1 < r.segments().len(),
            Some(r) => r.n < last,
            None => false,
        }
    }

    /// Where the trace has each object at `t` of sim-host episode `episode` (empty without a trace).
    pub fn native_at(&self, episode: usize, t: f64) -> BTreeMap<String, [f64; 3]> {
        let mut out = BTreeMap::new();
        if let Some(t) = self.trace(episode).and_then(|tr| at(&tr, t).map(|k| (tr, k))) {
            let (tr, k) = t;
            for (name, o) in tr.objects.iter().zip(&tr.samples[k].objects) {
                out.insert(name.clone(), [o[0], o[1], o[2]]);
            }
        }
        out
    }

    /// The objects the closed fingers hold at time `t` of sim-host episode `episode` (touching the
    /// robot with the fingers short of open, as `effects` calls an object grasped).
    pub fn held_at(&self, episode: usize, t: f64) -> Vec<String> {
        let Some(tr) = self.trace(episode) else { return Vec::new() };
        let (Some(k), Some(robot)) = (at(&tr, t), tr.owners.iter().position(|o| o == "robot")) else {
            return Vec::new();
        };
        let s = &tr.samples[k];
        if s.finger_m >= 0.95 * tr.finger_max_m {
            return Vec::new();
        }
        let robot = robot as u16;
        tr.objects
            .iter()
            .enumerate()
            .filter(|&(i, _)| s.contacts.contains(&[(i as u16).min(robot), (i as u16).max(robot)]))
            .map(|(_, n)| n.clone())
            .collect()
    }

    /// Where the trace has each object when round `round`'s motion begins (empty without a trace).
    pub fn native_positions(&self, round: u32) -> BTreeMap<String, [f64; 3]> {
        let Some(i) = self.rounds.iter().position(|r| r.n == round) else { return BTreeMap::new() };
        let (episode, t0, _) = self.windows()[i];
        self.native_at(episode, t0)
    }

    /// The observation a round's motion starts from: the round's first observation, or, for
    /// motion after a reset() within the round, the episode's first observation when the trace
    /// shows the reset put every object back where that one saw them (the simulation profile's
    /// reset restores the placement). None, with the reason, when there is none.
    pub fn motion_obs(&self, round: u32) -> Result<PathBuf, String> {
        let Some(i) = self.rounds.iter().position(|r| r.n == round) else { return Err(format!("no round {round}")) };
        let r = &self.rounds[i];
        if r.motion_segment() == 0 {
            return r.obs_before.clone().ok_or_else(|| "the record has no observation from the round's start".into());
        }
        let (episode, _, _) = self.windows()[i];
        let (Some(first), Some(now)) = (self.trace(2), self.trace(episode)) else {
            return Err(
                "its motion follows a reset() and the record has no trace to tell where that left the objects".into()
            );
        };
        let same = first.objects == now.objects
            && match (first.samples.first(), now.samples.first()) {
                (Some(a), Some(b)) => a.objects.iter().zip(&b.objects).all(|(p, q)| {
                    ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt() < SAME_PLACE_M
                }),
                _ => false,
            };
        match (same, self.rounds.first().and_then(|r0| r0.obs_before.clone())) {
            (true, Some(obs)) => Ok(obs),
            _ => Err("its motion follows a reset() that did not restore the first observation's placement, and nothing was observed after it".into()),
        }
    }

    /// The observations of the episode from its last reset() on, in order (each round's first
    /// observation once), up to and including `upto`: what a tracker must have seen to name the
    /// objects of `upto` as extraction did.
    pub fn observations_upto(&self, upto: &Path) -> Vec<PathBuf> {
        let mut out: Vec<PathBuf> = Vec::new();
        for r in &self.rounds {
            if self.exploration(r.n) {
                continue;
            }
            let Ok(obs) = self.motion_obs(r.n) else { continue };
            if out.last() != Some(&obs) {
                out.push(obs.clone());
            }
            if obs == upto {
                return out;
            }
        }
        out.push(upto.to_path_buf());
        out.dedup();
        out
    }

    /// Per round: the gripper value last commanded before its motion began (`initial` after a
    /// reset(): the scene's starting gripper).
    pub fn commanded_gripper(&self, initial: f64) -> Vec<f64> {
        let mut g = initial;
        let mut out = Vec::new();
        for r in &self.rounds {
            let k = r.motion_segment();
            let mut at_motion = g;
            for (i, seg) in r.segments().iter().enumerate() {
                if i > 0 {
                    g = initial;
                }
                if i == k {
                    at_motion = g;
                }
                for c in seg.iter().filter(|c| c["fn"] == "post_actions" && c["result"] == 1) {
                    let width = if c["type"] == "joint" { 7 } else { 6 };
                    if let Some(v) = c["actions"].as_array().and_then(|a| a.last()).and_then(|w| w[width].as_f64()) {
                        g = v;
                    }
                }
            }
            out.push(at_motion);
        }
        out
    }

    /// Labels every round (see the module text).
    pub fn labels(&self) -> anyhow::Result<Vec<Label>> {
        let scene = Scene::load(&self.scene).with_context(|| format!("the run's scene {}", self.scene.display()))?;
        let mut cached: Option<(usize, Trace)> = None;
        let mut out = Vec::new();
        for (r, (episode, t0, t1)) in self.rounds.iter().zip(self.windows()) {
            let exploration = self.exploration(r.n);
            let mut notes = Vec::new();
            if exploration {
                notes.push("before the episode's last reset(): exploration, kept out of skills".to_string());
            }
            let Some(exec) = &r.exec else {
                out.push(Label {
                    exploration,
                    notes,
                    ..Label::new(r.n, Outcome::Unknown, vec!["no program".into()], None)
                });
                continue;
            };
            if r.observe_only {
                // reset() and post_actions() are refused by design in this turn: nothing to judge.
                notes.push("the observation-only turn".into());
                if let Some(v) = exec["violation"].as_str() {
                    notes.push(format!("sandbox: {v} (not a motion failure)"));
                }
                out.push(Label {
                    exploration,
                    notes,
                    ..Label::new(r.n, Outcome::Unknown, vec!["observation only".into()], None)
                });
                continue;
            }
            // How the program ended decides nothing about its motion (a program that pushed the
            // block and then raised on its own strict check still pushed it).
            let k = r.motion_segment();
            let executed = r.segments()[k].iter().any(|c| c["fn"] == "post_actions" && c["result"] == 1);
            if exec["exit"] != "ok" {
                let what = exec["exc_type"]
                    .as_str()
                    .map(|t| format!("{} ({t})", exec["exit"].as_str().unwrap_or("?")))
                    .unwrap_or_else(|| exec["exit"].as_str().unwrap_or("?").to_string());
                notes.push(if executed {
                    format!("the program ended with {what} after its motion; the executed motion is kept")
                } else {
                    format!("the program ended with {what}")
                });
            }
            if let Some(v) = exec["violation"].as_str() {
                notes.push(format!("sandbox: {v} (not a motion failure)"));
            }
            if k > 0 && r.segments()[..k].iter().any(|s| s.iter().any(|c| c["fn"] == "post_actions")) {
                notes.push("its chunks before its own reset() were exploration and are left out".into());
            }
            let mut reasons = Vec::new();
            if let Some(n) = exec["budget_refusals"].as_u64().filter(|n| *n > 0) {
                reasons.push(format!("{n} chunk(s) refused by the control-step budget"));
            }
            let mut sent = 0;
            for c in r.segments()[k].iter().filter(|c| c["fn"] == "post_actions") {
                if c["result"] == 1 {
                    sent += 1;
                } else {
                    reasons.push(format!(
                        "a chunk was {}: {}",
                        c["feedback"]["status"].as_str().unwrap_or("refused"),
                        c["feedback"]["reason"].as_str().unwrap_or_default()
                    ));
                }
            }
            if cached.as_ref().is_none_or(|(k, _)| *k != episode) {
                cached = self.trace(episode).map(|t| (episode, t));
            }
            let effects = cached.as_ref().and_then(|(_, t)| effects(&scene, t, t0, t1));
            if let Some(e) = &effects {
                if closes(r) && e.closed_on_nothing {
                    if e.physical() {
                        notes.push(
                            "the fingers ended shut on nothing, on purpose: the round had a physical effect".into(),
                        );
                    } else {
                        reasons.push("the gripper was closed and shut on nothing (no physical effect)".into());
                    }
                }
                for (o, d) in &e.fell {
                    reasons.push(format!("{o} fell {d:.2} m while nothing held it"));
                }
                for (o, a) in &e.toppled {
                    reasons.push(format!("{o} toppled ({:.0} degrees)", a.to_degrees()));
                }
            }
            let outcome = if !reasons.is_empty() {
                Outcome::Negative
            } else if sent == 0 {
                reasons.push("sent no motion".into());
                Outcome::Unknown
            } else {
                Outcome::Positive
            };
            out.push(Label { round: r.n, outcome, reasons, effects, exploration, notes });
        }
        Ok(out)
    }
}

/// Whether a round commanded the gripper from open to closed (the last waypoint's gripper value
/// above +0.5 after one below 0, starting from the measured value).
fn closes(r: &Round) -> bool {
    let mut g = r.state_before["gripper"][0].as_f64().unwrap_or(-1.0);
    for c in r.motion_calls().iter().filter(|c| c["fn"] == "post_actions" && c["result"] == 1) {
        let width = if c["type"] == "joint" { 7 } else { 6 };
        if let Some(v) = c["actions"].as_array().and_then(|a| a.last()).and_then(|w| w[width].as_f64()) {
            if g < 0.0 && v > 0.5 {
                return true;
            }
            g = v;
        }
    }
    false
}

/// Angle between the object's z axis in two orientations (w, x, y, z).
fn up_angle(a: [f64; 4], b: [f64; 4]) -> f64 {
    let z = |q: [f64; 4]| {
        let [w, x, y, zz] = q;
        [2.0 * (x * zz + w * y), 2.0 * (y * zz - w * x), 1.0 - 2.0 * (x * x + y * y)]
    };
    let (u, v) = (z(a), z(b));
    (u[0] * v[0] + u[1] * v[1] + u[2] * v[2]).clamp(-1.0, 1.0).acos()
}

fn at(trace: &Trace, t: f64) -> Option<usize> {
    if trace.samples.is_empty() {
        return None;
    }
    Some(trace.samples.partition_point(|s| s.t_s <= t + 1e-9).saturating_sub(1))
}

fn passing(scene: &Scene, trace: &Trace, upto: usize) -> (usize, usize) {
    let prefix = Trace { samples: trace.samples[..=upto].to_vec(), ..trace.clone() };
    let e = evaluate(scene, &prefix);
    (e.checks.values().filter(|c| c.pass).count(), e.checks.len())
}

/// What changed between the samples nearest `t0` and `t1` of an episode's trace.
pub fn effects(scene: &Scene, trace: &Trace, t0: f64, t1: f64) -> Option<Effects> {
    let (i0, i1) = (at(trace, t0)?, at(trace, t1)?);
    if i1 < i0 {
        return None;
    }
    let (s0, s1): (&Sample, &Sample) = (&trace.samples[i0], &trace.samples[i1]);
    let robot = trace.owners.iter().position(|o| o == "robot")? as u16;
    let table = trace.owners.iter().position(|o| o == "table").map(|i| i as u16);
    let touching = |s: &Sample, a: u16, b: u16| s.contacts.contains(&[a.min(b), a.max(b)]);
    let mut e = Effects::default();
    for (k, name) in trace.objects.iter().enumerate() {
        let (p0, p1) = (s0.objects[k], s1.objects[k]);
        let d = ((p1[0] - p0[0]).powi(2) + (p1[1] - p0[1]).powi(2) + (p1[2] - p0[2]).powi(2)).sqrt();
        if d >= MOVED_M {
            e.moved.push((name.clone(), d));
        }
        if p1[2] - p0[2] >= ROSE_M {
            e.rose.push((name.clone(), p1[2] - p0[2]));
        }
        let held = touching(s1, k as u16, robot);
        if held && s1.finger_m < 0.95 * trace.finger_max_m {
            e.grasped.push(name.clone());
        }
        // Free drops and tilts: measured from the last sample the robot touched it (or the
        // round's start), over the samples it was free.
        let (mut z_ref, mut q_ref, mut drop, mut tilt) = (p0[2], [p0[3], p0[4], p0[5], p0[6]], 0.0f64, 0.0f64);
        for s in &trace.samples[i0..=i1] {
            let o = s.objects[k];
            if touching(s, k as u16, robot) {
                (z_ref, q_ref) = (o[2], [o[3], o[4], o[5], o[6]]);
            } else {
                drop = drop.max(z_ref - o[2]);
                tilt = tilt.max(up_angle(q_ref, [o[3], o[4], o[5], o[6]]));
            }
        }
        if drop >= FELL_M {
            e.fell.push((name.clone(), drop));
        }
        // Tilted over and lying on the table (or the floor): toppled. Tilting while hanging from
        // a fixture (a mug on a peg) is not.
        let floor = trace.owners.iter().position(|o| o == "floor").map(|i| i as u16);
        let lying = [table, floor].iter().flatten().any(|&t| touching(s1, k as u16, t));
        if tilt >= TOPPLED_RAD && lying {
            e.toppled.push((name.clone(), tilt));
        }
        if !held {
            for (j, other) in trace.owners.iter().enumerate() {
                let j = j as u16;
                if j as usize != k && j != robot && Some(j) != table && other != "floor" && touching(s1, k as u16, j) {
                    let oz = trace.objects.iter().position(|n| n == other).map(|q| s1.objects[q][2]);
                    if oz.is_none_or(|z| z < p1[2]) {
                        e.rests_on.push((name.clone(), other.clone()));
                    }
                }
            }
        }
    }
    // Closed on a fixture's handle counts as something in the hand too.
    let floor = trace.owners.iter().position(|o| o == "floor").map(|i| i as u16);
    let ground = |j: u16| Some(j) == table || Some(j) == floor || j == robot;
    let in_hand = (0..trace.owners.len() as u16).any(|j| !ground(j) && touching(s1, j, robot));
    e.closed_on_nothing = s1.finger_m < 0.1 * trace.finger_max_m && !in_hand;
    for s in &trace.samples[i0..=i1] {
        for &[a, b] in &s.contacts {
            let other = if a == robot {
                b
            } else if b == robot {
                a
            } else {
                continue;
            };
            if !ground(other) {
                if let Some(name) = trace.owners.get(other as usize) {
                    if !e.touched.contains(name) {
                        e.touched.push(name.clone());
                    }
                }
            }
        }
    }
    for (k, fixture) in trace.joints.iter().enumerate() {
        let (Some(&a), Some(&b)) = (s0.joints.get(k), s1.joints.get(k)) else { continue };
        let joint = scene.fixtures.iter().find(|f| &f.name == fixture).and_then(|f| f.joint.as_ref());
        let slide = joint.is_some_and(|j| j.kind == sim_host::scene::JointKind::Slide);
        if (b - a).abs() >= if slide { SLIDE_M } else { HINGE_DEG } {
            e.joints.push(JointChange {
                fixture: fixture.clone(),
                kind: if slide { "slide" } else { "hinge" }.into(),
                from: a,
                to: b,
                range: joint.and_then(|j| if slide { j.range_m } else { j.range_deg }),
            });
        }
    }
    let (b, total) = passing(scene, trace, i0);
    let (a, _) = passing(scene, trace, i1);
    e.checks_before = b;
    e.checks_after = a;
    e.checks_total = total;
    Some(e)
}
