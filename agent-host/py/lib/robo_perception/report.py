"""Warnings: what the library noticed but could still answer (an ambiguous prompt, an
implausible support plane, a track that vanished). They are `PerceptionWarning`s, printed every
time (to stderr, so a stage program's output shows them) and kept in ``scene.warnings``; a
program that wants them as errors runs ``warnings.simplefilter("error", PerceptionWarning)``."""

from __future__ import annotations

import warnings
from typing import Any, Optional


class PerceptionWarning(UserWarning):
    """Something `robo_perception` answered but would not trust without a second look."""


warnings.simplefilter("always", PerceptionWarning)


def warn(message: str, scene: Optional[Any] = None) -> None:
    """Issue a PerceptionWarning and keep its text in ``scene.warnings`` when a scene is given."""
    if scene is not None and hasattr(scene, "warnings"):
        scene.warnings.append(message)
    warnings.warn(message, PerceptionWarning, stacklevel=3)
