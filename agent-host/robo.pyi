"""Type stubs of `robo`, the agent-facing robot API of the Real2Gym runtime.

Generated code uses only ``from robo import reset, get_state, post_actions``. See
robot-skill/api/README.md for the full contract.
"""
from typing import Literal, Mapping, Sequence, TypedDict, Union

SCHEMA_VERSION: int

Status = Literal[
    "accepted", "executed", "rejected", "failed", "recovered_replan_required", "operator_required", "none"
]

class ControlFeedback(TypedDict):
    status: Status
    """What became of the last request."""
    reason: str
    """Why, in words a model can act on (which field, which limit, by how much); "" on success."""
    executed: int
    """Waypoints fully executed."""
    request_id: int
    final_joint_error_rad: float

class Intrinsics(TypedDict):
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

class EffectiveSafety(TypedDict, total=False):
    joint_position_min_rad: list[float]
    joint_position_max_rad: list[float]
    joint_position_margin_rad: float
    joint_velocity_max_rad_s: list[float]
    joint_acceleration_max_rad_s2: list[float]
    speed_scale: float
    max_chunk_len: int
    default_freq_hz: float
    tick_period_s: float

class State(TypedDict):
    joint: list[float]
    """7 joint positions, rad."""
    ee_pose: list[float]
    """TCP in the robot base frame: x, y, z (m), then axis-angle ax, ay, az (rad)."""
    gripper: list[float]
    """One value: -1 open ... +1 closed."""
    timestamp: float
    """Time of the state, s (simulated time in lockstep mode)."""
    joint_velocity: list[float]
    backend: str
    mode: Literal["wall", "lockstep"]
    control_type: Union[Literal["joint", "ee_pose"], None]
    """The control type fixed for this episode, once the first chunk was accepted."""
    image: dict[str, bytes]
    """PNG bytes per requested camera."""
    image_timestamp: dict[str, float]
    camera_intrinsics: dict[str, Intrinsics]
    camera_extrinsics: dict[str, list[list[float]]]
    """4x4 base_from_camera per camera; the optical frame has x right, y down, z forward."""
    control_feedback: ControlFeedback
    effective_safety: EffectiveSafety

CameraSelection = Union[None, str, Sequence[str], Mapping[str, tuple[int, int]]]

class Actions(TypedDict):
    actions: Sequence[Sequence[float]]
    """joint: [q1..q7, g] (rad); ee_pose: [x, y, z, ax, ay, az, g] (m, rad); absolute targets."""
    type: Literal["joint", "ee_pose"]
    freq: Union[str, float, int]
    """"" for 20 Hz, or an upper bound on the waypoint rate in Hz."""

def reset() -> int:
    """Restores the scene (simulation profile). 1 on success, 0 on failure (see control_feedback)."""

def get_state(cameras: CameraSelection = None) -> State:
    """Observes the robot. cameras: None (all), a name, a list of names, a dict
    name -> (width, height), or [] (numeric state only)."""

def post_actions(cmd: Actions) -> int:
    """Executes a chunk of absolute targets and blocks until it finished: 1 executed, 0 rejected
    or failed (the reason is in get_state()["control_feedback"]). Never clipped into acceptance."""

def instance() -> str:
    """The instance this process talks to (R2G_INSTANCE, default "default")."""
