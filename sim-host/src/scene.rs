//! The scene spec: a TOML file naming the robot, cameras, objects, fixtures, lights and the task
//! of a gym. Paths inside it are relative to the file. Unknown fields are refused so typos never
//! pass silently, and every error names the file, the field and what is accepted, on one line.
//! The format is documented with examples in `sim-host/SCENES.md`.

use std::path::{Path, PathBuf};

use serde::Deserialize;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    #[error("cannot read scene file {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("scene file {path} is not valid: {detail}")]
    Parse { path: PathBuf, detail: String },
    #[error("scene {path}: {detail}")]
    Invalid { path: PathBuf, detail: String },
    #[error("cannot read robot URDF {path}: {source}")]
    Urdf { path: PathBuf, source: std::io::Error },
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    pub name: String,
    pub robot: RobotSpec,
    #[serde(default)]
    pub table: Option<TableSpec>,
    /// Absent: the default `agentview` and `wrist` cameras at 640×480.
    #[serde(default = "default_cameras")]
    pub cameras: Vec<CameraSpec>,
    #[serde(default)]
    pub objects: Vec<ObjectSpec>,
    /// Static or articulated furniture: supports, shelves, hooks, drawers, doors.
    #[serde(default)]
    pub fixtures: Vec<FixtureSpec>,
    /// Absent: one key light above the table.
    #[serde(default)]
    pub lights: Vec<LightSpec>,
    /// Physics timestep; one command sample is applied per step.
    #[serde(default = "default_timestep")]
    pub timestep_s: f64,
    #[serde(default)]
    pub safety: Option<SafetySpec>,
    #[serde(default)]
    pub task: TaskSpec,
}

fn default_timestep() -> f64 {
    0.001
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSpec {
    pub urdf: PathBuf,
    #[serde(default = "default_tcp")]
    pub tcp_link: String,
    #[serde(default)]
    pub base_position_m: [f64; 3],
    /// Rotation of the base about world z, rad.
    #[serde(default)]
    pub base_yaw_rad: f64,
    pub initial_joints_rad: [f64; 7],
    /// −1 open … +1 closed.
    #[serde(default = "default_gripper")]
    pub initial_gripper: f64,
    /// Limit profile: "panda" (default) or "fr3"; kinematics come from the URDF either way.
    #[serde(default = "default_limits")]
    pub limits: String,
}

impl RobotSpec {
    /// The limit profile (checked at load, so this is always a known name).
    pub fn profile(&self) -> controllers::Profile {
        controllers::Profile::from_name(&self.limits).unwrap_or(controllers::Profile::Panda)
    }
}

fn default_limits() -> String {
    "panda".into()
}

/// What the runtime checks besides joint limits (read by `r2g-control`; validated here too).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SafetySpec {
    /// Workspace box of the TCP in the robot base frame, m (both or neither).
    pub workspace_min_m: Option<[f64; 3]>,
    pub workspace_max_m: Option<[f64; 3]>,
    /// Clearance required between bodies and to obstacles, m.
    pub margin_m: Option<f64>,
}

fn default_tcp() -> String {
    "hand_tcp".into()
}
fn default_gripper() -> f64 {
    -1.0
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TableSpec {
    /// Centre of the top surface.
    pub top_center_m: [f64; 3],
    pub size_m: [f64; 2],
    #[serde(default = "default_table_rgba")]
    pub rgba: [f64; 4],
}

fn default_table_rgba() -> [f64; 4] {
    [0.55, 0.42, 0.30, 1.0]
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub name: String,
    /// Link the camera rides on; absent means fixed in the world.
    #[serde(default)]
    pub link: Option<String>,
    /// In the world, or in the link frame when `link` is set.
    pub position_m: [f64; 3],
    /// The point the optical axis passes through, same frame as `position_m`.
    pub look_at_m: [f64; 3],
    /// Image "up" hint, same frame; default world z, or link x for mounted cameras.
    #[serde(default)]
    pub up: Option<[f64; 3]>,
    /// Vertical field of view, degrees (default 45; not together with `fx, fy, cx, cy`).
    #[serde(default)]
    pub fovy_deg: Option<f64>,
    /// Pinhole intrinsics in pixels, all four or none (then `fovy_deg` must not be given):
    /// focal lengths and the principal point, pixel-index convention (the centre of pixel
    /// `(u, v)` is the point `(u, v)`), as [`crate::render::intrinsics`] reports them.
    #[serde(default)]
    pub fx: Option<f64>,
    #[serde(default)]
    pub fy: Option<f64>,
    #[serde(default)]
    pub cx: Option<f64>,
    #[serde(default)]
    pub cy: Option<f64>,
    #[serde(default = "default_width")]
    pub width: u32,
    #[serde(default = "default_height")]
    pub height: u32,
    /// Render depth (metres along the optical axis) beside RGB.
    #[serde(default = "default_true")]
    pub depth: bool,
}

/// A RealSense-like view from across the table, and a camera on the hand looking past the
/// fingers, as on a DROID-style robot PC.
fn default_cameras() -> Vec<CameraSpec> {
    vec![
        CameraSpec {
            name: "agentview".into(),
            link: None,
            position_m: [1.4, 0.0, 0.95],
            look_at_m: [0.3, 0.0, 0.18],
            up: None,
            fovy_deg: Some(50.0),
            fx: None,
            fy: None,
            cx: None,
            cy: None,
            width: 640,
            height: 480,
            depth: true,
        },
        CameraSpec {
            name: "wrist".into(),
            link: Some("hand".into()),
            position_m: [-0.1, 0.0, 0.0],
            look_at_m: [0.05, 0.0, 0.25],
            up: Some([-1.0, 0.0, 0.0]),
            fovy_deg: Some(60.0),
            fx: None,
            fy: None,
            cx: None,
            cy: None,
            width: 640,
            height: 480,
            depth: true,
        },
    ]
}

/// The vertical field of view of a camera given without `fovy_deg` and without intrinsics.
pub const DEFAULT_FOVY_DEG: f64 = 45.0;

impl CameraSpec {
    /// The pinhole intrinsics given in the spec (`fx, fy, cx, cy`), when all four are.
    pub fn given_intrinsics(&self) -> Option<(f64, f64, f64, f64)> {
        Some((self.fx?, self.fy?, self.cx?, self.cy?))
    }

    /// The vertical field of view, degrees: `fovy_deg` (default 45), or the one `fy` gives.
    pub fn vertical_fov_deg(&self) -> f64 {
        match self.given_intrinsics() {
            Some((_, fy, _, _)) => (2.0 * (0.5 * self.height as f64 / fy).atan()).to_degrees(),
            None => self.fovy_deg.unwrap_or(DEFAULT_FOVY_DEG),
        }
    }
}
fn default_width() -> u32 {
    640
}
fn default_height() -> u32 {
    480
}

#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum Shape {
    Box,
    Cylinder,
    Sphere,
    Capsule,
    /// A triangle mesh from an OBJ or STL file. MuJoCo collides with its convex hull, so a
    /// concave object (cup, bowl) needs primitive collision parts and the mesh as its visual.
    Mesh,
}

#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Default)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Drawn and colliding (compiled into one visual and one collision geom).
    #[default]
    Both,
    Visual,
    Collision,
}

/// One geometric piece of an object or fixture, in its owner's frame.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PartSpec {
    pub shape: Shape,
    /// MuJoCo size convention: box half-extents; cylinder/capsule radius and half-length; sphere
    /// radius. Not used by meshes.
    #[serde(default)]
    pub size_m: Vec<f64>,
    /// OBJ or STL file (relative to the scene file) when `shape = "mesh"`.
    #[serde(default)]
    pub mesh: Option<PathBuf>,
    #[serde(default = "default_scale")]
    pub mesh_scale: [f64; 3],
    #[serde(default)]
    pub position_m: [f64; 3],
    #[serde(default = "default_quat")]
    pub quat_wxyz: [f64; 4],
    /// Default: the owner's colour.
    #[serde(default)]
    pub rgba: Option<[f64; 4]>,
    #[serde(default)]
    pub role: Role,
}

fn default_scale() -> [f64; 3] {
    [1.0; 3]
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectSpec {
    pub name: String,
    /// A single-shape object; use `parts` instead for compound ones (cups, bowls, mugs).
    #[serde(default)]
    pub shape: Option<Shape>,
    #[serde(default)]
    pub size_m: Vec<f64>,
    #[serde(default)]
    pub mesh: Option<PathBuf>,
    #[serde(default)]
    pub parts: Vec<PartSpec>,
    pub position_m: [f64; 3],
    #[serde(default = "default_quat")]
    pub quat_wxyz: [f64; 4],
    /// Total mass, spread over the collision parts by volume.
    #[serde(default = "default_mass")]
    pub mass_kg: f64,
    #[serde(default = "default_friction")]
    pub friction: f64,
    #[serde(default = "default_rgba")]
    pub rgba: [f64; 4],
    /// False for objects welded to the world.
    #[serde(default = "default_true")]
    pub free: bool,
    /// The object's interior for `inside` checks: a box in the object frame.
    #[serde(default)]
    pub cavity_min_m: Option<[f64; 3]>,
    #[serde(default)]
    pub cavity_max_m: Option<[f64; 3]>,
    /// Augmentation: with a non-zero seed the start position moves by up to this much in x and y.
    #[serde(default)]
    pub jitter_xy_m: f64,
    /// Augmentation: with a non-zero seed the start yaw turns by up to this many degrees.
    #[serde(default)]
    pub jitter_yaw_deg: f64,
}

impl ObjectSpec {
    /// The parts of the object: its `parts`, or the single `shape`.
    pub fn all_parts(&self) -> Vec<PartSpec> {
        match self.shape {
            Some(shape) => vec![PartSpec {
                shape,
                size_m: self.size_m.clone(),
                mesh: self.mesh.clone(),
                mesh_scale: default_scale(),
                position_m: [0.0; 3],
                quat_wxyz: default_quat(),
                rgba: None,
                role: Role::Both,
            }],
            None => self.parts.clone(),
        }
    }
}

#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum JointKind {
    Slide,
    Hinge,
}

/// A fixture: a static body (its `parts`) and optionally one moving body on a joint.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FixtureSpec {
    pub name: String,
    pub position_m: [f64; 3],
    #[serde(default = "default_quat")]
    pub quat_wxyz: [f64; 4],
    #[serde(default = "default_fixture_rgba")]
    pub rgba: [f64; 4],
    #[serde(default = "default_friction")]
    pub friction: f64,
    #[serde(default)]
    pub parts: Vec<PartSpec>,
    #[serde(default)]
    pub joint: Option<FixtureJoint>,
    /// The fixture's interior for `inside` checks: a box in the fixture frame.
    #[serde(default)]
    pub cavity_min_m: Option<[f64; 3]>,
    #[serde(default)]
    pub cavity_max_m: Option<[f64; 3]>,
}

fn default_fixture_rgba() -> [f64; 4] {
    [0.7, 0.7, 0.72, 1.0]
}

/// The moving part of a fixture: a drawer on a slide or a door on a hinge.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FixtureJoint {
    pub kind: JointKind,
    /// In the fixture frame; normalised.
    pub axis: [f64; 3],
    /// A point on the axis (hinge) in the fixture frame; also the moving body's origin.
    #[serde(default)]
    pub anchor_m: [f64; 3],
    /// Slide travel, m (`kind = "slide"`).
    #[serde(default)]
    pub range_m: Option<[f64; 2]>,
    /// Hinge travel, degrees (`kind = "hinge"`).
    #[serde(default)]
    pub range_deg: Option<[f64; 2]>,
    /// Start position: m for a slide, degrees for a hinge.
    #[serde(default)]
    pub initial: f64,
    /// Viscous damping, N·s/m or N·m·s/rad.
    #[serde(default = "default_damping")]
    pub damping: f64,
    /// Dry friction, N or N·m.
    #[serde(default)]
    pub frictionloss: f64,
    /// Mass of the moving body, kg.
    #[serde(default = "default_moving_mass")]
    pub mass_kg: f64,
    /// Geometry of the moving body, in its frame (origin at `anchor_m`).
    pub parts: Vec<PartSpec>,
    #[serde(default)]
    pub rgba: Option<[f64; 4]>,
}

impl FixtureJoint {
    /// Travel in MuJoCo units (m or rad).
    pub fn range(&self) -> [f64; 2] {
        match self.kind {
            JointKind::Slide => self.range_m.unwrap_or([0.0, 0.0]),
            JointKind::Hinge => self.range_deg.map(|r| [r[0].to_radians(), r[1].to_radians()]).unwrap_or([0.0, 0.0]),
        }
    }

    /// Start position in MuJoCo units.
    pub fn initial_native(&self) -> f64 {
        match self.kind {
            JointKind::Slide => self.initial,
            JointKind::Hinge => self.initial.to_radians(),
        }
    }

    /// Converts a native position (m or rad) to the spec's unit (m or degrees).
    pub fn to_spec_unit(&self, v: f64) -> f64 {
        match self.kind {
            JointKind::Slide => v,
            JointKind::Hinge => v.to_degrees(),
        }
    }
}

fn default_damping() -> f64 {
    1.0
}
fn default_moving_mass() -> f64 {
    0.5
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightSpec {
    pub position_m: [f64; 3],
    /// Where the light points; default straight down.
    #[serde(default = "default_light_dir")]
    pub direction: [f64; 3],
    #[serde(default = "default_diffuse")]
    pub diffuse: [f64; 3],
    #[serde(default = "default_true")]
    pub cast_shadow: bool,
}

fn default_light_dir() -> [f64; 3] {
    [0.0, 0.0, -1.0]
}
fn default_diffuse() -> [f64; 3] {
    [0.6, 0.6, 0.6]
}

/// What the agent is asked, how success is judged, and a demonstration that achieves it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskSpec {
    /// What the task asks, in plain language.
    #[serde(default)]
    pub instruction: String,
    /// Joint + gripper trajectory (CSV: q1..q7, gripper; one row per 1/freq s).
    #[serde(default)]
    pub demonstration: Option<PathBuf>,
    /// Rate of the demonstration's rows, Hz.
    #[serde(default = "default_demo_hz")]
    pub demonstration_hz: f64,
    /// Every rule must hold for success.
    #[serde(default)]
    pub success: Vec<Criterion>,
    /// Deepest penetration allowed to persist (longer than 0.1 s), m.
    #[serde(default = "default_penetration")]
    pub max_penetration_m: f64,
    /// Physics time the episode runs on after the last action before judging, s.
    #[serde(default = "default_settle")]
    pub settle_s: f64,
}

impl Default for TaskSpec {
    fn default() -> Self {
        Self {
            instruction: String::new(),
            demonstration: None,
            demonstration_hz: default_demo_hz(),
            success: Vec::new(),
            max_penetration_m: default_penetration(),
            settle_s: default_settle(),
        }
    }
}

fn default_demo_hz() -> f64 {
    20.0
}
fn default_penetration() -> f64 {
    0.002
}
fn default_settle() -> f64 {
    1.0
}

/// A success rule over the recorded native trace. Names refer to objects and fixtures; `table`
/// is the table.
#[derive(Debug, Clone, Deserialize, serde::Serialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Criterion {
    /// The object's origin ends inside a container's cavity, or inside a world box.
    Inside {
        object: String,
        #[serde(default)]
        container: Option<String>,
        #[serde(default)]
        min_m: Option<[f64; 3]>,
        #[serde(default)]
        max_m: Option<[f64; 3]>,
    },
    /// The object ends touching the support and above its lowest point.
    On { object: String, support: String },
    /// The object ends touching nothing but the named things (e.g. a mug on a hook only).
    TouchesOnly { object: String, others: Vec<String> },
    /// A fixture joint ends within [min, max] (m for slides, degrees for hinges).
    Joint {
        fixture: String,
        #[serde(default)]
        min: Option<f64>,
        #[serde(default)]
        max: Option<f64>,
    },
    /// The object's z axis ends within `tolerance_deg` of world up.
    Upright {
        object: String,
        #[serde(default = "default_upright_tol")]
        tolerance_deg: f64,
    },
    /// The robot has let go: over the final `window_s` no robot geometry touches any named
    /// object (with none named: any object or fixture), and the TCP ends at least
    /// `min_distance_m` from every named object. How far the fingers are open does not count,
    /// unless `require_open` asks for the old proxy as well (fingers at least half open).
    Released {
        objects: Vec<String>,
        #[serde(default = "default_release_distance")]
        min_distance_m: f64,
        #[serde(default = "default_release_window")]
        window_s: f64,
        #[serde(default)]
        require_open: bool,
    },
    /// The objects move less than `max_speed_m_s` over the final `duration_s`.
    Stable {
        #[serde(default)]
        objects: Vec<String>,
        /// Fixtures whose joint must have come to rest too.
        #[serde(default)]
        fixtures: Vec<String>,
        #[serde(default = "default_stable_duration")]
        duration_s: f64,
        #[serde(default = "default_stable_speed")]
        max_speed_m_s: f64,
        /// Hinges must turn slower than this (slides use `max_speed_m_s`).
        #[serde(default = "default_stable_joint_speed")]
        max_joint_deg_s: f64,
    },
    /// The two named things (objects, fixtures, `robot`, `table`) end not touching.
    Apart { a: String, b: String },
    /// The object's origin ends with its coordinate `axis` (0 x, 1 y, 2 z) past a plane.
    Past {
        object: String,
        axis: usize,
        #[serde(default)]
        above: Option<f64>,
        #[serde(default)]
        below: Option<f64>,
    },
}

fn default_upright_tol() -> f64 {
    15.0
}
fn default_release_distance() -> f64 {
    0.05
}
fn default_release_window() -> f64 {
    0.5
}
fn default_stable_duration() -> f64 {
    0.5
}
fn default_stable_joint_speed() -> f64 {
    2.0
}
fn default_stable_speed() -> f64 {
    0.02
}

impl Criterion {
    /// A name for the check in reports: the kind and what it is about.
    pub fn label(&self) -> String {
        match self {
            Criterion::Inside { object, container, .. } => {
                format!("inside:{object}:{}", container.as_deref().unwrap_or("region"))
            }
            Criterion::On { object, support } => format!("on:{object}:{support}"),
            Criterion::TouchesOnly { object, others } => format!("touches_only:{object}:{}", others.join("+")),
            Criterion::Joint { fixture, .. } => format!("joint:{fixture}"),
            Criterion::Upright { object, .. } => format!("upright:{object}"),
            Criterion::Released { objects, .. } if objects.is_empty() => "released:gripper".into(),
            Criterion::Released { objects, .. } => format!("released:{}", objects.join("+")),
            Criterion::Stable { objects, fixtures, .. } => {
                format!("stable:{}", objects.iter().chain(fixtures).cloned().collect::<Vec<_>>().join("+"))
            }
            Criterion::Apart { a, b } => format!("apart:{a}:{b}"),
            Criterion::Past { object, axis, .. } => {
                format!("past:{object}:{}", ["x", "y", "z"].get(*axis).unwrap_or(&"?"))
            }
        }
    }
}

fn default_quat() -> [f64; 4] {
    [1.0, 0.0, 0.0, 0.0]
}
fn default_mass() -> f64 {
    0.1
}
fn default_friction() -> f64 {
    1.0
}
fn default_rgba() -> [f64; 4] {
    [0.8, 0.2, 0.2, 1.0]
}
fn default_true() -> bool {
    true
}

/// Turns a TOML/serde error into one line: where it is and what is wrong.
fn one_line(text: &str, e: &toml::de::Error) -> String {
    let msg = e.message().trim().replace('\n', " ");
    match e.span() {
        Some(span) => {
            let start = span.start.min(text.len());
            let line = text[..start].matches('\n').count() + 1;
            // The offending line itself names the field.
            let source = text.lines().nth(line - 1).unwrap_or("").trim();
            let source: String = source.chars().take(60).collect();
            format!("line {line} ({source}): {msg}")
        }
        None => msg,
    }
}

impl Scene {
    /// Reads and checks a scene file; paths are resolved against the file's folder.
    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Read { path: path.into(), source })?;
        let mut scene: Scene =
            toml::from_str(&text).map_err(|e| SceneError::Parse { path: path.into(), detail: one_line(&text, &e) })?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let resolve = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = dir.join(&*p);
            }
        };
        resolve(&mut scene.robot.urdf);
        for o in &mut scene.objects {
            o.mesh.iter_mut().for_each(resolve);
            o.parts.iter_mut().filter_map(|p| p.mesh.as_mut()).for_each(resolve);
        }
        for f in &mut scene.fixtures {
            f.parts.iter_mut().filter_map(|p| p.mesh.as_mut()).for_each(resolve);
            if let Some(j) = &mut f.joint {
                j.parts.iter_mut().filter_map(|p| p.mesh.as_mut()).for_each(resolve);
            }
        }
        scene.task.demonstration.iter_mut().for_each(resolve);
        scene.check().map_err(|detail| SceneError::Invalid { path: path.into(), detail })?;
        Ok(scene)
    }

    /// Names of everything a criterion may refer to besides objects and fixtures.
    pub const TABLE: &'static str = "table";

    fn check(&self) -> Result<(), String> {
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if !(self.timestep_s.is_finite() && self.timestep_s > 0.0 && self.timestep_s <= 0.01) {
            return Err(format!("timestep_s = {}: accepted is a number in (0, 0.01]", self.timestep_s));
        }
        check_name("name", &self.name)?;
        if !finite(&self.robot.initial_joints_rad) {
            return Err("robot.initial_joints_rad: accepted are 7 finite numbers (rad)".into());
        }
        if !finite(&self.robot.base_position_m) || !self.robot.base_yaw_rad.is_finite() {
            return Err("robot.base_position_m / base_yaw_rad: accepted are finite numbers".into());
        }
        if !(self.robot.initial_gripper.is_finite() && (-1.0..=1.0).contains(&self.robot.initial_gripper)) {
            return Err(format!(
                "robot.initial_gripper = {}: accepted is a number in [-1, 1]",
                self.robot.initial_gripper
            ));
        }
        if controllers::Profile::from_name(&self.robot.limits).is_none() {
            return Err(format!("robot.limits = \"{}\": accepted are \"panda\" or \"fr3\"", self.robot.limits));
        }
        if let Some(t) = &self.table {
            if !finite(&t.top_center_m) || !t.size_m.iter().all(|s| s.is_finite() && *s > 0.0) {
                return Err("table: accepted are a finite top_center_m and a positive size_m".into());
            }
        }
        if let Some(s) = &self.safety {
            if s.workspace_min_m.is_some() != s.workspace_max_m.is_some() {
                return Err("safety: accepted are both workspace_min_m and workspace_max_m, or neither".into());
            }
            if let (Some(lo), Some(hi)) = (s.workspace_min_m, s.workspace_max_m) {
                if !(finite(&lo) && finite(&hi) && (0..3).all(|k| lo[k] < hi[k])) {
                    return Err(
                        "safety.workspace_min_m: accepted are finite values below workspace_max_m on every axis".into(),
                    );
                }
            }
            if s.margin_m.is_some_and(|m| !(m.is_finite() && (0.0..0.1).contains(&m))) {
                return Err("safety.margin_m: accepted is a number in [0, 0.1) m".into());
            }
        }
        self.check_cameras()?;
        let mut names = std::collections::HashSet::from([Self::TABLE.to_string()]);
        for (i, o) in self.objects.iter().enumerate() {
            let at = format!("objects[{i}] '{}'", o.name);
            check_name(&format!("objects[{i}].name"), &o.name)?;
            if !names.insert(o.name.clone()) {
                return Err(format!("{at}: the name is already used by another object or fixture (or is 'table')"));
            }
            if !(o.mass_kg.is_finite() && o.mass_kg > 0.0) {
                return Err(format!("{at}: mass_kg = {}: accepted is a positive number of kg", o.mass_kg));
            }
            if !(o.friction.is_finite() && o.friction > 0.0) {
                return Err(format!("{at}: friction = {}: accepted is a positive number", o.friction));
            }
            check_pose(&at, o.position_m, o.quat_wxyz)?;
            match (o.shape.is_some(), o.parts.is_empty()) {
                (true, false) => return Err(format!("{at}: give either shape or parts, not both")),
                (false, true) => return Err(format!("{at}: needs a shape or at least one entry in parts")),
                _ => {}
            }
            let parts = o.all_parts();
            check_parts(&at, &parts)?;
            if !parts.iter().any(|p| p.role != Role::Visual) {
                return Err(format!("{at}: needs at least one part that collides (role both or collision)"));
            }
            check_cavity(&at, o.cavity_min_m, o.cavity_max_m)?;
            let ok_xy = o.jitter_xy_m.is_finite() && (0.0..=0.2).contains(&o.jitter_xy_m);
            let ok_yaw = o.jitter_yaw_deg.is_finite() && (0.0..=180.0).contains(&o.jitter_yaw_deg);
            if !(ok_xy && ok_yaw) {
                return Err(format!("{at}: jitter_xy_m in [0, 0.2] and jitter_yaw_deg in [0, 180] are accepted"));
            }
        }
        for (i, f) in self.fixtures.iter().enumerate() {
            let at = format!("fixtures[{i}] '{}'", f.name);
            check_name(&format!("fixtures[{i}].name"), &f.name)?;
            if !names.insert(f.name.clone()) {
                return Err(format!("{at}: the name is already used by another object or fixture (or is 'table')"));
            }
            check_pose(&at, f.position_m, f.quat_wxyz)?;
            check_parts(&at, &f.parts)?;
            check_cavity(&at, f.cavity_min_m, f.cavity_max_m)?;
            if f.parts.is_empty() && f.joint.is_none() {
                return Err(format!("{at}: needs parts, a joint, or both"));
            }
            if let Some(j) = &f.joint {
                let at = format!("{at}.joint");
                if !finite(&j.axis) || j.axis.iter().map(|a| a * a).sum::<f64>() < 1e-12 {
                    return Err(format!("{at}.axis: accepted is a finite non-zero vector"));
                }
                if !finite(&j.anchor_m) {
                    return Err(format!("{at}.anchor_m: accepted are 3 finite numbers"));
                }
                let (field, range, other) = match j.kind {
                    JointKind::Slide => ("range_m", j.range_m, j.range_deg.is_some()),
                    JointKind::Hinge => ("range_deg", j.range_deg, j.range_m.is_some()),
                };
                if other {
                    return Err(format!("{at}: a {:?} joint takes {field} only", j.kind).to_lowercase());
                }
                let Some([lo, hi]) = range else {
                    return Err(format!("{at}.{field}: missing; accepted is [lower, upper]"));
                };
                if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                    return Err(format!("{at}.{field} = [{lo}, {hi}]: accepted is [lower, upper] with lower < upper"));
                }
                if !(j.initial.is_finite() && (lo..=hi).contains(&j.initial)) {
                    return Err(format!(
                        "{at}.initial = {}: accepted is a value within {field} [{lo}, {hi}]",
                        j.initial
                    ));
                }
                for (v, name) in [(j.damping, "damping"), (j.frictionloss, "frictionloss")] {
                    if !(v.is_finite() && v >= 0.0) {
                        return Err(format!("{at}.{name} = {v}: accepted is a number >= 0"));
                    }
                }
                if !(j.mass_kg.is_finite() && j.mass_kg > 0.0) {
                    return Err(format!("{at}.mass_kg = {}: accepted is a positive number of kg", j.mass_kg));
                }
                if j.parts.is_empty() {
                    return Err(format!("{at}.parts: the moving body needs at least one part"));
                }
                check_parts(&at, &j.parts)?;
            }
        }
        for (i, l) in self.lights.iter().enumerate() {
            if !finite(&l.position_m) || !finite(&l.direction) || !finite(&l.diffuse) {
                return Err(format!("lights[{i}]: accepted are finite position_m, direction and diffuse"));
            }
        }
        self.check_task()
    }

    fn check_cameras(&self) -> Result<(), String> {
        let mut names = std::collections::HashSet::new();
        if self.cameras.len() > ipc_schema::MAX_CAMERAS {
            return Err(format!(
                "cameras: {} given, at most {} are accepted",
                self.cameras.len(),
                ipc_schema::MAX_CAMERAS
            ));
        }
        for (i, c) in self.cameras.iter().enumerate() {
            let at = format!("cameras[{i}] '{}'", c.name);
            check_name(&format!("cameras[{i}].name"), &c.name)?;
            if !names.insert(c.name.clone()) {
                return Err(format!("{at}: the name is already used by another camera"));
            }
            if c.width == 0
                || c.height == 0
                || c.width as usize > ipc_schema::MAX_IMAGE_WIDTH
                || c.height as usize > ipc_schema::MAX_IMAGE_HEIGHT
            {
                return Err(format!(
                    "{at}: {}x{}; accepted are sizes from 1x1 to {}x{}",
                    c.width,
                    c.height,
                    ipc_schema::MAX_IMAGE_WIDTH,
                    ipc_schema::MAX_IMAGE_HEIGHT
                ));
            }
            if let Some(f) = c.fovy_deg {
                if !(f > 1.0 && f < 170.0) {
                    return Err(format!("{at}: fovy_deg = {f}: accepted is a number in (1, 170)"));
                }
            }
            check_intrinsics(&at, c)?;
            let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
            if !finite(&c.position_m) || !finite(&c.look_at_m) || !c.up.is_none_or(|u| finite(&u)) {
                return Err(format!("{at}: position_m, look_at_m and up: accepted are finite numbers"));
            }
        }
        if let Some(first) = self.cameras.first() {
            if self.cameras.iter().any(|c| (c.width, c.height) != (first.width, first.height)) {
                return Err("cameras: all cameras must share one width and height for now".into());
            }
        }
        Ok(())
    }

    fn check_task(&self) -> Result<(), String> {
        let t = &self.task;
        if !(t.demonstration_hz.is_finite() && t.demonstration_hz > 0.0 && t.demonstration_hz <= 1000.0) {
            return Err(format!("task.demonstration_hz = {}: accepted is a number in (0, 1000]", t.demonstration_hz));
        }
        if !(t.max_penetration_m.is_finite() && t.max_penetration_m > 0.0) {
            return Err("task.max_penetration_m: accepted is a positive number of m".into());
        }
        if !(t.settle_s.is_finite() && (0.0..=10.0).contains(&t.settle_s)) {
            return Err("task.settle_s: accepted is a number in [0, 10]".into());
        }
        if let Some(d) = &t.demonstration {
            if !d.is_file() {
                return Err(format!("task.demonstration: file {} does not exist", d.display()));
            }
        }
        let object = |n: &str, i: usize, field: &str| -> Result<(), String> {
            if self.objects.iter().any(|o| o.name == n) {
                Ok(())
            } else {
                Err(format!(
                    "task.success[{i}].{field} = '{n}': accepted are the objects ({})",
                    self.objects.iter().map(|o| o.name.as_str()).collect::<Vec<_>>().join(", ")
                ))
            }
        };
        let anything = |n: &str, i: usize, field: &str| -> Result<(), String> {
            if n == Self::TABLE || self.objects.iter().any(|o| o.name == n) || self.fixtures.iter().any(|f| f.name == n)
            {
                Ok(())
            } else {
                Err(format!(
                    "task.success[{i}].{field} = '{n}': accepted are 'table' and the names of objects and fixtures"
                ))
            }
        };
        for (i, c) in t.success.iter().enumerate() {
            match c {
                Criterion::Inside { object: o, container, min_m, max_m } => {
                    object(o, i, "object")?;
                    match (container, min_m, max_m) {
                        (Some(cn), None, None) => {
                            let has = self.objects.iter().any(|x| &x.name == cn && x.cavity_min_m.is_some())
                                || self.fixtures.iter().any(|x| &x.name == cn && x.cavity_min_m.is_some());
                            if !has {
                                return Err(format!(
                                    "task.success[{i}].container = '{cn}': accepted is an object or fixture with cavity_min_m/cavity_max_m"
                                ));
                            }
                        }
                        (None, Some(lo), Some(hi)) => {
                            check_cavity(&format!("task.success[{i}]"), Some(*lo), Some(*hi))?
                        }
                        _ => {
                            return Err(format!(
                                "task.success[{i}] (inside): accepted is either container or both min_m and max_m"
                            ))
                        }
                    }
                }
                Criterion::On { object: o, support } => {
                    object(o, i, "object")?;
                    anything(support, i, "support")?;
                }
                Criterion::TouchesOnly { object: o, others } => {
                    object(o, i, "object")?;
                    for n in others {
                        anything(n, i, "others")?;
                    }
                }
                Criterion::Joint { fixture, min, max } => {
                    if !self.fixtures.iter().any(|f| &f.name == fixture && f.joint.is_some()) {
                        return Err(format!(
                            "task.success[{i}].fixture = '{fixture}': accepted is a fixture with a joint"
                        ));
                    }
                    if min.is_none() && max.is_none()
                        || !min.unwrap_or(0.0).is_finite()
                        || !max.unwrap_or(0.0).is_finite()
                    {
                        return Err(format!("task.success[{i}] (joint): accepted is a finite min, max, or both"));
                    }
                }
                Criterion::Upright { object: o, tolerance_deg } => {
                    object(o, i, "object")?;
                    if !(tolerance_deg.is_finite() && *tolerance_deg > 0.0 && *tolerance_deg < 90.0) {
                        return Err(format!("task.success[{i}].tolerance_deg: accepted is a number in (0, 90)"));
                    }
                }
                Criterion::Released { objects, min_distance_m, window_s, .. } => {
                    for o in objects {
                        object(o, i, "objects")?;
                    }
                    if !(min_distance_m.is_finite() && *min_distance_m >= 0.0) {
                        return Err(format!("task.success[{i}].min_distance_m: accepted is a number >= 0"));
                    }
                    if !(window_s.is_finite() && *window_s >= 0.0) {
                        return Err(format!("task.success[{i}].window_s: accepted is a number >= 0"));
                    }
                }
                Criterion::Stable { objects, fixtures, duration_s, max_speed_m_s, max_joint_deg_s } => {
                    for o in objects {
                        object(o, i, "objects")?;
                    }
                    for f in fixtures {
                        if !self.fixtures.iter().any(|x| &x.name == f && x.joint.is_some()) {
                            return Err(format!(
                                "task.success[{i}].fixtures = '{f}': accepted are fixtures with a joint"
                            ));
                        }
                    }
                    let ok_duration = duration_s.is_finite() && *duration_s > 0.0 && *duration_s <= 60.0;
                    let ok_speed = max_speed_m_s.is_finite() && *max_speed_m_s > 0.0;
                    let ok_joint = max_joint_deg_s.is_finite() && *max_joint_deg_s > 0.0;
                    if !(ok_duration && ok_speed && ok_joint) || objects.is_empty() && fixtures.is_empty() {
                        return Err(format!(
                            "task.success[{i}] (stable): accepted are objects and/or fixtures, and positive duration_s, max_speed_m_s and max_joint_deg_s"
                        ));
                    }
                }
                Criterion::Apart { a, b } => {
                    for (n, field) in [(a, "a"), (b, "b")] {
                        if n != "robot" {
                            anything(n, i, field)?;
                        }
                    }
                }
                Criterion::Past { object: o, axis, above, below } => {
                    object(o, i, "object")?;
                    if *axis > 2 || above.is_none() && below.is_none() {
                        return Err(format!(
                            "task.success[{i}] (past): accepted are axis 0, 1 or 2 and above, below or both"
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}

/// `fx, fy, cx, cy`: all four or none, not with `fovy_deg`, focal lengths positive, the
/// principal point on the image (pixel-index convention: from 0 to width - 1 and height - 1).
pub(crate) fn check_intrinsics(at: &str, c: &CameraSpec) -> Result<(), String> {
    let fields = [("fx", c.fx), ("fy", c.fy), ("cx", c.cx), ("cy", c.cy)];
    let given: Vec<&str> = fields.iter().filter(|(_, v)| v.is_some()).map(|(n, _)| *n).collect();
    if given.is_empty() {
        return Ok(());
    }
    if given.len() != 4 {
        let missing: Vec<&str> = fields.iter().filter(|(_, v)| v.is_none()).map(|(n, _)| *n).collect();
        return Err(format!(
            "{at}: intrinsics need all four of fx, fy, cx, cy or none; given {}, missing {}",
            given.join(", "),
            missing.join(", ")
        ));
    }
    if c.fovy_deg.is_some() {
        return Err(format!(
            "{at}: fovy_deg and fx, fy, cx, cy both given; accepted is one of them (fy sets the field of view)"
        ));
    }
    for (name, v) in &fields[..2] {
        let v = v.unwrap_or(f64::NAN);
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("{at}: {name} = {v}: accepted is a positive number of pixels"));
        }
    }
    for (name, v, size) in [("cx", c.cx, c.width), ("cy", c.cy, c.height)] {
        let v = v.unwrap_or(f64::NAN);
        let hi = size as f64 - 1.0;
        if !(v.is_finite() && (0.0..=hi).contains(&v)) {
            return Err(format!(
                "{at}: {name} = {v}: accepted is a pixel coordinate in [0, {hi}] (pixel centres count from 0)"
            ));
        }
    }
    Ok(())
}

fn check_name(field: &str, name: &str) -> Result<(), String> {
    if name.is_empty()
        || name.len() >= ipc_schema::NAME_LEN
        || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
    {
        return Err(format!("{field} = '{name}': accepted are 1-31 characters of a-z A-Z 0-9 _"));
    }
    Ok(())
}

fn check_pose(at: &str, p: [f64; 3], q: [f64; 4]) -> Result<(), String> {
    if !p.iter().all(|x| x.is_finite()) {
        return Err(format!("{at}: position_m = {p:?}: accepted are 3 finite numbers"));
    }
    let n = q.iter().map(|x| x * x).sum::<f64>();
    if !(n.is_finite() && n > 1e-6) {
        return Err(format!("{at}: quat_wxyz = {q:?}: accepted is a finite non-zero quaternion (w, x, y, z)"));
    }
    Ok(())
}

fn check_cavity(at: &str, lo: Option<[f64; 3]>, hi: Option<[f64; 3]>) -> Result<(), String> {
    match (lo, hi) {
        (None, None) => Ok(()),
        (Some(lo), Some(hi)) if (0..3).all(|k| lo[k].is_finite() && hi[k].is_finite() && lo[k] < hi[k]) => Ok(()),
        _ => Err(format!("{at}: accepted is a box given by both min and max corners, min below max on every axis")),
    }
}

fn check_parts(at: &str, parts: &[PartSpec]) -> Result<(), String> {
    for (k, p) in parts.iter().enumerate() {
        let at = if parts.len() == 1 { at.to_string() } else { format!("{at}.parts[{k}]") };
        check_pose(&at, p.position_m, p.quat_wxyz)?;
        let want = match p.shape {
            Shape::Box => 3,
            Shape::Cylinder | Shape::Capsule => 2,
            Shape::Sphere => 1,
            Shape::Mesh => 0,
        };
        if p.shape == Shape::Mesh {
            let Some(m) = &p.mesh else {
                return Err(format!("{at}: shape \"mesh\" needs a mesh file (.obj or .stl)"));
            };
            let ext = m.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
            if ext != "obj" && ext != "stl" {
                return Err(format!("{at}: mesh {}: accepted are .obj and .stl files", m.display()));
            }
            if !m.is_file() {
                return Err(format!("{at}: mesh file {} does not exist", m.display()));
            }
            if !p.mesh_scale.iter().all(|s| s.is_finite() && *s > 0.0) {
                return Err(format!("{at}: mesh_scale: accepted are 3 positive numbers"));
            }
        } else {
            if p.mesh.is_some() {
                return Err(format!("{at}: mesh is only accepted with shape = \"mesh\""));
            }
            if p.size_m.len() != want || !p.size_m.iter().all(|s| s.is_finite() && *s > 0.0) {
                return Err(format!("{at}: size_m = {:?}: a {:?} accepts {want} positive numbers", p.size_m, p.shape)
                    .replace("Box", "box")
                    .replace("Cylinder", "cylinder")
                    .replace("Capsule", "capsule")
                    .replace("Sphere", "sphere"));
            }
        }
        if p.rgba.is_some_and(|c| !c.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x))) {
            return Err(format!("{at}: rgba: accepted are 4 numbers in [0, 1]"));
        }
    }
    Ok(())
}

/// Volume of a primitive part (meshes: None, MuJoCo computes theirs).
pub fn part_volume(p: &PartSpec) -> Option<f64> {
    let s = &p.size_m;
    let pi = std::f64::consts::PI;
    Some(match p.shape {
        Shape::Box => 8.0 * s[0] * s[1] * s[2],
        Shape::Cylinder => pi * s[0] * s[0] * 2.0 * s[1],
        Shape::Capsule => pi * s[0] * s[0] * 2.0 * s[1] + 4.0 / 3.0 * pi * s[0].powi(3),
        Shape::Sphere => 4.0 / 3.0 * pi * s[0].powi(3),
        Shape::Mesh => return None,
    })
}
