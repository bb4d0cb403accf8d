"""Prompts: colour, shape and spatial words of a text prompt, ranking and selecting segmented
objects by prompt and/or pixel, and `segment` (segment_scene then select)."""

from __future__ import annotations

import re
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from .camera import pixel_to_point
from .naming import _color_similarity
from .report import warn
from .segmentation import ObjectCluster, SceneSegmentation, segment_scene
from .transforms import ArrayLike


_COLOR_WORDS = {
    "red": "red", "crimson": "red", "scarlet": "red", "orange": "orange", "yellow": "yellow",
    "gold": "yellow", "golden": "yellow", "green": "green", "lime": "green", "cyan": "cyan",
    "teal": "cyan", "turquoise": "cyan", "blue": "blue", "navy": "blue", "purple": "purple",
    "violet": "purple", "magenta": "pink", "pink": "pink", "brown": "brown", "wooden": "brown",
    "white": "white", "cream": "white", "grey": "grey", "gray": "grey", "silver": "grey",
    "black": "black", "dark": "black",
}
_SHAPE_WORDS = {
    "block": "box", "blocks": "box", "cube": "box", "box": "box", "brick": "box", "cuboid": "box",
    "cylinder": "cylinder", "can": "cylinder", "cup": "cylinder", "mug": "cylinder", "bottle": "cylinder",
    "glass": "cylinder", "jar": "cylinder", "tube": "cylinder", "bowl": "bowl", "bowls": "bowl", "basin": "bowl",
    "plate": "plate", "plates": "plate", "dish": "plate", "disc": "plate", "disk": "plate", "saucer": "plate",
    "flat": "flat", "sheet": "flat", "board": "flat", "card": "flat", "pad": "flat",
    # fixture parts, recognised by shape: a handle is a bar, a door or a drawer front a panel
    "handle": "bar", "handles": "bar", "bar": "bar", "rail": "bar", "rod": "bar", "peg": "bar",
    "knob": "bar", "pull": "bar", "door": "panel", "doors": "panel", "drawer": "panel",
    "drawers": "panel", "panel": "panel", "lid": "panel", "wall": "panel",
    "object": "any", "objects": "any", "thing": "any", "things": "any", "item": "any",
}
_SHAPE_RELATED = {("plate", "flat"), ("box", "flat"), ("bowl", "cylinder"), ("box", "object"),
                  ("cylinder", "object"), ("bowl", "plate"), ("panel", "flat"), ("bar", "flat"),
                  ("bar", "cylinder"), ("panel", "plate")}
# words that carry no meaning for selection (articles, prepositions, "one")
_FILLER_WORDS = {
    "the", "a", "an", "one", "ones", "at", "to", "and", "its", "it", "that",
    "this", "which", "is", "coloured", "colored", "color", "colour", "side", "part", "most",
    "please", "pick", "grasp", "grab", "up", "shaped", "me",
}


# words that relate the object to another one ("the handle of the drawer", "the block on the
# plate"): what follows describes the other object, which selection does not use
_RELATION_WORDS = {"of", "on", "onto", "in", "inside", "into", "with", "under", "beside", "from", "by", "next"}


class PromptError(ValueError):
    """A prompt word `robo_perception` does not understand; the message lists the known words."""


def known_words() -> dict:
    """The words prompts may use, by kind: {"colors": [...], "shapes": [...], "spatial": [...],
    "filler": [...]} (synonyms included)."""
    return {"colors": sorted(_COLOR_WORDS), "shapes": sorted(_SHAPE_WORDS),
            "spatial": sorted(_SPATIAL_WORDS), "relations": sorted(_RELATION_WORDS),
            "filler": sorted(_FILLER_WORDS)}
_SPATIAL_WORDS = {
    "left": "left", "leftmost": "left", "right": "right", "rightmost": "right",
    "front": "front", "forward": "front", "ahead": "front", "back": "back", "behind": "back",
    "rear": "back", "nearest": "nearest", "closest": "nearest", "near": "nearest", "close": "nearest",
    "farthest": "farthest", "furthest": "farthest", "far": "farthest", "largest": "largest",
    "biggest": "largest", "big": "largest", "large": "largest", "bigger": "largest", "larger": "largest",
    "smallest": "smallest", "small": "smallest", "little": "smallest", "tiny": "smallest",
    "smaller": "smallest", "tallest": "tallest", "tall": "tallest", "highest": "tallest",
    "top": "tallest", "lowest": "lowest", "shortest": "lowest", "middle": "middle", "center": "middle",
    "centre": "middle",
}


def parse_prompt(prompt: str) -> dict:
    """Split a text prompt into colour, shape and spatial words (see module docs).

    Raises `PromptError` (a ValueError) naming every word that is none of these nor a filler
    word such as "the" or "of", and listing the words understood: an unknown word is never
    silently ignored (an ignored "rack" would match everything)."""
    if not isinstance(prompt, str):
        raise TypeError(f"the prompt must be a string, not {type(prompt).__name__}")
    words = re.findall(r"[a-z]+", prompt.lower())
    unknown = [w for w in words if w not in _COLOR_WORDS and w not in _SHAPE_WORDS
               and w not in _SPATIAL_WORDS and w not in _FILLER_WORDS and w not in _RELATION_WORDS]
    if unknown:
        k = known_words()
        raise PromptError(
            f"prompt {prompt!r}: {', '.join(repr(w) for w in unknown)} "
            f"{'is' if len(unknown) == 1 else 'are'} not understood. Describe the object by colour, "
            f"shape and position. Colours: {', '.join(k['colors'])}. Shapes and parts: "
            f"{', '.join(k['shapes'])}. Position and size: {', '.join(k['spatial'])}.")
    # the object is named before the first relation word; its noun is the last shape word there
    # ("drawer handle" -> handle); colour and shape words after it describe another object
    cut = next((i for i, w in enumerate(words) if w in _RELATION_WORDS), len(words))
    head, rest = words[:cut], words[cut:]
    colors = [_COLOR_WORDS[w] for w in head if w in _COLOR_WORDS]
    nouns = [_SHAPE_WORDS[w] for w in head if w in _SHAPE_WORDS]
    shapes = [nouns[-1]] if nouns and nouns[-1] != "any" else []
    spatial = [_SPATIAL_WORDS[w] for w in words if w in _SPATIAL_WORDS]
    if "dark" in head and len(colors) > 1:
        colors = [c for c in colors if c != "black"]
    context = [w for w in rest if w in _COLOR_WORDS or w in _SHAPE_WORDS]
    return {"colors": colors, "shapes": shapes, "spatial": spatial, "words": words, "context": context}


def _spatial_key(word: str, objs: list, origin: np.ndarray) -> np.ndarray:
    c = np.array([o.center for o in objs])
    if word == "left":
        return c[:, 1]
    if word == "right":
        return -c[:, 1]
    if word == "front":
        return c[:, 0]
    if word == "back":
        return -c[:, 0]
    dist = np.linalg.norm(c[:, :2] - origin[:2], axis=1)
    if word == "nearest":
        return -dist
    if word == "farthest":
        return dist
    size = np.array([o.size for o in objs])
    if word == "largest":
        return size
    if word == "smallest":
        return -size
    if word == "tallest":
        return np.array([o.top for o in objs])
    if word == "lowest":
        return -np.array([o.top for o in objs])
    if word == "middle":
        return -np.abs(c[:, 1] - np.median(c[:, 1]))
    return np.zeros(len(objs))


def rank_objects(scene: SceneSegmentation, prompt: str, origin: ArrayLike = (0.0, 0.0, 0.0),
                 min_score: float = 0.3) -> list[tuple[ObjectCluster, float]]:
    """Objects that fit the prompt, best first, with a score in [0, 1].

    Score = colour match (1 same name, 0.4 a neighbouring name such as orange/brown or
    white/grey, 0 otherwise) x shape match (1 same, 0.6 related, 0.35 other: shapes of partly
    seen objects are unreliable, colours less so); objects under ``min_score`` are left out, so
    "purple cube" finds nothing when there is only a blue plate.
    Spatial words order the best-scoring objects: left = +y, right = -y, front = +x, back = -x
    (base frame), nearest/farthest from ``origin`` (the robot base by default), largest/smallest
    by box volume, tallest/lowest by top height, middle by y."""
    q = parse_prompt(prompt)
    objs = list(scene.objects)
    if not objs:
        return []
    score = np.ones(len(objs))
    if q["colors"]:
        cs = np.array([max(_color_similarity(c, o.color_name) for c in q["colors"]) for o in objs])
        score *= cs
    if q["shapes"]:
        ss = []
        for o in objs:
            best = 0.35
            for s in q["shapes"]:
                if s == o.shape_name:
                    best = 1.0
                elif (s, o.shape_name) in _SHAPE_RELATED or (o.shape_name, s) in _SHAPE_RELATED:
                    best = max(best, 0.6)
            ss.append(best)
        score *= np.array(ss)
    cand = [i for i in range(len(objs)) if score[i] >= min_score]
    if not cand:
        return []
    top = max(score[i] for i in cand)
    # spatial words order the candidates that match best (and keep the rest after them)
    origin = np.asarray(origin, dtype=float)
    if q["spatial"]:
        best = [i for i in cand if score[i] >= top - 1e-9]
        rest = sorted([i for i in cand if score[i] < top - 1e-9], key=lambda i: -score[i])
        sub = [objs[i] for i in best]
        keys = np.zeros(len(sub))
        for w in q["spatial"]:
            k = _spatial_key(w, sub, origin)
            rng = float(k.max() - k.min())
            keys = keys * 1e3 + ((k - k.min()) / rng if rng > 0 else 0 * k)
        ordered = [best[i] for i in np.argsort(-keys, kind="stable")]
        return [(objs[i], float(score[i])) for i in ordered + rest]
    cand.sort(key=lambda i: (-score[i], -len(objs[i].points)))
    return [(objs[i], float(score[i])) for i in cand]


def select(scene: SceneSegmentation, prompt: Optional[str] = None, point: Optional[tuple] = None,
           camera: Optional[str] = None, origin: ArrayLike = (0.0, 0.0, 0.0),
           snap_radius: float = 0.03) -> Optional[ObjectCluster]:
    """Pick one object by text prompt and/or pixel.

    ``point=(u, v)`` (column, row) in ``camera`` (default: the first view) selects the cluster
    whose mask contains that pixel, or else the cluster nearest (within ``snap_radius``) to the
    pixel's back-projected 3D point. With a prompt, the best-ranked object is returned; with
    neither, the largest. Returns None if nothing matches.
    """
    if point is not None:
        view = scene.views[0] if camera is None else next(v for v in scene.views if v.name == camera)
        u, v = int(round(point[0])), int(round(point[1]))
        H, W = view.shape
        if not (0 <= u < W and 0 <= v < H):
            return None
        hits = [o for o in scene.objects if o.masks[view.name][v, u]]
        if prompt:
            ranked = [o for o, _ in rank_objects(scene, prompt, origin)]
            hits = [o for o in ranked if o in hits] or hits
        if hits:
            return hits[0]
        p = pixel_to_point(u, v, view.depth, view.intrinsics, view.base_from_camera)
        if p is None:
            return None
        best, bd = None, snap_radius
        for o in scene.objects:
            d = float(np.min(np.linalg.norm(o.points[:: max(1, len(o.points) // 3000)] - p, axis=1)))
            if d < bd:
                best, bd = o, d
        return best
    if prompt:
        r = rank_objects(scene, prompt, origin)
        context = parse_prompt(prompt)["context"]
        if context:
            warn(f"select({prompt!r}): relations to other objects are not understood; "
                 f"{' '.join(context)!r} was not used. Select each object by its own words.", scene)
        if not r:
            return None
        tied = [o for o, sc in r if sc >= r[0][1] - 1e-9]
        if len(tied) > 1 and not parse_prompt(prompt)["spatial"]:
            warn(f"select({prompt!r}) is ambiguous: {len(tied)} objects fit equally well ("
                 + "; ".join(o.describe() for o in tied[:4]) + f"); returning #{r[0][0].id}, the one seen best. "
                 "Add a colour, shape or position word (left, nearest, largest, ...).", scene)
        return r[0][0]
    if not scene.objects:
        return None
    return max(scene.objects, key=lambda o: o.size)


def segment(observations: Union[Mapping[str, Any], Sequence[Any]], prompt: Optional[str] = None,
            point: Optional[tuple] = None, camera: Optional[str] = None, **kwargs: Any
            ) -> tuple[Optional[ObjectCluster], SceneSegmentation]:
    """`segment_scene` then `select` in one call: returns (object or None, scene)."""
    scene = segment_scene(observations, **kwargs)
    return select(scene, prompt, point, camera), scene
