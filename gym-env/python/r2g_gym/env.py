"""``R2GEnv``: one gym as a gymnasium environment.

A step is one fixed control period (``period_s``, default 50 ms): the action is the target for
that period, limited like every command the runtime takes (joint position, velocity,
acceleration and jerk limits, step caps, collision and workspace checks), and
``info["action_status"]`` says whether it was ``reached``, ``limited`` or ``refused`` (with the
runtime's reason). The reward is the native evaluator's: a sparse 1.0 once the task's success
rules hold (``terminated``), judged by the simulator side on its own trace; the observation holds
only what a robot reports (joints, TCP pose, gripper, optional camera images), never object
poses.
"""

from __future__ import annotations

import ctypes
import itertools
import json
import os
import select
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from r2g_gym import _native

__all__ = ["R2GEnv", "InvalidActionError"]


class InvalidActionError(ValueError, AssertionError):
    """An action that is not in the action space (wrong shape, NaN, out of bounds). A
    ``ValueError`` for code that validates inputs, and an ``AssertionError`` for code written
    against gymnasium's classic environments, which assert ``action_space.contains(action)``."""


MAX_STEP_TICKS = 10_000
"""The longest step the runtime takes (runtime::controller::MAX_STEP_TICKS)."""
_instances = itertools.count()
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    # The instance ends with the process that started it, even when that one is SIGKILLed.
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def _scene(gym_arg: str) -> Path:
    from r2g_gym import gym_names, gyms_dir

    p = Path(gym_arg)
    if p.is_file():
        return p.resolve()
    if (p / "scene.toml").is_file():
        return (p / "scene.toml").resolve()
    named = gyms_dir() / gym_arg / "scene.toml"
    if named.is_file():
        return named.resolve()
    raise ValueError(
        f"no gym '{gym_arg}': give a gym name ({', '.join(gym_names()) or 'none found'}), a gym folder or a scene file"
    )


def _r2g_binary(explicit: str | None) -> str:
    for candidate in (explicit, os.environ.get("R2G_BIN"), shutil.which("r2g")):
        if candidate:
            return candidate
    checkout = Path(__file__).resolve().parents[3] / "target" / "release" / "r2g"
    if checkout.is_file():
        return str(checkout)
    raise FileNotFoundError(
        "mode='live' starts `r2g up`, and no r2g binary was found: pass r2g=PATH, set R2G_BIN, "
        "put r2g on PATH, or give instance=NAME of an instance started with `r2g up <gym> --env`"
    )


class _Instance:
    """An `r2g up <gym> --env` this environment started and stops."""

    def __init__(
        self, r2g: str, scene: Path, mode: str, render_hz: float, timeout_s: float, robot_config: str | None
    ) -> None:
        self.name = f"gym{os.getpid()}x{next(_instances)}"
        self.log = tempfile.TemporaryFile()
        cmd = [r2g, "up", str(scene), "--mode", mode, "--instance", self.name, "--env", "--render-hz", str(render_hz)]
        if robot_config is not None:
            # The instance limits commands with the same configuration the spaces are built from.
            cmd += ["--robot-config", str(Path(robot_config).resolve())]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=self.log, stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent
        )
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        line = b""
        while not line.startswith(b"READY"):
            left = deadline - time.monotonic()
            if left <= 0 or self.proc.poll() is not None:
                tail = self.log_tail()  # before stop() closes the log
                self.stop()
                raise RuntimeError(f"`{' '.join(cmd)}` did not become ready: {tail}")
            ready, _, _ = select.select([self.proc.stdout], [], [], min(left, 0.5))
            if ready:
                line = self.proc.stdout.readline()

    def log_tail(self) -> str:
        self.log.seek(0)
        return self.log.read().decode(errors="replace")[-2000:].strip() or "(no output)"

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self.log.close()


class R2GEnv(gym.Env[dict[str, Any], np.ndarray]):
    """One gym of the pack (or any gym folder) as a gymnasium environment.

    Args:
        gym: gym name, gym folder or scene file.
        mode: ``"local"``: in this process, lockstep, no shared memory (fast, deterministic);
            ``"live"``: through a live instance (``r2g up``; the real runtime and sim-host).
        control: ``"joint"`` (absolute joint targets + gripper), ``"joint_delta"`` (joint
            changes from the measured joints, at most ``max_delta_rad`` each, + gripper) or
            ``"ee_pose"`` (absolute TCP pose in the base frame: xyz, axis-angle, gripper).
        period_s: the control period one step lasts (a whole number of physics steps).
        cameras: camera names whose RGB images the observation holds (``obs["images"]``).
        image_size: (height, width) of those images.
        render_mode: ``"rgb_array"`` or None; ``render_camera``/``render_size`` choose the view.
        reward: ``"sparse"`` (1.0 on success) or ``"checks"`` (the fraction of the success
            rules that hold; still terminated on success).
        instance: live mode: drive this running instance (``r2g up <gym> --env``) instead of
            starting one.
        live_mode: ``"lockstep"`` (deterministic) or ``"wall"`` for an instance started here.
        robot_config: a ``robot.json`` (profile, step caps); default: the shipped one.
        r2g: the ``r2g`` binary for live mode (default: ``$R2G_BIN``, PATH, the checkout's).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        gym: str,
        mode: str = "local",
        control: str = "joint",
        period_s: float = 0.05,
        cameras: Sequence[str] = (),
        image_size: tuple[int, int] = (96, 128),
        render_mode: str | None = None,
        render_camera: str = "agentview",
        render_size: tuple[int, int] = (480, 640),
        reward: str = "sparse",
        max_delta_rad: float = 0.05,
        instance: str | None = None,
        live_mode: str = "lockstep",
        robot_config: str | None = None,
        r2g: str | None = None,
        start_timeout_s: float = 60.0,
    ) -> None:
        if mode not in ("local", "live"):
            raise ValueError(f"mode must be 'local' or 'live', not {mode!r}")
        if control not in ("joint", "joint_delta", "ee_pose"):
            raise ValueError(f"control must be 'joint', 'joint_delta' or 'ee_pose', not {control!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', not {render_mode!r}")
        if reward not in ("sparse", "checks"):
            raise ValueError(f"reward must be 'sparse' or 'checks', not {reward!r}")
        if live_mode not in ("lockstep", "wall"):
            raise ValueError(f"live_mode must be 'lockstep' or 'wall', not {live_mode!r}")
        self.render_mode = render_mode
        self.mode, self.control, self.reward_kind = mode, control, reward
        self.cameras = list(cameras)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.render_camera, self.render_size = render_camera, (int(render_size[0]), int(render_size[1]))
        self._instance: _Instance | None = None
        self._native: Any = None
        self._closed = False
        scene = _scene(gym)
        native_control = "ee_pose" if control == "ee_pose" else "joint"
        if mode == "local":
            self._native = _native.Local(str(scene), native_control, robot_config)
        else:
            if instance is None:
                render_hz = 100.0 if (self.cameras or render_mode) else 0.0
                self._instance = _Instance(
                    _r2g_binary(r2g), scene, live_mode, render_hz, start_timeout_s, robot_config
                )
                instance = self._instance.name
            try:
                self._native = _native.Live(instance, str(scene), native_control, robot_config)
            except BaseException:
                self.close()
                raise
        self.instance = instance
        spec = self._native.spec()
        self.gym_name: str = spec["gym"]
        ticks = period_s / spec["timestep_s"]
        if period_s <= 0 or abs(ticks - round(ticks)) > 1e-6:
            raise ValueError(f"period_s = {period_s} is not a whole number of {spec['timestep_s']} s physics steps")
        self.period_ticks = int(round(ticks))
        if self.period_ticks > MAX_STEP_TICKS:
            raise ValueError(f"period_s = {period_s} is longer than a step may last ({MAX_STEP_TICKS} physics steps)")
        self.period_s = period_s
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / period_s))}
        unknown = [c for c in self.cameras + ([render_camera] if render_mode else []) if c not in spec["cameras"]]
        if unknown:
            raise ValueError(f"no camera {unknown[0]!r}: this gym has {', '.join(sorted(spec['cameras']))}")
        q_min = np.array(spec["q_min"]) + spec["q_margin"]
        q_max = np.array(spec["q_max"]) - spec["q_margin"]
        dq_max = np.array(spec["dq_max"])
        if control == "joint":
            low, high = np.append(q_min, -1.0), np.append(q_max, 1.0)
        elif control == "joint_delta":
            low, high = np.append(np.full(7, -max_delta_rad), -1.0), np.append(np.full(7, max_delta_rad), 1.0)
        else:
            low = np.array([-1.0, -1.0, -0.2, -np.pi, -np.pi, -np.pi, -1.0])
            high = np.array([1.0, 1.0, 1.2, np.pi, np.pi, np.pi, 1.0])
        self.action_space = spaces.Box(low=low, high=high, dtype=np.float64)
        four_pi = 4 * np.pi
        obs: dict[str, spaces.Space[Any]] = {
            "joint": spaces.Box(np.array(spec["q_min"]) - 0.1, np.array(spec["q_max"]) + 0.1, dtype=np.float64),
            "joint_vel": spaces.Box(-4 * dq_max, 4 * dq_max, dtype=np.float64),
            "ee_pose": spaces.Box(
                np.array([-2.0, -2.0, -2.0, -four_pi, -four_pi, -four_pi]),
                np.array([2.0, 2.0, 2.0, four_pi, four_pi, four_pi]),
                dtype=np.float64,
            ),
            "gripper": spaces.Box(-1.1, 1.1, shape=(1,), dtype=np.float64),
        }
        if self.cameras:
            h, w = self.image_size
            obs["images"] = spaces.Dict(
                {c: spaces.Box(0, 255, shape=(h, w, 3), dtype=np.uint8) for c in self.cameras}
            )
        self.observation_space = spaces.Dict(obs)
        self._last_obs: dict[str, Any] | None = None
        self._dead: str | None = None

    # -- gymnasium API ---------------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        if options:
            raise ValueError(f"reset takes no options, got {sorted(options)}")
        self._check_open()
        # The scene's augmentation seed: the one given (0: the scene as written), else drawn
        # from the environment's generator so that unseeded resets still vary.
        episode_seed = int(seed) if seed is not None else int(self.np_random.integers(1, 2**62))
        if episode_seed < 0:
            raise ValueError(f"seed must be >= 0, not {episode_seed}")
        try:
            state = self._native.reset(episode_seed)
        except ConnectionError as e:
            self._dead = str(e)
            raise ConnectionError(f"{self._where()}: {e}") from e
        # A reset that went through: the instance answers again (a refused one raised
        # RuntimeError above and left the episode as it was).
        self._dead = None
        self._last_obs = self._observation(state)
        return self._copy(self._last_obs), {"episode_seed": episode_seed, "sim_time_s": state["sim_time_s"]}

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        self._check_open()
        if self._last_obs is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        a = self._checked(action)
        if self._dead is not None:
            return self._copy(self._last_obs), 0.0, False, True, {"instance_error": self._dead}
        if self.control == "joint_delta":
            target = np.append(self._last_obs["joint"] + a[:7], a[7])
        else:
            target = a
        try:
            state, outcome = self._native.step([float(v) for v in target], self.period_ticks)
            success, verdict_json = self._native.evaluate()
        except ConnectionError as e:
            # A dead or silent instance ends the episode: truncated, never a hang.
            self._dead = f"{self._where()}: {e}"
            return self._copy(self._last_obs), 0.0, False, True, {"instance_error": self._dead}
        self._last_obs = self._observation(state)
        verdict = json.loads(verdict_json)
        checks = {name: bool(c.get("pass")) for name, c in verdict.get("checks", {}).items()}
        if self.reward_kind == "sparse":
            reward = 1.0 if success else 0.0
        else:
            reward = sum(checks.values()) / max(len(checks), 1)
        info = {
            "action_status": outcome["status"],
            "reason": outcome["reason"],
            "target_error": outcome["error"],
            "success": bool(success),
            "checks": checks,
            "sim_time_s": state["sim_time_s"],
        }
        return self._copy(self._last_obs), float(reward), bool(success), False, info

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        if self.render_mode is None:
            gym.logger.warn("render() without a render_mode: make the environment with render_mode='rgb_array'")
            return None
        self._check_open()
        h, w = self.render_size
        return self._image(self.render_camera, h, w)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._native = None
        if self._instance is not None:
            self._instance.stop()
            self._instance = None

    # -- helpers ---------------------------------------------------------------------------

    def _where(self) -> str:
        return f"r2g instance '{self.instance}'" if self.mode == "live" else f"gym {self.gym_name}"

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("this environment is closed")

    def _checked(self, action: Any) -> np.ndarray:
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise InvalidActionError(f"the action is not an array of numbers: {e}") from None
        want = self.action_space.shape
        if a.shape != want:
            raise InvalidActionError(f"the action has shape {a.shape}, the action space {want}")
        bad = ~np.isfinite(a)
        if bad.any():
            raise InvalidActionError(f"the action holds NaN or infinity at index {int(np.argmax(bad))}: {a.tolist()}")
        space = self.action_space
        assert isinstance(space, spaces.Box)
        out = (a < space.low - 1e-9) | (a > space.high + 1e-9)
        if out.any():
            i = int(np.argmax(out))
            raise InvalidActionError(
                f"action[{i}] = {a[i]:.6g} is outside the action space [{space.low[i]:.6g}, {space.high[i]:.6g}]"
            )
        return a

    def _image(self, camera: str, h: int, w: int) -> np.ndarray:
        try:
            rgb = self._native.render(camera, w, h)
        except ConnectionError as e:
            self._dead = f"{self._where()}: {e}"
            return np.zeros((h, w, 3), dtype=np.uint8)
        return np.frombuffer(rgb, dtype=np.uint8).reshape(h, w, 3).copy()

    def _observation(self, state: dict[str, Any]) -> dict[str, Any]:
        obs: dict[str, Any] = {
            "joint": np.array(state["joint"], dtype=np.float64),
            "joint_vel": np.array(state["joint_vel"], dtype=np.float64),
            "ee_pose": np.array(state["ee_pose"], dtype=np.float64),
            "gripper": np.array(state["gripper"], dtype=np.float64),
        }
        if self.cameras:
            h, w = self.image_size
            obs["images"] = {c: self._image(c, h, w) for c in self.cameras}
        return obs

    @staticmethod
    def _copy(obs: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in obs.items():
            out[k] = R2GEnv._copy(v) if isinstance(v, dict) else v.copy()
        return out

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
