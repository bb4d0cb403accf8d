#![doc = include_str!("../README.md")]

pub mod process;

use core::time::Duration;

use iceoryx2::prelude::*;
use iceoryx2::service::attribute::{AttributeKey, AttributeValue};
use iceoryx2::service::port_factory::{event, publish_subscribe};

/// Bumped whenever any payload below changes layout or meaning. Every service carries it as
/// the attribute `r2g.schema`; a process of another build is refused when it connects.
pub const SCHEMA_VERSION: u32 = 12;
/// Attribute key that carries [`SCHEMA_VERSION`] on every service.
pub const SCHEMA_ATTRIBUTE: &str = "r2g.schema";

/// Arm joints of the supported robots (Panda, FR3).
pub const N_JOINTS: usize = 7;
/// Values per waypoint: 7 joints + gripper, or xyz + axis-angle + gripper (7, padded to 8).
pub const WAYPOINT_LEN: usize = 8;
/// Waypoints one chunk may carry.
pub const MAX_CHUNK: usize = 256;
/// Largest frame a camera service carries; smaller frames use the top-left part of the buffers.
pub const MAX_IMAGE_WIDTH: usize = 640;
/// See [`MAX_IMAGE_WIDTH`].
pub const MAX_IMAGE_HEIGHT: usize = 480;
/// Cameras one sim-host can publish.
pub const MAX_CAMERAS: usize = 4;
/// Bytes of a camera name, NUL-padded UTF-8.
pub const NAME_LEN: usize = 32;
/// Bytes of a reason text, NUL-padded UTF-8.
pub const REASON_LEN: usize = 240;
/// Bytes of [`RuntimeInfo::calibration`], NUL-padded UTF-8.
pub const CALIBRATION_LEN: usize = 8192;

/// A rigid transform: translation in metres and a unit quaternion `[x, y, z, w]`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("r2g.Pose.v1")]
pub struct Pose {
    pub position_m: [f64; 3],
    pub quat_xyzw: [f64; 4],
}

impl Default for Pose {
    fn default() -> Self {
        Self { position_m: [0.0; 3], quat_xyzw: [0.0, 0.0, 0.0, 1.0] }
    }
}

/// sim-host → runtime, once per physics step: the measured robot, as a real arm would report it.
/// Holds no object poses: privileged simulator state never crosses IPC.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.SimState.v4")]
pub struct SimState {
    /// Increments with every published state.
    pub seq: u64,
    /// The command sequence number this state answers (0 before the first command).
    pub command_seq: u64,
    /// The id of the last reset this sim-host completed (0: none).
    pub reset_id: u64,
    /// Simulated time in seconds.
    pub sim_time_s: f64,
    pub q_rad: [f64; N_JOINTS],
    pub dq_rad_s: [f64; N_JOINTS],
    /// Opening of one finger, 0 (closed) … `gripper_max_m`.
    pub finger_m: f64,
    pub finger_max_m: f64,
    pub base_from_tcp: Pose,
    /// Net contact force the environment exerts on the robot (arm and gripper), base frame, N.
    /// What a real arm's external-force estimate reports; the runtime's Franka reflexes use it.
    pub external_force_n: [f64; 3],
    /// Names this run of the robot side (nonzero, new at every start): the runtime tells a
    /// restarted robot side from the one it lost, and commands carry it back.
    pub session: u64,
    /// CLOCK_MONOTONIC when the robot side published this state, ns (0: not stamped).
    pub published_ns: u64,
    /// Nonzero: the robot side paces the tick. It publishes a state each cycle of the robot
    /// (a real arm's 1 kHz packets) and uses only the command answering that state; the runtime
    /// ticks on each state instead of its own clock (see runtime/README.md, "Who paces the tick").
    pub paced: u32,
    /// What the robot itself reports: [`ROBOT_OK`], [`ROBOT_RECOVERING`] or
    /// [`ROBOT_NEEDS_OPERATOR`]. A simulator always reports [`ROBOT_OK`].
    pub robot_error: u32,
    /// Reflexes the robot stopped a motion with and recovered from, since this robot side started.
    pub reflexes: u64,
    /// The robot's own words for its last error (for example the Franka error names), NUL-padded.
    /// (Three rows of 32 so that the payload keeps a derived `Default`.)
    pub error_text: [[u8; 32]; ERROR_TEXT_LEN / 32],
}

/// [`SimState::robot_error`]: the robot moves as commanded.
pub const ROBOT_OK: u32 = 0;
/// [`SimState::robot_error`]: one of the robot's own reflexes stopped the motion and the robot
/// side runs its bounded automatic recovery; it publishes no state until that ends.
pub const ROBOT_RECOVERING: u32 = 1;
/// [`SimState::robot_error`]: recovery failed: the robot side waits for an operator ([`JointCommand::clear_seq`]) before it tries again.
pub const ROBOT_NEEDS_OPERATOR: u32 = 2;
/// Bytes of [`SimState::error_text`].
pub const ERROR_TEXT_LEN: usize = 96;

impl SimState {
    /// [`SimState::error_text`] as text (up to the first NUL).
    pub fn error_str(&self) -> &str {
        let bytes = self.error_text.as_flattened();
        let n = bytes.iter().position(|&b| b == 0).unwrap_or(ERROR_TEXT_LEN);
        core::str::from_utf8(&bytes[..n]).unwrap_or("(not UTF-8)")
    }

    /// Sets [`SimState::error_text`], cut at a character boundary to fit.
    pub fn set_error(&mut self, text: &str) {
        let mut n = text.len().min(ERROR_TEXT_LEN);
        while !text.is_char_boundary(n) {
            n -= 1;
        }
        self.error_text = Default::default();
        self.error_text.as_flattened_mut()[..n].copy_from_slice(&text.as_bytes()[..n]);
    }
}

/// runtime → sim-host, once per tick: the limited joint command.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.JointCommand.v3")]
pub struct JointCommand {
    pub seq: u64,
    /// The state this command was computed from.
    pub state_seq: u64,
    pub q_rad: [f64; N_JOINTS],
    pub dq_rad_s: [f64; N_JOINTS],
    /// Commanded opening of one finger in metres.
    pub finger_m: f64,
    /// The [`SimState::session`] of the state this command was computed from. A robot side
    /// ignores commands of another session: a restarted one never follows a target meant for
    /// its predecessor.
    pub session: u64,
    /// Operator fault resets so far. A robot side waiting for an operator
    /// ([`ROBOT_NEEDS_OPERATOR`]) tries its recovery again when this grows.
    pub clear_seq: u64,
}

/// runtime → sim-host: restore the scene's initial state.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.SimReset.v1")]
pub struct SimReset {
    pub id: u64,
}

/// Control type of a chunk; fixed per episode in the simulation profile.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ControlType {
    Joint = 1,
    EePose = 2,
}

impl ControlType {
    pub fn from_u32(v: u32) -> Option<Self> {
        match v {
            1 => Some(Self::Joint),
            2 => Some(Self::EePose),
            _ => None,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Self::Joint => "joint",
            Self::EePose => "ee_pose",
        }
    }
}

/// What an agent asks of the runtime.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RequestKind {
    Chunk = 1,
    Reset = 2,
    /// Operator only (`r2g clear`): clears an `operator_required` fault (Franka profile).
    ClearFault = 3,
    /// One fixed control period (a gymnasium environment's step): the request's waypoints, if
    /// any, are taken as a chunk, and the runtime then runs exactly `step_ticks` ticks and
    /// replies [`Status::Stepped`]. In lockstep, once a client steps, simulated time advances
    /// only inside steps until the next reset.
    Step = 4,
}

/// agent → runtime: an action chunk or a reset.
#[repr(C)]
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("r2g.Request.v1")]
pub struct Request {
    /// Chosen by the agent, unique per agent process; the reply carries it back.
    pub id: u64,
    /// Identifies the requesting agent process, so replies can be matched to it.
    pub client: u64,
    /// A [`RequestKind`] as u32 (unknown values are rejected, not trusted).
    pub kind: u32,
    /// A [`ControlType`] as u32.
    pub control_type: u32,
    /// Waypoints used in `actions`.
    pub len: u32,
    /// [`RequestKind::Step`]: ticks the step lasts (ignored by other kinds).
    pub step_ticks: u32,
    /// Waypoint rate in Hz; 0 means the profile default (20 Hz).
    pub freq_hz: f64,
    pub actions: [[f64; WAYPOINT_LEN]; MAX_CHUNK],
}

/// Outcome of a request, as `robo` reports it in `control_feedback.status`.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    Accepted = 1,
    Executed = 2,
    Rejected = 3,
    Failed = 4,
    RecoveredReplanRequired = 5,
    OperatorRequired = 6,
    /// A [`RequestKind::Step`]'s period is over (its chunk may still be moving).
    Stepped = 7,
}

impl Status {
    pub fn from_u32(v: u32) -> Option<Self> {
        Some(match v {
            1 => Self::Accepted,
            2 => Self::Executed,
            3 => Self::Rejected,
            4 => Self::Failed,
            5 => Self::RecoveredReplanRequired,
            6 => Self::OperatorRequired,
            7 => Self::Stepped,
            _ => return None,
        })
    }
    pub fn name(self) -> &'static str {
        match self {
            Self::Accepted => "accepted",
            Self::Executed => "executed",
            Self::Rejected => "rejected",
            Self::Failed => "failed",
            Self::RecoveredReplanRequired => "recovered_replan_required",
            Self::OperatorRequired => "operator_required",
            Self::Stepped => "stepped",
        }
    }
}

/// runtime → agent: progress and outcome of a [`Request`].
#[repr(C)]
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("r2g.Reply.v4")]
pub struct Reply {
    pub id: u64,
    pub client: u64,
    /// A [`Status`] as u32.
    pub status: u32,
    /// Waypoints fully executed so far.
    pub executed: u32,
    /// Largest |measured − target| over the arm joints when the request ended, rad.
    pub final_joint_error_rad: f64,
    /// CLOCK_MONOTONIC when the runtime accepted the chunk, ns (0: not accepted).
    pub accepted_ns: u64,
    /// CLOCK_MONOTONIC of the first tick whose measured state showed the arm or fingers
    /// moving for this chunk, ns (0: no motion seen).
    pub first_motion_ns: u64,
    /// The contact force felt over the chunk, from acceptance to this reply: the largest and the
    /// mean magnitude of the runtime's filtered external force (`RobotState::external_force_n`),
    /// N, over `contact_ticks` ticks, and the waypoint (0-based) the arm was heading for at the
    /// largest. `contact_start_n` is the magnitude on the chunk's first tick: what was already
    /// felt (a held object's weight, a press that continues from the chunk before), so
    /// `contact_peak_n - contact_start_n` is what the chunk added. All 0 for a request that
    /// never ran.
    pub contact_start_n: f64,
    pub contact_peak_n: f64,
    pub contact_mean_n: f64,
    pub contact_peak_waypoint: u32,
    pub contact_ticks: u32,
    /// Why, in words a model can act on (NUL-padded UTF-8).
    pub reason: [u8; REASON_LEN],
}

impl Reply {
    pub fn new(id: u64, client: u64, status: Status, reason: &str) -> Self {
        Self::formatted(id, client, status, format_args!("{reason}"))
    }

    /// A reply whose reason is formatted straight into the fixed buffer, cut at a character
    /// boundary if too long. Allocation-free, so the tick path can use it.
    pub fn formatted(id: u64, client: u64, status: Status, reason: core::fmt::Arguments<'_>) -> Self {
        let mut r = Self {
            id,
            client,
            status: status as u32,
            executed: 0,
            final_joint_error_rad: 0.0,
            accepted_ns: 0,
            first_motion_ns: 0,
            contact_start_n: 0.0,
            contact_peak_n: 0.0,
            contact_mean_n: 0.0,
            contact_peak_waypoint: 0,
            contact_ticks: 0,
            reason: [0; REASON_LEN],
        };
        let mut w = FixedWriter { buf: &mut r.reason, len: 0 };
        let _ = core::fmt::write(&mut w, reason);
        r
    }

    pub fn reason_str(&self) -> &str {
        read_str(&self.reason)
    }
}

/// Tick-loop mode.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Wall = 1,
    Lockstep = 2,
}

/// runtime → agents, once per tick (wall) or per step (lockstep): the agent-facing robot state.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.RobotState.v4")]
pub struct RobotState {
    pub seq: u64,
    /// Simulated (or robot) time of the underlying measurement, s.
    pub timestamp_s: f64,
    /// CLOCK_MONOTONIC when the runtime published this, ns; a stale value means a dead runtime.
    pub published_ns: u64,
    pub q_rad: [f64; N_JOINTS],
    pub dq_rad_s: [f64; N_JOINTS],
    /// −1 open … +1 closed.
    pub gripper: f64,
    pub base_from_tcp: Pose,
    /// The TCP rotation as an axis-angle vector (rad), continuous from one report to the next:
    /// of the vectors that describe the rotation, the one nearest the previous report.
    pub tcp_rotvec: [f64; 3],
    /// The control type locked for this episode (0: none yet).
    pub control_type: u32,
    /// A [`Mode`] as u32.
    pub mode: u32,
    /// The request the runtime is executing (0: idle).
    pub active_request: u64,
    /// The last completed reset id.
    pub reset_id: u64,
    /// [`SimState::external_force_n`] low-pass filtered (20 ms), base frame, N.
    pub external_force_n: [f64; 3],
    /// Bit 0: an `operator_required` fault holds the arm (Franka profile). Bit 1: the robot
    /// side publishes no state; the arm holds and requests are refused until it is back.
    /// Bit 2: the gripper reports a fault or went silent ([`RobotState::gripper_error`]); the
    /// arm holds and chunks are refused until it is clear. Bit 3 (with bit 2): that is the
    /// gripper not acting yet or a condition that ends by itself (starting, activating, a minor
    /// device fault), not a fault.
    pub fault: u32,
    /// What the gripper knows about its fingers: a `GRASP_*` value.
    pub grasp: u32,
    /// The gripper's fault in words while fault bit 2 is set, NUL-padded UTF-8.
    pub gripper_error: [[u8; 32]; ERROR_TEXT_LEN / 32],
}

impl RobotState {
    /// [`RobotState::gripper_error`] as text (up to the first NUL).
    pub fn gripper_error_str(&self) -> &str {
        read_str(self.gripper_error.as_flattened())
    }
}

/// [`RobotState::grasp`] / [`GripperState::grasp`]: nothing known (no report yet).
pub const GRASP_UNKNOWN: u32 = 0;
/// The fingers move toward their target.
pub const GRASP_MOVING: u32 = 1;
/// The fingers stopped at their target: nothing between them.
pub const GRASP_AT_TARGET: u32 = 2;
/// The fingers stopped short of their target while closing: an object is held.
pub const GRASP_HOLDING: u32 = 3;
/// The fingers stopped short of their target while opening (something blocks them).
pub const GRASP_BLOCKED_OPENING: u32 = 4;

/// The name `control_feedback["grasp"]["status"]` shows for a `GRASP_*` value.
pub fn grasp_name(grasp: u32) -> &'static str {
    match grasp {
        GRASP_MOVING => "moving",
        GRASP_AT_TARGET => "at_target",
        GRASP_HOLDING => "holding",
        GRASP_BLOCKED_OPENING => "blocked_opening",
        _ => "unknown",
    }
}

/// gripper driver → runtime, at the driver's polling rate: a gripper that is its own device (a
/// Robotiq 2F-85 on a serial port), published by its driver process (`r2g-robotiq`). The
/// runtime takes the fingers from here instead of from [`SimState`] and holds the arm while
/// [`GripperState::fault`] is set or the stream is silent.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.GripperState.v1")]
pub struct GripperState {
    pub seq: u64,
    /// CLOCK_MONOTONIC when the driver published this, ns: a new reading, or the newest one
    /// again while the driver waits (on an answer, a reconnect, an activation), so that its
    /// silence always means the driver itself stopped.
    pub published_ns: u64,
    /// Opening of one finger, m (as [`SimState::finger_m`]).
    pub finger_m: f64,
    pub finger_max_m: f64,
    /// A `GRASP_*` value, from the device's own object detection.
    pub grasp: u32,
    /// 0: the gripper acts on commands. Otherwise the device's fault code, or
    /// [`GRIPPER_LINK_LOST`] / [`GRIPPER_NOT_READY`]; the text says which in words.
    pub fault: u32,
    /// Motor current, mA (0 when the device does not report it).
    pub current_ma: f64,
    /// Round trip of the last poll (request sent → answer parsed), µs.
    pub poll_us: u32,
    /// 1 when `fault` ends by itself and needs nobody (activating, a minor device fault such as
    /// a temperature warning): the arm holds while it lasts, but no operator is asked for.
    pub clears_itself: u32,
    pub fault_text: [[u8; 32]; ERROR_TEXT_LEN / 32],
}

/// [`GripperState::fault`]: the driver lost the device (port gone, no answer, bad frames).
pub const GRIPPER_LINK_LOST: u32 = 0x100;
/// [`GripperState::fault`]: the device is not activated yet (or reactivating).
pub const GRIPPER_NOT_READY: u32 = 0x101;

impl GripperState {
    /// [`GripperState::fault_text`] as text (up to the first NUL).
    pub fn fault_str(&self) -> &str {
        read_str(self.fault_text.as_flattened())
    }

    /// Sets [`GripperState::fault_text`], cut at a character boundary to fit.
    pub fn set_fault_text(&mut self, text: &str) {
        write_str(self.fault_text.as_flattened_mut(), text);
    }
}

/// runtime → agents, published once with history: the limits in force (`effective_safety`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.RuntimeInfo.v4")]
pub struct RuntimeInfo {
    pub schema: u32,
    pub mode: u32,
    pub tick_period_ns: u64,
    pub q_min_rad: [f64; N_JOINTS],
    pub q_max_rad: [f64; N_JOINTS],
    pub dq_max_rad_s: [f64; N_JOINTS],
    pub ddq_max_rad_s2: [f64; N_JOINTS],
    /// Position margin kept inside each joint limit, rad.
    pub q_margin_rad: f64,
    /// Fraction of the velocity limits that chunk timing plans for.
    pub speed_scale: f64,
    pub max_chunk: u32,
    pub default_freq_hz: f64,
    pub finger_max_m: f64,
    pub finger_speed_m_s: f64,
    /// A [`Profile`] as u32.
    pub profile: u32,
    /// 1 when `workspace_*` hold a workspace box.
    pub has_workspace: u32,
    pub workspace_min_m: [f64; 3],
    pub workspace_max_m: [f64; 3],
    pub collision_margin_m: f64,
    /// Largest change of any joint between consecutive joint waypoints (the first counted
    /// from the measured position), rad.
    pub max_joint_step_rad: f64,
    /// Largest TCP translation / rotation between consecutive ee_pose waypoints, m / rad.
    pub max_tcp_step_m: f64,
    pub max_tcp_step_rad: f64,
    /// Franka profile: contact force that stops a chunk (recoverable), N.
    pub reflex_force_n: f64,
    /// Franka profile: contact force that needs an operator, N.
    pub operator_force_n: f64,
    /// Where the TCP and the configured cameras' calibrations come from, one JSON object
    /// (`get_state()["calibration"]`, runtime/README.md "Calibration"), NUL-padded UTF-8.
    /// (Blocks of 32 × 32 bytes so that the payload keeps a derived `Default`.)
    pub calibration: [[[u8; 32]; 32]; CALIBRATION_LEN / 1024],
    /// What this runtime was started with, one JSON object (`get_state()["setup"]`: the gym and
    /// the SHA-256 of the robot configuration file in force), NUL-padded UTF-8. Memory records
    /// are keyed by it (robot-skill/memory/README.md), so it names the setup, never an episode.
    pub setup: [[u8; 32]; SETUP_LEN / 32],
}

/// Bytes of [`RuntimeInfo::setup`].
pub const SETUP_LEN: usize = 512;

impl RuntimeInfo {
    /// [`RuntimeInfo::calibration`] as text (up to the first NUL).
    pub fn calibration_str(&self) -> &str {
        read_str(self.calibration.as_flattened().as_flattened())
    }

    /// Sets [`RuntimeInfo::calibration`]; a text that does not fit is refused whole (a cut JSON
    /// object would not parse), with its length.
    pub fn set_calibration(&mut self, text: &str) -> Result<(), usize> {
        if text.len() > CALIBRATION_LEN {
            return Err(text.len());
        }
        write_str(self.calibration.as_flattened_mut().as_flattened_mut(), text);
        Ok(())
    }

    /// [`RuntimeInfo::setup`] as text (up to the first NUL).
    pub fn setup_str(&self) -> &str {
        read_str(self.setup.as_flattened())
    }

    /// Sets [`RuntimeInfo::setup`]; a text that does not fit is refused whole, with its length.
    pub fn set_setup(&mut self, text: &str) -> Result<(), usize> {
        if text.len() > SETUP_LEN {
            return Err(text.len());
        }
        write_str(self.setup.as_flattened_mut(), text);
        Ok(())
    }
}

/// Which semantics the runtime follows (`config/robot.json` `profile`).
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Profile {
    /// reset() restores the scene; the control type is fixed per episode; no contact reflexes.
    #[default]
    Simulation = 1,
    /// reset() only refreshes observations; contact reflexes stop chunks; faults need an operator.
    Franka = 2,
}

impl Profile {
    pub fn from_u32(v: u32) -> Option<Self> {
        match v {
            1 => Some(Self::Simulation),
            2 => Some(Self::Franka),
            _ => None,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Self::Simulation => "simulation",
            Self::Franka => "franka",
        }
    }
}

/// sim-host → agents, published once with history: which cameras exist.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.SimInfo.v1")]
pub struct SimInfo {
    pub schema: u32,
    pub camera_count: u32,
    pub camera_names: [[u8; NAME_LEN]; MAX_CAMERAS],
    pub physics_timestep_s: f64,
}

impl SimInfo {
    pub fn camera_name(&self, i: usize) -> &str {
        read_str(&self.camera_names[i])
    }
}

/// sim-host (or a camera host, for a real camera) → agents: one camera image. Written once into
/// a loaned sample; readers borrow it in place.
#[repr(C)]
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("r2g.CameraFrame.v1")]
pub struct CameraFrame {
    pub seq: u64,
    /// Simulated time of the state this frame shows, s.
    pub sim_time_s: f64,
    /// The [`SimState::seq`] of the physics state this frame shows.
    pub state_seq: u64,
    /// CLOCK_MONOTONIC at the end of rendering, ns (a camera host's frame: the exposure).
    pub rendered_ns: u64,
    pub width: u32,
    pub height: u32,
    /// 1 when `depth_m` holds depth for this frame.
    pub has_depth: u32,
    /// The [`SimState::reset_id`] (low 32 bits) of the episode this frame shows: simulated time
    /// starts again at each reset, so freshness is (reset_id, sim_time_s), in that order.
    pub reset_id: u32,
    /// Pinhole intrinsics in pixels (principal point at the image centre for rendered cameras).
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Camera optical frame (x right, y down, z forward) in the robot base frame.
    pub base_from_camera: Pose,
    /// Row-major RGB8, `width × height × 3` bytes used.
    pub rgb: [u8; MAX_IMAGE_WIDTH * MAX_IMAGE_HEIGHT * 3],
    /// Row-major depth in metres, `width × height` used when `has_depth`.
    pub depth_m: [f32; MAX_IMAGE_WIDTH * MAX_IMAGE_HEIGHT],
}

/// What a gymnasium environment asks the sim-host of its instance ([`Services::env_query`]).
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EnvQueryKind {
    /// Judge the episode so far: the evaluator's verdict on the trace up to now.
    Evaluate = 1,
    /// The augmentation seed of every episode from the next reset on.
    Seed = 2,
}

/// environment → sim-host, only where the sim-host serves environments (`r2g up --env`).
/// Nothing of the agent side (`robo`, the sandbox) opens these services.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("r2g.EnvQuery.v1")]
pub struct EnvQuery {
    /// Chosen by the environment; the answer carries it back.
    pub id: u64,
    /// An [`EnvQueryKind`] as u32.
    pub kind: u32,
    pub _pad: u32,
    /// [`EnvQueryKind::Seed`]: the seed.
    pub seed: u64,
}

/// Bytes of [`EnvAnswer::json`].
pub const ENV_ANSWER_LEN: usize = 4096;

/// sim-host → environment: the answer to an [`EnvQuery`]. The verdict is the evaluator's JSON
/// (`sim_host::trace::Evaluation`), judged on the native trace inside the sim-host.
#[repr(C)]
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("r2g.EnvAnswer.v1")]
pub struct EnvAnswer {
    pub id: u64,
    /// The reset id of the episode judged.
    pub reset_id: u64,
    /// Simulated time of the last state judged, s.
    pub sim_time_s: f64,
    /// 1: the task's success rules hold.
    pub success: u32,
    /// Bytes used in `json` (0 for a seed's answer).
    pub len: u32,
    pub json: [u8; ENV_ANSWER_LEN],
}

/// Everything of a [`CameraFrame`] but its pixels (see [`CameraFrame::fill`]).
#[derive(Debug, Clone, Copy, Default)]
pub struct FrameHeader {
    pub seq: u64,
    pub sim_time_s: f64,
    pub state_seq: u64,
    pub rendered_ns: u64,
    pub width: u32,
    pub height: u32,
    pub reset_id: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub base_from_camera: Pose,
}

impl CameraFrame {
    /// Writes a whole frame into a loaned, uninitialised sample: the header, `rgb` (row-major
    /// RGB8) and `depth_m` (metres; `has_depth` when given), each cut to `width × height` pixels
    /// and to the buffers' size, and zeros in the rest of both buffers, so that every byte is
    /// initialised.
    pub fn fill(dst: &mut core::mem::MaybeUninit<CameraFrame>, h: &FrameHeader, rgb: &[u8], depth_m: Option<&[f32]>) {
        const PIXELS: usize = MAX_IMAGE_WIDTH * MAX_IMAGE_HEIGHT;
        let n = (h.width as usize * h.height as usize).min(PIXELS);
        let rgb_used = rgb.len().min(3 * n);
        let depth_used = depth_m.map_or(0, |d| d.len().min(n));
        let p = dst.as_mut_ptr();
        // SAFETY: p points at a CameraFrame we may write; every field is a plain number (no
        // drop of what was there), and the copies stay inside the two pixel buffers (`rgb_used`
        // <= 3 × PIXELS, `depth_used` <= PIXELS), the rest of which is zeroed.
        unsafe {
            (*p).seq = h.seq;
            (*p).sim_time_s = h.sim_time_s;
            (*p).state_seq = h.state_seq;
            (*p).rendered_ns = h.rendered_ns;
            (*p).width = h.width;
            (*p).height = h.height;
            (*p).has_depth = u32::from(depth_m.is_some());
            (*p).reset_id = h.reset_id;
            (*p).fx = h.fx;
            (*p).fy = h.fy;
            (*p).cx = h.cx;
            (*p).cy = h.cy;
            (*p).base_from_camera = h.base_from_camera;
            let rgb_dst = core::ptr::addr_of_mut!((*p).rgb).cast::<u8>();
            core::ptr::copy_nonoverlapping(rgb.as_ptr(), rgb_dst, rgb_used);
            core::ptr::write_bytes(rgb_dst.add(rgb_used), 0, 3 * PIXELS - rgb_used);
            let depth_dst = core::ptr::addr_of_mut!((*p).depth_m).cast::<f32>();
            if let Some(d) = depth_m {
                core::ptr::copy_nonoverlapping(d.as_ptr(), depth_dst, depth_used);
            }
            core::ptr::write_bytes(depth_dst.add(depth_used), 0, PIXELS - depth_used);
        }
    }
}

/// Writes formatted text into a fixed buffer, dropping what does not fit (at a char boundary).
struct FixedWriter<'a> {
    buf: &'a mut [u8],
    len: usize,
}

impl core::fmt::Write for FixedWriter<'_> {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let room = self.buf.len() - self.len;
        let mut n = s.len().min(room);
        while !s.is_char_boundary(n) {
            n -= 1;
        }
        self.buf[self.len..self.len + n].copy_from_slice(&s.as_bytes()[..n]);
        self.len += n;
        Ok(())
    }
}

/// Copies `s` into a NUL-padded byte field, cutting at a UTF-8 boundary if it is too long.
pub fn write_str(dst: &mut [u8], s: &str) {
    dst.fill(0);
    let mut n = s.len().min(dst.len());
    while !s.is_char_boundary(n) {
        n -= 1;
    }
    dst[..n].copy_from_slice(&s.as_bytes()[..n]);
}

/// Reads a NUL-padded UTF-8 field written by [`write_str`]; invalid UTF-8 reads as empty.
pub fn read_str(src: &[u8]) -> &str {
    let end = src.iter().position(|&b| b == 0).unwrap_or(src.len());
    core::str::from_utf8(&src[..end]).unwrap_or("")
}

/// Errors when connecting to the services of an instance.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum SchemaError {
    #[error("invalid service name '{name}': {detail}")]
    BadName { name: String, detail: String },
    #[error(
        "schema version mismatch on service '{service}': this build speaks r2g schema {ours}, \
         the process that created the service speaks another one. Stop every r2g process and \
         start them all from the same build"
    )]
    VersionMismatch { service: String, ours: u32 },
    #[error("service '{service}' does not exist yet (is `r2g up` running for this instance?)")]
    Missing { service: String },
    #[error("cannot open service '{service}': {detail}")]
    Open { service: String, detail: String },
    #[error("cannot create an iceoryx2 node: {0}")]
    Node(String),
    #[error("iceoryx2 config {path} (from R2G_IPC_CONFIG): {detail}")]
    Config { path: String, detail: String },
}

/// Names of every service of one instance. Instances let many gyms share one machine.
#[derive(Debug, Clone)]
pub struct Services {
    pub instance: String,
}

impl Services {
    /// Instance names are 1–32 characters of `[A-Za-z0-9_-]`.
    pub fn new(instance: &str) -> Result<Self, SchemaError> {
        let ok = !instance.is_empty()
            && instance.len() <= 32
            && instance.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
        if !ok {
            return Err(SchemaError::BadName {
                name: instance.to_string(),
                detail: "an instance name is 1-32 characters of A-Z a-z 0-9 _ -".into(),
            });
        }
        Ok(Self { instance: instance.to_string() })
    }
    pub fn name(&self, leaf: &str) -> String {
        format!("r2g/{}/{}", self.instance, leaf)
    }
    pub fn sim_state(&self) -> String {
        self.name("sim/state")
    }
    pub fn sim_info(&self) -> String {
        self.name("sim/info")
    }
    pub fn sim_reset(&self) -> String {
        self.name("sim/reset")
    }
    pub fn command(&self) -> String {
        self.name("control/command")
    }
    pub fn robot_state(&self) -> String {
        self.name("control/state")
    }
    pub fn runtime_info(&self) -> String {
        self.name("control/info")
    }
    pub fn request(&self) -> String {
        self.name("agent/request")
    }
    pub fn reply(&self) -> String {
        self.name("control/reply")
    }
    /// A gripper driven by its own process (`r2g-robotiq`) publishes its state here.
    pub fn gripper_state(&self) -> String {
        self.name("gripper/state")
    }
    pub fn camera(&self, camera: &str) -> String {
        self.name(&format!("camera/{camera}"))
    }
    /// Wakes the sim-host when a command or reset is published.
    pub fn sim_wake(&self) -> String {
        self.name("sim/wake")
    }
    /// Wakes the runtime when a state or request is published.
    pub fn control_wake(&self) -> String {
        self.name("control/wake")
    }
    /// Wakes agents when a reply or frame is published.
    pub fn agent_wake(&self) -> String {
        self.name("agent/wake")
    }
    /// A gymnasium environment's questions to the sim-host (`r2g up --env` only).
    pub fn env_query(&self) -> String {
        self.name("env/query")
    }
    /// The sim-host's answers to them.
    pub fn env_answer(&self) -> String {
        self.name("env/answer")
    }
    /// Wakes the environment when an answer is published.
    pub fn env_wake(&self) -> String {
        self.name("env/wake")
    }
}

/// How a publish-subscribe service is sized. Defaults suit a state stream.
#[derive(Debug, Clone, Copy)]
pub struct Qos {
    pub history: usize,
    pub buffer: usize,
    pub max_publishers: usize,
    pub max_subscribers: usize,
    /// Samples one subscriber may hold at once (zero-copy views kept by a program).
    pub borrowed: usize,
}

impl Qos {
    /// Newest-sample streams with one trusted writer (state, command, info): one buffered
    /// sample, overwritten by the next. A second publisher is refused by iceoryx2.
    pub const STREAM: Qos = Qos { history: 1, buffer: 1, max_publishers: 1, max_subscribers: 16, borrowed: 2 };
    /// The runtime's robot state: a stream as [`Qos::STREAM`], but a subscriber may ask to keep
    /// up to 128 states (128 ms of ticks): a camera host places each exposure between the two
    /// states around it. Readers of the newest state only ask for a buffer of 1. Every opener
    /// uses this (the creator sets the limit).
    pub const ROBOT_STATE: Qos = Qos { history: 1, buffer: 128, max_publishers: 1, max_subscribers: 16, borrowed: 2 };
    /// Camera frames: one writer; each reader may keep a few frames borrowed in place.
    pub const CAMERA: Qos = Qos { history: 1, buffer: 1, max_publishers: 1, max_subscribers: 8, borrowed: 6 };
    /// Resets from the runtime to the sim-host: one writer, none lost.
    pub const CONTROL: Qos = Qos { history: 0, buffer: 16, max_publishers: 1, max_subscribers: 2, borrowed: 2 };
    /// Requests from agents to the runtime: many writers, one reader.
    pub const REQUESTS: Qos = Qos { history: 0, buffer: 16, max_publishers: 16, max_subscribers: 2, borrowed: 2 };
    /// Replies from the runtime to every agent; deep enough that a busy agent's rejections
    /// cannot push another agent's reply out while it waits.
    pub const REPLIES: Qos = Qos { history: 0, buffer: 256, max_publishers: 1, max_subscribers: 16, borrowed: 2 };
}

pub type PubSub<T> = publish_subscribe::PortFactory<ipc::Service, T, ()>;
pub type Event = event::PortFactory<ipc::Service>;

fn service_name(name: &str) -> Result<ServiceName, SchemaError> {
    ServiceName::new(name).map_err(|e| SchemaError::BadName { name: name.into(), detail: format!("{e:?}") })
}

fn verifier() -> AttributeVerifier {
    // Constant keys and values that fit the attribute limits: these cannot fail.
    let key = AttributeKey::try_from(SCHEMA_ATTRIBUTE).expect("constant attribute key");
    let value = AttributeValue::try_from(SCHEMA_VERSION.to_string().as_str()).expect("short attribute value");
    AttributeVerifier::new().require(&key, &value).expect("one attribute fits")
}

/// Opens the service, creating it if nobody has yet; refuses one of another schema version.
pub fn open_or_create_pubsub<T: core::fmt::Debug + ZeroCopySend>(
    node: &Node<ipc::Service>,
    name: &str,
    qos: Qos,
) -> Result<PubSub<T>, SchemaError> {
    let sn = service_name(name)?;
    let mut tries = 0;
    loop {
        let r = node
            .service_builder(&sn)
            .publish_subscribe::<T>()
            .history_size(qos.history)
            .subscriber_max_buffer_size(qos.buffer.max(qos.history).max(1))
            .max_publishers(qos.max_publishers)
            .max_subscribers(qos.max_subscribers)
            .subscriber_max_borrowed_samples(qos.borrowed.max(1))
            .max_nodes(32)
            .enable_safe_overflow(true)
            .open_or_create_with_attributes(&verifier());
        match r {
            Ok(s) => return Ok(s),
            Err(e) => {
                let text = format!("{e:?}");
                if text.contains("IncompatibleAttributes") || text.contains("IncompatibleTypes") {
                    return Err(SchemaError::VersionMismatch { service: name.into(), ours: SCHEMA_VERSION });
                }
                // A service being torn down by its last user can be re-created a moment later.
                if (text.contains("IsMarkedForDestruction") || text.contains("IsBeingCreatedByAnotherInstance"))
                    && tries < 50
                {
                    tries += 1;
                    std::thread::sleep(Duration::from_millis(10));
                    continue;
                }
                return Err(SchemaError::Open { service: name.into(), detail: text });
            }
        }
    }
}

/// Opens or creates an event service used to wake a waiting process.
pub fn open_or_create_event(node: &Node<ipc::Service>, name: &str) -> Result<Event, SchemaError> {
    let sn = service_name(name)?;
    let mut tries = 0;
    loop {
        let r = node
            .service_builder(&sn)
            .event()
            .max_notifiers(32)
            .max_listeners(32)
            .max_nodes(32)
            .open_or_create_with_attributes(&verifier());
        match r {
            Ok(s) => return Ok(s),
            Err(e) => {
                let text = format!("{e:?}");
                if text.contains("IncompatibleAttributes") {
                    return Err(SchemaError::VersionMismatch { service: name.into(), ours: SCHEMA_VERSION });
                }
                if text.contains("IsMarkedForDestruction") && tries < 50 {
                    tries += 1;
                    std::thread::sleep(Duration::from_millis(10));
                    continue;
                }
                return Err(SchemaError::Open { service: name.into(), detail: text });
            }
        }
    }
}

/// The iceoryx2 configuration of every r2g process: the file `$R2G_IPC_CONFIG` names (an
/// iceoryx2 TOML; deploy/ ships one per instance that moves the root path under `/run/r2g`),
/// else iceoryx2's own lookup (root path `/tmp/iceoryx2`). Loaded once per process; a file
/// that cannot be read, or that disagrees with a configuration already in use, is an error.
pub fn ipc_config() -> Result<&'static Config, SchemaError> {
    static LOADED: std::sync::OnceLock<Result<&'static Config, SchemaError>> = std::sync::OnceLock::new();
    LOADED.get_or_init(load_ipc_config).clone()
}

fn load_ipc_config() -> Result<&'static Config, SchemaError> {
    let Some(path) = std::env::var_os("R2G_IPC_CONFIG") else {
        return Ok(Config::global_config());
    };
    let shown = path.to_string_lossy().into_owned();
    let err = |detail: String| SchemaError::Config { path: shown.clone(), detail };
    let file = iceoryx2::prelude::FilePath::new(path.as_encoded_bytes())
        .map_err(|e| err(format!("not a usable file path ({e:?})")))?;
    let wanted = Config::from_file(&file).map_err(|e| err(format!("cannot be loaded ({e:?})")))?;
    let global = Config::setup_global_config_from_file(&file).map_err(|e| err(format!("cannot be loaded ({e:?})")))?;
    if global.global.root_path() != wanted.global.root_path() {
        return Err(err(format!(
            "this process already uses iceoryx2 root path {}, not the file's {}",
            global.global.root_path(),
            wanted.global.root_path()
        )));
    }
    Ok(global)
}

/// Creates a node for one r2g process. Signal handling stays with the process itself.
pub fn node(name: &str) -> Result<Node<ipc::Service>, SchemaError> {
    let node_name = NodeName::new(name).map_err(|e| SchemaError::Node(format!("{e:?}")))?;
    NodeBuilder::new()
        .config(ipc_config()?)
        .name(&node_name)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|e| SchemaError::Node(format!("{e:?}")))
}

/// Removes the shared-memory leftovers of r2g processes that died without cleaning up
/// (SIGKILL, power loss). Returns how many dead nodes were cleaned.
pub fn cleanup_dead_nodes() -> usize {
    let mut cleaned = 0;
    let Ok(config) = ipc_config() else { return 0 };
    let _ = Node::<ipc::Service>::list(config, |state| {
        if let NodeState::<ipc::Service>::Dead(view) = state {
            if view.try_remove_stale_resources().is_ok() {
                cleaned += 1;
            }
        }
        CallbackProgression::Continue
    });
    cleaned
}

/// CLOCK_MONOTONIC in nanoseconds, the time base of every `*_ns` field; comparable across processes.
pub fn monotonic_ns() -> u64 {
    let mut ts = TimeSpec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes into the valid timespec we pass; CLOCK_MONOTONIC always exists.
    unsafe { clock_gettime(1, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

#[repr(C)]
struct TimeSpec {
    tv_sec: i64,
    tv_nsec: i64,
}

extern "C" {
    fn clock_gettime(clk: i32, ts: *mut TimeSpec) -> i32;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strings_round_trip_and_cut_at_char_boundaries() {
        let mut buf = [0u8; 5];
        write_str(&mut buf, "héllo");
        assert_eq!(read_str(&buf), "héll");
        write_str(&mut buf, "ab");
        assert_eq!(read_str(&buf), "ab");
    }

    #[test]
    fn the_calibration_report_is_kept_whole_or_refused() {
        let mut i = RuntimeInfo::default();
        assert_eq!(i.calibration_str(), "");
        i.set_calibration(r#"{"tcp": {"source": "description"}}"#).expect("fits");
        assert_eq!(i.calibration_str(), r#"{"tcp": {"source": "description"}}"#);
        let full = "x".repeat(CALIBRATION_LEN);
        i.set_calibration(&full).expect("exactly fits");
        assert_eq!(i.calibration_str().len(), CALIBRATION_LEN);
        assert_eq!(i.set_calibration(&format!("{full}y")), Err(CALIBRATION_LEN + 1));
    }

    #[test]
    fn formatted_reasons_fit_the_buffer() {
        let r = Reply::formatted(1, 2, Status::Rejected, format_args!("joint {} off by {:.2}", 4, 0.5));
        assert_eq!(r.reason_str(), "joint 4 off by 0.50");
        let long = Reply::formatted(1, 2, Status::Rejected, format_args!("{}", "é".repeat(200)));
        assert!(long.reason_str().len() <= REASON_LEN && long.reason_str().chars().all(|c| c == 'é'));
    }

    #[test]
    fn instance_names_are_checked() {
        assert!(Services::new("gym-1_a").is_ok());
        assert!(Services::new("").is_err());
        assert!(Services::new("a/b").is_err());
        assert!(Services::new(&"x".repeat(33)).is_err());
    }

    #[test]
    fn enums_reject_unknown_values() {
        assert_eq!(ControlType::from_u32(1), Some(ControlType::Joint));
        assert_eq!(ControlType::from_u32(9), None);
        assert_eq!(Status::from_u32(0), None);
        assert_eq!(Status::from_u32(6).map(Status::name), Some("operator_required"));
    }

    #[test]
    fn payloads_keep_their_sizes() {
        // A layout change must bump SCHEMA_VERSION; this test makes the change visible.
        // Schema 2 added the external force (SimState, RobotState), the fault flag, the reply's
        // latency stamps and the profile limits; schema 3 the continuous TCP axis-angle vector
        // (RobotState); schema 4 the robot side's session (SimState, JointCommand); schema 5
        // pacing, the robot's own errors (SimState) and operator resets (JointCommand); schema 6
        // the calibration report (RuntimeInfo); schema 7 the gripper's grasp and error
        // (RobotState) and the gripper driver's state (GripperState); schema 8 no layout change
        // but meanings: `GripperState::clears_itself` (was padding), `RobotState::fault` bit 3, a
        // NaN finger target in `JointCommand`, the robot state's deeper subscriber buffer.
        assert_eq!(core::mem::size_of::<SimState>(), 248 + 8 + 4 + 4 + 8 + ERROR_TEXT_LEN);
        assert_eq!(core::mem::size_of::<JointCommand>(), 152);
        assert_eq!(core::mem::size_of::<Request>(), 40 + 8 * WAYPOINT_LEN * MAX_CHUNK);
        assert_eq!(core::mem::size_of::<RobotState>(), 280 + ERROR_TEXT_LEN);
        assert_eq!(core::mem::size_of::<GripperState>(), 56 + ERROR_TEXT_LEN);
        // Schema 11 adds the contact force over a chunk (Reply), 12 its value at the start.
        assert_eq!(core::mem::size_of::<Reply>(), 80 + REASON_LEN);
        // Schema 10 adds the setup report (RuntimeInfo).
        assert_eq!(core::mem::size_of::<RuntimeInfo>(), 392 + CALIBRATION_LEN + SETUP_LEN);
        // Schema 9 adds steps (RequestKind::Step, Request::step_ticks, Status::Stepped) and the
        // environment's own services (EnvQuery, EnvAnswer) to 8.
        assert_eq!(core::mem::size_of::<EnvQuery>(), 24);
        assert_eq!(core::mem::size_of::<EnvAnswer>(), 32 + ENV_ANSWER_LEN);
        assert_eq!(SCHEMA_VERSION, 12);
    }
}

#[cfg(test)]
mod schema_tests {
    use super::*;

    fn unique(tag: &str) -> String {
        format!("r2g/test-{}-{}/{tag}", std::process::id(), monotonic_ns())
    }

    #[test]
    fn a_service_of_another_schema_version_is_refused_clearly() {
        let node = node(&format!("schema-test-{}", std::process::id())).expect("node");
        let name = unique("state");
        let key = AttributeKey::try_from(SCHEMA_ATTRIBUTE).expect("key");
        let other = AttributeValue::try_from("999").expect("value");
        let _old = node
            .service_builder(&ServiceName::new(&name).expect("name"))
            .publish_subscribe::<SimState>()
            .create_with_attributes(&AttributeSpecifier::new().define(&key, &other).expect("define"))
            .expect("create service of another schema");
        let err = open_or_create_pubsub::<SimState>(&node, &name, Qos::STREAM).expect_err("must be refused");
        assert!(matches!(err, SchemaError::VersionMismatch { .. }), "{err}");
        assert!(err.to_string().contains("schema version mismatch"), "{err}");
    }

    #[test]
    fn a_service_with_another_payload_layout_is_refused_clearly() {
        let node = node(&format!("schema-test2-{}", std::process::id())).expect("node");
        let name = unique("cmd");
        let _ours = open_or_create_pubsub::<JointCommand>(&node, &name, Qos::STREAM).expect("create");
        let err = open_or_create_pubsub::<SimState>(&node, &name, Qos::STREAM).expect_err("must be refused");
        assert!(matches!(err, SchemaError::VersionMismatch { .. }), "{err}");
    }

    #[test]
    fn a_single_writer_stream_refuses_a_second_publisher() {
        let node = node(&format!("schema-test4-{}", std::process::id())).expect("node");
        let name = unique("command");
        let svc = open_or_create_pubsub::<JointCommand>(&node, &name, Qos::STREAM).expect("create");
        let _runtime = svc.publisher_builder().create().expect("the one writer");
        let intruder = open_or_create_pubsub::<JointCommand>(&node, &name, Qos::STREAM).expect("open");
        assert!(intruder.publisher_builder().create().is_err(), "a second command publisher must be refused");
    }

    #[test]
    fn the_same_schema_opens() {
        let node = node(&format!("schema-test3-{}", std::process::id())).expect("node");
        let name = unique("ok");
        let a = open_or_create_pubsub::<RobotState>(&node, &name, Qos::STREAM).expect("create");
        let b = open_or_create_pubsub::<RobotState>(&node, &name, Qos::STREAM).expect("open");
        let publisher = a.publisher_builder().create().expect("publisher");
        let subscriber = b.subscriber_builder().create().expect("subscriber");
        publisher.send_copy(RobotState { seq: 7, ..Default::default() }).expect("send");
        let got = subscriber.receive().expect("receive").expect("a sample");
        assert_eq!(got.seq, 7);
    }
}
