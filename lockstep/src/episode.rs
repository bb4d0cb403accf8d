//! One episode in one process: the runtime's controller ticks at the scene's physics rate and
//! the simulator steps once per command, exactly as `r2g-control` and `r2g-sim` do in lockstep
//! mode, minus the shared memory.

use std::path::{Path, PathBuf};

use anyhow::Context;
use controllers::LimiterConfig;
use ipc_schema::{
    ControlType, JointCommand, Mode, Reply, Request, RequestKind, RobotState, Status, MAX_CHUNK, WAYPOINT_LEN,
};
use runtime::controller::{Controller, Forward};
use sim_host::placement::Perturbation;
use sim_host::trace::{evaluate, Evaluation, Trace};
use sim_host::Sim;

use crate::demo::{read_demo, write_atomic};

pub struct Episode {
    pub sim: Sim,
    pub ctl: Controller,
    pub trace: Trace,
    seq: u64,
    last_cmd: u64,
    next_request: u64,
    /// The last reset's id (0: the episode as loaded).
    reset_id: u64,
    /// Ticks run (one per physics step).
    pub ticks: u64,
}

impl Episode {
    /// Loads a scene and starts an episode from its initial state, augmented by `seed`.
    pub fn new(scene: &Path, seed: u64) -> anyhow::Result<Self> {
        Self::with_setup(scene, seed, None, LimiterConfig::default())
    }

    /// As [`Episode::new`], with free objects moved by a placement perturbation drawn from
    /// `seed` (sim_host::placement), at this reset and every later one.
    pub fn perturbed(scene: &Path, seed: u64, perturbation: Option<Perturbation>) -> anyhow::Result<Self> {
        Self::with_setup(scene, seed, perturbation, LimiterConfig::default())
    }

    /// [`Self::new`] with the limiter settings of a robot configuration
    /// (`runtime::RobotConfig::limiter`: its step caps and chunk length), as `r2g-control` runs.
    pub fn with_limits(scene: &Path, seed: u64, limits: LimiterConfig) -> anyhow::Result<Self> {
        Self::with_setup(scene, seed, None, limits)
    }

    /// The episode with both: a placement perturbation and the limiter settings.
    pub fn with_setup(
        scene: &Path,
        seed: u64,
        perturbation: Option<Perturbation>,
        limits: LimiterConfig,
    ) -> anyhow::Result<Self> {
        let mut sim = Sim::load(scene).with_context(|| format!("loading scene {}", scene.display()))?;
        sim.seed = seed;
        sim.set_perturbation(perturbation)?;
        let (robot, safety) = runtime::scene_robot(scene)?;
        let ctl = Controller::new(robot, limits, sim.scene.timestep_s).with_safety(safety);
        let mut trace = sim.new_trace();
        sim.record(&mut trace);
        Ok(Self { sim, ctl, trace, seq: 1, last_cmd: 0, next_request: 1, reset_id: 0, ticks: 0 })
    }

    fn measure(&self) -> ipc_schema::SimState {
        self.sim.measure(self.seq, self.last_cmd, self.reset_id)
    }

    fn tick(&mut self) -> Option<Reply> {
        let state = self.measure();
        let (cmd, reply): (JointCommand, Option<Reply>) = self.ctl.tick(&state);
        self.last_cmd = cmd.seq;
        self.sim.step(&cmd);
        self.seq += 1;
        self.ticks += 1;
        self.sim.record(&mut self.trace);
        reply
    }

    /// Posts one chunk and runs until it has executed or failed; returns the final reply.
    pub fn run_chunk(&mut self, control: ControlType, actions: &[[f64; WAYPOINT_LEN]], freq_hz: f64) -> Reply {
        let id = self.next_request;
        self.next_request += 1;
        let req = request(id, RequestKind::Chunk, control, actions, freq_hz, 0);
        let state = self.measure();
        let (reply, _) = self.ctl.request(&req, &state);
        if let Some(r) = reply {
            if r.status != Status::Accepted as u32 {
                return r;
            }
        }
        loop {
            if let Some(r) = self.tick() {
                if r.id == id && r.status != Status::Accepted as u32 {
                    return r;
                }
            }
        }
    }

    /// Lets physics run on with the arm holding, for `seconds` of simulated time.
    pub fn hold(&mut self, seconds: f64) {
        let n = (seconds / self.sim.scene.timestep_s).round() as u64;
        for _ in 0..n {
            self.tick();
        }
    }

    pub fn evaluate(&self) -> Evaluation {
        evaluate(&self.sim.scene, &self.trace)
    }

    /// A new episode of the same scene, augmented by `seed`, started the way `r2g-control` and
    /// `r2g-sim` start one on a reset request: the controller takes the reset, the simulator
    /// restores the scene, and the controller holds the arm where the reset put it. The trace
    /// starts again.
    pub fn reset(&mut self, seed: u64) -> Result<(), String> {
        let id = self.next_request;
        self.next_request += 1;
        let req = request(id, RequestKind::Reset, ControlType::Joint, &[], 0.0, 0);
        let state = self.measure();
        let (reply, fwd) = self.ctl.request(&req, &state);
        let Forward::Reset { sim_reset_id } = fwd else {
            return Err(reply.map_or_else(|| "the controller took no reset".into(), |r| r.reason_str().to_string()));
        };
        self.sim.seed = seed;
        self.sim.reset();
        self.seq += 1;
        self.sim.reset_state_seq = self.seq;
        self.reset_id = sim_reset_id;
        self.trace = self.sim.new_trace();
        self.sim.record(&mut self.trace);
        let state = self.measure();
        match self.ctl.complete_reset(&state) {
            Some(r) if r.status == Status::Executed as u32 => Ok(()),
            r => Err(r.map_or_else(|| "the reset did not complete".into(), |r| r.reason_str().to_string())),
        }
    }

    /// One step of a fixed period, as a [`RequestKind::Step`] runs in `r2g-control`: `actions`
    /// (none: only time passes) are taken as the step's chunk, then exactly `ticks` ticks run.
    /// Returns every reply to the step's request in order, the last one `stepped`.
    pub fn step(
        &mut self,
        control: ControlType,
        actions: &[[f64; WAYPOINT_LEN]],
        freq_hz: f64,
        ticks: u32,
    ) -> Vec<Reply> {
        let id = self.next_request;
        self.next_request += 1;
        let req = request(id, RequestKind::Step, control, actions, freq_hz, ticks);
        let state = self.measure();
        let (reply, _) = self.ctl.request(&req, &state);
        let mut replies: Vec<Reply> = [reply, self.ctl.take_accepted()].into_iter().flatten().collect();
        let mut guard = ticks;
        while self.ctl.advancing() && guard > 0 {
            replies.extend(self.tick());
            // The runtime reports the state after every tick; the TCP's axis-angle vector is kept
            // continuous from one report to the next, so the reports must be the same here.
            self.robot_state();
            replies.extend(self.ctl.take_stepped());
            guard -= 1;
        }
        replies.retain(|r| r.id == id);
        replies
    }

    /// The agent-facing state of the present measurement, as the runtime publishes it.
    pub fn robot_state(&mut self) -> RobotState {
        let state = self.measure();
        self.ctl.robot_state(&state, self.seq, Mode::Lockstep as u32)
    }
}

/// A request of `kind` carrying `actions` (at most [`MAX_CHUNK`] are kept).
fn request(
    id: u64,
    kind: RequestKind,
    control: ControlType,
    actions: &[[f64; WAYPOINT_LEN]],
    freq_hz: f64,
    step_ticks: u32,
) -> Request {
    let mut req = Request {
        id,
        client: 1,
        kind: kind as u32,
        control_type: control as u32,
        len: actions.len().min(MAX_CHUNK) as u32,
        step_ticks,
        freq_hz,
        actions: [[0.0; WAYPOINT_LEN]; MAX_CHUNK],
    };
    for (dst, src) in req.actions.iter_mut().zip(actions) {
        *dst = *src;
    }
    req
}

/// How a replay went.
pub struct Replay {
    pub evaluation: Evaluation,
    /// Chunks that did not execute: (first row, reply reason).
    pub failures: Vec<(usize, String)>,
    pub trace_path: Option<PathBuf>,
}

/// Replays a scene's demonstration (or nothing, with `do_nothing`) in lockstep, lets physics
/// settle, and judges the trace. Chunks of at most 256 rows run one after the other.
pub fn replay(scene: &Path, seed: u64, do_nothing: bool, out: Option<&Path>) -> anyhow::Result<Replay> {
    replay_perturbed(scene, seed, None, do_nothing, out)
}

/// [`replay`] with the placement perturbation `perturbation` drawn from `seed`: the
/// demonstration's absolute joint targets, played where the objects no longer are.
pub fn replay_perturbed(
    scene: &Path,
    seed: u64,
    perturbation: Option<Perturbation>,
    do_nothing: bool,
    out: Option<&Path>,
) -> anyhow::Result<Replay> {
    let mut ep = Episode::perturbed(scene, seed, perturbation)?;
    let mut failures = Vec::new();
    if !do_nothing {
        let demo = ep
            .sim
            .scene
            .task
            .demonstration
            .clone()
            .with_context(|| format!("scene {} has no task.demonstration", scene.display()))?;
        let rows = read_demo(&demo)?;
        let hz = ep.sim.scene.task.demonstration_hz;
        for (k, chunk) in rows.chunks(MAX_CHUNK).enumerate() {
            let r = ep.run_chunk(ControlType::Joint, chunk, hz);
            if r.status != Status::Executed as u32 {
                failures.push((k * MAX_CHUNK, r.reason_str().to_string()));
            }
        }
    }
    ep.hold(ep.sim.scene.task.settle_s.max(if do_nothing { 2.0 } else { 0.0 }));
    let evaluation = ep.evaluate();
    let trace_path = match out {
        Some(dir) => {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            let p = dir.join(format!("{}-seed{seed}.trace.json", ep.sim.scene.name));
            write_atomic(&p, &serde_json::to_vec(&ep.trace)?)?;
            let e = dir.join(format!("{}-seed{seed}.eval.json", ep.sim.scene.name));
            write_atomic(&e, &serde_json::to_vec_pretty(&evaluation)?)?;
            Some(p)
        }
        None => None,
    };
    Ok(Replay { evaluation, failures, trace_path })
}
