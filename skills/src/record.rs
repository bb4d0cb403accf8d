//! Reading a finished episode's run record (agent-host's `Recorder`: config.json,
//! transcript.jsonl, rounds/NNN/{stage.py, calls.json, obs.npz}, result.json, and the native
//! traces under episodes/) and labelling each code round's local effect.
//!
//! The label comes from what was measured, never from the model's words: a round whose program
//! raised, was stopped by the sandbox, or had a chunk refused or failed is **negative**, as is one
//! in which an object fell (dropped 5 cm while nothing held it) or toppled (tilted 30° while
//! free and ended lying on the table or floor), or that closed the gripper on nothing; one that executed every chunk it sent without that is **positive**; a round that sent
//! nothing is **unknown**. The task checks passing before and after are reported beside (a
//! grasp rightly undoes "released"), not judged. The native trace is read here, after the
//! episode: the policy never saw it.

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
    /// The fingers ended (nearly) shut with nothing between them.
    pub closed_on_nothing: bool,
    /// Task checks passing at the round's start and end.
    pub checks_before: usize,
    pub checks_after: usize,
    pub checks_total: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct Label {
    pub round: u32,
    pub outcome: Outcome,
    pub reasons: Vec<String>,
    pub effects: Option<Effects>,
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
                exec: r.get("exec").cloned(),
                state_before: r["state_before"].clone(),
                state_after: r["state_after"].clone(),
                obs_before: r["obs_before"].as_str().map(|p| dir.join(p)),
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

    /// Per round: the sim-host episode its end falls in and the simulated times (s) of its
    /// start and end there. Episode 1 ends at the host's reset before the first round; each
    /// reset a program sends ends one more (a round that resets starts at 0 in the new one).
    fn windows(&self) -> Vec<(usize, f64, f64)> {
        let mut episode = 2usize;
        self.rounds
            .iter()
            .map(|r| {
                let resets = r.resets();
                let t0 = if resets > 0 { 0.0 } else { r.state_before["timestamp"].as_f64().unwrap_or(0.0) };
                episode += resets;
                (episode, t0, r.state_after["timestamp"].as_f64().unwrap_or(t0))
            })
            .collect()
    }

    /// Where the trace has each object when round `round` begins (empty without a trace).
    pub fn native_positions(&self, round: u32) -> BTreeMap<String, [f64; 3]> {
        let mut out = BTreeMap::new();
        let Some(i) = self.rounds.iter().position(|r| r.n == round) else { return out };
        let (episode, t0, _) = self.windows()[i];
        if let Some(t) = self.trace(episode) {
            if let Some(k) = at(&t, t0) {
                for (name, o) in t.objects.iter().zip(&t.samples[k].objects) {
                    out.insert(name.clone(), [o[0], o[1], o[2]]);
                }
            }
        }
        out
    }

    /// Labels every round (see the module text).
    pub fn labels(&self) -> anyhow::Result<Vec<Label>> {
        let scene = Scene::load(&self.scene).with_context(|| format!("the run's scene {}", self.scene.display()))?;
        let mut cached: Option<(usize, Trace)> = None;
        let mut out = Vec::new();
        for (r, (episode, t0, t1)) in self.rounds.iter().zip(self.windows()) {
            let mut reasons = Vec::new();
            let Some(exec) = &r.exec else {
                out.push(Label {
                    round: r.n,
                    outcome: Outcome::Unknown,
                    reasons: vec!["no program".into()],
                    effects: None,
                });
                continue;
            };
            if exec["exit"] != "ok" {
                reasons.push(format!("the program ended with {}", exec["exit"].as_str().unwrap_or("?")));
            }
            if let Some(v) = exec["violation"].as_str() {
                reasons.push(format!("sandbox: {v}"));
            }
            let mut sent = 0;
            for c in r.chunks() {
                sent += 1;
                if c["result"] != 1 {
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
                    reasons.push("the gripper was closed and shut on nothing".into());
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
            out.push(Label { round: r.n, outcome, reasons, effects });
        }
        Ok(out)
    }
}

/// Whether a round commanded the gripper from open to closed (the last waypoint's gripper value
/// above +0.5 after one below 0, starting from the measured value).
fn closes(r: &Round) -> bool {
    let mut g = r.state_before["gripper"][0].as_f64().unwrap_or(-1.0);
    for c in r.chunks().filter(|c| c["result"] == 1) {
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
    let in_hand = trace.objects.iter().enumerate().any(|(k, _)| touching(s1, k as u16, robot));
    e.closed_on_nothing = s1.finger_m < 0.1 * trace.finger_max_m && !in_hand;
    let (b, total) = passing(scene, trace, i0);
    let (a, _) = passing(scene, trace, i1);
    e.checks_before = b;
    e.checks_after = a;
    e.checks_total = total;
    Some(e)
}
