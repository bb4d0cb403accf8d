//! The scene spec: a TOML file naming the robot, cameras and objects of a gym.
//! Paths inside it are relative to the file. The full spec (fixtures, meshes, task criteria)
//! grows with the sim-host issue; unknown fields are refused so typos never pass silently.

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
    /// What the task asks, in plain language.
    #[serde(default)]
    pub instruction: String,
    pub robot: RobotSpec,
    #[serde(default)]
    pub table: Option<TableSpec>,
    #[serde(default)]
    pub cameras: Vec<CameraSpec>,
    #[serde(default)]
    pub objects: Vec<ObjectSpec>,
    /// Physics timestep; one command sample is applied per step.
    #[serde(default = "default_timestep")]
    pub timestep_s: f64,
    #[serde(default)]
    pub safety: Option<SafetySpec>,
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
    #[serde(default = "default_fovy")]
    pub fovy_deg: f64,
    #[serde(default = "default_width")]
    pub width: u32,
    #[serde(default = "default_height")]
    pub height: u32,
}

fn default_fovy() -> f64 {
    45.0
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
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectSpec {
    pub name: String,
    pub shape: Shape,
    /// MuJoCo size convention: box half-extents; cylinder/capsule radius and half-length; sphere radius.
    pub size_m: Vec<f64>,
    pub position_m: [f64; 3],
    #[serde(default = "default_quat")]
    pub quat_wxyz: [f64; 4],
    #[serde(default = "default_mass")]
    pub mass_kg: f64,
    #[serde(default = "default_friction")]
    pub friction: f64,
    #[serde(default = "default_rgba")]
    pub rgba: [f64; 4],
    /// False for objects welded to the world.
    #[serde(default = "default_true")]
    pub free: bool,
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

impl Scene {
    /// Reads and checks a scene file; the robot path is resolved against the file's folder.
    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Read { path: path.into(), source })?;
        let mut scene: Scene =
            toml::from_str(&text).map_err(|e| SceneError::Parse { path: path.into(), detail: e.to_string() })?;
        let dir = path.parent().unwrap_or(Path::new("."));
        if scene.robot.urdf.is_relative() {
            scene.robot.urdf = dir.join(&scene.robot.urdf);
        }
        scene.check().map_err(|detail| SceneError::Invalid { path: path.into(), detail })?;
        Ok(scene)
    }

    fn check(&self) -> Result<(), String> {
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if !(self.timestep_s.is_finite() && self.timestep_s > 0.0 && self.timestep_s <= 0.01) {
            return Err(format!("timestep_s = {} must be in (0, 0.01]", self.timestep_s));
        }
        if !finite(&self.robot.initial_joints_rad) || !finite(&self.robot.base_position_m) {
            return Err("robot values must be finite numbers".into());
        }
        if controllers::Profile::from_name(&self.robot.limits).is_none() {
            return Err(format!("robot limits = \"{}\" is unknown: use \"panda\" or \"fr3\"", self.robot.limits));
        }
        if let Some(s) = &self.safety {
            if s.workspace_min_m.is_some() != s.workspace_max_m.is_some() {
                return Err("[safety] needs both workspace_min_m and workspace_max_m, or neither".into());
            }
            if let (Some(lo), Some(hi)) = (s.workspace_min_m, s.workspace_max_m) {
                if !(finite(&lo) && finite(&hi) && (0..3).all(|k| lo[k] < hi[k])) {
                    return Err(
                        "[safety] workspace_min_m must be finite and below workspace_max_m on every axis".into()
                    );
                }
            }
            if s.margin_m.is_some_and(|m| !(m.is_finite() && (0.0..0.1).contains(&m))) {
                return Err("[safety] margin_m must be in [0, 0.1) m".into());
            }
        }
        let mut names = std::collections::HashSet::new();
        if self.cameras.len() > ipc_schema::MAX_CAMERAS {
            return Err(format!(
                "{} cameras given, at most {} are supported",
                self.cameras.len(),
                ipc_schema::MAX_CAMERAS
            ));
        }
        for c in &self.cameras {
            if !names.insert(c.name.clone()) {
                return Err(format!("camera name '{}' is used twice", c.name));
            }
            if c.name.is_empty()
                || c.name.len() >= ipc_schema::NAME_LEN
                || !c.name.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_')
            {
                return Err(format!("camera name '{}' must be 1-31 characters of a-z A-Z 0-9 _", c.name));
            }
            if c.width == 0
                || c.height == 0
                || c.width as usize > ipc_schema::MAX_IMAGE_WIDTH
                || c.height as usize > ipc_schema::MAX_IMAGE_HEIGHT
            {
                return Err(format!(
                    "camera '{}' is {}x{}; sizes from 1x1 to {}x{} are supported",
                    c.name,
                    c.width,
                    c.height,
                    ipc_schema::MAX_IMAGE_WIDTH,
                    ipc_schema::MAX_IMAGE_HEIGHT
                ));
            }
            if !(c.fovy_deg > 1.0 && c.fovy_deg < 170.0) {
                return Err(format!("camera '{}' fovy_deg = {} must be in (1, 170)", c.name, c.fovy_deg));
            }
            if !finite(&c.position_m) || !finite(&c.look_at_m) {
                return Err(format!("camera '{}' has a non-finite position or look_at", c.name));
            }
        }
        if let Some(first) = self.cameras.first() {
            if self.cameras.iter().any(|c| (c.width, c.height) != (first.width, first.height)) {
                return Err("all cameras must share one resolution for now".into());
            }
        }
        for o in &self.objects {
            if !names.insert(o.name.clone()) {
                return Err(format!("name '{}' is used twice", o.name));
            }
            let want = match o.shape {
                Shape::Box => 3,
                Shape::Cylinder | Shape::Capsule => 2,
                Shape::Sphere => 1,
            };
            if o.size_m.len() != want || !o.size_m.iter().all(|s| s.is_finite() && *s > 0.0) {
                return Err(format!("object '{}' ({:?}) needs size_m of {want} positive numbers", o.name, o.shape));
            }
            if !(o.mass_kg.is_finite() && o.mass_kg > 0.0 && finite(&o.position_m) && finite(&o.quat_wxyz)) {
                return Err(format!("object '{}' needs a positive mass and finite pose", o.name));
            }
        }
        Ok(())
    }
}
