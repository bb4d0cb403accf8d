"""Skills for `robo` stage programs (numpy + standard library, importable in the sandbox).

A skill (robot-skill/skills/README.md) carries object-relative motion rules: "put the TCP at this
offset and yaw from this feature of that object". This package binds such rules to the objects
`robo_perception` sees now and runs a skill's procedure without a model:

* ``frames`` - anchor frames on oriented boxes (centre, top face, support plane, major axis),
  ``bind`` (rule + object seen now -> TCP pose) and its inverse ``relate``;
* ``execute`` - ``SkillRunner`` / ``run_skill``: observe, bind, move, check effects, retry;
* ``lint`` - the check that refuses base-frame coordinates written into a skill's code.

    import robo_skills as rs
    rs.run_skill(skill_dict)                       # the whole procedure, one JSON line per event
    runner = rs.SkillRunner(skill_dict)
    scene, state = runner.observe()
    pose = runner.target("approach_item", scene, state)   # for an ee_pose waypoint
"""

from __future__ import annotations

from .frames import FEATURES, Anchor, AnchorError, bind, frame, relate, same_grasp
from .execute import CAMERAS, SkillRunner, StageFailed, run_skill
from .lint import LintError, check_code

__all__ = ["FEATURES", "Anchor", "AnchorError", "bind", "frame", "relate", "same_grasp",
           "CAMERAS", "SkillRunner", "StageFailed", "run_skill", "LintError", "check_code"]
