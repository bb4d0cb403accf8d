//! Self-collision, static-obstacle and workspace checks for one arm configuration.
//!
//! The robot is a set of bodies, one per URDF link that carries collision geometry, each made of
//! capsules or boxes attached to a kinematic frame. A check runs forward kinematics once, places
//! every shape in the base frame and asks parry3d for the gap between the shapes of each pair
//! that is checked. Everything that can be decided once (which shapes, which pairs, which bodies
//! meet obstacles) is decided when the model is built; [`CollisionModel::check`] works on the
//! stack and does not allocate.
//!
//! Distances are gaps between surfaces in metres. A negative gap means the shapes overlap: for
//! two capsules its size is the overlap depth along the line between their axes; where a box or
//! a half-space is involved parry reports only "touching", so the gap then stops at minus the
//! capsule's radius (or 0 for a box) however deep the overlap is.

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d::math::{Pose, Rot3, Vector};
use parry3d::query::{self, PointQuery};
use parry3d::shape::{Cuboid, HalfSpace, Segment, Shape};

use crate::kinematics::FrameId;
use crate::mesh;
use crate::robot::RobotModel;
use crate::{Kinematics, N};

/// Most collision shapes a robot may have (the check keeps them in a fixed-size stack array).
pub const MAX_SHAPES: usize = 32;

/// Bodies moved by at most this many joints are the robot's mount: for the Panda, link0 (fixed)
/// and link1 (which only spins about the vertical joint-1 axis). Whatever `q` is, they fill the
/// same column above the mounting surface, so they are not checked against obstacles or the
/// workspace: an obstacle touching that column (the table the robot is bolted to) would be a
/// violation at every configuration.
pub const MOUNT_JOINTS: usize = 1;

/// Two bodies are checked against each other only if at least this many joints separate them
/// (bodies fixed to the same joint are 0 apart, the parent and child of one joint 1 apart), and
/// the pair is not in [`EXCLUDED_PAIRS`].
///
/// How the filter was chosen: the test `pair_filter_matches_sampled_contacts` in
/// `tests/collision.rs` places the Panda at 20 000 uniformly random configurations within its
/// joint limits and records, for every pair of bodies, how often they touch. Pairs 0 or 1
/// joint apart either touch at every sample (a parent's and a child's capsules overlap around
/// the joint they share: link0/link1 by 6 cm, link7/hand, the hand and its fingers) or never come
/// within 4 cm (link6/hand, link7/fingers, whose relative pose only one joint changes); checking
/// them would reject everything or nothing. Of the pairs 2 joints apart only link1/link3 touches
/// often (about a quarter of the samples, see [`EXCLUDED_PAIRS`]); the others touch at a few
/// per cent of samples at most, and those contacts are real ones - the hand folding back onto
/// link5 - so they stay checked. Franka's own tools likewise skip a link's direct neighbours.
pub const MIN_JOINTS_APART: usize = 2;

/// Pairs (by link name in robots/panda/*.urdf) not checked although they are
/// [`MIN_JOINTS_APART`] apart. The model applies the rule by position in the chain,
/// [`EXCLUDED_JOINT_PAIRS`], so that a description naming its links otherwise (`panda_link1`)
/// gets the same pairs.
///
/// link1/link3: link3's capsule lies on joint 3's axis, so the gap between the two depends on
/// joint 2 alone, and the capsules touch once |q2| passes about 1.3 rad - about a quarter of the
/// range the real arm is built to reach without hitting itself. The contact comes from the
/// capsules being wider than the real shoulder, so checking it would forbid much of the
/// workspace for nothing. Capsules bounding the real meshes are wider still (see
/// [`mesh::bounding_capsule`]), so the same holds for them.
pub const EXCLUDED_PAIRS: [(&str, &str); 1] = [("link1", "link3")];

/// [`EXCLUDED_PAIRS`] by the number of joints that move each body: the body turned by joint 1
/// alone (link1) and the one joints 1 to 3 move (link3).
pub const EXCLUDED_JOINT_PAIRS: [(usize, usize); 1] = [(1, 3)];

/// Errors while building a collision model, scene or workspace.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum BuildError {
    #[error("URDF does not parse: {0}")]
    Urdf(String),
    #[error("collision geometry of link '{link}' is not usable: {detail}")]
    Geometry { link: String, detail: String },
    #[error("the robot has {found} collision shapes, at most {max} are supported")]
    TooManyShapes { found: usize, max: usize },
    #[error("obstacle '{name}' is not usable: {detail}")]
    Obstacle { name: String, detail: String },
    #[error("workspace box is not usable: {0}")]
    Workspace(String),
}

/// The shape of one collision element in the frame of the last joint that moves it.
#[derive(Debug, Clone, Copy)]
enum Local {
    /// A capsule (or a sphere when `a == b`): its axis end points and radius.
    Capsule {
        a: Point3<f64>,
        b: Point3<f64>,
        radius: f32,
    },
    Cuboid {
        pose: Isometry3<f64>,
        half: Cuboid,
    },
}

#[derive(Debug, Clone, Copy)]
struct Element {
    body: usize,
    /// Joints `0..moved_by` move this element (0: fixed to the base).
    moved_by: usize,
    local: Local,
}

/// A collision element placed in the base frame (f32, as parry3d works).
#[derive(Debug, Clone, Copy)]
enum Placed {
    Capsule(Segment, f32),
    Cuboid(Pose, Cuboid),
}

const UNPLACED: Placed = Placed::Capsule(Segment { a: Vector::ZERO, b: Vector::ZERO }, 0.0);

/// A sphere around a placed shape. The gap between two shapes is never smaller than the gap
/// between their spheres, so a pair whose spheres are already too far apart to matter skips
/// the exact query (the broad phase).
#[derive(Debug, Clone, Copy)]
struct Sphere {
    centre: Vector,
    radius: f32,
}

impl Sphere {
    fn around(p: &Placed) -> Self {
        match p {
            Placed::Capsule(s, r) => Self { centre: (s.a + s.b) * 0.5, radius: (s.b - s.a).length() * 0.5 + r },
            Placed::Cuboid(pose, c) => Self { centre: pose.translation, radius: c.half_extents.length() },
        }
    }

    fn gap(&self, other: &Self) -> f32 {
        (self.centre - other.centre).length() - self.radius - other.radius
    }
}

/// Every shape of the robot placed at one configuration, and the TCP position.
struct Posed {
    shapes: [Placed; MAX_SHAPES],
    spheres: [Sphere; MAX_SHAPES],
    tcp: Vector3<f64>,
}

#[derive(Debug, Clone)]
struct Body {
    name: String,
    moved_by: usize,
}

/// The robot's collision geometry attached to its kinematic chain.
#[derive(Debug, Clone)]
pub struct CollisionModel {
    kin: Kinematics,
    bodies: Vec<Body>,
    elements: Vec<Element>,
    /// Element pairs checked for self-collision.
    pairs: Vec<(u8, u8)>,
    /// Elements checked against obstacles and (optionally) the workspace.
    exposed: Vec<u8>,
    tcp_name: String,
}

fn isometry(o: &urdf_rs::Pose) -> Isometry3<f64> {
    let [x, y, z] = *o.xyz;
    let [r, p, yaw] = *o.rpy;
    Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(r, p, yaw))
}

fn v32(p: &Point3<f64>) -> Vector {
    Vector::new(p.x as f32, p.y as f32, p.z as f32)
}

fn pose32(t: &Isometry3<f64>) -> Pose {
    let v = t.translation.vector;
    let q = t.rotation.quaternion();
    Pose::from_parts(
        Vector::new(v.x as f32, v.y as f32, v.z as f32),
        Rot3::from_xyzw(q.i as f32, q.j as f32, q.k as f32, q.w as f32),
    )
}

/// Where the mesh files a URDF names are found: relative to the URDF's file and on the
/// `package://` search path ([`mesh::package_search_path`], the sim-host's too).
#[derive(Debug, Clone)]
struct MeshFiles {
    urdf: Option<PathBuf>,
    search: Vec<PathBuf>,
}

impl MeshFiles {
    fn new(urdf: Option<&Path>) -> Self {
        let search = match urdf {
            Some(u) => mesh::package_search_path(u),
            None => std::env::var_os(mesh::PACKAGE_PATH_ENV)
                .map(|v| std::env::split_paths(&v).filter(|p| !p.as_os_str().is_empty()).collect())
                .unwrap_or_default(),
        };
        Self { urdf: urdf.map(Path::to_path_buf), search }
    }

    /// The mesh of a `<mesh>` element, scaled, in the geometry's own frame.
    fn points(&self, link: &str, filename: &str, scale: Option<&urdf_rs::Vec3>) -> Result<mesh::Mesh, BuildError> {
        let err = |detail: String| BuildError::Geometry {
            link: link.into(),
            detail: format!(
                "mesh '{filename}': {detail} (package search path: {})",
                self.search.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(":")
            ),
        };
        let relative =
            !(filename.starts_with("package://") || filename.starts_with("file://") || filename.starts_with('/'));
        let path = match &self.urdf {
            Some(u) => mesh::resolve(filename, u, &self.search),
            None if relative => {
                Err("a relative mesh path needs the URDF's file: build with CollisionModel::from_urdf_file".into())
            }
            None => mesh::resolve(filename, Path::new("/"), &self.search),
        }
        .map_err(err)?;
        let s = scale.map_or([1.0; 3], |s| [s[0], s[1], s[2]]);
        if !s.iter().all(|v| v.is_finite()) {
            return Err(err(format!("scale {s:?} is not finite")));
        }
        let m = mesh::read_mesh(&path).map_err(|e| err(e.to_string()))?;
        Ok(m.map(|p| Point3::new(p.x * s[0], p.y * s[1], p.z * s[2])))
    }
}

/// Half extents of a box around primitive geometry `g` centred on its origin, in its own frame.
fn bounding_half_extents(link: &str, g: &urdf_rs::Geometry) -> Result<Vector3<f64>, BuildError> {
    let e = match *g {
        urdf_rs::Geometry::Box { ref size } => Vector3::new(size[0], size[1], size[2]) / 2.0,
        urdf_rs::Geometry::Capsule { radius, length } => Vector3::new(radius, radius, length / 2.0 + radius),
        urdf_rs::Geometry::Cylinder { radius, length } => Vector3::new(radius, radius, length / 2.0),
        urdf_rs::Geometry::Sphere { radius } => Vector3::new(radius, radius, radius),
        urdf_rs::Geometry::Mesh { .. } => {
            return Err(BuildError::Geometry { link: link.into(), detail: "a mesh has no primitive extents".into() })
        }
    };
    check_extents(link, &e)?;
    Ok(e)
}

/// A mesh whose convex hull contains geometry `g`, in its own frame: a primitive's bounding-box
/// corners (no triangles), or the mesh file's.
fn hull_mesh(link: &str, g: &urdf_rs::Geometry, meshes: &MeshFiles) -> Result<mesh::Mesh, BuildError> {
    if let urdf_rs::Geometry::Mesh { ref filename, ref scale } = *g {
        return meshes.points(link, filename, scale.as_ref());
    }
    let e = bounding_half_extents(link, g)?;
    let points = (0..8)
        .map(|k| {
            Point3::new(
                if k & 1 == 0 { -e.x } else { e.x },
                if k & 2 == 0 { -e.y } else { e.y },
                if k & 4 == 0 { -e.z } else { e.z },
            )
        })
        .collect();
    Ok(mesh::Mesh { points, triangles: Vec::new() })
}

fn check_extents(link: &str, e: &Vector3<f64>) -> Result<(), BuildError> {
    if e.iter().all(|v| v.is_finite() && *v >= 0.0) {
        Ok(())
    } else {
        Err(BuildError::Geometry { link: link.into(), detail: format!("sizes must be finite and >= 0, got {e:?}") })
    }
}

/// The elements for a collision shape on a chain link; `at` is the shape origin in the frame of
/// the last joint that moves the link. A mesh becomes the capsules
/// [`mesh::bounding_capsules`] puts around its (scaled) vertices.
fn elements_on_chain(
    link: &str,
    g: &urdf_rs::Geometry,
    at: Isometry3<f64>,
    meshes: &MeshFiles,
) -> Result<Vec<Local>, BuildError> {
    let capsule = |radius: f64, half: f64| -> Result<Vec<Local>, BuildError> {
        check_extents(link, &Vector3::new(radius, radius, half))?;
        Ok(vec![Local::Capsule {
            a: at * Point3::new(0.0, 0.0, -half),
            b: at * Point3::new(0.0, 0.0, half),
            radius: radius as f32,
        }])
    };
    match *g {
        urdf_rs::Geometry::Capsule { radius, length } => capsule(radius, length / 2.0),
        // A cylinder becomes the capsule of the same axis and radius: longer by the radius at
        // each end, so never smaller than the real part.
        urdf_rs::Geometry::Cylinder { radius, length } => capsule(radius, length / 2.0),
        urdf_rs::Geometry::Sphere { radius } => capsule(radius, 0.0),
        urdf_rs::Geometry::Mesh { .. } => {
            let caps = mesh::bounding_capsules(&hull_mesh(link, g, meshes)?, mesh::MAX_CAPSULES_PER_MESH).ok_or_else(
                || BuildError::Geometry { link: link.into(), detail: "mesh vertices are not finite".into() },
            )?;
            // Rounding the radius to f32 must not shrink it.
            let r32 = |r: f64| (r as f32).max((r + 1e-7 * r.abs()) as f32);
            Ok(caps.iter().map(|c| Local::Capsule { a: at * c.a, b: at * c.b, radius: r32(c.radius) }).collect())
        }
        urdf_rs::Geometry::Box { .. } => {
            let e = bounding_half_extents(link, g)?;
            let half = Cuboid::new(Vector::new(e.x as f32, e.y as f32, e.z as f32));
            Ok(vec![Local::Cuboid { pose: at, half }])
        }
    }
}

impl CollisionModel {
    /// Reads the collision geometry of `model`'s robot from the same URDF text. Without the
    /// URDF's file, meshes are found only by absolute path, `file://` or `package://` on
    /// `$R2G_PACKAGE_PATH`; [`Self::from_urdf_file`] resolves them as the sim-host does.
    pub fn from_urdf_str(xml: &str, model: &RobotModel) -> Result<Self, BuildError> {
        let robot = urdf_rs::read_from_string(xml).map_err(|e| BuildError::Urdf(e.to_string()))?;
        Self::build(&robot, model, &MeshFiles::new(None))
    }

    /// As [`Self::from_urdf_str`] for URDF text `xml` read from the file `urdf`: mesh filenames
    /// resolve as the sim-host resolves them ([`mesh::resolve`]: relative to the file's folder,
    /// `package://` on [`mesh::package_search_path`]). Mesh files are read here, once.
    pub fn from_urdf_file(xml: &str, urdf: &Path, model: &RobotModel) -> Result<Self, BuildError> {
        let robot = urdf_rs::read_from_string(xml).map_err(|e| BuildError::Urdf(e.to_string()))?;
        Self::build(&robot, model, &MeshFiles::new(Some(urdf)))
    }

    /// Bodies: every link that is a kinematic frame of `model` and has collision geometry, plus
    /// every link hung from such a link by a prismatic joint (gripper fingers). A finger is
    /// replaced by one box in its parent's frame that covers all its collision shapes over the
    /// whole joint range (for the Franka Hand: each finger's 20 x 12 x 54 mm pad from closed to
    /// fully open, a 20 x 52 x 54 mm box per side). The box does not move with the fingers, so it
    /// is exact when the gripper is open and conservative otherwise. Links further down, or below
    /// a revolute joint that is not an arm joint, are not modelled.
    ///
    /// Mesh geometry on a chain link becomes 1 to [`mesh::MAX_CAPSULES_PER_MESH`] capsules that
    /// together contain the mesh ([`mesh::bounding_capsules`]); on a finger all its vertices
    /// count in the box.
    /// Meshes are found as [`Self::from_urdf_str`] says.
    pub fn new(robot: &urdf_rs::Robot, model: &RobotModel) -> Result<Self, BuildError> {
        Self::build(robot, model, &MeshFiles::new(None))
    }

    fn build(robot: &urdf_rs::Robot, model: &RobotModel, meshes: &MeshFiles) -> Result<Self, BuildError> {
        let kin = model.kin.clone();
        let mut bodies = Vec::new();
        let mut elements = Vec::new();
        let links: HashMap<&str, &urdf_rs::Link> = robot.links.iter().map(|l| (l.name.as_str(), l)).collect();
        for (id, frame) in kin.frames().iter().enumerate() {
            let id = FrameId(id);
            let Some(link) = links.get(frame.name.as_str()) else { continue };
            if link.collision.is_empty() {
                continue;
            }
            let body = bodies.len();
            bodies.push(Body { name: frame.name.clone(), moved_by: frame.moved_by });
            for c in &link.collision {
                let at = kin.offset(id) * isometry(&c.origin);
                for local in elements_on_chain(&link.name, &c.geometry, at, meshes)? {
                    elements.push(Element { body, moved_by: frame.moved_by, local });
                }
            }
        }
        for j in robot.joints.iter().filter(|j| matches!(j.joint_type, urdf_rs::JointType::Prismatic)) {
            let Some(parent) = kin.frame(&j.parent.link) else { continue };
            if kin.frame(&j.child.link).is_some() {
                continue;
            }
            let Some(link) = links.get(j.child.link.as_str()) else { continue };
            if link.collision.is_empty() {
                continue;
            }
            let axis = Vector3::new(j.axis.xyz[0], j.axis.xyz[1], j.axis.xyz[2]);
            let (lo, hi) = (j.limit.lower, j.limit.upper);
            if !(lo.is_finite() && hi.is_finite() && lo <= hi && axis.iter().all(|v| v.is_finite())) {
                return Err(BuildError::Geometry { link: link.name.clone(), detail: "joint range is unusable".into() });
            }
            let mut min = Vector3::repeat(f64::INFINITY);
            let mut max = Vector3::repeat(f64::NEG_INFINITY);
            for c in &link.collision {
                let points = hull_mesh(&link.name, &c.geometry, meshes)?.points;
                for s in [lo, hi] {
                    let t = isometry(&j.origin) * Translation3::from(axis * s) * isometry(&c.origin);
                    for corner in &points {
                        let p = (t * corner).coords;
                        min = min.inf(&p);
                        max = max.sup(&p);
                    }
                }
            }
            let half = (max - min) / 2.0;
            let centre = Translation3::from((max + min) / 2.0);
            let frame = &kin.frames()[parent.0];
            let body = bodies.len();
            bodies.push(Body { name: link.name.clone(), moved_by: frame.moved_by });
            elements.push(Element {
                body,
                moved_by: frame.moved_by,
                local: Local::Cuboid {
                    pose: kin.offset(parent) * Isometry3::from_parts(centre, UnitQuaternion::identity()),
                    half: Cuboid::new(Vector::new(half.x as f32, half.y as f32, half.z as f32)),
                },
            });
        }
        if elements.len() > MAX_SHAPES {
            return Err(BuildError::TooManyShapes { found: elements.len(), max: MAX_SHAPES });
        }
        let mut pairs = Vec::new();
        for i in 0..elements.len() {
            for k in i + 1..elements.len() {
                let (a, b) = (&bodies[elements[i].body], &bodies[elements[k].body]);
                let listed = EXCLUDED_JOINT_PAIRS
                    .iter()
                    .any(|&(x, y)| (a.moved_by, b.moved_by) == (x, y) || (a.moved_by, b.moved_by) == (y, x));
                if a.moved_by.abs_diff(b.moved_by) >= MIN_JOINTS_APART && !listed {
                    pairs.push((i as u8, k as u8));
                }
            }
        }
        let exposed = (0..elements.len()).filter(|&i| elements[i].moved_by > MOUNT_JOINTS).map(|i| i as u8).collect();
        let tcp_name = kin.frames()[kin.tcp.0].name.clone();
        Ok(Self { kin, bodies, elements, pairs, exposed, tcp_name })
    }

    /// Names of the bodies, in the order body indices refer to.
    pub fn body_names(&self) -> impl Iterator<Item = &str> {
        self.bodies.iter().map(|b| b.name.as_str())
    }

    /// Number of joints separating two bodies: 0 when fixed to the same joint.
    pub fn joints_apart(&self, a: usize, b: usize) -> usize {
        self.bodies[a].moved_by.abs_diff(self.bodies[b].moved_by)
    }

    /// Whether bodies `a` and `b` (indices into [`Self::body_names`]) are checked against each
    /// other for self-collision.
    pub fn is_checked(&self, a: usize, b: usize) -> bool {
        self.pairs.iter().any(|&(i, k)| {
            let (x, y) = (self.elements[i as usize].body, self.elements[k as usize].body);
            (x, y) == (a, b) || (x, y) == (b, a)
        })
    }

    /// The body pairs checked for self-collision (each listed once).
    pub fn checked_body_pairs(&self) -> Vec<(&str, &str)> {
        let mut out: Vec<(&str, &str)> = Vec::new();
        for &(i, k) in &self.pairs {
            let a = self.bodies[self.elements[i as usize].body].name.as_str();
            let b = self.bodies[self.elements[k as usize].body].name.as_str();
            if !out.contains(&(a, b)) {
                out.push((a, b));
            }
        }
        out
    }

    /// Number of collision shapes (capsules and boxes).
    pub fn shape_count(&self) -> usize {
        self.elements.len()
    }

    fn place(&self, q: &[f64; N]) -> Result<Posed, Violation<'static>> {
        if let Some(joint) = q.iter().position(|v| !v.is_finite()) {
            return Err(Violation::NotFinite { joint, value: q[joint] });
        }
        let joints = self.kin.joint_frames(q);
        let at = |moved_by: usize| if moved_by == 0 { Isometry3::identity() } else { joints[moved_by - 1] };
        let mut shapes = [UNPLACED; MAX_SHAPES];
        let mut spheres = [Sphere { centre: Vector::ZERO, radius: 0.0 }; MAX_SHAPES];
        for ((p, sphere), e) in shapes.iter_mut().zip(spheres.iter_mut()).zip(&self.elements) {
            let t = at(e.moved_by);
            *p = match e.local {
                Local::Capsule { a, b, radius } => Placed::Capsule(Segment::new(v32(&(t * a)), v32(&(t * b))), radius),
                Local::Cuboid { pose, half } => Placed::Cuboid(pose32(&(t * pose)), half),
            };
            *sphere = Sphere::around(p);
        }
        let tcp = self.kin.frames()[self.kin.tcp.0].moved_by;
        let tcp = (at(tcp) * self.kin.offset(self.kin.tcp)).translation.vector;
        Ok(Posed { shapes, spheres, tcp })
    }

    /// The checked self-collision pair with the smallest gap, if that gap is below `below`:
    /// (element, element, gap). Pairs whose bounding spheres are at least `below` (or the best
    /// gap found so far) apart are skipped.
    fn nearest_self(&self, posed: &Posed, below: f32) -> Option<(usize, usize, f32)> {
        let mut best = None;
        let mut cut = below;
        for &(i, k) in &self.pairs {
            let (i, k) = (i as usize, k as usize);
            if posed.spheres[i].gap(&posed.spheres[k]) >= cut {
                continue;
            }
            let d = gap(&posed.shapes[i], &posed.shapes[k]);
            if d < cut {
                cut = d;
                best = Some((i, k, d));
            }
        }
        best
    }

    /// As [`Self::nearest_self`] for (exposed element, obstacle) pairs: (element, obstacle, gap).
    fn nearest_obstacle(&self, posed: &Posed, scene: &StaticScene, below: f32) -> Option<(usize, usize, f32)> {
        let mut best = None;
        let mut cut = below;
        for &i in &self.exposed {
            let i = i as usize;
            for (o, obstacle) in scene.obstacles.iter().enumerate() {
                if obstacle.lower_bound(&posed.spheres[i]) >= cut {
                    continue;
                }
                let d = gap_to_obstacle(&posed.shapes[i], obstacle);
                if d < cut {
                    cut = d;
                    best = Some((i, o, d));
                }
            }
        }
        best
    }

    fn check_workspace<'a>(&'a self, posed: &Posed, ws: &Workspace) -> Result<(), Violation<'a>> {
        let tcp = posed.tcp;
        ws.contains(&self.tcp_name, [tcp.x, tcp.y, tcp.z])?;
        if ws.bodies {
            for &i in &self.exposed {
                let name = self.bodies[self.elements[i as usize].body].name.as_str();
                let mut result = Ok(());
                for_each_reference_point(&posed.shapes[i as usize], |p| {
                    if result.is_ok() {
                        result = ws.contains(name, [p.x as f64, p.y as f64, p.z as f64]);
                    }
                });
                result?;
            }
        }
        Ok(())
    }

    /// Checks configuration `q`. In this order, the first failure is returned: a non-finite
    /// joint value or margin; the workspace (see [`Workspace`]); self-collision, reported for
    /// the closest checked pair whose gap is below `margin_m`; obstacles, reported for the
    /// closest (body, obstacle) pair whose gap is below `margin_m`. Does not allocate.
    pub fn check<'a>(
        &'a self,
        q: &[f64; N],
        scene: &'a StaticScene,
        workspace: &Workspace,
        margin_m: f64,
    ) -> Result<(), Violation<'a>> {
        if !(margin_m.is_finite() && margin_m >= 0.0) {
            return Err(Violation::BadMargin { margin_m });
        }
        let posed = self.place(q)?;
        self.check_workspace(&posed, workspace)?;
        let below = margin_m as f32;
        if let Some((i, k, d)) = self.nearest_self(&posed, below) {
            return Err(Violation::SelfCollision {
                a: self.body_name(i),
                b: self.body_name(k),
                distance_m: d as f64,
                margin_m,
            });
        }
        if let Some((i, o, d)) = self.nearest_obstacle(&posed, scene, below) {
            return Err(Violation::Obstacle {
                link: self.body_name(i),
                obstacle: &scene.obstacles[o].name,
                distance_m: d as f64,
                margin_m,
            });
        }
        Ok(())
    }

    /// The closest checked self-collision pair and the closest (body, obstacle) pair at `q`,
    /// for diagnostics. Fails only for a non-finite `q`. Does not allocate.
    pub fn clearance<'a>(&'a self, q: &[f64; N], scene: &'a StaticScene) -> Result<Clearance<'a>, Violation<'a>> {
        let posed = self.place(q)?;
        let near_self = self.nearest_self(&posed, f32::INFINITY).map(|(i, k, d)| Proximity {
            a: self.body_name(i),
            b: self.body_name(k),
            distance_m: d as f64,
        });
        let near_obstacle = self.nearest_obstacle(&posed, scene, f32::INFINITY).map(|(i, o, d)| Proximity {
            a: self.body_name(i),
            b: &scene.obstacles[o].name,
            distance_m: d as f64,
        });
        Ok(Clearance { self_pair: near_self, obstacle: near_obstacle })
    }

    /// Gap between two bodies at `q` over all their shapes, whether or not the pair is checked
    /// (the pair filter is studied with this).
    pub fn body_distance(&self, q: &[f64; N], a: usize, b: usize) -> Result<f64, Violation<'static>> {
        let posed = self.place(q)?;
        let mut best = f32::INFINITY;
        for (i, _) in self.elements.iter().enumerate().filter(|(_, e)| e.body == a) {
            for (k, _) in self.elements.iter().enumerate().filter(|(_, e)| e.body == b) {
                best = best.min(gap(&posed.shapes[i], &posed.shapes[k]));
            }
        }
        Ok(best as f64)
    }

    fn body_name(&self, element: usize) -> &str {
        &self.bodies[self.elements[element].body].name
    }
}

/// parry's distance between two convex shapes; a pair it cannot handle (none of the shapes used
/// here) counts as touching, so it fails safe.
fn shape_distance(p1: &Pose, s1: &dyn Shape, p2: &Pose, s2: &dyn Shape) -> f32 {
    query::distance(p1, s1, p2, s2).map_or(0.0, |d| d.distance)
}

fn gap(x: &Placed, y: &Placed) -> f32 {
    match (x, y) {
        (Placed::Capsule(s1, r1), Placed::Capsule(s2, r2)) => {
            query::details::distance_segment_segment(&Pose::IDENTITY, s1, s2) - r1 - r2
        }
        (Placed::Capsule(s, r), Placed::Cuboid(p, c)) | (Placed::Cuboid(p, c), Placed::Capsule(s, r)) => {
            shape_distance(p, c, &Pose::IDENTITY, s) - r
        }
        (Placed::Cuboid(p1, c1), Placed::Cuboid(p2, c2)) => shape_distance(p1, c1, p2, c2),
    }
}

fn gap_to_obstacle(x: &Placed, o: &Obstacle) -> f32 {
    let (shape, pose): (&dyn Shape, &Pose) = match &o.shape {
        ObstacleShape::Cuboid(p, c) => (c, p),
        ObstacleShape::HalfSpace(p, h) => (h, p),
    };
    match x {
        Placed::Capsule(s, r) => shape_distance(pose, shape, &Pose::IDENTITY, s) - r,
        Placed::Cuboid(p, c) => shape_distance(pose, shape, p, c),
    }
}

/// The points of a placed shape that the workspace check looks at: a capsule's axis end points
/// (not widened by its radius) or a box's eight corners.
fn for_each_reference_point(p: &Placed, mut f: impl FnMut(Vector)) {
    match p {
        Placed::Capsule(s, _) => {
            f(s.a);
            f(s.b);
        }
        Placed::Cuboid(pose, c) => {
            let e = c.half_extents;
            for k in 0..8 {
                let corner = Vector::new(
                    if k & 1 == 0 { -e.x } else { e.x },
                    if k & 2 == 0 { -e.y } else { e.y },
                    if k & 4 == 0 { -e.z } else { e.z },
                );
                f(pose * corner);
            }
        }
    }
}

#[derive(Debug, Clone)]
enum ObstacleShape {
    Cuboid(Pose, Cuboid),
    HalfSpace(Pose, HalfSpace),
}

#[derive(Debug, Clone)]
struct Obstacle {
    name: String,
    shape: ObstacleShape,
}

impl Obstacle {
    /// A value the gap between this obstacle and anything inside `s` cannot be below.
    fn lower_bound(&self, s: &Sphere) -> f32 {
        match &self.shape {
            // Distance from the sphere's centre to the solid box: tight for flat boxes such as
            // table tops, which a sphere around the box would bound badly.
            ObstacleShape::Cuboid(pose, c) => c.distance_to_point(pose, s.centre, true) - s.radius,
            // The half-space pose is a pure translation to a point on the plane.
            ObstacleShape::HalfSpace(pose, h) => h.normal.dot(s.centre - pose.translation) - s.radius,
        }
    }
}

/// Known fixed obstacles in the robot base frame, each named. Build it once; checking against it
/// does not allocate.
#[derive(Debug, Clone, Default)]
pub struct StaticScene {
    obstacles: Vec<Obstacle>,
}

impl StaticScene {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a box centred at `pose` (base frame) with half extents `half_extents_m`.
    pub fn add_box(&mut self, name: &str, pose: Isometry3<f64>, half_extents_m: [f64; 3]) -> Result<(), BuildError> {
        let bad = |detail: &str| BuildError::Obstacle { name: name.into(), detail: detail.into() };
        if !half_extents_m.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(bad("half extents must be finite and > 0"));
        }
        if !(pose.translation.vector.iter().chain(pose.rotation.coords.iter()).all(|v| v.is_finite())) {
            return Err(bad("pose must be finite"));
        }
        let [x, y, z] = half_extents_m.map(|v| v as f32);
        self.push(name, ObstacleShape::Cuboid(pose32(&pose), Cuboid::new(Vector::new(x, y, z))))
    }

    /// Adds the half-space behind the plane through `point_m` with normal `normal`: the normal
    /// points away from the obstacle, into free space (a floor at z = 0 is point [0, 0, 0],
    /// normal [0, 0, 1]).
    pub fn add_half_space(&mut self, name: &str, point_m: [f64; 3], normal: [f64; 3]) -> Result<(), BuildError> {
        let bad = |detail: &str| BuildError::Obstacle { name: name.into(), detail: detail.into() };
        let n = Vector3::from(normal);
        if !(point_m.iter().all(|v| v.is_finite()) && n.iter().all(|v| v.is_finite()) && n.norm() > 1e-9) {
            return Err(bad("point and normal must be finite and the normal non-zero"));
        }
        let n = n.normalize();
        let pose = Pose::from_translation(Vector::new(point_m[0] as f32, point_m[1] as f32, point_m[2] as f32));
        self.push(name, ObstacleShape::HalfSpace(pose, HalfSpace::new(Vector::new(n.x as f32, n.y as f32, n.z as f32))))
    }

    fn push(&mut self, name: &str, shape: ObstacleShape) -> Result<(), BuildError> {
        if self.obstacles.iter().any(|o| o.name == name) {
            return Err(BuildError::Obstacle { name: name.into(), detail: "the name is already used".into() });
        }
        self.obstacles.push(Obstacle { name: name.into(), shape });
        Ok(())
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.obstacles.iter().map(|o| o.name.as_str())
    }
}

/// An axis of the base frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    X,
    Y,
    Z,
}

impl fmt::Display for Axis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::X => "x",
            Self::Y => "y",
            Self::Z => "z",
        })
    }
}

/// An axis-aligned box in the base frame that the TCP origin must stay inside (bounds
/// included). With [`Workspace::with_bodies`], the reference points of every body that is not
/// part of the mount (see [`MOUNT_JOINTS`]) must stay inside too: capsule axis end points (not
/// widened by the radius) and box corners. The collision margin does not apply here.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Workspace {
    min: [f64; 3],
    max: [f64; 3],
    bodies: bool,
}

impl Workspace {
    /// A box for the TCP only. Bounds may be infinite (no limit on that side) but not NaN.
    pub fn new(min_m: [f64; 3], max_m: [f64; 3]) -> Result<Self, BuildError> {
        for i in 0..3 {
            let (lo, hi) = (min_m[i], max_m[i]);
            if lo.is_nan() || hi.is_nan() || lo >= hi || lo == f64::INFINITY || hi == f64::NEG_INFINITY {
                return Err(BuildError::Workspace(format!(
                    "min {:?} must be below max {:?} on every axis",
                    min_m, max_m
                )));
            }
        }
        Ok(Self { min: min_m, max: max_m, bodies: false })
    }

    /// The box's corners in the base frame, m (infinite where a side is open).
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        (self.min, self.max)
    }

    /// No limit at all.
    pub fn unbounded() -> Self {
        Self { min: [f64::NEG_INFINITY; 3], max: [f64::INFINITY; 3], bodies: false }
    }

    /// Also keep every moving body's reference points inside.
    pub fn with_bodies(self) -> Self {
        Self { bodies: true, ..self }
    }

    fn contains<'a>(&self, point: &'a str, p: [f64; 3]) -> Result<(), Violation<'a>> {
        for (i, axis) in [Axis::X, Axis::Y, Axis::Z].into_iter().enumerate() {
            if !(p[i] >= self.min[i] && p[i] <= self.max[i]) {
                return Err(Violation::Workspace { point, axis, value: p[i], min: self.min[i], max: self.max[i] });
            }
        }
        Ok(())
    }
}

/// Why a configuration was refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Violation<'a> {
    /// `q[joint]` is NaN or infinite.
    NotFinite { joint: usize, value: f64 },
    /// The margin is negative, NaN or infinite.
    BadMargin { margin_m: f64 },
    /// `point` (the TCP frame or a body) is outside the workspace box along `axis`.
    Workspace { point: &'a str, axis: Axis, value: f64, min: f64, max: f64 },
    /// Two bodies of the robot come closer than the margin.
    SelfCollision { a: &'a str, b: &'a str, distance_m: f64, margin_m: f64 },
    /// A body comes closer than the margin to a named obstacle.
    Obstacle { link: &'a str, obstacle: &'a str, distance_m: f64, margin_m: f64 },
}

fn closeness(f: &mut fmt::Formatter<'_>, a: &str, b: &dyn fmt::Display, d: f64, margin: f64) -> fmt::Result {
    if d <= 0.0 {
        write!(f, "{a} would touch or overlap {b} (gap {d:.3} m, needs {margin:.3} m)")
    } else {
        write!(f, "{a} would come within {d:.3} m of {b} (needs {margin:.3} m)")
    }
}

impl fmt::Display for Violation<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::NotFinite { joint, value } => {
                write!(f, "joint {} position is {value}, not a finite number", joint + 1)
            }
            Self::BadMargin { margin_m } => {
                write!(f, "collision margin {margin_m} m is not usable: give a finite value >= 0")
            }
            Self::Workspace { point, axis, value, min, max } => write!(
                f,
                "{point} would be at {axis} = {value:.3} m, outside the workspace [{min:.3}, {max:.3}] m on {axis}"
            ),
            Self::SelfCollision { a, b, distance_m, margin_m } => closeness(f, a, &b, distance_m, margin_m),
            Self::Obstacle { link, obstacle, distance_m, margin_m } => {
                closeness(f, link, &format_args!("obstacle '{obstacle}'"), distance_m, margin_m)
            }
        }
    }
}

impl std::error::Error for Violation<'_> {}

/// A pair of things and the gap between them, m (negative: overlap).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Proximity<'a> {
    pub a: &'a str,
    pub b: &'a str,
    pub distance_m: f64,
}

/// The closest checked self-collision pair and the closest (body, obstacle) pair; `None` when
/// there is no such pair (no obstacles, or no pair far enough apart in the chain).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Clearance<'a> {
    pub self_pair: Option<Proximity<'a>>,
    pub obstacle: Option<Proximity<'a>>,
}

#[cfg(test)]
mod tests {
    use super::*;

    const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

    fn third_party() -> Option<PathBuf> {
        let p = Path::new(ROOT).join("robots/packages/example-robot-data/robots/panda_description/urdf/panda.urdf");
        p.is_file().then_some(p)
    }

    /// Our Panda with link3's collision capsule replaced by `mesh` (a `<collision>` element's
    /// inside), written beside `dir`'s files as `robot.urdf`.
    fn with_link3_mesh(dir: &Path, collision: &str) -> (String, PathBuf, RobotModel) {
        let text = std::fs::read_to_string(Path::new(ROOT).join("robots/panda/panda.urdf")).expect("URDF");
        let old = r#"<collision><origin xyz="0 0 -0.145" rpy="0 0 0"/><geometry><capsule radius="0.06" length="0.15"/></geometry></collision>"#;
        assert!(text.contains(old));
        let xml = text.replace(old, &format!("<collision>{collision}</collision>"));
        let path = dir.join("robot.urdf");
        std::fs::write(&path, &xml).expect("write");
        let robot = RobotModel::from_urdf_str(&xml, "hand_tcp", crate::Profile::Panda).expect("model");
        (xml, path, robot)
    }

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("r2g-collision-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("temp dir");
        d
    }

    /// Capsules (in their joint frame) of the elements of body `name`.
    fn capsules(col: &CollisionModel, name: &str) -> Vec<mesh::Capsule> {
        col.elements
            .iter()
            .filter(|e| col.bodies[e.body].name == name)
            .map(|e| match e.local {
                Local::Capsule { a, b, radius } => mesh::Capsule { a, b, radius: f64::from(radius) },
                Local::Cuboid { .. } => panic!("{name}: a box"),
            })
            .collect()
    }

    #[test]
    fn a_mesh_is_scaled_placed_and_held() {
        let d = scratch("scaled");
        // A unit cube, binary STL, scaled to 0.04 x 0.06 x 0.2 and placed off the link origin.
        let mut cube = mesh::Mesh::default();
        for k in 0..8 {
            cube.points.push(Point3::new(f64::from(k & 1), f64::from((k >> 1) & 1), f64::from((k >> 2) & 1)));
        }
        let faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]];
        let mut stl = vec![0u8; 80];
        stl.extend(12u32.to_le_bytes());
        for f in faces {
            for t in [[f[0], f[1], f[2]], [f[0], f[2], f[3]]] {
                stl.extend([0u8; 12]);
                for i in t {
                    stl.extend(cube.points[i].coords.iter().flat_map(|v| (*v as f32).to_le_bytes()));
                }
                stl.extend([0u8; 2]);
            }
        }
        std::fs::write(d.join("cube.stl"), stl).expect("write");
        let origin = urdf_rs::Pose { xyz: urdf_rs::Vec3([0.01, -0.02, -0.25]), rpy: urdf_rs::Vec3([0.3, 0.0, 0.5]) };
        let (xml, path, robot) = with_link3_mesh(
            &d,
            r#"<origin xyz="0.01 -0.02 -0.25" rpy="0.3 0 0.5"/><geometry><mesh filename="cube.stl" scale="0.04 0.06 0.2"/></geometry>"#,
        );
        let col = CollisionModel::from_urdf_file(&xml, &path, &robot).expect("model");
        let caps = capsules(&col, "link3");
        let at = col.kin.offset(col.kin.frame("link3").expect("link3")) * isometry(&origin);
        for p in &cube.points {
            let q = at * Point3::new(p.x * 0.04, p.y * 0.06, p.z * 0.2);
            assert!(caps.iter().any(|c| c.axis_distance(&q) <= c.radius), "corner {q:?} outside {caps:?}");
        }
        // Tight enough: no capsule wider than the box's half diagonal across its long axis.
        assert!(caps.iter().all(|c| c.radius <= (0.02f64.hypot(0.03)) + 1e-5), "{caps:?}");
        // Without the URDF's file a relative path cannot be found.
        let e = CollisionModel::from_urdf_str(&xml, &robot).unwrap_err().to_string();
        assert!(e.contains("link3") && e.contains("cube.stl") && e.contains("needs the URDF's file"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn bad_meshes_are_errors_naming_link_file_and_line() {
        let d = scratch("bad");
        std::fs::write(d.join("bad.obj"), "v 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n").expect("write");
        let (xml, path, robot) = with_link3_mesh(&d, r#"<geometry><mesh filename="bad.obj"/></geometry>"#);
        let e = CollisionModel::from_urdf_file(&xml, &path, &robot).unwrap_err().to_string();
        assert!(e.contains("link 'link3'") && e.contains("bad.obj:3: bad vertex line 'v 0 1 zero'"), "{e}");
        let (xml, path, robot) =
            with_link3_mesh(&d, r#"<geometry><mesh filename="package://no_such_pkg/m.stl"/></geometry>"#);
        let e = CollisionModel::from_urdf_file(&xml, &path, &robot).unwrap_err().to_string();
        assert!(e.contains("no package 'no_such_pkg'") && e.contains("package search path"), "{e}");
        let (xml, path, robot) = with_link3_mesh(&d, r#"<geometry><mesh filename="missing.stl"/></geometry>"#);
        let e = CollisionModel::from_urdf_file(&xml, &path, &robot).unwrap_err().to_string();
        assert!(e.contains("missing.stl does not exist"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }

    /// The third-party Panda (example-robot-data, STL collision meshes, `panda_` link names):
    /// every mesh vertex inside its body's capsules in the joint frame, the same pair rule as
    /// ours by chain position, and the fingers' boxes. Skipped without robots/packages/.
    #[test]
    fn third_party_panda_collision_model() {
        let Some(urdf) = third_party() else {
            eprintln!("skipped: robots/packages/ missing (scripts/setup-venv.sh)");
            return;
        };
        let xml = std::fs::read_to_string(&urdf).expect("URDF");
        let robot = RobotModel::from_urdf_str(&xml, "panda_hand_tcp", crate::Profile::Panda).expect("model");
        let t = std::time::Instant::now();
        let col = CollisionModel::from_urdf_file(&xml, &urdf, &robot).expect("collision model");
        eprintln!("third-party collision model: {} shapes, built in {:?}", col.shape_count(), t.elapsed());
        let parsed = urdf_rs::read_from_string(&xml).expect("parse");
        let files = MeshFiles::new(Some(&urdf));
        for name in ["panda_link0", "panda_link1", "panda_link2", "panda_link3", "panda_link4", "panda_link5"]
            .into_iter()
            .chain(["panda_link6", "panda_link7", "panda_hand"])
        {
            let caps = capsules(&col, name);
            assert!((1..=mesh::MAX_CAPSULES_PER_MESH).contains(&caps.len()), "{name}: {}", caps.len());
            let link = parsed.links.iter().find(|l| l.name == name).expect("link");
            let at = col.kin.offset(col.kin.frame(name).expect("frame")) * isometry(&link.collision[0].origin);
            let m = hull_mesh(name, &link.collision[0].geometry, &files).expect("mesh");
            for p in &m.points {
                let q = at * p;
                assert!(caps.iter().any(|c| c.axis_distance(&q) <= c.radius), "{name}: {q:?}");
            }
        }
        let names: Vec<&str> = col.body_names().collect();
        assert_eq!(names.len(), 11, "{names:?}");
        let idx = |n: &str| names.iter().position(|&x| x == n).expect("body");
        assert!(!col.is_checked(idx("panda_link1"), idx("panda_link3")), "EXCLUDED_PAIRS by chain position");
        assert!(col.is_checked(idx("panda_link2"), idx("panda_link4")));
        assert!(col
            .check(&[0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785], &StaticScene::new(), &Workspace::unbounded(), 0.002)
            .is_ok());
        assert!(col.shape_count() <= MAX_SHAPES);
    }
}
