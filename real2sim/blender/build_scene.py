"""Builds a gym's scene in Blender from the document `r2g blender` exports, keyframes every body
and camera so the physics plays back, saves the .blend and renders chosen instants with Cycles on
the CPU. Runs in the Python of .venv-blender (Blender as a Python module, bpy 5.0.1).

The document (written by real2sim/src/blender.rs, `export`) holds MuJoCo's drawn geoms (primitive
type and size, or a mesh's vertices and faces), their colours and bodies, per state every moving
body's and camera's world pose, the cameras' intrinsics and resolution, and the lights.

Colours follow MuJoCo's renderer rather than a photographic camera: the view transform is Raw
(a pixel's byte is 255 times its linear value, as in MuJoCo's OpenGL output), MuJoCo's rgba is the
surface's base colour as it is, and the headlight's ambient term is the world's light seen by
everything but camera rays, which see the sky's mean colour. A 2-D texture on a plane (the
checkered floor) is drawn from its pixels with the texture coordinates MuJoCo generates there
(`plane_uvs`), times the geom's colour; every other texture (cube and skybox textures, textures
on other geoms) only tints the colour with its mean, which the export has already applied.
Lights: a spot light becomes a Cycles spot light with MuJoCo's cone (cutoff), dimmed off its
axis by the cosine to MuJoCo's exponent, whose strength does not fall off with distance (MuJoCo's
default attenuation is none; other attenuations are not reproduced); a directional light, and
the point and image lights that MuJoCo's OpenGL renderer does not set up, become suns; the
headlight is a sun along the camera's view. Strengths are set so that a white surface facing a
light reflects its diffuse colour, as in MuJoCo.

Masks: a second render of every shot draws each object in a flat colour (red = 8 x (object index
+ 1), everything else black), one sample per pixel at the pixel's centre, with no denoising.
"""

import argparse
import base64
import json
import math
import os
import sys
import time

import bpy  # first: bmesh and mathutils load with it
import bmesh
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from plane_uv import plane_st  # noqa: E402

LABEL_STEP = 8


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", required=True, help="the document r2g blender exports")
    p.add_argument("--summary", required=True, help="where to write the summary JSON")
    p.add_argument("--blend", help="the .blend to write")
    p.add_argument("--render", help="folder for rgb/ and label/ PNGs")
    p.add_argument("--samples", type=int, default=16)
    p.add_argument("--percent", type=int, default=50)
    p.add_argument("--shot", action="append", default=[], help="ID:STATE:CAMERA")
    p.add_argument("--threads", type=int, default=0, help="render threads (0: Blender decides)")
    return p.parse_args(argv)


def fail(msg):
    print(f"build_scene: {msg}", file=sys.stderr)
    sys.exit(2)


# ---------------------------------------------------------------------------------------------
# Geometry


def primitive_mesh(name, kind, size):
    bm = bmesh.new()
    if kind == "box":
        bmesh.ops.create_cube(bm, size=2.0)
        for v in bm.verts:
            v.co.x *= size[0]
            v.co.y *= size[1]
            v.co.z *= size[2]
    elif kind == "sphere":
        bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=size[0])
    elif kind == "ellipsoid":
        bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=1.0)
        for v in bm.verts:
            v.co.x *= size[0]
            v.co.y *= size[1]
            v.co.z *= size[2]
    elif kind == "cylinder":
        bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=48, radius1=size[0], radius2=size[0],
                              depth=2.0 * size[1])
    elif kind == "capsule":
        # A tube and two spheres at its ends: the same surface MuJoCo draws.
        bmesh.ops.create_cone(bm, cap_ends=False, cap_tris=False, segments=32, radius1=size[0], radius2=size[0],
                              depth=2.0 * size[1])
        for z in (size[1], -size[1]):
            r = bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=size[0])
            bmesh.ops.translate(bm, verts=r["verts"], vec=(0.0, 0.0, z))
    elif kind == "plane":
        # MuJoCo's plane: half sizes in x and y (a zero size is drawn as a large plane).
        sx = size[0] if size[0] > 0 else 50.0
        sy = size[1] if size[1] > 0 else 50.0
        vs = [bm.verts.new(c) for c in ((-sx, -sy, 0), (sx, -sy, 0), (sx, sy, 0), (-sx, sy, 0))]
        bm.faces.new(vs)
    else:
        fail(f"unknown primitive '{kind}'")
    me = bpy.data.meshes.new(name)
    bm.to_mesh(me)
    bm.free()
    if kind in ("sphere", "ellipsoid", "capsule"):
        me.shade_smooth()
    elif kind == "cylinder":
        me.set_sharp_from_angle(angle=math.radians(40))
    return me


def mesh_from_arrays(name, m):
    v = np.frombuffer(base64.b64decode(m["vertices_f32le_b64"]), dtype="<f4")
    f = np.frombuffer(base64.b64decode(m["faces_i32le_b64"]), dtype="<i4")
    if v.size != 3 * m["vertices"] or f.size != 3 * m["faces"]:
        fail(f"mesh {name}: {v.size // 3} vertices and {f.size // 3} faces, the document says "
             f"{m['vertices']} and {m['faces']}")
    if f.size and (f.min() < 0 or f.max() >= m["vertices"]):
        fail(f"mesh {name}: a face names a vertex that does not exist")
    me = bpy.data.meshes.new(name)
    me.from_pydata(v.reshape(-1, 3).tolist(), [], f.reshape(-1, 3).tolist())
    me.validate()
    # MuJoCo draws meshes with smooth normals; creases (as on the Panda's links) stay sharp.
    me.set_sharp_from_angle(angle=math.radians(40))
    return me


def material(name, rgba, image=None):
    """A surface of colour `rgba`; with `image`, the image (looked up at the mesh's UVs,
    repeated) times that colour, as MuJoCo modulates a texture by the geom's colour."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (rgba[0], rgba[1], rgba[2], 1.0)
    bsdf.inputs["Roughness"].default_value = 0.5
    bsdf.inputs["Alpha"].default_value = rgba[3]
    mat.diffuse_color = tuple(rgba)
    if image is not None:
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = image
        tex.interpolation = "Linear"
        tex.extension = "REPEAT"
        tint = nt.nodes.new("ShaderNodeVectorMath")
        tint.operation = "MULTIPLY"
        tint.inputs[1].default_value = (rgba[0], rgba[1], rgba[2])
        nt.links.new(tex.outputs["Color"], tint.inputs[0])
        nt.links.new(tint.outputs["Vector"], bsdf.inputs["Base Color"])
    return mat


def texture_image(name, t):
    """A 2-D texture of the document (RGB bytes, MuJoCo's first row first) as a packed Blender
    image whose first row is v = 0, as MuJoCo's first row is texture coordinate t = 0."""
    w, h = int(t["width"]), int(t["height"])
    raw = np.frombuffer(base64.b64decode(t["rgb_b64"]), dtype=np.uint8)
    if w <= 0 or h <= 0 or raw.size != 3 * w * h:
        fail(f"texture {name}: {raw.size} bytes for {w}x{h} RGB pixels")
    img = bpy.data.images.new(name, width=w, height=h, alpha=False)
    # MuJoCo draws the bytes as they are (sRGB ones decoded first), as Raw view shows them.
    img.colorspace_settings.name = "sRGB" if t.get("srgb") else "Non-Color"
    px = np.ones((w * h, 4), dtype=np.float32)
    px[:, :3] = raw.reshape(-1, 3) / np.float32(255.0)
    img.pixels.foreach_set(px.ravel())
    img.pack()
    return img


def plane_uvs(me, size, t):
    """The plane's UVs: the texture coordinates MuJoCo gives it (`plane_uv.plane_st`)."""
    uv = me.uv_layers.new(name="mujoco")
    for loop in me.loops:
        co = me.vertices[loop.vertex_index].co
        uv.data[loop.index].uv = plane_st(co.x, co.y, size, t["repeat"], t["uniform"])


# ---------------------------------------------------------------------------------------------
# Animation


def keyframe(obj, frames, poses):
    """Keys location and quaternion of `obj` at `frames` from rows (x, y, z, qw, qx, qy, qz)."""
    from bpy_extras import anim_utils

    obj.rotation_mode = "QUATERNION"
    obj.animation_data_create()
    act = bpy.data.actions.new(obj.name + "_motion")
    obj.animation_data.action = act
    slot = obj.animation_data.action_slot
    if slot is None:
        slot = act.slots.new(id_type="OBJECT", name=obj.name)
        obj.animation_data.action_slot = slot
    bag = anim_utils.action_ensure_channelbag_for_slot(act, slot)
    n = len(frames)
    p = np.asarray(poses, dtype=np.float64)
    # Quaternions q and -q are one rotation: keep consecutive ones on the same side so the
    # interpolation between keys takes the short way.
    q = p[:, 3:7].copy()
    for i in range(1, n):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    fr = np.asarray(frames, dtype=np.float32)
    for path, cols in (("location", p[:, 0:3]), ("rotation_quaternion", q)):
        for i in range(cols.shape[1]):
            fc = bag.fcurves.new(path, index=i)
            fc.keyframe_points.add(n)
            co = np.empty(2 * n, dtype=np.float32)
            co[0::2] = fr
            co[1::2] = cols[:, i]
            fc.keyframe_points.foreach_set("co", co)
            fc.keyframe_points.foreach_set("interpolation", [1] * n)  # LINEAR
            fc.update()
    obj.location = p[0, 0:3]
    obj.rotation_quaternion = q[0]


def frame_numbers(times, fps):
    """Blender frame of each state: 1 + its time since the first state at `fps`, kept increasing."""
    frames = []
    for t in times:
        f = 1 + int(round((t - times[0]) * fps))
        if frames and f <= frames[-1]:
            f = frames[-1] + 1
        frames.append(f)
    return frames


# ---------------------------------------------------------------------------------------------
# Cameras


def set_intrinsics(cam_data, scene, c, percent):
    """Blender camera from pinhole intrinsics (pixel-index convention: the centre of pixel (u, v)
    is the point (u, v), so the image centre is ((w - 1) / 2, (h - 1) / 2))."""
    w, h = c["width"], c["height"]
    fx, fy, cx, cy = c["fx"], c["fy"], c["cx"], c["cy"]
    scene.render.resolution_x = w
    scene.render.resolution_y = h
    scene.render.resolution_percentage = percent
    # fx != fy: Blender stretches pixels instead (a pixel aspect of fx / fy, y over x).
    aspect = fx / fy
    if aspect > 1:
        scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = 1.0, aspect
    else:
        scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = 1.0 / aspect, 1.0
    cam_data.sensor_fit = "AUTO"
    cam_data.sensor_width = 36.0
    px, py = scene.render.pixel_aspect_x, scene.render.pixel_aspect_y
    horizontal = px * w >= py * h
    view = w if horizontal else (py / px) * h
    cam_data.lens = fx * cam_data.sensor_width / view
    cam_data.shift_x = -(cx - (w - 1) / 2.0) / view
    cam_data.shift_y = (cy - (h - 1) / 2.0) * aspect / view
    cam_data.clip_start = 0.01
    cam_data.clip_end = 50.0


# ---------------------------------------------------------------------------------------------
# World and lights


def sun(name, direction, strength, shadow):
    light = bpy.data.lights.new(name, "SUN")
    light.energy = strength
    light.angle = 0.0
    light.use_shadow = bool(shadow)
    obj = bpy.data.objects.new(name, light)
    obj.rotation_mode = "QUATERNION"
    obj.rotation_quaternion = track_quat(direction)
    return obj


# Cycles' point and spot lights: a white surface facing one of power P at the distance where the
# falloff is constant reflects P / (4 pi^2) (measured: 1.000 for P = 4 pi^2).
POINT_POWER_PER_UNIT = 4.0 * math.pi ** 2


def spot(name, l):
    """MuJoCo's spot light as Cycles draws it: a cone of half angle `cutoff_deg`, inside which
    the light is dimmed by cos(angle off the axis) ** exponent, as OpenGL's fixed-function spot
    light that MuJoCo's renderer sets up; its strength does not fall off with distance (the
    constant output of the Light Falloff node), as MuJoCo's default attenuation (1, 0, 0)."""
    d = max(max(l["diffuse"]), 1e-9)
    att = l.get("attenuation", [1.0, 0.0, 0.0])
    if any(abs(a - b) > 1e-9 for a, b in zip(att, (1.0, 0.0, 0.0))):
        print(f"build_scene: light {name}: attenuation {att} is not reproduced (drawn as (1, 0, 0): "
              "no falloff with distance)", file=sys.stderr)
    light = bpy.data.lights.new(name, "SPOT")
    light.energy = POINT_POWER_PER_UNIT * max(l["diffuse"])
    light.color = [c / d for c in l["diffuse"]]
    light.spot_size = min(2.0 * math.radians(l["cutoff_deg"]), math.pi)
    light.spot_blend = 0.0
    light.shadow_soft_size = 0.0
    light.use_shadow = bool(l["cast_shadow"])
    if hasattr(light, "use_soft_falloff"):
        light.use_soft_falloff = False
    light.use_nodes = True
    nt = light.node_tree
    emission = nt.nodes["Emission"]
    falloff = nt.nodes.new("ShaderNodeLightFalloff")
    falloff.inputs["Strength"].default_value = 1.0
    # A light's Normal coordinate is the direction it shines along, in the light's frame, whose
    # -z is its axis.
    coord = nt.nodes.new("ShaderNodeTexCoord")
    xyz = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(coord.outputs["Normal"], xyz.inputs[0])

    def math_node(op, a, b):
        n = nt.nodes.new("ShaderNodeMath")
        n.operation = op
        for k, v in enumerate((a, b)):
            if isinstance(v, (int, float)):
                n.inputs[k].default_value = v
            else:
                nt.links.new(v, n.inputs[k])
        return n.outputs[0]

    cos_axis = math_node("MAXIMUM", math_node("MULTIPLY", xyz.outputs["Z"], -1.0), 0.0)
    dim = math_node("POWER", cos_axis, float(l["exponent"]))
    nt.links.new(math_node("MULTIPLY", dim, falloff.outputs["Constant"]), emission.inputs["Strength"])
    obj = bpy.data.objects.new(name, light)
    obj.rotation_mode = "QUATERNION"
    obj.rotation_quaternion = track_quat(l["dir"])
    return obj


def track_quat(direction):
    """The rotation that points an object's -z along `direction` (image up along +y)."""
    from mathutils import Vector

    d = np.asarray(direction, dtype=float)
    d = d / max(np.linalg.norm(d), 1e-12)
    return Vector(d.tolist()).to_track_quat("-Z", "Y")


def make_world(name, sky, ambient):
    world = bpy.data.worlds.new(name)
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputWorld")
    seen = nt.nodes.new("ShaderNodeBackground")
    seen.inputs["Color"].default_value = (*sky, 1.0)
    lit = nt.nodes.new("ShaderNodeBackground")
    lit.inputs["Color"].default_value = (*ambient, 1.0)
    path = nt.nodes.new("ShaderNodeLightPath")
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(path.outputs["Is Camera Ray"], mix.inputs["Fac"])
    nt.links.new(lit.outputs["Background"], mix.inputs[1])
    nt.links.new(seen.outputs["Background"], mix.inputs[2])
    nt.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    return world


def label_material():
    mat = bpy.data.materials.new("r2g_label")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    info = nt.nodes.new("ShaderNodeObjectInfo")
    scale = nt.nodes.new("ShaderNodeMath")
    scale.operation = "MULTIPLY"
    scale.inputs[1].default_value = LABEL_STEP / 255.0
    rgb = nt.nodes.new("ShaderNodeCombineColor")
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    nt.links.new(info.outputs["Object Index"], scale.inputs[0])
    nt.links.new(scale.outputs["Value"], rgb.inputs[0])
    nt.links.new(rgb.outputs["Color"], emit.inputs["Color"])
    nt.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return mat


# ---------------------------------------------------------------------------------------------


def build(doc):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.name = doc["gym"]
    fps = doc["fps"]
    scene.render.fps = int(round(fps))
    scene.render.fps_base = scene.render.fps / fps
    frames = frame_numbers(doc["times_s"], fps)
    scene.frame_start, scene.frame_end = frames[0], frames[-1]
    scene["r2g_source"] = doc["source"]
    scene["r2g_objects"] = doc["objects"]

    body_objs = {0: None}
    for b in doc["bodies"]:
        e = bpy.data.objects.new(b["name"], None)
        e.empty_display_size = 0.05
        scene.collection.objects.link(e)
        if len(b["poses"]) != len(frames):
            fail(f"body {b['name']}: {len(b['poses'])} poses for {len(frames)} states")
        keyframe(e, frames, b["poses"])
        body_objs[b["id"]] = e

    meshes = [mesh_from_arrays(m["name"] or f"mesh{i}", m) for i, m in enumerate(doc["meshes"])]
    mats = {}
    images = {}
    n_obj = len(doc["objects"])
    for i, g in enumerate(doc["geoms"]):
        gname = g["name"] or f"geom{i}"
        if g["type"] == "mesh":
            data = meshes[g["mesh"]]
        else:
            data = primitive_mesh(gname, g["type"], g["size"])
        key = tuple(round(c, 4) for c in g["rgba"])
        tex = g.get("texture")
        if tex is not None:
            if g["type"] != "plane":
                fail(f"geom {gname}: a texture is mapped on planes only, this is a {g['type']}")
            key = (*key, tex["name"], *tex["repeat"], tex["uniform"])
            plane_uvs(data, g["size"], tex)
        if key not in mats:
            image = None
            if tex is not None:
                # One image per texture, however many materials use it.
                if tex["rgb_b64"] not in images:
                    images[tex["rgb_b64"]] = texture_image(tex["name"] or f"texture{len(images)}", tex)
                image = images[tex["rgb_b64"]]
            mats[key] = material(f"rgba_{len(mats)}", g["rgba"], image)
        obj = bpy.data.objects.new(gname, data)
        if g["type"] == "mesh":
            # Geoms may share a mesh: the mesh has one empty slot, each object fills it.
            if not data.materials:
                data.materials.append(None)
            obj.material_slots[0].link = "OBJECT"
            obj.material_slots[0].material = mats[key]
        else:
            data.materials.append(mats[key])
        scene.collection.objects.link(obj)
        parent = body_objs.get(g["body"])
        if g["body"] != 0 and parent is None:
            fail(f"geom {gname} is on body {g['body']}, which the document does not pose")
        obj.parent = parent
        obj.rotation_mode = "QUATERNION"
        obj.location = g["pos"]
        obj.rotation_quaternion = g["quat_wxyz"]
        obj.pass_index = g["object"] + 1 if g["object"] is not None and g["object"] < n_obj else 0
        obj["r2g_owner"] = g["owner"] or ""
        obj["r2g_body"] = g["body"]

    cams = {}
    for c in doc["cameras"]:
        data = bpy.data.cameras.new(c["name"])
        obj = bpy.data.objects.new(c["name"], data)
        scene.collection.objects.link(obj)
        if len(c["poses"]) != len(frames):
            fail(f"camera {c['name']}: {len(c['poses'])} poses for {len(frames)} states")
        keyframe(obj, frames, c["poses"])
        for k in ("width", "height", "fx", "fy", "cx", "cy"):
            obj[k] = c[k]
        cams[c["name"]] = (obj, c)

    # Lights: MuJoCo's, then the headlight (a sun along the active camera's view).
    for i, l in enumerate(doc["lights"]):
        name = l["name"] or f"light{i}"
        if l["type"] == "spot":
            s = spot(name, l)
        else:
            s = sun(name, l["dir"], math.pi * max(l["diffuse"]), l["cast_shadow"])
            s.data.color = [d / max(max(l["diffuse"]), 1e-9) for d in l["diffuse"]]
        s.location = l["pos"]
        scene.collection.objects.link(s)
    head = doc["headlight"]
    headlight = None
    if head["active"] and max(head["diffuse"]) > 0:
        headlight = sun("headlight", (0, 0, -1), math.pi * max(head["diffuse"]), False)
        scene.collection.objects.link(headlight)
    ambient = [a + sum(l["ambient"][k] for l in doc["lights"]) for k, a in enumerate(head["ambient"])]
    sky = doc.get("sky_mean_rgb") or [0.5, 0.5, 0.5]
    scene.world = make_world("r2g_world", sky, ambient if head["active"] else [0.0, 0.0, 0.0])

    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.view_settings.view_transform = "Raw"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.dither_intensity = 0.0
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.color_depth = "8"
    scene.render.film_transparent = False
    if cams:
        first = next(iter(cams.values()))
        set_intrinsics(first[0].data, scene, first[1], 100)
        scene.camera = first[0]
        if headlight is not None:
            point_headlight(headlight, first[0])
    return scene, frames, cams, headlight


def point_headlight(headlight, cam_obj):
    headlight.parent = cam_obj
    headlight.location = (0, 0, 0)
    headlight.rotation_quaternion = (1, 0, 0, 0)


def save_blend(path):
    tmp = f"{path}.tmp{os.getpid()}.blend"
    bpy.context.preferences.filepaths.save_version = 0
    bpy.ops.wm.save_as_mainfile(filepath=tmp, check_existing=False, compress=True)
    os.replace(tmp, path)


def render_shots(scene, frames, cams, headlight, args):
    out = args.render
    os.makedirs(os.path.join(out, "rgb"), exist_ok=True)
    os.makedirs(os.path.join(out, "label"), exist_ok=True)
    for s in (scene.cycles,):
        s.use_adaptive_sampling = False
    if args.threads > 0:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = args.threads
    world = scene.world
    black = bpy.data.worlds.new("r2g_black")
    black.use_nodes = True
    black.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    label = label_material()
    shots = []
    for s in args.shot:
        i, state, cam = s.split(":", 2)
        if cam not in cams:
            fail(f"--shot {s}: no camera '{cam}'")
        if not 0 <= int(state) < len(frames):
            fail(f"--shot {s}: state {state} is not one of the {len(frames)}")
        shots.append((int(i), int(state), cam))
    times = []
    vl = scene.view_layers[0]
    for i, state, cam in shots:
        obj, c = cams[cam]
        scene.camera = obj
        set_intrinsics(obj.data, scene, c, args.percent)
        if headlight is not None:
            point_headlight(headlight, obj)
        scene.frame_set(frames[state])
        # The image.
        scene.world = world
        vl.material_override = None
        scene.cycles.samples = args.samples
        scene.cycles.use_denoising = True
        scene.cycles.pixel_filter_type = "BLACKMAN_HARRIS"
        scene.cycles.filter_width = 1.5
        scene.render.filepath = os.path.join(out, "rgb", f"{i:06d}.png")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        t_rgb = time.perf_counter() - t0
        # Flat per-object colours, one sample at each pixel's centre.
        scene.world = black
        vl.material_override = label
        scene.cycles.samples = 1
        scene.cycles.use_denoising = False
        scene.cycles.pixel_filter_type = "BOX"
        scene.cycles.filter_width = 0.01
        scene.render.filepath = os.path.join(out, "label", f"{i:06d}.png")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        t_label = time.perf_counter() - t0
        times.append({"id": i, "camera": cam, "frame": frames[state], "rgb_s": round(t_rgb, 3),
                      "label_s": round(t_label, 3)})
    scene.world = world
    vl.material_override = None
    return times


def main(argv):
    args = parse_args(argv)
    with open(args.scene) as f:
        doc = json.load(f)
    t0 = time.perf_counter()
    scene, frames, cams, headlight = build(doc)
    summary = {"bpy": bpy.app.version_string, "frames": len(frames), "objects": len(bpy.data.objects),
               "build_s": round(time.perf_counter() - t0, 3)}
    if args.blend:
        t0 = time.perf_counter()
        save_blend(args.blend)
        summary["save_s"] = round(time.perf_counter() - t0, 3)
    if args.render:
        shots = render_shots(scene, frames, cams, headlight, args)
        summary["shots"] = shots
        summary["samples"] = args.samples
        summary["percent"] = args.percent
        if shots:
            summary["mean_rgb_s"] = round(sum(s["rgb_s"] for s in shots) / len(shots), 3)
            summary["mean_label_s"] = round(sum(s["label_s"] for s in shots) / len(shots), 3)
    with open(args.summary, "w") as f:
        json.dump(summary, f)


if __name__ == "__main__":
    main(sys.argv[1:])
