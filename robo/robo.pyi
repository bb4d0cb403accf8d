"""Type stubs of `robo`, the agent-facing robot API of the Real2Gym runtime.

Generated code uses only ``from robo import reset, get_state, post_actions``. Units are SI
(rad, m, s, N); poses are the TCP in the robot base frame, ``[x, y, z, ax, ay, az]`` with an
axis-angle rotation; the gripper is one number, -1 open ... +1 closed. See
robot-skill/api/README.md for the full contract.
"""
from typing import Literal, Mapping, Optional, Sequence, TypedDict, Union, overload

import numpy as np
import numpy.typing as npt

SCHEMA_VERSION: int
"""Version of the interface (integer)."""

Status = Literal[
    "none", "accepted", "executed", "rejected", "failed", "recovered_replan_required", "operator_required"
]

class ControlFeedback(TypedDict):
    """Outcome of this process's last reset() or post_actions()."""

    status: Status
    """"none" before this process sent anything; see robot-skill/api/README.md for each status."""
    reason: str
    """Why, naming the field, waypoint, limit and excess; "" when nothing went wrong."""
    executed: int
    """Waypoints completed; with `not reached:`, the waypoints commanded (the arm may have been
    stopped well before the last of them: the reason gives the measured error)."""
    request_id: int
    final_joint_error_rad: float
    """Largest joint distance from the last target when the chunk ended."""
    submit_to_accept_us: Optional[float]
    """Microseconds from submission until the runtime accepted the chunk; None if not accepted."""
    submit_to_first_motion_us: Optional[float]
    """Microseconds from submission until measured motion began; None if the arm did not move."""
    contact: Optional[Contact]
    """The force felt during the chunk; None when it never ran (rejected, a reset)."""
    grasp: Grasp
    """What the gripper knows about its fingers now (not tied to the last request)."""

class Contact(TypedDict):
    """The magnitude of the filtered external force over a chunk, from acceptance to its end."""

    start_n: float
    """On the chunk's first tick: what was already felt (a held object's weight, a press that
    continues); ``peak_n - start_n`` is what the chunk added."""
    peak_n: float
    mean_n: float
    peak_waypoint: Optional[int]
    """The waypoint (0-based) the arm was heading for at the peak; None when nothing was felt."""

class Grasp(TypedDict):
    """The gripper's own view of its fingers."""

    status: Literal["unknown", "moving", "at_target", "holding", "blocked_opening"]
    """"holding": the fingers stopped short of a closing command (something is between them);
    "at_target": they reached the commanded opening (nothing held, or the object was lost)."""
    object_detected: bool
    """status == "holding"."""
    gripper_fault: Optional[str]
    """A gripper that is its own device (Robotiq 2F-85) reports a fault or went silent: the arm
    holds and chunks are refused until it is clear. None otherwise."""

class Intrinsics(TypedDict):
    """Pinhole intrinsics in pixels, for the image size actually returned."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

class EffectiveSafety(TypedDict):
    """Limits in force now; they win over config/robot.json."""

    profile: Literal["simulation", "franka"]
    joint_position_min_rad: list[float]
    joint_position_max_rad: list[float]
    joint_position_margin_rad: float
    """Targets must stay this far inside the joint limits."""
    joint_velocity_max_rad_s: list[float]
    joint_acceleration_max_rad_s2: list[float]
    speed_scale: float
    """Fraction of the velocity limits motion may use."""
    max_chunk_len: int
    max_joint_step_rad: float
    """Largest change of any joint between consecutive waypoints (and from the measured pose to
    the first one) in a joint chunk."""
    max_tcp_step_m: float
    """Largest TCP move per step in an ee_pose chunk."""
    max_tcp_step_rad: float
    """Largest TCP turn per step in an ee_pose chunk."""
    default_freq_hz: float
    tick_period_s: float
    workspace_min_m: Optional[list[float]]
    """Lower corner of the base-frame box the TCP and arm must stay in; None if the scene sets none."""
    workspace_max_m: Optional[list[float]]
    collision_margin_m: float
    reflex_force_n: Optional[float]
    """Franka: force above which (after >5 N growth during the chunk) the arm stops; None in simulation."""
    operator_force_n: Optional[float]
    """Franka: force above which the arm faults until a person clears it; None in simulation."""

class TcpCalibration(TypedDict):
    """The TCP the runtime uses for ee_pose and ee_pose targets."""

    source: str
    """"file: PATH" (a measured flange-to-TCP file named in config/robot.json) or "description"
    (the robot description's TCP)."""
    flange_from_tcp: list[list[float]]
    """4x4 row-major transform in use, m: TCP frame -> flange frame."""

class CameraCalibration(TypedDict, total=False):
    """One camera: always "source"; "reason" when missing; the file's values when from a file."""

    source: str
    """"file: PATH", "missing" (named in config/robot.json but unreadable or invalid: nothing is
    made up for it), or "scene" (no file; its frames carry the simulator's calibration)."""
    reason: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: Optional[list[float]]
    """k1, k2, p1, p2, k3 (OpenCV order), or None."""
    base_from_camera: list[list[float]]
    """Fixed camera: 4x4, camera optical frame -> base frame."""
    flange_from_camera: list[list[float]]
    """Camera on the hand: 4x4, camera optical frame -> flange frame."""

class Calibration(TypedDict):
    """Where the TCP and each camera's calibration come from (empty until the runtime has
    published its limits)."""

    tcp: TcpCalibration
    cameras: dict[str, CameraCalibration]

class Setup(TypedDict, total=False):
    """What the runtime was started with (empty until it has published its limits)."""

    gym: Optional[str]
    """The gym (the scene's folder name)."""
    robot_config_sha256: Optional[str]
    """SHA-256 (hex) of the bytes of the robot configuration file in force; None: the runtime
    runs on its built-in defaults."""

class _StateBase(TypedDict):
    joint: list[float]
    """7 measured joint positions, rad."""
    ee_pose: list[float]
    """Measured TCP in the robot base frame: x, y, z (m), then axis-angle ax, ay, az (rad); of the
    equivalent axis-angle vectors, the one nearest the previous report (no flips in normal use)."""
    gripper: list[float]
    """One measured value: -1 open ... +1 closed. Short of +1 after closing: something is held."""
    joint_velocity: list[float]
    """7 measured joint velocities, rad/s."""
    timestamp: float
    """Time of the state, s (simulated time in simulation)."""
    external_force_n: list[float]
    """Net contact force the environment exerts on the robot, [fx, fy, fz] in N, base frame,
    low-pass filtered over about 20 ms. The Franka reflexes watch its magnitude."""
    fault: Optional[str]
    """None, or the reason: an operator-required fault (Franka), or a robot side that publishes
    no state (the arm holds; every command returns 0 until it is back)."""
    backend: Literal["simulation", "franka"]
    mode: Literal["wall", "lockstep"]
    control_type: Optional[Literal["joint", "ee_pose"]]
    """Simulation: the type fixed for this episode by its first accepted chunk (None before)."""
    image_timestamp: dict[str, float]
    camera_intrinsics: dict[str, Intrinsics]
    camera_extrinsics: dict[str, list[list[float]]]
    """4x4 base_from_camera per camera; optical frame x right, y down, z forward. The wrist
    camera's matrix follows the arm."""
    control_feedback: ControlFeedback
    effective_safety: EffectiveSafety
    calibration: Calibration
    """Sources of the TCP and camera calibrations; a camera named in config/robot.json whose
    file is missing or invalid reads {"source": "missing", "reason": ...}."""
    setup: Setup
    """The gym and robot configuration in force; memory records are keyed by it."""

class State(_StateBase):
    """get_state() with raw=False."""

    image: dict[str, bytes]
    """PNG bytes (RGB, 8 bit) per requested camera."""

class RawState(_StateBase):
    """get_state(..., raw=True)."""

    image: dict[str, npt.NDArray[np.uint8]]
    """(height, width, 3) RGB per camera. At the native size: a read-only view into shared
    memory (copy with np.array(a) to write); resized requests are copies."""
    depth: dict[str, npt.NDArray[np.float32]]
    """(height, width) planar depth in m along the optical axis, only for cameras that render
    depth. Pixel (u, v) = array[v, u] with depth d is the camera point
    ((u - cx) * d / fx, (v - cy) * d / fy, d)."""

CameraSelection = Union[None, str, Sequence[str], Mapping[str, tuple[int, int]]]
"""None: all cameras; a name; a list of names; {name: (width, height)} resized, 1..4096 each;
[]: numeric state only (about 10 us)."""

class _ActionsRequired(TypedDict):
    actions: list[list[float]]
    """joint: [q1..q7, g] (rad); ee_pose: [x, y, z, ax, ay, az, g] (TCP in base frame, m, rad).
    Absolute targets, plain lists of numbers."""
    type: Literal["joint", "ee_pose"]

class Actions(_ActionsRequired, total=False):
    freq: Union[str, float, int]
    """"" or omitted: 20 Hz. A number (or numeric string) 0.5..1000: upper bound on the waypoint
    rate in Hz; motion is still slowed to speed_scale x the joint velocity limits."""

def reset() -> int:
    """Simulation: restores the robot and the objects and starts a new episode (frees the
    control type). Franka: only refreshes the observation, moves nothing, clears no fault.
    Returns 1 on success, 0 on failure (see control_feedback)."""

@overload
def get_state(cameras: CameraSelection = None, raw: Literal[False] = False) -> State:
    """Observes the robot. cameras: None (all cameras), a name, a list of names, a dict
    name -> (width, height), or [] (numeric state only). Images are PNG bytes; they show the
    scene after the last post_actions/reset finished. Raises TypeError for a wrong cameras type,
    ValueError for an unknown camera or a bad size, ConnectionError when no runtime answers."""

@overload
def get_state(cameras: CameraSelection, raw: Literal[True]) -> RawState:
    """As above, but images are numpy uint8 (h, w, 3) RGB arrays and "depth" holds float32
    (h, w) planar depth in m. Native-size arrays are read-only views into shared memory."""

@overload
def get_state(cameras: CameraSelection = None, *, raw: Literal[True]) -> RawState: ...

@overload
def get_state(cameras: CameraSelection = None, raw: bool = False) -> Union[State, RawState]: ...

def post_actions(cmd: Actions) -> int:
    """Executes a chunk of absolute targets and blocks until it has executed or failed.

    Returns 1 when executed (the measured state reached the last waypoint: joints within 0.005
    rad, or the TCP within 5 mm and 0.02 rad; not proof the task step worked) and 0 when rejected
    or failed (`not reached:` when the arm ended short of the last waypoint); the reason is in get_state([])["control_feedback"]. Every waypoint step (and the
    step from the measured pose to the first one) must stay within max_joint_step_rad (joint) or
    max_tcp_step_m / max_tcp_step_rad (ee_pose). Nothing is clipped into acceptance; a rejected
    chunk moved nothing.

    Raises TypeError (and records it as rejected) when cmd is not a dict, has an unknown key,
    lacks "actions" or "type", "type" is not a string, "freq" is neither a string nor a number,
    or "actions" is not a list of lists of numbers. Other bad commands return 0 without raising.
    """

def instance() -> str:
    """The runtime instance this process talks to (R2G_INSTANCE, default "default")."""
