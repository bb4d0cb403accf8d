//! What one tick decides, without any I/O: accept or reject requests, advance the active
//! chunk, limit the command, and tell when a request has finished. The same code runs in
//! wall and lockstep mode, so lockstep results carry over.

use controllers::diffik::{self, DiffIkConfig};
use controllers::error::Text;
use controllers::ik::{IkConfig, IkSolver};
use controllers::safety::SafetyChecks;
use controllers::Reference;
use controllers::{ChunkPlan, JointTracker, LimiterConfig, Rejection, RobotModel};
use ipc_schema::{
    ControlType, JointCommand, Profile, Reply, Request, RequestKind, RobotState, SimState, Status, N_JOINTS,
    WAYPOINT_LEN,
};

use crate::robot_config::Reflexes;

/// Measured joints must come this close to the final target for a chunk to count as settled.
const SETTLE_TOL_RAD: f64 = 0.002;
const SETTLE_VEL_RAD_S: f64 = 0.02;
/// A chunk counts as executed only when the measured state ends this close to its last
/// waypoint (documented in robot-skill/api/README.md): joints for joint chunks, ...
pub const REACH_TOL_RAD: f64 = 0.005;
/// ... the TCP's position and (geodesic) rotation for ee_pose chunks.
pub const REACH_TOL_M: f64 = 0.005;
pub const REACH_TOL_TCP_RAD: f64 = 0.02;
/// A joint counts as at its limit within this distance of it, rad.
const AT_LIMIT_RAD: f64 = 0.01;
/// Longest wait for settling after the command has arrived, s.
const SETTLE_TIMEOUT_S: f64 = 1.5;
/// How long past the planned duration the command may take to reach the last waypoint, s.
const MOVE_OVERTIME_S: f64 = 10.0;
/// Time constant of the low-pass filter on the measured external force, s.
const FORCE_FILTER_S: f64 = 0.02;
/// Contact reflexes need the force to have grown by this much since the chunk began, so an arm
/// already pressing on something can still back away from it, N.
const REFLEX_GROWTH_N: f64 = 5.0;
/// A chunk checked off the tick (see [`Controller::commit`]) is refused when the command has
/// moved further than this from where its checks started, rad (any joint).
pub const STALE_START_RAD: f64 = 0.05;
/// The longest step a [`RequestKind::Step`] may ask for, ticks (10 s at 1 kHz).
pub const MAX_STEP_TICKS: u32 = 10_000;

#[derive(Debug, Clone, Copy)]
enum Phase {
    Moving,
    Settling { since_s: f64 },
}

#[derive(Debug, Clone, Copy)]
struct Active {
    id: u64,
    client: u64,
    t_s: f64,
    phase: Phase,
    accepted_ns: u64,
    first_motion_ns: u64,
    /// Measured joints and finger at acceptance, to see the first motion.
    q0: [f64; N_JOINTS],
    finger0: f64,
    /// The filtered external force over the chunk so far.
    contact: ContactStats,
}

/// The force felt over a chunk: every tick's magnitude of the filtered external force.
#[derive(Debug, Clone, Copy, Default)]
struct ContactStats {
    start_n: f64,
    peak_n: f64,
    sum_n: f64,
    ticks: u32,
    peak_waypoint: u32,
}

impl Active {
    /// Stamps a reply to this chunk with its acceptance and first-motion times and the force
    /// felt over it.
    fn stamp(&self, mut r: Reply) -> Reply {
        r.accepted_ns = self.accepted_ns;
        r.first_motion_ns = self.first_motion_ns;
        let c = &self.contact;
        r.contact_start_n = c.start_n;
        r.contact_peak_n = c.peak_n;
        r.contact_mean_n = if c.ticks > 0 { c.sum_n / f64::from(c.ticks) } else { 0.0 };
        r.contact_peak_waypoint = c.peak_waypoint;
        r.contact_ticks = c.ticks;
        r
    }
}

pub struct Controller {
    pub robot: RobotModel,
    pub cfg: LimiterConfig,
    dt_s: f64,
    tracker: Option<JointTracker>,
    /// The running chunk's plan. Boxed once: an accepted plan is swapped in, never copied.
    plan: Box<ChunkPlan>,
    /// Where [`Self::plan_now`] puts a plan before [`Self::commit`] swaps it in.
    spare: Box<ChunkPlan>,
    reference: Reference,
    active: Option<Active>,
    locked: Option<ControlType>,
    pending_reset: Option<(u64, u64, u64)>,
    next_reset_id: u64,
    finger_prev: f64,
    finger_still_ticks: u32,
    cmd_seq: u64,
    /// Why the last request was refused, for counting (`None` after an accepted one).
    pub last_rejection: Option<&'static str>,
    /// Braking-policy ticks of trackers dropped at resets.
    braking_before: u64,
    /// Collision, obstacle and workspace checks (none: joint limits only).
    safety: Option<SafetyChecks>,
    /// The last reported TCP axis-angle vector (continuity of [`Self::robot_state`]).
    rotvec: Option<[f64; 3]>,
    /// Checks ee_pose waypoints at acceptance, with a bounded effort per waypoint.
    ik: IkSolver,
    diffik: DiffIkConfig,
    /// The joint reference that differential IK integrates while an ee_pose chunk runs.
    q_ref: [f64; N_JOINTS],
    /// A safety check stopped the motion: brake until at rest.
    halting: bool,
    profile: Profile,
    /// Contact reflexes (Franka profile only).
    reflexes: Option<Reflexes>,
    /// External force, low-pass filtered, base frame, N.
    force_n: [f64; 3],
    /// Its magnitude when the running chunk was accepted.
    force_at_start_n: f64,
    /// An `operator_required` fault holds the arm until [`RequestKind::ClearFault`].
    fault: Option<Text>,
    /// The `accepted` reply of the chunk just taken, for [`Self::take_accepted`].
    accepted: Option<Reply>,
    /// The reply of a chunk stopped by a safety check or reflex, sent once the arm rests.
    stop_reply: Option<Reply>,
    /// Ticks since start, in seconds (the time base of `robot_lost_since_s`).
    clock_s: f64,
    /// The robot side went silent at this clock time (see [`Self::robot_lost`]).
    robot_lost_since_s: Option<f64>,
    /// How long it had been silent when that was noticed, ms.
    lost_after_ms: f64,
    /// The command restarted at the measured state since the last [`Self::take_restarted`].
    restarted: bool,
    /// Operator fault resets so far (carried in every command, see [`JointCommand::clear_seq`]).
    clear_seq: u64,
    /// The robot side's own error report last seen ([`SimState::robot_error`]).
    robot_error: u32,
    /// Its reflex count last seen ([`SimState::reflexes`]).
    robot_reflexes: u64,
    /// Clock time of the last reflex the robot reported, s.
    last_reflex_s: Option<f64>,
    /// A gripper of its own (a driver process, not the robot side) reports a fault or is silent:
    /// the arm holds and chunks are refused while this lasts.
    gripper_fault: Option<Text>,
    /// Whether that fault is one the Franka profile latches (see [`Self::gripper_reports`]).
    gripper_latching: bool,
    /// That gripper has acted on commands at least once.
    gripper_ready: bool,
    /// What that gripper's own object detection says (a `GRASP_*` value); None: no such gripper,
    /// the controller judges the grasp from the measured fingers.
    gripper_grasp: Option<u32>,
    /// A second reflex within this many seconds of the previous one needs an operator.
    reflex_window_s: f64,
    /// The step in progress: request id, client, ticks left.
    step: Option<(u64, u64, u32)>,
    /// Its `stepped` reply once its period is over (see [`Self::take_stepped`]).
    stepped: Option<Reply>,
    /// The client that steps in this episode: in lockstep, time advances only inside steps.
    paced: Option<u64>,
}

/// What a gripper driven by its own process (`r2g-robotiq`) says on a tick (see
/// [`Controller::gripper_reports`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GripperReport<'a> {
    /// It acts on commands; its fingers are open `finger_m` (m, one finger).
    Ready { finger_m: f64 },
    /// It cannot act now but needs nobody: no state from its driver yet, activating, a minor
    /// fault that ends by itself. The arm holds and chunks are refused while it lasts.
    NotReady(&'a str),
    /// A device fault, the link to it lost, or its driver silent: as `NotReady`, and latched on
    /// the Franka profile once the gripper has been ready (before that the start goes on).
    Fault(&'a str),
}

/// A request the controller wants passed to the simulator.
pub enum Forward {
    None,
    Reset { sim_reset_id: u64 },
}

/// A chunk that passed [`Controller::admit`]: what its own checks need besides its waypoints.
#[derive(Debug, Clone, Copy)]
pub struct Job {
    pub id: u64,
    pub client: u64,
    pub ct: ControlType,
    /// Waypoints used (at most `MAX_CHUNK`).
    pub len: usize,
    pub freq_hz: f64,
    /// The command when the request arrived: where the chunk's checks start.
    pub start_q: [f64; N_JOINTS],
}

/// What [`Controller::admit`] decided.
#[allow(clippy::large_enum_variant)] // returned by value on the tick: a box would allocate
pub enum Admission {
    /// Decided already: the reply to send now (none for a reset in progress) and what to
    /// forward to the simulator.
    Answer(Option<Reply>, Forward),
    /// A chunk whose own checks are left ([`Acceptance::plan`]); the outcome goes to
    /// [`Controller::commit`].
    Plan(Job),
}

/// What a chunk's own checks need (shape, limits, step caps, IK and collisions along the
/// path), copied from a controller for a thread of their own (see `planner`).
#[derive(Clone)]
pub struct Acceptance {
    robot: RobotModel,
    cfg: LimiterConfig,
    ik: IkSolver,
    safety: Option<SafetyChecks>,
}

impl Acceptance {
    /// The plan of `job`, whose waypoints are `actions[..job.len]`, or why it is refused.
    pub fn plan(&self, job: &Job, actions: &[[f64; WAYPOINT_LEN]]) -> Result<ChunkPlan, Rejection> {
        plan_chunk(job, actions, &self.robot, &self.cfg, &self.ik, self.safety.as_ref())
    }
}

fn plan_chunk(
    job: &Job,
    actions: &[[f64; WAYPOINT_LEN]],
    robot: &RobotModel,
    cfg: &LimiterConfig,
    ik: &IkSolver,
    safety: Option<&SafetyChecks>,
) -> Result<ChunkPlan, Rejection> {
    let actions = &actions[..job.len.min(actions.len())];
    match job.ct {
        ControlType::Joint => ChunkPlan::joint(actions, job.freq_hz, job.start_q, robot, cfg, safety),
        ControlType::EePose => ChunkPlan::ee_pose(actions, job.freq_hz, job.start_q, robot, cfg, ik, safety),
    }
}

impl Controller {
    pub fn new(robot: RobotModel, cfg: LimiterConfig, dt_s: f64) -> Self {
        let ik_cfg = IkConfig {
            limit_margin_rad: cfg.q_margin_rad,
            max_restarts: 16,
            max_total_iterations: 1500,
            ..IkConfig::default()
        };
        #[allow(clippy::expect_used)] // the settings above are valid by construction
        let ik = IkSolver::new(&robot, ik_cfg).expect("valid IK settings");
        let plan = Box::new(ChunkPlan::hold([0.0; N_JOINTS], -1.0));
        let spare = Box::new(ChunkPlan::hold([0.0; N_JOINTS], -1.0));
        let reference = plan.sample(0.0);
        Self {
            robot,
            cfg,
            dt_s,
            tracker: None,
            plan,
            spare,
            reference,
            active: None,
            locked: None,
            pending_reset: None,
            next_reset_id: 1,
            finger_prev: 0.0,
            finger_still_ticks: 0,
            cmd_seq: 0,
            last_rejection: None,
            braking_before: 0,
            safety: None,
            rotvec: None,
            ik,
            diffik: DiffIkConfig::default(),
            q_ref: [0.0; N_JOINTS],
            halting: false,
            profile: Profile::Simulation,
            reflexes: None,
            force_n: [0.0; 3],
            force_at_start_n: 0.0,
            fault: None,
            accepted: None,
            stop_reply: None,
            clock_s: 0.0,
            robot_lost_since_s: None,
            lost_after_ms: 0.0,
            restarted: false,
            clear_seq: 0,
            robot_error: ipc_schema::ROBOT_OK,
            gripper_fault: None,
            gripper_latching: false,
            gripper_ready: false,
            gripper_grasp: None,
            robot_reflexes: 0,
            last_reflex_s: None,
            reflex_window_s: 10.0,
            step: None,
            stepped: None,
            paced: None,
        }
    }

    /// Follows the semantics of `profile`; contact reflexes apply in the Franka profile only.
    pub fn with_profile(mut self, profile: Profile, reflexes: Reflexes) -> Self {
        self.profile = profile;
        self.reflexes = (profile == Profile::Franka).then_some(reflexes);
        self
    }

    pub fn safety(&self) -> Option<&SafetyChecks> {
        self.safety.as_ref()
    }

    pub fn profile(&self) -> Profile {
        self.profile
    }

    /// The `accepted` reply of a chunk taken by the last [`Self::request`], once.
    pub fn take_accepted(&mut self) -> Option<Reply> {
        self.accepted.take()
    }

    /// The operator fault holding the arm, if any.
    pub fn fault(&self) -> Option<&str> {
        self.fault.as_ref().map(Text::as_str)
    }

    /// The operator's fault reset (only ever called for a request from the operator socket).
    /// Returns whether there was a fault to clear. A gripper in a fault counts: the reset goes to
    /// its driver too (through [`JointCommand::clear_seq`]), which then reactivates it; the
    /// gripper's fault itself ends only when the gripper reports clear.
    pub fn clear_fault(&mut self) -> bool {
        let had = self.fault.take().is_some();
        if had {
            self.last_reflex_s = None;
        }
        if had || self.gripper_fault.is_some() {
            // A robot side (or gripper) waiting for an operator tries its recovery again.
            self.clear_seq += 1;
        }
        had || self.gripper_fault.is_some()
    }

    /// A second reflex of the robot within `window_s` of the previous one needs an operator.
    pub fn with_reflex_window(mut self, window_s: f64) -> Self {
        self.reflex_window_s = window_s;
        self
    }

    /// Whether the robot itself is stopped by one of its reflexes (recovering, or waiting for
    /// an operator): the runtime holds and refuses chunks until the robot side reports it clear.
    pub fn is_robot_stopped(&self) -> bool {
        self.robot_error != ipc_schema::ROBOT_OK
    }

    /// Takes note of what the robot itself reports about its errors (a real arm's reflexes; a
    /// simulator never reports any). Called with every fresh state before [`Self::tick`].
    /// Returns the stopped chunk's final reply once the outcome is known: recovered
    /// (`recovered_replan_required`, the command restarts at the measured joints) or not
    /// (`operator_required`, latched until the operator clears it). A second reflex within the
    /// window needs the operator too. Allocation-free.
    pub fn robot_reports(&mut self, state: &SimState) -> Option<Reply> {
        use ipc_schema::{ROBOT_NEEDS_OPERATOR, ROBOT_OK};
        let (before, now) = (self.robot_error, state.robot_error);
        let new_reflex = state.reflexes > self.robot_reflexes;
        self.robot_reflexes = state.reflexes;
        if before == now && !new_reflex {
            // Still waiting for an operator after a cleared fault (the retried recovery failed
            // again): latched again, so that the next `r2g clear` retries once more.
            if now == ipc_schema::ROBOT_NEEDS_OPERATOR && self.fault.is_none() {
                let text = state.error_str();
                self.fault = Some(Text::of(format_args!("the robot did not recover from its error ({text})")));
            }
            return None;
        }
        self.robot_error = now;
        let text = state.error_str();
        if before == ROBOT_OK && (now != ROBOT_OK || new_reflex) {
            // The robot's own reflex stopped the motion.
            let repeated = self.last_reflex_s.is_some_and(|t| self.clock_s - t < self.reflex_window_s);
            self.last_reflex_s = Some(self.clock_s);
            if repeated && self.fault.is_none() {
                self.fault = Some(Text::of(format_args!(
                    "a second reflex of the robot within {:.0} s ({text})",
                    self.reflex_window_s
                )));
            }
            if let Some(a) = self.active.take() {
                let n = self.plan.len();
                let done = self.reference.reached;
                let r = if repeated {
                    let why = format_args!(
                        "stopped: the robot's own reflex ({text}) stopped waypoint {} of {n}, the second within {:.0} s; the arm holds and needs an operator: stop sending actions and report",
                        (done + 1).min(n),
                        self.reflex_window_s
                    );
                    Reply::formatted(a.id, a.client, Status::OperatorRequired, why)
                } else {
                    let why = format_args!(
                        "reflex: the robot stopped itself ({text}) during waypoint {} of {n} and recovered automatically; observe and replan from the measured state",
                        (done + 1).min(n)
                    );
                    Reply::formatted(a.id, a.client, Status::RecoveredReplanRequired, why)
                };
                let mut r = a.stamp(r);
                r.executed = done as u32;
                self.stop_reply = Some(r);
            }
            if self.tracker.is_some() {
                self.halting = true;
            }
        }
        if now == ROBOT_NEEDS_OPERATOR {
            if self.fault.is_none() {
                self.fault = Some(Text::of(format_args!("the robot did not recover from its error ({text})")));
            }
            if let Some(r) = self.stop_reply.as_mut().filter(|r| r.status != Status::OperatorRequired as u32) {
                let why = format_args!(
                    "stopped: the robot's own reflex ({text}) stopped the motion and automatic recovery did not clear it; the arm holds and needs an operator: stop sending actions and report"
                );
                let mut escalated = Reply::formatted(r.id, r.client, Status::OperatorRequired, why);
                (escalated.executed, escalated.accepted_ns, escalated.first_motion_ns) =
                    (r.executed, r.accepted_ns, r.first_motion_ns);
                *r = escalated;
            }
            return self.stop_reply.take();
        }
        if now == ROBOT_OK {
            // Recovered: restart at rest at the measured joints, as after a robot side came back.
            self.halting = false;
            self.braking_before += self.tracker.map_or(0, |t| t.braking_ticks);
            self.tracker = None;
            *self.plan = ChunkPlan::hold(state.q_rad, -1.0);
            self.finger_prev = state.finger_m;
            self.finger_still_ticks = 0;
            self.ensure_tracker(state);
            self.q_ref = state.q_rad;
            return self.stop_reply.take();
        }
        None
    }

    /// What a gripper driven by its own process reports, every tick before [`Self::tick`]: its
    /// object detection, and whether it acts on commands (see [`GripperReport`]). Anything but
    /// [`GripperReport::Ready`] stops the running chunk (its reply, `failed`, goes out once the
    /// arm rests), holds the arm and refuses chunks while it lasts. A [`GripperReport::Fault`]
    /// after the gripper was once ready is latched on the Franka profile (`operator_required`
    /// until the operator clears it). Allocation-free.
    pub fn gripper_reports(&mut self, grasp: u32, report: GripperReport<'_>) {
        self.gripper_grasp = Some(grasp);
        let (text, latching) = match report {
            GripperReport::Ready { finger_m } => {
                if !self.gripper_ready {
                    // Its first reading: the fingers stay where they are until a chunk moves
                    // them (until now the command carried no finger target at all).
                    self.gripper_ready = true;
                    let f = if finger_m.is_finite() { finger_m.clamp(0.0, self.robot.finger_max_m) } else { 0.0 };
                    if let Some(t) = self.tracker.as_mut() {
                        t.finger_m = f;
                    }
                    self.reference.gripper = self.robot.gripper_from_finger(f);
                    self.finger_prev = f;
                }
                (self.gripper_fault, self.gripper_latching) = (None, false);
                return;
            }
            GripperReport::NotReady(t) => (t, false),
            // Before it was ever ready, the start is still going on (a port not there yet, no
            // answer yet): that needs no operator.
            GripperReport::Fault(t) => (t, self.gripper_ready),
        };
        let new = self.gripper_fault.is_none();
        let escalates = latching && !self.gripper_latching;
        self.gripper_fault = Some(Text::of(format_args!("{text}")));
        self.gripper_latching = latching;
        let franka = self.reflexes.is_some();
        if escalates && franka && self.fault.is_none() {
            self.fault = Some(Text::of(format_args!("gripper: {text}")));
        }
        if !new {
            return;
        }
        let Some(a) = self.active.take() else { return };
        let n = self.plan.len();
        let done = self.reference.reached;
        let at = (done + 1).min(n);
        let mut r = match (latching, franka) {
            (true, true) => Reply::formatted(a.id, a.client, Status::OperatorRequired, format_args!(
                "stopped: the gripper reports a fault ({text}) during waypoint {at} of {n}; the arm holds and needs an operator: stop sending actions and report"
            )),
            (true, false) => Reply::formatted(a.id, a.client, Status::Failed, format_args!(
                "stopped: the gripper reports a fault ({text}) during waypoint {at} of {n}; the arm holds and chunks are refused until the gripper is clear"
            )),
            (false, _) => Reply::formatted(a.id, a.client, Status::Failed, format_args!(
                "stopped: the gripper cannot act ({text}) during waypoint {at} of {n}; the arm holds and chunks are refused until it can: observe again later"
            )),
        };
        r.executed = done as u32;
        // Sent by the tick once the arm rests (a tracker exists from the first tick on).
        self.stop_reply = Some(a.stamp(r));
        self.halting = true;
    }

    /// Whether a gripper of its own has acted on commands at least once (its readings are the
    /// fingers from then on).
    pub fn gripper_ready(&self) -> bool {
        self.gripper_ready
    }

    /// The gripper's fault while one holds the arm (see [`Self::gripper_reports`]).
    pub fn gripper_fault(&self) -> Option<&str> {
        self.gripper_fault.as_ref().map(Text::as_str)
    }

    /// Whether the robot side is silent (between [`Self::robot_lost`] and [`Self::robot_back`]).
    pub fn is_robot_lost(&self) -> bool {
        self.robot_lost_since_s.is_some()
    }

    /// The robot side has published no state for `silent_ms`: the running chunk (or reset) ends
    /// with a fault, the command brakes to rest within the limits from where it is (the last
    /// safe command, never a new target), and requests are refused until [`Self::robot_back`].
    /// Allocation-free (called between ticks).
    pub fn robot_lost(&mut self, silent_ms: f64) {
        if self.robot_lost_since_s.is_some() {
            return;
        }
        self.robot_lost_since_s = Some(self.clock_s);
        self.lost_after_ms = silent_ms;
        let why = format_args!(
            "stopped: the robot side published no state for {silent_ms:.0} ms (it stopped or hangs); the arm holds its last command, and chunks are refused until it is back"
        );
        if let Some(a) = self.active.take() {
            let mut r = Reply::formatted(a.id, a.client, Status::Failed, why);
            r.executed = self.reference.reached as u32;
            self.stop_reply = Some(a.stamp(r));
        } else if let Some((id, client, _)) = self.pending_reset.take() {
            self.stop_reply = Some(Reply::formatted(id, client, Status::Failed, why));
        }
        if self.tracker.is_some() {
            self.halting = true;
        }
    }

    /// Fresh state after [`Self::robot_lost`]: the command restarts at rest at the measured
    /// joints (never at an old target), and requests are taken again. Returns the stopped
    /// chunk's reply if the arm had not come to rest before.
    pub fn robot_back(&mut self, state: &SimState) -> Option<Reply> {
        self.robot_lost_since_s?;
        self.robot_lost_since_s = None;
        self.halting = false;
        self.braking_before += self.tracker.map_or(0, |t| t.braking_ticks);
        self.tracker = None;
        *self.plan = ChunkPlan::hold(state.q_rad, -1.0);
        self.finger_prev = state.finger_m;
        self.finger_still_ticks = 0;
        self.rotvec = None;
        self.ensure_tracker(state);
        self.q_ref = state.q_rad;
        self.stop_reply.take()
    }

    /// Adds collision, obstacle and workspace checks to chunk acceptance and to every tick.
    pub fn with_safety(mut self, safety: SafetyChecks) -> Self {
        self.safety = Some(safety);
        self
    }

    /// True while a chunk, reset or step is in progress.
    pub fn busy(&self) -> bool {
        self.active.is_some() || self.pending_reset.is_some() || self.halting || self.step.is_some()
    }

    /// Whether lockstep advances simulated time now: inside a step, or (in an episode that no
    /// client steps) while anything is in progress.
    pub fn advancing(&self) -> bool {
        self.step.is_some() || (self.paced.is_none() && self.busy())
    }

    /// The `stepped` reply of a step whose period just ended, once.
    pub fn take_stepped(&mut self) -> Option<Reply> {
        self.stepped.take()
    }

    pub fn locked(&self) -> Option<ControlType> {
        self.locked
    }

    pub fn active_request(&self) -> u64 {
        self.active.map(|a| a.id).or(self.pending_reset.map(|r| r.0)).unwrap_or(0)
    }

    /// Takes a request and decides it at once, the chunk's own checks included (lockstep, and
    /// wall mode when acceptance runs on the tick): [`Self::admit`], [`Self::plan_now`] and
    /// [`Self::commit`] in a row. Returns an immediate reply for rejections (or the superseded
    /// chunk's reply); accepted work replies later from [`Self::tick`].
    pub fn request(&mut self, req: &Request, state: &SimState) -> (Option<Reply>, Forward) {
        match self.admit(req, state, None) {
            Admission::Answer(reply, fwd) => (reply, fwd),
            Admission::Plan(job) => {
                let outcome = self.plan_now(&job, req);
                (self.commit(&job, outcome, None, state), Forward::None)
            }
        }
    }

    /// What a chunk's own checks need, for the planner thread.
    pub fn acceptance(&self) -> Acceptance {
        Acceptance { robot: self.robot.clone(), cfg: self.cfg, ik: self.ik.clone(), safety: self.safety.clone() }
    }

    /// The first half of taking a request, on the tick's side and cheap: everything that
    /// depends on the controller's state (operator-only requests, a lost robot side, braking,
    /// another request running, faults, the robot's own recovery, resets, the control type,
    /// the length). A chunk that passes comes back as a [`Job`] whose own checks are left to
    /// [`Acceptance::plan`] (here: [`Self::plan_now`]); their outcome goes to [`Self::commit`].
    /// `in_flight`: the client whose chunks are being checked elsewhere, if any; they count as
    /// that client's running chunk (others wait, its own next chunk will replace it).
    /// Allocation-free.
    pub fn admit(&mut self, req: &Request, state: &SimState, in_flight: Option<u64>) -> Admission {
        if state.seq > 0 {
            self.ensure_tracker(state);
        }
        self.last_rejection = None;
        if req.kind == RequestKind::ClearFault as u32 {
            // Anyone who can open the request service can send this: only the operator socket
            // (SO_PEERCRED-checked, see `operator`) clears faults.
            self.last_rejection = Some("operator_only");
            let why = "clearing a fault is an operator request: it is taken only on the operator socket (`r2g clear`), never from the agent channel";
            return Admission::Answer(Some(Reply::new(req.id, req.client, Status::Rejected, why)), Forward::None);
        }
        // A step's period starts now, whatever happens to its waypoints: time advances by it
        // even when they are refused (and with none, the step only lets time pass).
        let step = req.kind == RequestKind::Step as u32;
        if step {
            if self.step.is_some() {
                let why = "a step is already running: wait for its `stepped` reply before the next one";
                return Admission::Answer(Some(Reply::new(req.id, req.client, Status::Rejected, why)), Forward::None);
            }
            if !(1..=MAX_STEP_TICKS).contains(&req.step_ticks) {
                let why = format_args!("a step lasts 1 to {MAX_STEP_TICKS} ticks, not {}: nothing ran", req.step_ticks);
                let r = Reply::formatted(req.id, req.client, Status::Rejected, why);
                return Admission::Answer(Some(r), Forward::None);
            }
            self.step = Some((req.id, req.client, req.step_ticks));
            self.paced = Some(req.client);
            if req.len == 0 {
                return Admission::Answer(None, Forward::None);
            }
        }
        // A new chunk from the client whose chunk is running (or being checked) replaces it,
        // blending from the current command; anything else waits for the running request, and
        // nothing but the stepping client's own chunks runs during a step.
        if req.kind == RequestKind::Reset as u32
            && self.profile != Profile::Franka
            && self.step.is_none()
            && self.paced == Some(req.client)
        {
            // Between its steps time stands still, so what the stepping client left moving (or
            // braking) would never end: its reset ends it, as a reset restores the arm anyway.
            // Never on a real arm: there a reset restores nothing, and a braking arm keeps
            // braking until it holds.
            self.active = None;
            self.halting = false;
            self.stop_reply = None;
        }
        let chunk = req.kind == RequestKind::Chunk as u32 || step;
        let running = self.active.map(|a| a.client).or(in_flight);
        let preempts = chunk && running == Some(req.client);
        let stepping = self.step.is_some_and(|(_, c, _)| !chunk || c != req.client);
        let others = self.active.is_some() || self.pending_reset.is_some() || self.halting || stepping;
        let busy = (others || in_flight.is_some()) && !preempts;
        if let Some(r) = self.refusal(req.id, req.client, chunk, busy) {
            return Admission::Answer(Some(r), Forward::None);
        }
        let Some(tracker) = self.tracker else {
            let r = Reply::new(
                req.id,
                req.client,
                Status::Failed,
                "the runtime has no robot state yet: the simulator is not running",
            );
            return Admission::Answer(Some(r), Forward::None);
        };
        match req.kind {
            k if k == RequestKind::Reset as u32 && self.profile == Profile::Franka => {
                let why = "reset on the franka profile only refreshes observations: nothing moved, objects are not restored, faults are not cleared";
                Admission::Answer(Some(Reply::new(req.id, req.client, Status::Executed, why)), Forward::None)
            }
            k if k == RequestKind::Reset as u32 => {
                let sim_id = self.next_reset_id;
                self.next_reset_id += 1;
                self.pending_reset = Some((req.id, req.client, sim_id));
                Admission::Answer(None, Forward::Reset { sim_reset_id: sim_id })
            }
            k if k == RequestKind::Chunk as u32 || k == RequestKind::Step as u32 => {
                let Some(ct) = ControlType::from_u32(req.control_type) else {
                    return self.reject(req, Rejection::UnknownControlType(req.control_type));
                };
                if let Some(why) = self.locked_out(ct) {
                    return self.reject(req, why);
                }
                let len = (req.len as usize).min(req.actions.len() + 1);
                if len > req.actions.len() {
                    return self.reject(req, Rejection::TooLong { len: req.len as usize, max: req.actions.len() });
                }
                Admission::Plan(Job {
                    id: req.id,
                    client: req.client,
                    ct,
                    len,
                    freq_hz: req.freq_hz,
                    start_q: tracker.q_rad,
                })
            }
            other => self.reject(req, Rejection::UnknownRequestKind(other)),
        }
    }

    /// A chunk's own checks, here and now: the plan goes to a spare box that [`Self::commit`]
    /// swaps in. `req` is the request `job` was admitted from.
    pub fn plan_now(&mut self, job: &Job, req: &Request) -> Result<(), Rejection> {
        *self.spare = plan_chunk(job, &req.actions, &self.robot, &self.cfg, &self.ik, self.safety.as_ref())?;
        Ok(())
    }

    /// The second half of taking a chunk, on the tick's side: the outcome of its checks. The
    /// state is checked again, since it may have changed while the checks ran (a stop, a fault,
    /// a lost robot side, the control type locked by the chunk before), and so is the start:
    /// the checks started from the command at admission, so the chunk is refused when the
    /// command has since moved more than [`STALE_START_RAD`] on any joint (the chunk it
    /// replaces kept moving while a slow planner worked). Otherwise the plan (`plan`, or with
    /// `None` the spare filled by [`Self::plan_now`]) is swapped in, neither copied nor
    /// allocated, and runs from the next tick on, blending from the current command as any
    /// replacing chunk does: the limiter takes the command from where it is onto the new
    /// reference within every limit, and each tick's safety checks cover the stretch between.
    /// Returns the reply to send now (a rejection, or the replaced chunk's `failed`); the
    /// `accepted` reply follows from [`Self::take_accepted`]. Allocation-free.
    pub fn commit(
        &mut self,
        job: &Job,
        outcome: Result<(), Rejection>,
        plan: Option<&mut Box<ChunkPlan>>,
        state: &SimState,
    ) -> Option<Reply> {
        self.last_rejection = None;
        if let Err(why) = outcome {
            return Some(self.rejection(job.id, job.client, why));
        }
        let busy = self.pending_reset.is_some() || self.active.is_some_and(|a| a.client != job.client);
        if let Some(r) = self.refusal(job.id, job.client, true, busy) {
            return Some(r);
        }
        if let Some(why) = self.locked_out(job.ct) {
            return Some(self.rejection(job.id, job.client, why));
        }
        let Some(tracker) = self.tracker else {
            let why = "the runtime has no robot state yet: the simulator is not running";
            return Some(Reply::new(job.id, job.client, Status::Failed, why));
        };
        let (mut moved, mut joint) = (0.0f64, 0);
        for j in 0..N_JOINTS {
            let d = (tracker.q_rad[j] - job.start_q[j]).abs();
            if d > moved {
                (moved, joint) = (d, j);
            }
        }
        if moved > STALE_START_RAD {
            self.last_rejection = Some("stale_start");
            let why = format_args!(
                "the arm moved {moved:.3} rad at joint {} while this chunk was being checked (more than {STALE_START_RAD} rad); nothing of it ran: send it again from the current state",
                joint + 1
            );
            return Some(Reply::formatted(job.id, job.client, Status::Rejected, why));
        }
        let superseded = self.active.map(|old| {
            let mut r = old.stamp(Reply::formatted(
                old.id,
                old.client,
                Status::Failed,
                format_args!("superseded by request {} before it finished", job.id),
            ));
            r.executed = self.reference.reached as u32;
            r
        });
        match plan {
            Some(p) => std::mem::swap(&mut self.plan, p),
            None => std::mem::swap(&mut self.plan, &mut self.spare),
        }
        self.q_ref = tracker.q_rad;
        self.locked = Some(job.ct);
        let now = ipc_schema::monotonic_ns();
        self.active = Some(Active {
            id: job.id,
            client: job.client,
            t_s: 0.0,
            phase: Phase::Moving,
            accepted_ns: now,
            first_motion_ns: 0,
            q0: state.q_rad,
            finger0: state.finger_m,
            contact: ContactStats::default(),
        });
        self.force_at_start_n = norm(self.force_n);
        let mut accepted = Reply::new(job.id, job.client, Status::Accepted, "accepted: executing");
        accepted.accepted_ns = now;
        self.accepted = Some(accepted);
        superseded
    }

    /// Why the controller's state refuses a request now, if it does: the robot side is silent,
    /// the arm is braking, another request runs (`busy`), or (chunks only) an operator fault or
    /// the robot's own recovery holds the arm. Checked on arrival and again at commit.
    fn refusal(&mut self, id: u64, client: u64, chunk: bool, busy: bool) -> Option<Reply> {
        if let Some(since) = self.robot_lost_since_s {
            self.last_rejection = Some("robot_lost");
            let why = format_args!(
                "the robot side has published no state for {:.0} ms: the arm holds its last command and requests are refused until fresh state arrives; observe again later, or stop and report",
                (self.clock_s - since) * 1e3 + self.lost_after_ms
            );
            return Some(Reply::formatted(id, client, Status::Rejected, why));
        }
        if self.halting {
            return Some(self.rejection(id, client, Rejection::Halting));
        }
        if busy {
            return Some(self.rejection(id, client, Rejection::Busy));
        }
        if !chunk {
            return None;
        }
        if let Some(f) = self.fault {
            self.last_rejection = Some("operator_required");
            let why = format_args!(
                "the arm is in a fault ({f}) and needs an operator to clear it; every command returns 0 until then: stop and report"
            );
            return Some(Reply::formatted(id, client, Status::OperatorRequired, why));
        }
        if let Some(g) = self.gripper_fault {
            if self.gripper_latching {
                self.last_rejection = Some("gripper_fault");
                let why = format_args!(
                    "the gripper reports a fault ({g}): the arm holds and chunks are refused until the gripper is clear; observe again later, or stop and report"
                );
                return Some(Reply::formatted(id, client, Status::Rejected, why));
            }
            self.last_rejection = Some("gripper_not_ready");
            let why = format_args!(
                "the gripper cannot act now ({g}): the arm holds and chunks are refused until it can; observe again later"
            );
            return Some(Reply::formatted(id, client, Status::Rejected, why));
        }
        if self.robot_error != ipc_schema::ROBOT_OK {
            self.last_rejection = Some("robot_recovering");
            let why = "the robot's own reflex stopped the arm and its automatic recovery is running; observe again in a moment and replan from the measured state";
            return Some(Reply::new(id, client, Status::Rejected, why));
        }
        None
    }

    /// Simulation profile: a chunk of another control type than the episode's first.
    fn locked_out(&self, ct: ControlType) -> Option<Rejection> {
        match (self.locked, self.profile) {
            (Some(locked), Profile::Simulation) if locked != ct => {
                Some(Rejection::ControlTypeLocked { locked: locked.name(), requested: ct.name() })
            }
            _ => None,
        }
    }

    fn rejection(&mut self, id: u64, client: u64, why: Rejection) -> Reply {
        self.last_rejection = Some(why.kind());
        Reply::formatted(id, client, Status::Rejected, format_args!("{why}"))
    }

    fn reject(&mut self, req: &Request, why: Rejection) -> Admission {
        Admission::Answer(Some(self.rejection(req.id, req.client, why)), Forward::None)
    }

    /// The simulator's reset id the runtime waits for, if a reset is in flight.
    pub fn pending_reset(&self) -> Option<u64> {
        self.pending_reset.map(|r| r.2)
    }

    /// Finishes a pending reset once `state` shows it: the arm is held where the reset put it,
    /// the control type unlocks, and nothing of the previous episode carries over.
    pub fn complete_reset(&mut self, state: &SimState) -> Option<Reply> {
        let (id, client, sim_id) = self.pending_reset?;
        if state.reset_id != sim_id {
            return None;
        }
        self.braking_before += self.tracker.map_or(0, |t| t.braking_ticks);
        self.tracker = None;
        self.locked = None;
        self.pending_reset = None;
        self.paced = None;
        self.finger_prev = state.finger_m;
        self.finger_still_ticks = 0;
        // Every episode reports its start pose the same way, whatever the last one did.
        self.rotvec = None;
        self.ensure_tracker(state);
        Some(Reply::new(id, client, Status::Executed, "reset: robot and objects restored"))
    }

    /// The final reply of a chunk whose command has come to rest: `executed` only when the
    /// measured state is within the reach tolerance of the last waypoint (the TCP pose for
    /// ee_pose chunks, the joints for joint chunks), else `failed` with the measured error and
    /// the joints at their limits. `err`/`worst`: the largest joint distance from the last
    /// target and its joint. Allocation-free (tick path).
    fn reached(&self, id: u64, client: u64, q: &[f64; N_JOINTS], err: f64, worst: usize) -> Reply {
        let mut at_limit = [0u8; N_JOINTS];
        let mut n_at = 0;
        // The limiter keeps every command `q_margin_rad` inside the limits: that is where a joint
        // that cannot go further stops.
        let margin = self.cfg.q_margin_rad;
        for (j, lim) in self.robot.joints.iter().enumerate() {
            if q[j] - (lim.q_min_rad + margin) < AT_LIMIT_RAD || (lim.q_max_rad - margin) - q[j] < AT_LIMIT_RAD {
                at_limit[n_at] = (j + 1) as u8;
                n_at += 1;
            }
        }
        let limits = JointList(&at_limit[..n_at]);
        if let Some(goal) = self.plan.last_pose() {
            let tcp = self.robot.kin.fk(q, self.robot.kin.tcp);
            let dp = (tcp.translation.vector - goal.translation.vector).norm();
            let dr = tcp.rotation.angle_to(&goal.rotation);
            if dp > REACH_TOL_M || dr > REACH_TOL_TCP_RAD {
                return Reply::formatted(
                    id,
                    client,
                    Status::Failed,
                    format_args!(
                        "not reached: the TCP stopped {:.1} mm and {dr:.3} rad from the last waypoint \
                         (tolerance {:.0} mm, {REACH_TOL_TCP_RAD} rad){limits}; the arm holds there",
                        dp * 1e3,
                        REACH_TOL_M * 1e3
                    ),
                );
            }
        } else if err > REACH_TOL_RAD {
            return Reply::formatted(
                id,
                client,
                Status::Failed,
                format_args!(
                    "not reached: the arm stopped {err:.4} rad from the last waypoint at joint {} \
                     (tolerance {REACH_TOL_RAD} rad; blocked by contact?){limits}; the arm holds there",
                    worst + 1
                ),
            );
        }
        Reply::new(id, client, Status::Executed, "executed")
    }

    /// One tick: the command to send and, when a request just finished, its reply.
    pub fn tick(&mut self, state: &SimState) -> (JointCommand, Option<Reply>) {
        self.clock_s += self.dt_s;
        let mut reply = self.complete_reset(state);
        self.ensure_tracker(state);
        if let Some(a) = self.active.as_mut().filter(|a| a.first_motion_ns == 0) {
            let moved = (0..N_JOINTS).any(|j| (state.q_rad[j] - a.q0[j]).abs() > 1e-4)
                || (state.finger_m - a.finger0).abs() > 1e-5;
            if moved {
                a.first_motion_ns = ipc_schema::monotonic_ns();
            }
        }
        let timing = self.active;
        if let Some(a) = self.active.as_mut() {
            a.t_s += self.dt_s;
            match self.plan.sample_pose(a.t_s) {
                // ee_pose: differential IK turns the TCP reference into a joint reference.
                Some(p) => {
                    let (dq, _) = diffik::step(
                        &self.q_ref,
                        &p.pose,
                        &p.twist,
                        &self.plan.start_q(),
                        &self.robot,
                        &self.cfg,
                        &self.diffik,
                    );
                    for (q, v) in self.q_ref.iter_mut().zip(dq.iter()) {
                        *q += v * self.dt_s;
                    }
                    self.reference = Reference {
                        q_rad: self.q_ref,
                        dq_rad_s: std::array::from_fn(|j| dq[j]),
                        gripper: p.gripper,
                        goal_q_rad: [f64::NAN; N_JOINTS],
                        reached: p.reached,
                        finished: p.finished,
                    };
                }
                None => self.reference = self.plan.sample(a.t_s),
            }
        }
        let alpha = self.dt_s / (FORCE_FILTER_S + self.dt_s);
        for (f, m) in self.force_n.iter_mut().zip(state.external_force_n) {
            *f += alpha * (m - *f);
        }
        if let Some(a) = self.active.as_mut() {
            let f = self.force_n.iter().map(|v| v * v).sum::<f64>().sqrt();
            let c = &mut a.contact;
            if c.ticks == 0 {
                c.start_n = f;
            }
            c.sum_n += f;
            c.ticks = c.ticks.saturating_add(1);
            if f > c.peak_n {
                c.peak_n = f;
                // The waypoint the arm heads for (0-based; the last once all are reached).
                c.peak_waypoint = self.reference.reached.min(self.plan.len().saturating_sub(1)) as u32;
            }
        }
        if let Some(r) = self.contact_reflex() {
            self.stop_reply = Some(r);
        }
        let Some(tracker) = self.tracker.as_mut() else { unreachable!("set above") };
        let before = *tracker;
        if self.halting {
            tracker.brake(self.dt_s, &self.robot, &self.cfg);
        } else {
            tracker.step(&self.reference, self.dt_s, &self.robot, &self.cfg);
        }
        // The command and the configuration its braking would end in must both pass the
        // checks; if not, brake along the path checked on the previous tick.
        if let (false, Some(safety)) = (self.halting, self.safety.as_ref()) {
            if let Err(v) = safety.check(&tracker.q_rad).and_then(|_| safety.check(&tracker.stop_q_rad)) {
                *tracker = before;
                tracker.brake(self.dt_s, &self.robot, &self.cfg);
                self.halting = true;
                if let Some(a) = self.active.take() {
                    let mut r = Reply::formatted(a.id, a.client, Status::Failed, format_args!("stopped: {v}"));
                    r.executed = self.reference.reached as u32;
                    self.stop_reply = Some(a.stamp(r));
                }
            }
        }
        if self.halting && tracker.stopped() && self.robot_error != ipc_schema::ROBOT_RECOVERING {
            self.halting = false;
            // The stopped chunk's reply goes out once the arm rests, so the caller can move at
            // once; after a robot reflex, only once the robot reports the recovery's outcome
            // (`robot_reports` sends or escalates it).
            reply = self.stop_reply.take();
            self.reference = Reference {
                q_rad: tracker.q_rad,
                dq_rad_s: [0.0; N_JOINTS],
                gripper: self.reference.gripper,
                goal_q_rad: tracker.q_rad,
                reached: self.reference.reached,
                finished: true,
            };
        }
        let tracker = *tracker;

        // Gripper counts as done when the measured finger has stopped or reached the command.
        if (state.finger_m - self.finger_prev).abs() < 2e-6 {
            self.finger_still_ticks = self.finger_still_ticks.saturating_add(1);
        } else {
            self.finger_still_ticks = 0;
        }
        self.finger_prev = state.finger_m;

        if let Some(mut a) = self.active {
            match a.phase {
                Phase::Moving => {
                    if self.reference.finished && tracker.settled_on(&self.reference, &self.robot) {
                        a.phase = Phase::Settling { since_s: a.t_s };
                    } else if a.t_s > self.plan.duration_s() + MOVE_OVERTIME_S {
                        // The command never converged: stop here rather than stay busy forever.
                        let mut r = Reply::new(
                            a.id,
                            a.client,
                            Status::Failed,
                            "the command did not converge on the target; the arm holds where it is",
                        );
                        r.executed = self.reference.reached as u32;
                        reply = Some(r);
                        self.active = None;
                        self.reference.q_rad = tracker.q_rad;
                        self.reference.goal_q_rad = tracker.q_rad;
                        self.reference.dq_rad_s = [0.0; N_JOINTS];
                    }
                }
                Phase::Settling { since_s } => {
                    let target = self.reference;
                    let mut err = 0.0f64;
                    let mut worst = 0;
                    let mut moving = false;
                    for j in 0..N_JOINTS {
                        let e = (state.q_rad[j] - target.q_rad[j]).abs();
                        if e > err {
                            err = e;
                            worst = j;
                        }
                        moving |= state.dq_rad_s[j].abs() > SETTLE_VEL_RAD_S;
                    }
                    let finger_done = ((state.finger_m - tracker.finger_m).abs() < 1e-3 || self.finger_still_ticks > 50)
                        // A gripper with its own detection says when its fingers have stopped.
                        && self.gripper_grasp != Some(ipc_schema::GRASP_MOVING);
                    let timed_out = a.t_s - since_s > SETTLE_TIMEOUT_S;
                    if (err < SETTLE_TOL_RAD && !moving && finger_done) || timed_out {
                        let mut r = self.reached(a.id, a.client, &state.q_rad, err, worst);
                        let reached = r.status == Status::Executed as u32;
                        // Not reached: the last waypoint was commanded but never attained.
                        r.executed = (self.plan.len() - usize::from(!reached)) as u32;
                        r.final_joint_error_rad = err;
                        reply = Some(r);
                        self.active = None;
                        self.reference.dq_rad_s = [0.0; N_JOINTS];
                        if !reached {
                            // Hold where the arm measurably is instead of pressing on towards a
                            // target it cannot reach (contact, a limit).
                            self.reference.q_rad = state.q_rad;
                            self.reference.goal_q_rad = state.q_rad;
                            self.q_ref = state.q_rad;
                        }
                    }
                }
            }
            if let Some(act) = self.active.as_mut() {
                act.phase = a.phase;
            }
        }
        if let (Some(r), Some(a)) = (reply.as_mut(), timing) {
            if r.id == a.id && r.client == a.client {
                *r = a.stamp(*r);
            }
        }
        if let Some((id, client, left)) = self.step.as_mut() {
            *left -= 1;
            if *left == 0 {
                self.stepped = Some(Reply::new(*id, *client, Status::Stepped, "stepped: the period is over"));
                self.step = None;
            }
        }
        self.cmd_seq += 1;
        let cmd = JointCommand {
            seq: self.cmd_seq,
            state_seq: state.seq,
            q_rad: tracker.q_rad,
            dq_rad_s: tracker.dq_rad_s,
            finger_m: match (self.gripper_grasp.is_some(), self.gripper_ready) {
                (false, _) => tracker.finger_m,
                // A gripper of its own: no target (NaN: r2g-robotiq and r2g-sim keep their
                // fingers) until its first reading became the target, then the waypoint's own
                // goal, which the gripper ramps at its own speed (the tracker's ramp would be a
                // new request every few counts).
                (true, false) => f64::NAN,
                (true, true) => self.robot.finger_from_gripper(self.reference.gripper),
            },
            session: state.session,
            clear_seq: self.clear_seq,
        };
        (cmd, reply)
    }

    /// Franka profile: stops the running chunk when the contact force passes a threshold, as the
    /// arm's own reflexes would. Returns the chunk's final reply.
    fn contact_reflex(&mut self) -> Option<Reply> {
        let rx = self.reflexes?;
        if self.halting {
            // A collision hard enough to keep the force rising while the arm brakes escalates.
            let f = norm(self.force_n);
            let r = self.stop_reply.as_mut().filter(|r| r.status == Status::RecoveredReplanRequired as u32)?;
            if f > rx.operator_force_n {
                self.fault =
                    Some(Text::of(format_args!("contact force {f:.1} N over the {:.0} N limit", rx.operator_force_n)));
                let why = format_args!(
                    "stopped: contact force rose to {f:.1} N while braking, past the {:.0} N operator limit; the arm holds and needs an operator: stop sending actions and report",
                    rx.operator_force_n
                );
                let mut escalated = Reply::formatted(r.id, r.client, Status::OperatorRequired, why);
                (escalated.executed, escalated.accepted_ns, escalated.first_motion_ns) =
                    (r.executed, r.accepted_ns, r.first_motion_ns);
                *r = escalated;
            }
            return None;
        }
        let a = self.active?;
        let f = norm(self.force_n);
        let (done, n) = (self.reference.reached, self.plan.len());
        let at = (done + 1).min(n);
        // Only a force that grew during this chunk counts, so the arm can back out of a contact.
        if f <= self.force_at_start_n + REFLEX_GROWTH_N {
            return None;
        }
        let mut r = if f > rx.operator_force_n {
            self.fault =
                Some(Text::of(format_args!("contact force {f:.1} N over the {:.0} N limit", rx.operator_force_n)));
            let why = format_args!(
                "stopped: contact force {f:.1} N exceeded the {:.0} N operator limit during waypoint {at} of {n}; the arm holds and needs an operator: stop sending actions and report",
                rx.operator_force_n
            );
            Reply::formatted(a.id, a.client, Status::OperatorRequired, why)
        } else if f > rx.reflex_force_n {
            let why = format_args!(
                "contact reflex: force {f:.1} N exceeded the {:.0} N threshold during waypoint {at} of {n}; the arm stopped and recovered by itself: observe and replan from the measured state",
                rx.reflex_force_n
            );
            Reply::formatted(a.id, a.client, Status::RecoveredReplanRequired, why)
        } else {
            return None;
        };
        r.executed = done as u32;
        self.active = None;
        self.halting = true;
        self.last_rejection = None;
        Some(a.stamp(r))
    }

    /// Whether the command restarted at the measured state (first state, reset, robot side
    /// back) since the last call.
    pub fn take_restarted(&mut self) -> bool {
        std::mem::take(&mut self.restarted)
    }

    /// Whether `cmd` keeps every joint inside its position and velocity limits and, from
    /// `prev` one tick before, inside the limiter's acceleration limit (1 % slack for rounding).
    /// Allocation-free.
    pub fn within_limits(&self, prev: &JointCommand, cmd: &JointCommand) -> bool {
        self.robot.joints.iter().enumerate().all(|(j, l)| {
            let (q, dq) = (cmd.q_rad[j], cmd.dq_rad_s[j]);
            let ddq = (dq - prev.dq_rad_s[j]) / self.dt_s;
            q.is_finite()
                && dq.is_finite()
                && q >= l.q_min_rad
                && q <= l.q_max_rad
                && dq.abs() <= l.dq_max_rad_s * 1.0001
                && ddq.abs() <= self.cfg.accel_scale * l.ddq_max_rad_s2 * 1.01
        })
    }

    /// First state, or first after a reset: hold exactly where the arm is. A gripper of its own
    /// that has a target keeps it: it went on holding while the arm restarted, and its measured
    /// opening as the new target would loosen a grasp.
    fn ensure_tracker(&mut self, state: &SimState) {
        if self.tracker.is_none() {
            self.restarted = true;
            let t = JointTracker::at_rest(state.q_rad, state.finger_m, &self.robot, &self.cfg);
            let gripper =
                if self.gripper_ready { self.reference.gripper } else { self.robot.gripper_from_finger(t.finger_m) };
            self.reference = Reference {
                q_rad: t.q_rad,
                dq_rad_s: [0.0; N_JOINTS],
                gripper,
                goal_q_rad: t.q_rad,
                reached: 0,
                finished: true,
            };
            self.tracker = Some(t);
        }
    }

    /// Ticks on which the limiter's braking policy overrode tracking, since start.
    pub fn braking_ticks(&self) -> u64 {
        self.braking_before + self.tracker.map_or(0, |t| t.braking_ticks)
    }

    /// The agent-facing state for the latest measurement. The TCP pose is this controller's FK
    /// of the measured joints (its TCP: the description's, or a measured one from
    /// [`crate::calibration`]), not the robot side's, so that `ee_pose` reports the point that
    /// ee_pose targets move. Its axis-angle vector is the one nearest the previous report, so
    /// reports never flip between equivalent vectors.
    pub fn robot_state(&mut self, state: &SimState, seq: u64, mode: u32) -> RobotState {
        let (p, q) = controllers::kinematics::to_arrays(&self.robot.kin.fk(&state.q_rad, self.robot.kin.tcp));
        let tcp_rotvec = match self.rotvec {
            Some(prev) => controllers::math::axis_angle_near(q, prev),
            None => controllers::math::axis_angle(q),
        };
        self.rotvec = Some(tcp_rotvec);
        RobotState {
            seq,
            timestamp_s: state.sim_time_s,
            published_ns: ipc_schema::monotonic_ns(),
            q_rad: state.q_rad,
            dq_rad_s: state.dq_rad_s,
            gripper: self.robot.gripper_from_finger(state.finger_m),
            base_from_tcp: ipc_schema::Pose { position_m: p, quat_xyzw: q },
            tcp_rotvec,
            control_type: self.locked.map(|c| c as u32).unwrap_or(0),
            mode,
            active_request: self.active_request(),
            reset_id: state.reset_id,
            external_force_n: self.force_n,
            fault: u32::from(self.fault.is_some())
                | (u32::from(self.robot_lost_since_s.is_some()) << 1)
                | (u32::from(self.gripper_fault.is_some()) << 2)
                | (u32::from(self.gripper_fault.is_some() && !self.gripper_latching) << 3),
            grasp: self.gripper_grasp.unwrap_or_else(|| self.grasp(state)),
            gripper_error: self
                .gripper_fault
                .map(|t| {
                    let mut e = [[0u8; 32]; ipc_schema::ERROR_TEXT_LEN / 32];
                    ipc_schema::write_str(e.as_flattened_mut(), t.as_str());
                    e
                })
                .unwrap_or_default(),
        }
    }

    /// The grasp judged from the measured fingers, for grippers without object detection of
    /// their own (the simulated ones, the Franka Hand): fingers still short of a closing command
    /// hold something, as a Robotiq's own detection would say.
    fn grasp(&self, state: &SimState) -> u32 {
        let Some(t) = self.tracker.as_ref() else { return ipc_schema::GRASP_UNKNOWN };
        let gap = state.finger_m - t.finger_m;
        if self.finger_still_ticks <= 50 && gap.abs() >= 1e-3 {
            ipc_schema::GRASP_MOVING
        } else if gap.abs() < 1e-3 {
            ipc_schema::GRASP_AT_TARGET
        } else if gap > 0.0 {
            ipc_schema::GRASP_HOLDING
        } else {
            ipc_schema::GRASP_BLOCKED_OPENING
        }
    }
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// Formats ", joints at their limits: 4, 7" (nothing for an empty list) without allocating.
struct JointList<'a>(&'a [u8]);

impl std::fmt::Display for JointList<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, j) in self.0.iter().enumerate() {
            f.write_str(if i == 0 { "; joints at their limits: " } else { ", " })?;
            write!(f, "{j}")?;
        }
        Ok(())
    }
}
