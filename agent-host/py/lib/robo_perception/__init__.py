"""Local RGB-D perception for `robo` stage programs (numpy + standard library only).

Three layers, each usable on its own:

* **Geometry** - frame conversions (pose <-> 4x4, axis-angle <-> matrix, base <-> camera),
  back-projection of pixels and depth images into the robot base frame, oriented bounding
  boxes (PCA or minimum-area in a support plane), RANSAC plane fitting, normals.
* **Segmentation** - removes the support plane, clusters what stands on it with a voxel-grid
  connected-components pass (optionally split where the colour changes), names each cluster's
  colour and shape, and selects one from a text prompt ("red block", "the bowl on the left",
  "the largest object") or from a pixel. Several cameras (e.g. agentview + wrist) are fused.
* **Grasps** - parallel-jaw candidates on a cluster (top-down slices and antipodal normal
  pairs), checked against the gripper stroke, the fingers' and hand's sweep through the cloud
  and the support plane, scored and returned as TCP poses ``[x, y, z, ax, ay, az]`` in the base
  frame with a pre-grasp pose, ready for ``post_actions`` ee_pose waypoints.

Conventions (those of `robo`): metres, radians, base frame +x forward, +y left, +z up; camera
optical frame x right, y down, z forward; ``camera_extrinsics`` are ``base_from_camera``.
The TCP frame of the Franka Hand: z is the approach direction (out of the fingertips), y is the
axis the fingers move along, x = y cross z. Pointing straight down at yaw 0 is ``[pi, 0, 0]``.

Typical use inside a stage program::

    from robo import get_state
    import robo_perception as rp
    state = get_state(["agentview", "wrist"], raw=True)
    scene = rp.segment_scene(state)
    block = rp.select(scene, "red block")
    grasps = rp.propose_grasps(block, scene, reference_pose=state["ee_pose"])
    best = grasps[0]   # best.pregrasp, best.pose, best.width, best.gripper_open

The package has one module per concept; every name is re-exported here, so ``rp.X`` and
``from robo_perception import X`` work as they did when this was a single file:

* ``hand`` - the gripper model (HandGeometry, FRANKA_HAND, opening <-> gripper command);
* ``transforms`` - frame conversions, point transforms, pose interpolation and waypoints;
* ``camera`` - CameraView, views from ``get_state``, back-projection and projection;
* ``geometry`` - Plane, OrientedBox, hulls and rectangles, RANSAC planes, normals;
* ``voxels`` - voxel grids, down-sampling, connected components, Euclidean clustering;
* ``naming`` - colour and shape names;
* ``segmentation`` - ObjectCluster, SceneSegmentation, segment_scene;
* ``prompts`` - parse_prompt (unknown words are a PromptError), rank_objects, select, segment;
* ``grasps`` - Grasp, grasp_rotation, propose_grasps (steerable by region and closing direction);
* ``placing`` - place_poses (place / pre-place / retreat TCP poses), find_markings;
* ``relations`` - on(obj, support), inside(obj, container): the judge's relations, as seen;
* ``tracking`` - Tracker: object identities and names across the observations of an episode;
* ``report`` - PerceptionWarning (ambiguous prompts, implausible planes);
* ``images`` - projection, markers, crops and PNG files;
* ``robot`` - the Panda's description, forward kinematics, the self-filter (robot_mask).
"""

from __future__ import annotations

from .hand import FRANKA_HAND, GRIPPER_MAX_WIDTH, HandGeometry, gripper_to_width, width_to_gripper
from .transforms import (axis_angle_to_matrix, base_to_camera, camera_to_base, interpolate_poses,
                         invert_transform, matrix_to_axis_angle, matrix_to_pose, pose_to_matrix,
                         rotation_distance, transform_points, waypoints)
from .camera import CameraView, depth_to_points, pixel_to_point, project_points, views_from_state
from .voxels import voxel_downsample
from .geometry import (OrientedBox, Plane, convex_hull_2d, estimate_normals, fit_plane_ransac, min_area_rect,
                       obb_in_plane, obb_pca)
from .naming import COLOR_NAMES, SHAPE_NAMES, color_name, shape_name
from .segmentation import ObjectCluster, SceneSegmentation, segment_scene
from .prompts import PromptError, known_words, parse_prompt, rank_objects, segment, select
from .report import PerceptionWarning
from .tracking import Track, Tracker
from .grasps import Grasp, grasp_rotation, propose_grasps
from .placing import Marking, Placement, find_markings, place_poses
from .relations import Relation, inside, on
from .images import crop_image, draw_markers, encode_png, fingertip_points, project, save_png, show, visible
from .robot import (PANDA, RobotCapsule, RobotDescription, RobotJoint, RobotShapes, capsule_distances, link_poses,
                    robot_distance, robot_mask, robot_shapes, rpy_to_matrix, tcp_matrix, tcp_pose)
from .articulation import HingedPart, PartFace, SlidingPart, fit_face, measure_hinged, measure_sliding

__all__ = [
    # constants
    "GRIPPER_MAX_WIDTH", "HandGeometry", "FRANKA_HAND",
    # frames
    "axis_angle_to_matrix", "matrix_to_axis_angle", "pose_to_matrix", "matrix_to_pose",
    "invert_transform", "transform_points", "base_to_camera", "camera_to_base",
    "rotation_distance", "interpolate_poses", "waypoints", "width_to_gripper", "gripper_to_width",
    # camera geometry
    "CameraView", "views_from_state", "pixel_to_point", "depth_to_points", "project_points",
    # shapes
    "OrientedBox", "Plane", "obb_pca", "obb_in_plane", "convex_hull_2d", "min_area_rect",
    "fit_plane_ransac", "voxel_downsample", "estimate_normals",
    # segmentation
    "ObjectCluster", "SceneSegmentation", "segment_scene", "select", "rank_objects", "segment",
    "color_name", "shape_name", "parse_prompt", "COLOR_NAMES", "SHAPE_NAMES", "PromptError", "known_words",
    "PerceptionWarning", "Track", "Tracker",
    # grasps
    "Grasp", "propose_grasps", "grasp_rotation",
    # placing
    "Placement", "place_poses", "Marking", "find_markings",
    # relations as the judge means them
    "Relation", "on", "inside",
    # images
    "project", "visible", "fingertip_points", "draw_markers", "crop_image", "save_png", "encode_png", "show",
    # the robot's own body (self-filter)
    "PANDA", "RobotDescription", "RobotJoint", "RobotCapsule", "RobotShapes", "link_poses", "tcp_matrix",
    "tcp_pose", "robot_shapes", "capsule_distances", "robot_mask", "robot_distance", "rpy_to_matrix",
    "HingedPart", "SlidingPart", "PartFace", "measure_hinged", "measure_sliding", "fit_face",  # articulated parts
]

# Private helpers stay in their modules (``from robo_perception.voxels import _euclidean_groups``).
