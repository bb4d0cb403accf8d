"""Identity across observations: `Tracker` keeps each object's number and name for the whole
episode, so the bowl seen at the start is still "#1 orange bowl" while it is held (when only a
slice of it shows and it looks like a cylinder) and after it is put down.

Association is by predicted position, size and colour: a track's predicted position is where it
was last seen, moved with the TCP when it was held or touched by the hand then (or when the
object is gripped or touched now: it may have been picked up or pushed since); each object of
the new observation takes the track that is cheapest to reach (distance / 4 cm + chromaticity
difference / 0.04 + |log volume ratio|), within a gate of 10 cm (15 cm for held or touched
tracks) and 0.08 in chromaticity; greedy, cheapest pair first. A track neither held then nor now
is never given to an object seen with under a fifth of the points it had (a fragment: a shadow,
a sliver beside the fingers); a held one is (the fingers hide most of what they hold). An
object no track claims starts a new track. A track that is not seen stays (it may be hidden by
the hand or inside another object) and is listed in ``scene.unseen``.

Per object the tracker adds ``held_evidence["moves_with_tcp"]`` (True: it moved with the TCP
since the last sighting, within 2 cm; False: it did not; None: not judged, the TCP moved less
than 2 cm since or the track had no TCP position) and ``held_evidence["moved_m"]`` (how far its
centre moved since), and sets ``pushed``: its centre moved more than 1 cm while it was held
neither then nor now, and the cameras now see through at least a fifth of the places its
points were then (the table or what is behind shows there: not merely another side of it in
view, nor a hand in front of it). Moving with the TCP
makes an object held only when the fingers are closed on something now and the object is in
contact with the hand (a held object seen as a slice beside the fingers); an object pushed
along by fingers that did not close on it moves with them too and is not held.

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
from dataclasses import asdict, dataclass, field
from typing import Any, Optional

import numpy as np

from .naming import _chromaticity
from .transforms import ArrayLike
from .voxels import voxel_downsample

TRACKS_ENV = "R2G_PERCEPTION_TRACKS"
_GATE_M = 0.10
_GATE_HELD_M = 0.15
_GATE_CHROMA = 0.08
FRAGMENT_SHARE = 0.2
"""A track held neither then nor now is never given to an object with fewer than this share of
the points it had when last seen."""
PUSHED_M = 0.01
"""An object that moved more than this (m) since its last sighting, held neither then nor now,
is ``pushed`` (when the cameras also see through where it was)."""
VACATED_SHARE = 0.2
"""... at this share of the points it had then, at least."""


@dataclass
class Track:
    """One object's identity: ``id`` and name (``color_name``, ``shape_name``) fixed at first
    sight; ``center``/``dims``/``chroma`` as last seen (base frame, m); ``held`` then; the TCP
    position then; how many observations saw it; the time it was last seen (s); ``points``: how
    many points it had then; ``in_contact`` then; ``sample``: up to 300 of its points then (1 cm
    voxel centres, mm), to tell an object that moved from one seen from another side."""

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
    points: int = 0
    in_contact: bool = False
    sample: list = field(default_factory=list)


def _sample(points: np.ndarray) -> list:
    """Up to 300 points standing for a cloud: its 1 cm voxel centres, rounded to 1 mm."""
    if len(points) == 0:
        return []
    C, _, _ = voxel_downsample(np.asarray(points, dtype=float), 0.01)
    return np.round(C[:: max(1, len(C) // 300)], 3).tolist()


def _vacated(sample: list, views: list) -> Optional[float]:
    """The share of an object's earlier ``sample`` points where a camera now sees through the
    place: the depth at the point's pixel lies more than 1 cm beyond it (table or something
    behind shows where the object was). Points hidden behind something nearer, or on a surface
    seen now, do not count as vacated. None without a sample or a view that sees it."""
    if not sample or not views:
        return None
    from .camera import project_points
    P = np.asarray(sample, dtype=float)
    through = np.zeros(len(P), dtype=bool)
    seen = np.zeros(len(P), dtype=bool)
    for v in views:
        uv, z = project_points(P, v.intrinsics, v.base_from_camera)
        H, W = v.shape
        u, w = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < W) & (w >= 0) & (w < H)
        D = np.full(len(P), np.nan)
        D[ok] = np.asarray(v.depth, dtype=float)[w[ok], u[ok]]
        good = ok & np.isfinite(D) & (D > 0)
        seen |= good
        through |= good & (D > z + 0.01)
    return float(through.sum() / seen.sum()) if seen.any() else None


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
                held_now = bool(o.held)  # this object, not the gripper holding something else
                if not (t.held or held_now) and len(o.points) < FRAGMENT_SHARE * t.points:
                    continue  # a fragment never takes the identity of a whole object
                hand = t.held or held_now or t.in_contact or bool(getattr(o, "in_contact", False))
                d = float(np.linalg.norm(o.center - last))
                if hand:
                    # carried or pushed since (or picked up since): it may also have been put
                    # down where the hand was when it opened, so the nearer prediction counts
                    d = min(d, float(np.linalg.norm(o.center - carried)))
                gate = _GATE_HELD_M if hand else _GATE_M
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
            do = o.center - np.asarray(t.center, dtype=float)
            if t.tcp is not None and tcp_now is not None:
                dt = tcp_now - np.asarray(t.tcp, dtype=float)
                if np.linalg.norm(dt) > 0.02:
                    moved = bool(np.linalg.norm(do - dt) < 0.02)
            o.held_evidence["moves_with_tcp"] = moved
            o.held_evidence["moved_m"] = float(np.linalg.norm(do))
            # carried along while the fingers are closed on something: the object is what they
            # hold even where it shows only as a slice beside them (never for fingers that did
            # not close on anything: an object pushed along moves with them too)
            if moved and o.held_evidence.get("gripper_closed_on_something") and bool(getattr(o, "in_contact", False)):
                o.held = True
            # moved: its centre moved, and the cameras now see through where it was (a part seen
            # now that was hidden before moves the centre too)
            if float(np.linalg.norm(do)) > PUSHED_M and not t.held and not o.held:
                vac = _vacated(t.sample, list(getattr(scene, "views", []) or []))
                o.pushed = vac is not None and vac >= VACATED_SHARE
            o.track_id = t.id
            o.seen_as = f"{o.color_name} {o.shape_name}"
            o.color_name, o.shape_name = t.color_name, t.shape_name
            t.center, t.dims, t.chroma = o.center.tolist(), o.obb.extents.tolist(), chroma_of(o.colors).tolist()
            t.held, t.tcp = bool(o.held), (tcp_now.tolist() if tcp_now is not None else None)
            t.points, t.in_contact = len(o.points), bool(getattr(o, "in_contact", False))
            t.sample = _sample(o.points)
            t.seen += 1
            t.last_seen = self.time
        new_ids = set()
        for oi, o in enumerate(objs):
            if oi in o_used:
                continue
            t = Track(id=self.next_id, color_name=o.color_name, shape_name=o.shape_name,
                      center=o.center.tolist(), dims=o.obb.extents.tolist(), chroma=chroma_of(o.colors).tolist(),
                      held=bool(o.held), tcp=tcp_now.tolist() if tcp_now is not None else None, seen=1,
                      last_seen=self.time, points=len(o.points), in_contact=bool(getattr(o, "in_contact", False)),
                      sample=_sample(o.points))
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
