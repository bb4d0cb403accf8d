//! Scene + URDF → MJCF. The robot keeps its URDF structure (one body per link, hinge/slide per
//! joint); collision geometry is hidden (group 3), visual geometry is drawn and never collides.
//!
//! URDF meshes (`<mesh filename=… scale=…>`) become MuJoCo mesh assets: visual meshes are drawn
//! as they are, collision meshes collide as their convex hulls (MuJoCo's rule for mesh geoms).
//! A filename is `package://NAME/PATH` (looked up on [`package_search_path`]), `file://ABSOLUTE`,
//! an absolute path or a path relative to the URDF's folder. STL, OBJ and MSH files go to MuJoCo
//! directly; a COLLADA file `X.dae`, which MuJoCo cannot read, is drawn from the OBJ parts that
//! `robots/assets.py` converted it into (`X.dae.parts/parts.txt`: one `FILE R G B A` line per
//! material), each part in its own colour.
//!
//! Actuation: per arm joint a position servo and a velocity servo, driven with the runtime's
//! position and velocity command (a PD that tracks without lag), on bodies with gravity
//! compensation, with the total joint torque capped at the URDF effort. The gripper is one
//! position servo on a tendon averaging the two fingers, which an equality keeps symmetric.

use std::collections::HashMap;
use std::fmt::Write;
use std::path::PathBuf;

use crate::scene::{part_volume, CameraSpec, JointKind, PartSpec, Role, Scene, Shape};

/// Names the sim-host looks up in the compiled model.
pub const TCP_SITE: &str = "r2g_tcp";
pub const GRIPPER_ACTUATOR: &str = "r2g_gripper";
/// A fixture's moving body is named `<fixture><MOVING_SUFFIX>`, its joint `<fixture><JOINT_SUFFIX>`.
pub const MOVING_SUFFIX: &str = "__moving";
pub const JOINT_SUFFIX: &str = "__joint";
pub use controllers::mesh::{package_search_path, PACKAGE_PATH_ENV};
/// Geom groups: drawn visuals and hidden collision shapes.
const VISUAL_GROUP: u32 = 2;
const COLLISION_GROUP: u32 = 3;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MjcfError {
    #[error("URDF does not parse: {0}")]
    Urdf(String),
    #[error("URDF geometry of link '{link}' is not supported yet: {what}")]
    Unsupported { link: String, what: String },
    #[error("URDF link '{link}': mesh '{file}': {detail} (package search path: {})", show_path(.search))]
    Mesh { link: String, file: String, detail: String, search: Vec<PathBuf> },
    #[error("camera '{camera}' is mounted on link '{link}', which the robot does not have")]
    NoSuchLink { camera: String, link: String },
    #[error("URDF has no link without a parent (no root)")]
    NoRoot,
    #[error("camera '{camera}': look_at equals position, or up is parallel to the view direction")]
    BadCamera { camera: String },
}

fn show_path(p: &[PathBuf]) -> String {
    if p.is_empty() {
        return "empty".into();
    }
    p.iter().map(|d| d.display().to_string()).collect::<Vec<_>>().join(":")
}

/// Gains of the joint servos for a joint of the given effort limit.
fn servo_gains(effort: f64) -> (f64, f64) {
    if effort > 50.0 {
        (4500.0, 450.0)
    } else {
        (2000.0, 200.0)
    }
}

fn f3(v: [f64; 3]) -> String {
    format!("{} {} {}", v[0], v[1], v[2])
}

fn f4(v: [f64; 4]) -> String {
    format!("{} {} {} {}", v[0], v[1], v[2], v[3])
}

/// Writes the geoms of an object's or fixture's parts: each part becomes a drawn visual geom
/// that never collides and/or a hidden collision geom (group 3) that always does (objects with
/// fingers, containers, supports and each other: contype/conaffinity 1 and 3, never disabled).
/// `mass` is spread over the collision parts by volume (meshes share by their bounding guess:
/// an equal part); None leaves fixtures static.
#[allow(clippy::too_many_arguments)]
fn parts(
    o: &mut String,
    parts: &[PartSpec],
    owner: &str,
    rgba: [f64; 4],
    friction: f64,
    mass: Option<f64>,
    indent: &str,
    meshes: &mut Vec<(String, std::path::PathBuf, [f64; 3])>,
) {
    let colliding: Vec<&PartSpec> = parts.iter().filter(|p| p.role != Role::Visual).collect();
    let known: f64 = colliding.iter().filter_map(|p| part_volume(p)).sum();
    let unknown = colliding.iter().filter(|p| part_volume(p).is_none()).count();
    // Meshes count as the average primitive (or 1 each when all are meshes).
    let mesh_share = if unknown == 0 {
        0.0
    } else if known > 0.0 {
        known / colliding.len().max(1) as f64
    } else {
        1.0
    };
    let total = known + mesh_share * unknown as f64;
    for (k, p) in parts.iter().enumerate() {
        let (t, size) = match p.shape {
            Shape::Box => ("box", p.size_m.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(" ")),
            Shape::Cylinder => ("cylinder", format!("{} {}", p.size_m[0], p.size_m[1])),
            Shape::Capsule => ("capsule", format!("{} {}", p.size_m[0], p.size_m[1])),
            Shape::Sphere => ("sphere", p.size_m[0].to_string()),
            Shape::Mesh => ("mesh", String::new()),
        };
        let shape = if p.shape == Shape::Mesh {
            let name = format!("{owner}_mesh{k}");
            meshes.push((name.clone(), p.mesh.clone().unwrap_or_default(), p.mesh_scale));
            format!("type=\"mesh\" mesh=\"{name}\"")
        } else {
            format!("type=\"{t}\" size=\"{size}\"")
        };
        let c = p.rgba.unwrap_or(rgba);
        let at = format!("pos=\"{}\" quat=\"{}\"", f3(p.position_m), f4(p.quat_wxyz));
        if p.role != Role::Collision {
            writeln!(
                o,
                "{indent}<geom {shape} {at} rgba=\"{}\" contype=\"0\" conaffinity=\"0\" group=\"{VISUAL_GROUP}\" mass=\"0\"/>",
                f4(c)
            )
            .ok();
        }
        if p.role != Role::Visual {
            let share = part_volume(p).unwrap_or(mesh_share);
            let m = mass.map(|m| m * share / total.max(1e-12)).unwrap_or(0.0);
            writeln!(
                o,
                "{indent}<geom name=\"{owner}_c{k}\" {shape} {at} mass=\"{m}\" friction=\"{friction} 0.01 0.0002\" rgba=\"{} 0.5\" contype=\"1\" conaffinity=\"3\" condim=\"4\" solref=\"0.004 1\" solimp=\"0.95 0.99 0.001\" group=\"{COLLISION_GROUP}\"/>",
                f3([c[0], c[1], c[2]])
            )
            .ok();
        }
    }
}

fn v3(v: &urdf_rs::Vec3) -> [f64; 3] {
    [v.0[0], v.0[1], v.0[2]]
}

/// xyaxes of a MuJoCo camera (it looks along its −z, image up along +y) aimed at `look_at`.
fn camera_xyaxes(c: &CameraSpec, default_up: [f64; 3]) -> Option<String> {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross =
        |a: [f64; 3], b: [f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let norm = |a: [f64; 3]| {
        let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        if n < 1e-9 {
            None
        } else {
            Some([a[0] / n, a[1] / n, a[2] / n])
        }
    };
    let fwd = norm(sub(c.look_at_m, c.position_m))?;
    let right = norm(cross(fwd, c.up.unwrap_or(default_up)))?;
    let up = cross(right, fwd);
    Some(format!("{} {}", f3(right), f3(up)))
}

/// Width and height of one pixel of the notional sensor MuJoCo's intrinsics are expressed on,
/// m. Only ratios reach the image, so any positive size gives the same projection.
const PIXEL_PITCH_M: f64 = 1e-5;

/// A camera's lens attributes: `fovy` (degrees), or, for a camera given with pinhole
/// intrinsics, MuJoCo's `focalpixel`, `principalpixel`, `sensorsize` and `resolution`.
///
/// MuJoCo's `principalpixel` is the principal point's offset from the image centre, and a
/// positive offset moves the projection of every point up and left (checked by rendering, see
/// `tests/intrinsics.rs`): in the pixel-index convention, where the image centre is
/// `((w - 1) / 2, (h - 1) / 2)`, the offset for a principal point `(cx, cy)` is
/// `((w - 1) / 2 - cx, (h - 1) / 2 - cy)`.
fn lens(c: &CameraSpec) -> String {
    match c.given_intrinsics() {
        None => format!("fovy=\"{}\"", c.fovy_deg.unwrap_or(crate::scene::DEFAULT_FOVY_DEG)),
        Some((fx, fy, cx, cy)) => {
            let (w, h) = (c.width as f64, c.height as f64);
            format!(
                "focalpixel=\"{fx} {fy}\" principalpixel=\"{} {}\" sensorsize=\"{} {}\" resolution=\"{} {}\"",
                (w - 1.0) / 2.0 - cx,
                (h - 1.0) / 2.0 - cy,
                w * PIXEL_PITCH_M,
                h * PIXEL_PITCH_M,
                c.width,
                c.height
            )
        }
    }
}

/// Rotation matrix of URDF roll-pitch-yaw (fixed axes x, y, z): Rz(yaw)·Ry(pitch)·Rx(roll).
fn rpy_matrix(rpy: [f64; 3]) -> [[f64; 3]; 3] {
    let (sr, cr) = rpy[0].sin_cos();
    let (sp, cp) = rpy[1].sin_cos();
    let (sy, cy) = rpy[2].sin_cos();
    [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
}

struct Writer<'a> {
    robot: &'a urdf_rs::Robot,
    materials: HashMap<String, [f64; 4]>,
    children: HashMap<String, Vec<&'a urdf_rs::Joint>>,
    cameras_by_link: HashMap<String, Vec<&'a CameraSpec>>,
    tcp_link: String,
    /// Arm joint ranges from the robot model: its profile's limits, not necessarily the URDF's.
    ranges: HashMap<String, (f64, f64)>,
    out: String,
    /// The URDF file (relative mesh paths) and the package roots for `package://`.
    urdf_path: PathBuf,
    search: Vec<PathBuf>,
    /// Mesh assets: (name, file, scale); `mesh_names` finds one already declared.
    meshes: Vec<(String, PathBuf, [f64; 3])>,
    mesh_names: HashMap<(PathBuf, String), String>,
}

/// One drawable piece of a URDF geometry: a primitive's MJCF type and size, or a mesh asset with
/// the colour its file gives it (a converted DAE's material).
enum Piece {
    Primitive(&'static str, String),
    Mesh(String, Option<[f64; 4]>),
}

impl Writer<'_> {
    /// Declares (once per file and scale) the mesh assets a URDF mesh needs: one for STL/OBJ/MSH,
    /// one per converted part for DAE.
    fn mesh_pieces(&mut self, link: &str, filename: &str, scale: [f64; 3]) -> Result<Vec<Piece>, MjcfError> {
        let err = |detail: String| MjcfError::Mesh {
            link: link.into(),
            file: filename.into(),
            detail,
            search: self.search.clone(),
        };
        let path = controllers::mesh::resolve(filename, &self.urdf_path, &self.search).map_err(err)?;
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        let files: Vec<(PathBuf, Option<[f64; 4]>)> = match ext.as_str() {
            "stl" | "obj" | "msh" => vec![(path.clone(), None)],
            "dae" => controllers::mesh::converted_parts(&path)
                .map_err(err)?
                .into_iter()
                .map(|(file, rgba)| (file, Some(rgba)))
                .collect(),
            _ => return Err(err(format!("{}: unknown mesh format '{ext}' (STL, OBJ, MSH or DAE)", path.display()))),
        };
        let mut pieces = Vec::new();
        for (file, rgba) in files {
            let key = (file.clone(), f3(scale));
            let name = match self.mesh_names.get(&key) {
                Some(n) => n.clone(),
                None => {
                    let n = format!("r2g_urdf_mesh{}", self.meshes.len());
                    self.meshes.push((n.clone(), file, scale));
                    self.mesh_names.insert(key, n.clone());
                    n
                }
            };
            pieces.push(Piece::Mesh(name, rgba));
        }
        Ok(pieces)
    }

    fn pieces(&mut self, link: &str, g: &urdf_rs::Geometry) -> Result<Vec<Piece>, MjcfError> {
        Ok(vec![match g {
            urdf_rs::Geometry::Box { size } => {
                Piece::Primitive("box", f3([size.0[0] / 2.0, size.0[1] / 2.0, size.0[2] / 2.0]))
            }
            urdf_rs::Geometry::Cylinder { radius, length } => {
                Piece::Primitive("cylinder", format!("{radius} {}", length / 2.0))
            }
            urdf_rs::Geometry::Capsule { radius, length } => {
                Piece::Primitive("capsule", format!("{radius} {}", length / 2.0))
            }
            urdf_rs::Geometry::Sphere { radius } => Piece::Primitive("sphere", format!("{radius}")),
            urdf_rs::Geometry::Mesh { filename, scale } => {
                let scale = scale.as_ref().map(v3).unwrap_or([1.0; 3]);
                return self.mesh_pieces(link, filename, scale);
            }
        }])
    }

    fn geoms(&mut self, link: &urdf_rs::Link, indent: &str) -> Result<(), MjcfError> {
        let shape = |p: &Piece| match p {
            Piece::Primitive(t, size) => format!("type=\"{t}\" size=\"{size}\""),
            Piece::Mesh(name, _) => format!("type=\"mesh\" mesh=\"{name}\""),
        };
        for v in &link.visual {
            let urdf_rgba = v
                .material
                .as_ref()
                .and_then(|m| m.color.as_ref().map(|c| c.rgba.0).or_else(|| self.materials.get(&m.name).copied()));
            for p in self.pieces(&link.name, &v.geometry)? {
                // A URDF colour wins; else a converted part's own; else light grey.
                let own = if let Piece::Mesh(_, c) = &p { *c } else { None };
                let rgba = urdf_rgba.or(own).unwrap_or([0.8, 0.8, 0.8, 1.0]);
                writeln!(
                    self.out,
                    "{indent}<geom {} pos=\"{}\" euler=\"{}\" rgba=\"{} {} {} {}\" contype=\"0\" conaffinity=\"0\" group=\"2\" mass=\"0\"/>",
                    shape(&p),
                    f3(v3(&v.origin.xyz)),
                    f3(v3(&v.origin.rpy)),
                    rgba[0], rgba[1], rgba[2], rgba[3]
                )
                .ok();
            }
        }
        // Collision shapes named `*_envelope` wrap parts the simulator models in detail (the
        // fingers): they serve the runtime's self-collision checks only and never touch objects.
        for c in link.collision.iter().filter(|c| !c.name.as_deref().is_some_and(|n| n.ends_with("_envelope"))) {
            // Robot geoms collide with the scene (conaffinity 1) but not with each other: the
            // runtime checks self-collision on commands before they ever reach the simulator.
            // A mesh collides as its convex hull.
            for p in self.pieces(&link.name, &c.geometry)? {
                writeln!(
                    self.out,
                    "{indent}<geom {} pos=\"{}\" euler=\"{}\" contype=\"2\" conaffinity=\"1\" group=\"3\" friction=\"1.2 0.01 0.0002\" mass=\"0\" rgba=\"0.5 0.5 0.9 0.4\"/>",
                    shape(&p),
                    f3(v3(&c.origin.xyz)),
                    f3(v3(&c.origin.rpy))
                )
                .ok();
            }
        }
        Ok(())
    }

    fn body(&mut self, link_name: &str, depth: usize) -> Result<(), MjcfError> {
        let indent = "  ".repeat(depth + 2);
        let Some(link) = self.robot.links.iter().find(|l| l.name == link_name) else {
            return Ok(());
        };
        let i = &link.inertial;
        if i.mass.value > 0.0 {
            let t = &i.inertia;
            // MJCF takes no orientation beside fullinertia: express the tensor in the body frame.
            let r = rpy_matrix(v3(&i.origin.rpy));
            let local = [[t.ixx, t.ixy, t.ixz], [t.ixy, t.iyy, t.iyz], [t.ixz, t.iyz, t.izz]];
            let mut b = [[0.0; 3]; 3];
            for (a, row) in b.iter_mut().enumerate() {
                for (c, v) in row.iter_mut().enumerate() {
                    *v = (0..3).map(|k| (0..3).map(|l| r[a][k] * local[k][l] * r[c][l]).sum::<f64>()).sum();
                }
            }
            writeln!(
                self.out,
                "{indent}<inertial pos=\"{}\" mass=\"{}\" fullinertia=\"{} {} {} {} {} {}\"/>",
                f3(v3(&i.origin.xyz)),
                i.mass.value,
                b[0][0],
                b[1][1],
                b[2][2],
                b[0][1],
                b[0][2],
                b[1][2]
            )
            .ok();
        }
        self.geoms(link, &indent)?;
        if link_name == self.tcp_link {
            writeln!(self.out, "{indent}<site name=\"{TCP_SITE}\" size=\"0.005\" rgba=\"1 0 0 0\"/>").ok();
        }
        for cam in self.cameras_by_link.remove(link_name).unwrap_or_default() {
            let xy =
                camera_xyaxes(cam, [1.0, 0.0, 0.0]).ok_or_else(|| MjcfError::BadCamera { camera: cam.name.clone() })?;
            writeln!(
                self.out,
                "{indent}<camera name=\"{}\" pos=\"{}\" xyaxes=\"{xy}\" {}/>",
                cam.name,
                f3(cam.position_m),
                lens(cam)
            )
            .ok();
        }
        for j in self.children.get(link_name).cloned().unwrap_or_default() {
            writeln!(
                self.out,
                "{indent}<body name=\"{}\" pos=\"{}\" euler=\"{}\" gravcomp=\"1\">",
                j.child.link,
                f3(v3(&j.origin.xyz)),
                f3(v3(&j.origin.rpy))
            )
            .ok();
            let kind = match j.joint_type {
                urdf_rs::JointType::Revolute => Some("hinge"),
                urdf_rs::JointType::Prismatic => Some("slide"),
                urdf_rs::JointType::Fixed => None,
                ref other => {
                    return Err(MjcfError::Unsupported {
                        link: j.child.link.clone(),
                        what: format!("joint type {other:?}"),
                    })
                }
            };
            if let Some(kind) = kind {
                let (armature, damping) = if kind == "hinge" { (0.1, 1.0) } else { (0.0, 5.0) };
                let (lower, upper) = self.ranges.get(&j.name).copied().unwrap_or((j.limit.lower, j.limit.upper));
                writeln!(
                    self.out,
                    "{indent}  <joint name=\"{}\" type=\"{kind}\" axis=\"{}\" range=\"{} {}\" armature=\"{armature}\" damping=\"{damping}\" actuatorfrcrange=\"{} {}\"/>",
                    j.name,
                    f3(v3(&j.axis.xyz)),
                    lower,
                    upper,
                    -j.limit.effort,
                    j.limit.effort
                )
                .ok();
            }
            self.body(&j.child.link, depth + 1)?;
            writeln!(self.out, "{indent}</body>").ok();
        }
        Ok(())
    }
}

/// Compiles a scene and its robot into one MJCF document.
/// Compiles a scene around the robot of `model` (its arm joints, gripper and joint ranges).
pub fn compile(scene: &Scene, urdf_xml: &str, model: &controllers::RobotModel) -> Result<String, MjcfError> {
    let (arm_joints, finger_joint) = (&model.joint_names, model.finger_joint.as_str());
    let robot = urdf_rs::read_from_string(urdf_xml).map_err(|e| MjcfError::Urdf(e.to_string()))?;
    let child_links: Vec<&str> = robot.joints.iter().map(|j| j.child.link.as_str()).collect();
    let root = robot.links.iter().find(|l| !child_links.contains(&l.name.as_str())).ok_or(MjcfError::NoRoot)?;
    let mut children: HashMap<String, Vec<&urdf_rs::Joint>> = HashMap::new();
    for j in &robot.joints {
        children.entry(j.parent.link.clone()).or_default().push(j);
    }
    let mut cameras_by_link: HashMap<String, Vec<&CameraSpec>> = HashMap::new();
    for c in scene.cameras.iter().filter(|c| c.link.is_some()) {
        let link = c.link.clone().unwrap_or_default();
        if !robot.links.iter().any(|l| l.name == link) {
            return Err(MjcfError::NoSuchLink { camera: c.name.clone(), link });
        }
        cameras_by_link.entry(link).or_default().push(c);
    }
    let materials =
        robot.materials.iter().filter_map(|m| m.color.as_ref().map(|c| (m.name.clone(), c.rgba.0))).collect();
    let mut w = Writer {
        robot: &robot,
        materials,
        children,
        cameras_by_link,
        tcp_link: scene.robot.tcp_link.clone(),
        ranges: model
            .joint_names
            .iter()
            .cloned()
            .zip(model.joints.iter().map(|l| (l.q_min_rad, l.q_max_rad)))
            .collect(),
        out: String::new(),
        urdf_path: scene.robot.urdf.clone(),
        search: package_search_path(&scene.robot.urdf),
        meshes: Vec::new(),
        mesh_names: HashMap::new(),
    };
    let max_w = scene.cameras.iter().map(|c| c.width).max().unwrap_or(640);
    let max_h = scene.cameras.iter().map(|c| c.height).max().unwrap_or(480);

    let o = &mut w.out;
    writeln!(o, "<mujoco model=\"{}\">", scene.name).ok();
    writeln!(o, "  <compiler angle=\"radian\" eulerseq=\"xyz\" autolimits=\"true\"/>").ok();
    writeln!(
        o,
        "  <option timestep=\"{}\" integrator=\"implicitfast\" cone=\"elliptic\" impratio=\"10\"/>",
        scene.timestep_s
    )
    .ok();
    writeln!(o, "  <visual><global offwidth=\"{max_w}\" offheight=\"{max_h}\"/><quality shadowsize=\"1024\"/><headlight ambient=\"0.35 0.35 0.35\" diffuse=\"0.5 0.5 0.5\"/></visual>").ok();
    writeln!(o, "  <asset>\n    <texture name=\"sky\" type=\"skybox\" builtin=\"gradient\" rgb1=\"0.75 0.82 0.9\" rgb2=\"0.25 0.3 0.38\" width=\"256\" height=\"256\"/>").ok();
    writeln!(o, "    <texture name=\"floor\" type=\"2d\" builtin=\"checker\" rgb1=\"0.42 0.44 0.46\" rgb2=\"0.32 0.34 0.36\" width=\"256\" height=\"256\"/>").ok();
    writeln!(o, "    <material name=\"floor\" texture=\"floor\" texrepeat=\"6 6\"/>\n{MESH_PLACEHOLDER}  </asset>")
        .ok();
    writeln!(o, "  <worldbody>").ok();
    if scene.lights.is_empty() {
        writeln!(o, "    <light name=\"key\" pos=\"0.4 -0.6 2.0\" dir=\"-0.1 0.3 -1\" diffuse=\"0.6 0.6 0.6\" castshadow=\"true\"/>").ok();
    }
    for (i, l) in scene.lights.iter().enumerate() {
        writeln!(
            o,
            "    <light name=\"light{i}\" pos=\"{}\" dir=\"{}\" diffuse=\"{}\" castshadow=\"{}\"/>",
            f3(l.position_m),
            f3(l.direction),
            f3(l.diffuse),
            l.cast_shadow
        )
        .ok();
    }
    let mut meshes = Vec::new();
    let floor_z = scene.table.as_ref().map(|t| t.top_center_m[2] - 0.75).unwrap_or(0.0);
    writeln!(o, "    <geom name=\"floor\" type=\"plane\" size=\"3 3 0.1\" pos=\"0 0 {floor_z}\" material=\"floor\" contype=\"1\" conaffinity=\"3\"/>").ok();
    if let Some(t) = &scene.table {
        let c = t.top_center_m;
        writeln!(
            o,
            "    <geom name=\"table\" type=\"box\" size=\"{} {} 0.025\" pos=\"{} {} {}\" rgba=\"{} {} {} {}\" contype=\"1\" conaffinity=\"3\" friction=\"0.8 0.005 0.0001\"/>",
            t.size_m[0] / 2.0, t.size_m[1] / 2.0, c[0], c[1], c[2] - 0.025, t.rgba[0], t.rgba[1], t.rgba[2], t.rgba[3]
        )
        .ok();
    }
    for c in scene.cameras.iter().filter(|c| c.link.is_none()) {
        let xy = camera_xyaxes(c, [0.0, 0.0, 1.0]).ok_or_else(|| MjcfError::BadCamera { camera: c.name.clone() })?;
        writeln!(o, "    <camera name=\"{}\" pos=\"{}\" xyaxes=\"{xy}\" {}/>", c.name, f3(c.position_m), lens(c)).ok();
    }
    for ob in &scene.objects {
        writeln!(o, "    <body name=\"{}\" pos=\"{}\" quat=\"{}\">", ob.name, f3(ob.position_m), f4(ob.quat_wxyz)).ok();
        if ob.free {
            writeln!(o, "      <freejoint name=\"{}_free\"/>", ob.name).ok();
        }
        parts(o, &ob.all_parts(), &ob.name, ob.rgba, ob.friction, Some(ob.mass_kg), "      ", &mut meshes);
        writeln!(o, "    </body>").ok();
    }
    for fx in &scene.fixtures {
        writeln!(o, "    <body name=\"{}\" pos=\"{}\" quat=\"{}\">", fx.name, f3(fx.position_m), f4(fx.quat_wxyz)).ok();
        parts(o, &fx.parts, &fx.name, fx.rgba, fx.friction, None, "      ", &mut meshes);
        if let Some(j) = &fx.joint {
            let kind = match j.kind {
                JointKind::Slide => "slide",
                JointKind::Hinge => "hinge",
            };
            let [lo, hi] = j.range();
            writeln!(o, "      <body name=\"{}{MOVING_SUFFIX}\" pos=\"{}\">", fx.name, f3(j.anchor_m)).ok();
            writeln!(
                o,
                "        <joint name=\"{}{JOINT_SUFFIX}\" type=\"{kind}\" axis=\"{}\" range=\"{lo} {hi}\" damping=\"{}\" frictionloss=\"{}\" limited=\"true\" ref=\"0\"/>",
                fx.name,
                f3(j.axis),
                j.damping,
                j.frictionloss
            )
            .ok();
            let rgba = j.rgba.unwrap_or(fx.rgba);
            parts(
                o,
                &j.parts,
                &format!("{}{MOVING_SUFFIX}", fx.name),
                rgba,
                fx.friction,
                Some(j.mass_kg),
                "        ",
                &mut meshes,
            );
            writeln!(o, "      </body>").ok();
        }
        writeln!(o, "    </body>").ok();
    }
    let b = scene.robot.base_position_m;
    writeln!(o, "    <body name=\"{}\" pos=\"{}\" euler=\"0 0 {}\">", root.name, f3(b), scene.robot.base_yaw_rad).ok();
    w.body(&root.name.clone(), 1)?;
    let o = &mut w.out;
    writeln!(o, "    </body>\n  </worldbody>").ok();

    // The robot is bolted to the table: its base never collides with the world's geometry.
    // The base is the root link and every link fixed to it (a URDF may mount `link0` on a
    // `world` or `base` link). Its first moving links only turn about the mount axis, and their
    // collision shapes (written for self-collision checks) reach down into the mount, so they
    // are excluded too.
    writeln!(o, "  <contact>").ok();
    let mut base: Vec<&str> = vec![root.name.as_str()];
    let mut i = 0;
    while i < base.len() {
        let parent = base[i];
        base.extend(
            robot
                .joints
                .iter()
                .filter(|j| j.parent.link == parent && matches!(j.joint_type, urdf_rs::JointType::Fixed))
                .map(|j| j.child.link.as_str()),
        );
        i += 1;
    }
    let first: Vec<&str> = robot
        .joints
        .iter()
        .filter(|j| base.contains(&j.parent.link.as_str()) && !matches!(j.joint_type, urdf_rs::JointType::Fixed))
        .map(|j| j.child.link.as_str())
        .collect();
    for b in base.iter().copied().chain(first) {
        writeln!(o, "    <exclude body1=\"world\" body2=\"{b}\"/>").ok();
    }
    // A fixture's moving part never collides with its own static parts: the joint's range is its
    // end stop (MuJoCo does not filter these, because the static body is welded to the world).
    for fx in scene.fixtures.iter().filter(|f| f.joint.is_some()) {
        writeln!(o, "    <exclude body1=\"{}\" body2=\"{}{MOVING_SUFFIX}\"/>", fx.name, fx.name).ok();
    }
    writeln!(o, "  </contact>").ok();
    // The mimic joints of the gripper follow the driven finger.
    let mimics: Vec<&urdf_rs::Joint> =
        robot.joints.iter().filter(|j| j.mimic.as_ref().is_some_and(|m| m.joint == finger_joint)).collect();
    writeln!(o, "  <tendon>\n    <fixed name=\"r2g_fingers\">").ok();
    let coef = 1.0 / (1 + mimics.len()) as f64;
    writeln!(o, "      <joint joint=\"{finger_joint}\" coef=\"{coef}\"/>").ok();
    for m in &mimics {
        writeln!(o, "      <joint joint=\"{}\" coef=\"{coef}\"/>", m.name).ok();
    }
    writeln!(o, "    </fixed>\n  </tendon>").ok();
    if !mimics.is_empty() {
        writeln!(o, "  <equality>").ok();
        for m in &mimics {
            writeln!(
                o,
                "    <joint joint1=\"{}\" joint2=\"{finger_joint}\" solimp=\"0.95 0.99 0.001\" solref=\"0.005 1\"/>",
                m.name
            )
            .ok();
        }
        writeln!(o, "  </equality>").ok();
    }
    writeln!(o, "  <actuator>").ok();
    for name in arm_joints {
        let effort = robot.joints.iter().find(|j| &j.name == name).map(|j| j.limit.effort).unwrap_or(12.0);
        let (kp, kv) = servo_gains(effort);
        writeln!(o, "    <position name=\"{name}_pos\" joint=\"{name}\" kp=\"{kp}\"/>").ok();
        writeln!(o, "    <velocity name=\"{name}_vel\" joint=\"{name}\" kv=\"{kv}\"/>").ok();
    }
    let finger_max = robot.joints.iter().find(|j| j.name == finger_joint).map(|j| j.limit.upper).unwrap_or(0.04);
    writeln!(
        o,
        "    <position name=\"{GRIPPER_ACTUATOR}\" tendon=\"r2g_fingers\" kp=\"2000\" kv=\"40\" ctrlrange=\"0 {finger_max}\" forcerange=\"-70 70\"/>\n  </actuator>\n</mujoco>"
    )
    .ok();
    meshes.append(&mut w.meshes);
    let assets: String = meshes
        .iter()
        .map(|(name, file, scale)| {
            format!("    <mesh name=\"{name}\" file=\"{}\" scale=\"{}\"/>\n", file.display(), f3(*scale))
        })
        .collect();
    Ok(w.out.replace(MESH_PLACEHOLDER, &assets))
}

const MESH_PLACEHOLDER: &str = "<!--r2g meshes-->\n";
