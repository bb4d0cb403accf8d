"""Identity across observations: `Tracker` keeps each object's number and name for the whole
episode, so the bowl seen at the start is still "#1 orange bowl" while it is held (when only a
slice of it shows and it looks like a cylinder) and after it is put down.

Association is by predicted position, size and colour: a track's predicted position is where it
was last seen, moved with the TCP when it was held then (or when the object is gripped now: it
may have been picked up since); each object of the new observation
takes the track that is cheapest to reach (distance / 4 cm + chromaticity difference / 0.04 +
|log volume ratio|), within a gate of 10 cm (15 cm for held tracks) and 0.08 in chromaticity;
greedy, cheapest pair first. An object no track claims starts a new track. A track that is not
seen stays (it may be hidden by the hand or inside another object) and is listed in
``scene.unseen``.

A tracker lives in memory, or in a JSON file that carries it from one stage program to the next
(write-then-rename). In the sandbox the host names that file in ``$R2G_PERCEPTION_TRACKS``
(inside the episode's scratch folder), and `segment_scene` uses it by default. The tracks are
dropped when the observation's time goes backwards (a ``reset()`` starts a new episode) or the
runtime instance changes."""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass
from typing import Any, Optional

import numpy as np

from .naming import _chromaticity
from .transforms import ArrayLike

TRACKS_ENV = "R2G_PERCEPTION_TRACKS"
_GATE_M = 0.10
_GATE_HELD_M = 0.15
_GATE_CHROMA = 0.08


@dataclass
class Track:
    """One object's identity: ``id`` and name (``color_name``, ``shape_name``) fixed at first
    sight; ``center``/``dims``/``chroma`` as last seen (base frame, m); ``held`` then; the TCP
    position then; how many observations saw it; the time it was last seen (s)."""

    id: int
    color_name: str
    shape_name: str
    center: list
    dims: list
    chroma: list
    held: bool
    tcp: Optional[list]
    seen: int
    last_seen: float


def chroma_of(colors: np.ndarray) -> np.ndarray:
    """Mean (r, g) chromaticity of RGB samples (uint8), the colour cue used for association."""
    return _chromaticity(np.asarray(colors).reshape(-1, 3)).mean(axis=0).astype(np.float64)


class Tracker:
    """Tracks objects over the observations of one episode (see the module text)."""

    def __init__(self, path: Optional[str] = None):
        self.path = path
        self.tracks: list[Track] = []
        self.next_id = 0
        self.time = -math.inf
        self.instance = os.environ.get("R2G_INSTANCE", "default")
        self.plane: Optional[list] = None  # [nx, ny, nz, offset] of the last support plane
        if path and os.path.exists(path):
            self._load()

    def _load(self) -> None:
        try:
            with open(self.path) as f:
                d = json.load(f)
            if d.get("instance") != self.instance:
                return
            self.tracks = [Track(**t) for t in d["tracks"]]
            self.next_id = int(d["next_id"])
            self.time = float(d["time"])
            self.plane = d.get("plane")
        except (OSError, ValueError, KeyError, TypeError) as e:
            # a damaged file costs the names, never the observation
            from .report import warn
            warn(f"tracker file {self.path} could not be read ({e}); starting new tracks")
            self.tracks, self.next_id, self.time = [], 0, -math.inf

    def save(self) -> None:
        """Write the tracks to ``path`` (write-then-rename); no-op for an in-memory tracker."""
        if not self.path:
            return
        d = {"instance": self.instance, "next_id": self.next_id, "time": self.time, "plane": self.plane,
             "tracks": [asdict(t) for t in self.tracks]}
        folder = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tracks-", dir=folder)
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(d, f)
            os.replace(tmp, self.path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    def reset(self) -> None:
        self.tracks, self.next_id, self.time, self.plane = [], 0, -math.inf, None

    def update(self, scene: Any, timestamp: Optional[float], tcp: Optional[ArrayLike]) -> None:
        """Give every object of ``scene`` its track's id and name; record what is unseen; add the
        "moves with the TCP" evidence to ``held``; then save."""
        inst = os.environ.get("R2G_INSTANCE", "default")
        if inst != self.instance:
            self.reset()
            self.instance = inst
        if timestamp is not None:
            if timestamp < self.time - 1e-6:
                self.reset()
            self.time = max(self.time, float(timestamp))
        tcp_now = np.asarray(tcp, dtype=float)[:3] if tcp is not None else None
        objs = list(scene.objects)
        cand = []
        for ti, t in enumerate(self.tracks):
            last = np.asarray(t.center, dtype=float)
            # where it would be had it moved with the TCP since (it was held, or is held now)
            carried = last + (tcp_now - np.asarray(t.tcp, dtype=float)) \
                if t.tcp is not None and tcp_now is not None else last
            for oi, o in enumerate(objs):
                grip = bool(o.held or o.held_evidence.get("gripper_closed_on_something"))
                d = float(np.linalg.norm(o.center - last))
                if t.held or grip:
                    # carried since (or picked up since): it may also have been put down where
                    # the hand was when it opened, so the nearer of the two predictions counts
                    d = min(d, float(np.linalg.norm(o.center - carried)))
                gate = _GATE_HELD_M if (t.held or grip) else _GATE_M
                dc = float(np.linalg.norm(chroma_of(o.colors) - np.asarray(t.chroma)))
                if d > gate or dc > _GATE_CHROMA:
                    continue
                vol_o = float(np.prod(np.maximum(o.obb.extents, 0.01)))
                vol_t = float(np.prod(np.maximum(np.asarray(t.dims), 0.01)))
                cost = d / 0.04 + dc / 0.04 + abs(math.log(vol_o / vol_t))
                cand.append((cost, ti, oi))
        cand.sort()
        t_used, o_used = set(), set()
        for cost, ti, oi in cand:
            if ti in t_used or oi in o_used:
                continue
            t_used.add(ti)
            o_used.add(oi)
            t, o = self.tracks[ti], objs[oi]
            moved = None
            if t.tcp is not None and tcp_now is not None:
                dt = tcp_now - np.asarray(t.tcp, dtype=float)
                if np.linalg.norm(dt) > 0.02:
                    do = o.center - np.asarray(t.center, dtype=float)
                    moved = bool(np.linalg.norm(do - dt) < 0.02)
            o.held_evidence["moves_with_tcp"] = moved
            if moved and o.held_evidence.get("gripper_closed_on_something"):
                o.held = True
            o.track_id = t.id
            o.seen_as = f"{o.color_name} {o.shape_name}"
            o.color_name, o.shape_name = t.color_name, t.shape_name
            t.center, t.dims, t.chroma = o.center.tolist(), o.obb.extents.tolist(), chroma_of(o.colors).tolist()
            t.held, t.tcp = bool(o.held), (tcp_now.tolist() if tcp_now is not None else None)
            t.seen += 1
            t.last_seen = self.time
        new_ids = set()
        for oi, o in enumerate(objs):
            if oi in o_used:
                continue
            t = Track(id=self.next_id, color_name=o.color_name, shape_name=o.shape_name,
                      center=o.center.tolist(), dims=o.obb.extents.tolist(), chroma=chroma_of(o.colors).tolist(),
                      held=bool(o.held), tcp=tcp_now.tolist() if tcp_now is not None else None, seen=1,
                      last_seen=self.time)
            self.next_id += 1
            new_ids.add(t.id)
            self.tracks.append(t)
            o.track_id = t.id
            o.seen_as = f"{o.color_name} {o.shape_name}"
        scene.unseen = [t for ti, t in enumerate(self.tracks) if ti not in t_used and t.id not in new_ids]
        self.save()


_DEFAULT: dict = {}


def default_tracker() -> Optional[Tracker]:
    """The tracker `segment_scene` uses when not told otherwise: the file named by
    ``$R2G_PERCEPTION_TRACKS`` (set by the sandbox host), else none."""
    path = os.environ.get(TRACKS_ENV)
    if not path:
        return None
    t = _DEFAULT.get(path)
    if t is None:
        t = _DEFAULT[path] = Tracker(path)
    return t
