"""Gymnasium environments of the Real2Gym gyms.

``import r2g_gym`` registers ``r2g/<GymName>-v0`` for every gym of the pack (``PickBlockPlate``
for ``pick_block_plate``) and ``r2g/Gym-v0`` for any gym folder (``gym=`` names it).
``gymnasium.make("r2g/PickBlockPlate-v0")`` runs in this process (lockstep, no shared memory);
``mode="live"`` drives a live ``r2g up`` instance (started here, or ``instance=`` names one
started with ``--env``). See ``r2g_gym.env.R2GEnv`` for the options.
"""

from __future__ import annotations

import os
from pathlib import Path

# The native module links the libmujoco that the `mujoco` wheel ships; importing mujoco first
# loads that library (its soname then satisfies ours), wherever this package is installed.
import mujoco

import gymnasium

_MUJOCO_VERSION = mujoco.__version__

__all__ = ["gyms_dir", "gym_names", "env_id", "register_folder", "InvalidActionError"]


def _bundled() -> Path:
    return Path(__file__).resolve().parent / "data"


def gyms_dir() -> Path:
    """Where the gym pack is: ``$R2G_GYMS``, the pack inside this wheel, or the checkout's."""
    env = os.environ.get("R2G_GYMS")
    if env:
        return Path(env)
    bundled = _bundled() / "gyms"
    if bundled.is_dir():
        return bundled
    # An editable install (maturin develop) from a checkout: gym-env/python/r2g_gym/.
    return Path(__file__).resolve().parents[3] / "gyms"


def gym_names() -> list[str]:
    """The gyms of the pack: folders of ``gyms_dir()`` holding a ``scene.toml``, sorted."""
    d = gyms_dir()
    if not d.is_dir():
        return []
    return sorted(p.name for p in d.iterdir() if (p / "scene.toml").is_file())


def env_id(gym: str) -> str:
    """``pick_block_plate`` → ``r2g/PickBlockPlate-v0``."""
    camel = "".join(part[:1].upper() + part[1:] for part in gym.replace("-", "_").split("_") if part)
    return f"r2g/{camel}-v0"


MAX_EPISODE_STEPS = 400
"""Steps before an episode is truncated: 20 s at the default 20 Hz."""


def register_folder(folder: str | os.PathLike[str], max_episode_steps: int = MAX_EPISODE_STEPS) -> str:
    """Registers a gym folder (holding ``scene.toml``) as ``r2g/<Name>-v0``; returns the id."""
    path = Path(folder).resolve()
    if not (path / "scene.toml").is_file():
        raise FileNotFoundError(f"{path} holds no scene.toml: not a gym folder")
    eid = env_id(path.name)
    if eid not in gymnasium.registry:
        gymnasium.register(
            id=eid,
            entry_point="r2g_gym.env:R2GEnv",
            kwargs={"gym": str(path)},
            max_episode_steps=max_episode_steps,
        )
    return eid


def _register_pack() -> None:
    for name in gym_names():
        register_folder(gyms_dir() / name)
    if "r2g/Gym-v0" not in gymnasium.registry:
        gymnasium.register(id="r2g/Gym-v0", entry_point="r2g_gym.env:R2GEnv", max_episode_steps=MAX_EPISODE_STEPS)


from r2g_gym.env import InvalidActionError  # noqa: E402

_register_pack()
