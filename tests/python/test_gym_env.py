"""r2g_gym against gymnasium's own checker and vector environments, in this process and through
real `r2g up` instances (lockstep), and the project's wheel installed into a fresh venv."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import r2g_gym
from r2g_gym import InvalidActionError

from conftest import R2G, ROOT

os.environ.setdefault("R2G_BIN", str(R2G))
GYMS = r2g_gym.gym_names()


def test_every_gym_of_the_pack_is_registered() -> None:
    assert len(GYMS) == 8
    for g in GYMS:
        assert r2g_gym.env_id(g) in gym.registry
    assert r2g_gym.env_id("pick_block_plate") == "r2g/PickBlockPlate-v0"


@pytest.mark.parametrize("gym_name", GYMS)
def test_check_env_in_process(gym_name: str) -> None:
    env = gym.make(r2g_gym.env_id(gym_name), render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the advice to normalise the action space
        check_env(env.unwrapped)
    env.reset(seed=1)
    frame = env.render()
    assert frame is not None and frame.shape == (480, 640, 3) and frame.dtype == np.uint8 and frame.std() > 5
    env.close()


@pytest.mark.parametrize("gym_name", GYMS)
def test_check_env_through_a_live_lockstep_instance(gym_name: str) -> None:
    # check_env makes two more environments from the spec (render mode, close): each starts
    # and stops an instance of its own.
    env = gym.make(r2g_gym.env_id(gym_name), mode="live")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            check_env(env.unwrapped, skip_render_check=gym_name != "pick_block_plate")
    finally:
        env.close()


def _rollout(env: gym.Env, seed: int, steps: int) -> list[tuple]:
    obs, _ = env.reset(seed=seed)
    out: list[tuple] = [({k: v.copy() for k, v in obs.items()},)]
    rng = np.random.default_rng(seed)
    space = env.action_space
    assert isinstance(space, gym.spaces.Box)
    for _ in range(steps):
        a = rng.uniform(space.low, space.high)
        obs, r, term, trunc, info = env.step(a)
        out.append(({k: v.copy() for k, v in obs.items()}, r, term, trunc, info))
    return out


def _same(a: list[tuple], b: list[tuple]) -> bool:
    for x, y in zip(a, b, strict=True):
        if any(not np.array_equal(x[0][k], y[0][k]) for k in x[0]) or x[1:] != y[1:]:
            return False
    return True


def test_same_seed_same_first_observation_and_trajectory_in_both_modes() -> None:
    local = gym.make("r2g/StackBowls-v0", control="joint_delta")
    live = gym.make("r2g/StackBowls-v0", control="joint_delta", mode="live")
    try:
        a = _rollout(local, 7, 30)
        b = _rollout(local, 7, 30)
        c = _rollout(live, 7, 30)
        assert _same(a, b), "in-process lockstep is not deterministic"
        assert _same(a, c), "a live lockstep instance differs from the in-process episode"
        # Another seed moves the jittered objects: the arm's start is the same, what follows is not
        # guaranteed to be (it is here only if nothing touches an object).
        d = _rollout(local, 8, 1)
        assert np.array_equal(d[0][0]["joint"], a[0][0]["joint"])
        statuses = {step[4]["action_status"] for step in a[1:]}
        assert statuses <= {"reached", "limited", "refused"} and statuses
    finally:
        local.close()
        live.close()


def test_an_absolute_target_too_far_for_one_step_is_refused_with_the_runtime_reason() -> None:
    env = gym.make("r2g/PickBlockPlate-v0")
    obs, _ = env.reset(seed=0)
    far = np.append(obs["joint"], -1.0)
    far[1] += 0.6
    _, _, _, _, info = env.step(far)
    assert info["action_status"] == "refused" and "cap" in info["reason"], info
    near = np.append(obs["joint"], -1.0)
    near[0] += 0.001
    _, _, _, _, info = env.step(near)
    assert info["action_status"] == "reached", info
    env.close()


def test_bad_actions_raise_what_gymnasium_users_expect() -> None:
    env = gym.make("r2g/PickBlockPlate-v0")
    with pytest.raises(gym.error.ResetNeeded):
        env.unwrapped.step(np.zeros(8))
    obs, _ = env.reset(seed=0)
    good = np.append(obs["joint"], -1.0)
    for bad, words in [
        (np.zeros(3), "shape"),
        (np.append(good[:7], np.nan), "NaN"),
        (np.append(good[:7], 2.0), "outside the action space"),
        ("left", "not an array"),
    ]:
        with pytest.raises(ValueError, match=words):
            env.step(bad)
        with pytest.raises(AssertionError):
            env.step(bad)
    assert issubclass(InvalidActionError, ValueError)
    # Nothing of a bad action ran: time has not moved.
    _, _, _, _, info = env.step(good)
    assert info["sim_time_s"] == pytest.approx(0.05)
    env.close()


def test_a_dead_instance_truncates_the_episode_and_the_next_reset_says_why() -> None:
    env = gym.make("r2g/PickBlockPlate-v0", mode="live")
    env.reset(seed=0)
    inst = env.unwrapped._instance
    assert inst is not None
    inst.proc.send_signal(signal.SIGKILL)  # `r2g up` dies; its children follow (PDEATHSIG)
    inst.proc.wait()
    t0 = time.monotonic()
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert truncated and not terminated and reward == 0.0, info
    assert "instance_error" in info and env.unwrapped.instance in info["instance_error"], info
    assert time.monotonic() - t0 < 30
    with pytest.raises(ConnectionError):
        env.reset()
    env.close()


def _our_processes() -> set[int]:
    out = subprocess.run(["pgrep", "-P", str(os.getpid())], capture_output=True, text=True).stdout
    return {int(p) for p in out.split()}


@pytest.mark.parametrize("vector", ["sync", "async"])
def test_vector_environments_run_instances_side_by_side(vector: str) -> None:
    fns = [lambda: gym.make("r2g/PickBlockPlate-v0", mode="live", control="joint_delta") for _ in range(2)]
    fns.append(lambda: gym.make("r2g/PickBlockPlate-v0", control="joint_delta"))
    venv = gym.vector.SyncVectorEnv(fns) if vector == "sync" else gym.vector.AsyncVectorEnv(fns)
    try:
        obs, _ = venv.reset(seed=[3, 3, 3])
        assert obs["joint"].shape == (3, 7)
        if vector == "sync":
            names = [e.unwrapped.instance for e in venv.envs[:2]]
            assert len(set(names)) == 2
        venv.single_action_space.seed(0)
        for _ in range(10):
            a = venv.single_action_space.sample()
            obs, reward, term, trunc, info = venv.step(np.stack([a, a, a]))
        # The same seed and actions: the two live instances and the in-process one agree.
        assert np.array_equal(obs["joint"][0], obs["joint"][1])
        assert np.array_equal(obs["joint"][0], obs["joint"][2])
        assert not trunc.any()
    finally:
        venv.close()
    deadline = time.monotonic() + 15
    while _our_processes() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _our_processes(), "an instance outlived its environment"


def test_the_wheel_installs_into_a_fresh_venv_and_passes_the_checker_there(tmp_path: Path) -> None:
    wheels = sorted((ROOT / "target" / "wheels").glob("r2g_gym-*.whl"))
    assert wheels, "no r2g_gym wheel: make test builds it (scripts/gym-wheel.sh)"
    venv = tmp_path / "user-venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--no-index", "--find-links", str(ROOT / ".wheelhouse"), str(wheels[-1])],
        check=True,
    )
    program = (
        "import sys, warnings, gymnasium as gym, r2g_gym\n"
        "from gymnasium.utils.env_checker import check_env\n"
        "assert 'site-packages' in r2g_gym.__file__ and sys.prefix != sys.base_prefix\n"
        "env = gym.make('r2g/OpenDrawer-v0', render_mode='rgb_array')\n"
        "warnings.simplefilter('ignore')\n"
        "check_env(env.unwrapped)\n"
        "print('CHECKED', r2g_gym.gyms_dir())\n"
    )
    # Nothing of the project's venv or checkout: a clean environment, run from elsewhere.
    env = {"PATH": "/usr/bin:/bin", "MUJOCO_GL": "egl", "HOME": str(tmp_path)}
    r = subprocess.run([str(py), "-c", program], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "CHECKED" in r.stdout and str(venv) in r.stdout, r.stdout
