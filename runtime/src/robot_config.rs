//! `config/robot.json`: which profile the runtime follows and the limits it adds on top of the
//! robot's own (chunk length, step caps, Franka contact thresholds). Parsed strictly: an
//! unknown key or an unusable value is an error naming the key and what is accepted. The
//! calibration files it names are read by [`crate::calibration`].

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use controllers::LimiterConfig;
use ipc_schema::{Profile, MAX_CAMERAS, MAX_CHUNK, NAME_LEN};
use serde_json::{Map, Value};

/// Franka profile: contact forces (magnitude of the filtered external force, N) that stop a chunk.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reflexes {
    /// Stops the chunk; the arm recovers by itself (`recovered_replan_required`).
    pub reflex_force_n: f64,
    /// Stops the chunk and holds the arm until an operator clears it (`operator_required`).
    pub operator_force_n: f64,
    /// A second reflex of the real robot within this many seconds needs an operator.
    pub window_s: f64,
    /// Real arm (FCI): joint torques above which the robot reports a contact, and above which
    /// its own collision reflex stops it, Nm (the robot's set-collision-behaviour thresholds,
    /// the same in its acceleration and constant-velocity phases).
    pub contact_torque_nm: [f64; 7],
    pub collision_torque_nm: [f64; 7],
    /// The same for the Cartesian force/torque at the end effector (x, y, z in N, then the
    /// moments in Nm).
    pub contact_force_n: [f64; 6],
    pub collision_force_n: [f64; 6],
}

#[derive(Debug, Clone, PartialEq)]
pub struct RobotConfig {
    pub profile: Profile,
    pub default_freq_hz: f64,
    pub max_chunk_waypoints: usize,
    pub max_joint_step_rad: f64,
    pub max_tcp_step_m: f64,
    pub max_tcp_step_rad: f64,
    pub reflexes: Reflexes,
    /// Calibration files (`calibration` table); read at start by [`crate::calibration`].
    pub calibration: CalibrationFiles,
    /// Which gripper the arm carries (`gripper` table).
    pub gripper: Gripper,
    /// Cameras that are devices (`cameras` table), sorted by name; each runs in a camera host.
    pub cameras: Vec<CameraDevice>,
}

/// The gripper a robot config names (`gripper.driver`).
#[derive(Debug, Clone, PartialEq, Default)]
pub enum Gripper {
    /// The robot side's own fingers: the simulated ones in r2g-sim; none with a real arm.
    #[default]
    Sim,
    /// The Franka Hand, driven by r2g-fci over the arm's network link.
    FrankaHand,
    /// A Robotiq 2F-85 on a serial port (Modbus RTU), driven by its own process, `r2g-robotiq`.
    Robotiq2f85(Robotiq),
}

/// A Robotiq 2F-85's link and settings (`gripper` with `"driver": "robotiq_2f85"`).
#[derive(Debug, Clone, PartialEq)]
pub struct Robotiq {
    /// Serial device, e.g. `/dev/ttyUSB0` (better: a stable `/dev/serial/by-id/...` link).
    pub port: PathBuf,
    /// Modbus slave id (the gripper's default is 9).
    pub slave: u8,
    pub baud: u32,
    /// Finger speed (0..255, the device's own scale) and grip force (0..255).
    pub speed: u8,
    pub force: u8,
    /// Position count at which the fingers touch (fully closed); 0 is fully open.
    pub closed_count: u8,
}

impl Gripper {
    /// The `driver` name as the config writes it.
    pub fn driver(&self) -> &'static str {
        match self {
            Self::Sim => "sim",
            Self::FrankaHand => "franka_hand",
            Self::Robotiq2f85(_) => "robotiq_2f85",
        }
    }
}

/// A camera device a robot config names (`cameras.NAME`).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraDevice {
    pub name: String,
    pub driver: CameraDriver,
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    /// Publish depth too (RealSense only).
    pub depth: bool,
}

/// Where a camera's frames come from.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraDriver {
    /// An Intel RealSense, by serial number (librealsense2).
    Realsense { serial: String },
    /// A UVC camera through V4L2, by device path (RGB only).
    Uvc { device: PathBuf },
    /// Frames from a file fed through librealsense's software device: the RealSense code path
    /// without hardware (tests, offline checks); `frames`: end the host after that many (a
    /// camera that stops), None: loop for ever.
    Replay { file: PathBuf, frames: Option<u32> },
}

impl CameraDevice {
    /// The camera host's arguments after `--instance NAME`.
    pub fn host_args(&self) -> Vec<String> {
        let mut a = vec!["--camera".to_string(), self.name.clone()];
        match &self.driver {
            CameraDriver::Realsense { serial } => {
                a.extend(["--driver".into(), "realsense".into(), "--serial".into(), serial.clone()])
            }
            CameraDriver::Uvc { device } => {
                a.extend(["--driver".into(), "uvc".into(), "--device".into(), device.display().to_string()])
            }
            CameraDriver::Replay { file, frames } => {
                a.extend(["--driver".into(), "replay".into(), "--replay".into(), file.display().to_string()]);
                if let Some(n) = frames {
                    a.extend(["--frames".into(), n.to_string()]);
                }
            }
        }
        a.extend([
            "--width".into(),
            self.width.to_string(),
            "--height".into(),
            self.height.to_string(),
            "--fps".into(),
            self.fps.to_string(),
        ]);
        if !self.depth {
            a.push("--no-depth".into());
        }
        a
    }
}

fn gripper(v: Option<&Value>) -> anyhow::Result<Gripper> {
    let Some(v) = v else { return Ok(Gripper::Sim) };
    let m = table(v, "gripper", &["driver", "port", "slave", "baud", "speed", "force", "closed_count"])?;
    let driver = m.get("driver").and_then(Value::as_str);
    let only_driver = |name: &str| -> anyhow::Result<()> {
        if let Some(k) = m.keys().find(|k| *k != "driver") {
            bail!("gripper.{k} does not apply to the {name} gripper (only robotiq_2f85 takes settings)");
        }
        Ok(())
    };
    match driver {
        Some("sim") => only_driver("sim").map(|_| Gripper::Sim),
        Some("franka_hand") => only_driver("franka_hand").map(|_| Gripper::FrankaHand),
        Some("robotiq_2f85") => {
            let port = match m.get("port").and_then(Value::as_str) {
                Some(p) if p.starts_with('/') && p.len() <= 200 && !p.chars().any(char::is_control) => PathBuf::from(p),
                _ => bail!("gripper.port must be the absolute path of the serial device, e.g. \"/dev/ttyUSB0\""),
            };
            let whole = |key: &str, default: f64, lo: f64, hi: f64| -> anyhow::Result<f64> {
                let x = number(m, "gripper", key, default, lo, hi)?;
                if x.fract() != 0.0 {
                    bail!("gripper.{key} = {x} must be a whole number");
                }
                Ok(x)
            };
            let baud = whole("baud", 115200.0, 1200.0, 1_000_000.0)? as u32;
            Ok(Gripper::Robotiq2f85(Robotiq {
                port,
                slave: whole("slave", 9.0, 1.0, 247.0)? as u8,
                baud,
                speed: whole("speed", 255.0, 0.0, 255.0)? as u8,
                force: whole("force", 100.0, 0.0, 255.0)? as u8,
                closed_count: whole("closed_count", 230.0, 100.0, 255.0)? as u8,
            }))
        }
        _ => bail!("gripper.driver must be \"sim\", \"franka_hand\" or \"robotiq_2f85\", got {:?}", m.get("driver")),
    }
}

fn cameras(v: Option<&Value>, calibration: &CalibrationFiles) -> anyhow::Result<Vec<CameraDevice>> {
    let Some(v) = v else { return Ok(Vec::new()) };
    let Some(m) = v.as_object() else { bail!("cameras must be an object camera name → its device") };
    if m.len() > MAX_CAMERAS {
        bail!("cameras names {} cameras, at most {MAX_CAMERAS} are accepted", m.len());
    }
    let mut out = Vec::new();
    for (name, v) in m {
        if name.is_empty()
            || name.len() > NAME_LEN
            || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            bail!("cameras: \"{name}\" is not a camera name (1 to {NAME_LEN} of A-Z a-z 0-9 _ -)");
        }
        let what = format!("cameras.{name}");
        let c = table(v, &what, &["driver", "serial", "device", "file", "frames", "width", "height", "fps", "depth"])?;
        let text = |key: &str| {
            c.get(key)
                .and_then(Value::as_str)
                .filter(|s| !s.is_empty() && s.len() <= 200 && !s.chars().any(char::is_control))
        };
        let driver = match c.get("driver").and_then(Value::as_str) {
            Some("realsense") => CameraDriver::Realsense {
                serial: text("serial")
                    .filter(|s| s.chars().all(|c| c.is_ascii_alphanumeric()))
                    .ok_or_else(|| {
                        anyhow::anyhow!("{what}.serial must be the RealSense's serial number (letters and digits)")
                    })?
                    .to_string(),
            },
            Some("uvc") => CameraDriver::Uvc {
                device: text("device")
                    .filter(|s| s.starts_with('/'))
                    .ok_or_else(|| {
                        anyhow::anyhow!(
                            "{what}.device must be the absolute path of a V4L2 device, e.g. \"/dev/video0\""
                        )
                    })?
                    .into(),
            },
            Some("replay") => CameraDriver::Replay {
                file: text("file")
                    .ok_or_else(|| anyhow::anyhow!("{what}.file must name a .npz of recorded frames"))?
                    .into(),
                frames: match c.get("frames") {
                    None => None,
                    Some(v) => Some(v.as_u64().filter(|n| (1..=u64::from(u32::MAX)).contains(n)).ok_or_else(|| {
                        anyhow::anyhow!("{what}.frames must be a whole number of frames, at least 1, got {v}")
                    })? as u32),
                },
            },
            other => bail!("{what}.driver must be \"realsense\", \"uvc\" or \"replay\", got {other:?}"),
        };
        let allowed: &[&str] = match driver {
            CameraDriver::Realsense { .. } => &["serial"],
            CameraDriver::Uvc { .. } => &["device"],
            CameraDriver::Replay { .. } => &["file", "frames"],
        };
        if let Some(k) =
            ["serial", "device", "file", "frames"].iter().find(|k| c.contains_key(**k) && !allowed.contains(k))
        {
            bail!("{what}.{k} does not apply to its driver");
        }
        let whole = |key: &str, default: f64, lo: f64, hi: f64| -> anyhow::Result<u32> {
            let x = number(c, &what, key, default, lo, hi)?;
            if x.fract() != 0.0 {
                bail!("{what}.{key} = {x} must be a whole number");
            }
            Ok(x as u32)
        };
        let depth = match c.get("depth") {
            None => !matches!(driver, CameraDriver::Uvc { .. }),
            Some(Value::Bool(b)) => *b,
            Some(v) => bail!("{what}.depth must be true or false, got {v}"),
        };
        if depth && matches!(driver, CameraDriver::Uvc { .. }) {
            bail!("{what}.depth: a UVC camera gives no depth");
        }
        if !calibration.cameras.iter().any(|(n, _)| n == name) {
            bail!(
                "{what} has no calibration file (calibration.cameras.{name}): where the camera sits is unknown, so its \
                 images cannot be related to the robot; add one (runtime/README.md, \"Calibration\")"
            );
        }
        out.push(CameraDevice {
            name: name.clone(),
            driver,
            width: whole("width", 640.0, 16.0, ipc_schema::MAX_IMAGE_WIDTH as f64)?,
            height: whole("height", 480.0, 16.0, ipc_schema::MAX_IMAGE_HEIGHT as f64)?,
            fps: whole("fps", 30.0, 1.0, 90.0)?,
            depth,
        });
    }
    out.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(out)
}

/// The calibration files a robot config names. [`RobotConfig::load`] resolves relative paths
/// against the config file's folder; [`RobotConfig::parse`] keeps them as written.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CalibrationFiles {
    /// Measured flange-to-TCP transform (`calibration.tcp`); None: the description's TCP.
    pub tcp: Option<PathBuf>,
    /// Camera name → its calibration file (`calibration.cameras`), sorted by name.
    pub cameras: Vec<(String, PathBuf)>,
}

/// Longest calibration path accepted, bytes (so that the report always fits its buffer).
pub const MAX_CALIBRATION_PATH: usize = 256;

impl CalibrationFiles {
    fn parse(m: &Map<String, Value>) -> anyhow::Result<Self> {
        let path = |what: &str, v: &Value| -> anyhow::Result<PathBuf> {
            match v.as_str() {
                Some(p) if !p.is_empty() && p.len() <= MAX_CALIBRATION_PATH && !p.chars().any(char::is_control) => {
                    Ok(PathBuf::from(p))
                }
                _ => bail!(
                    "{what} must be a file path (1 to {MAX_CALIBRATION_PATH} bytes, no control characters), got {v}"
                ),
            }
        };
        let tcp = m.get("tcp").map(|v| path("calibration.tcp", v)).transpose()?;
        let mut cameras = Vec::new();
        if let Some(v) = m.get("cameras") {
            let Some(c) = v.as_object() else {
                bail!("calibration.cameras must be an object camera name → file path")
            };
            if c.len() > MAX_CAMERAS {
                bail!("calibration.cameras names {} cameras, at most {MAX_CAMERAS} are accepted", c.len());
            }
            for (name, v) in c {
                let ok = (1..=NAME_LEN).contains(&name.len())
                    && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
                if !ok {
                    bail!("calibration.cameras: \"{name}\" is not a camera name (1 to {NAME_LEN} of A-Z a-z 0-9 _ -)");
                }
                cameras.push((name.clone(), path(&format!("calibration.cameras.{name}"), v)?));
            }
        }
        Ok(Self { tcp, cameras })
    }

    /// Relative paths made relative to `dir` (and absolute, for the report).
    fn resolved(mut self, dir: &Path) -> anyhow::Result<Self> {
        let fix = |p: &mut PathBuf| -> anyhow::Result<()> {
            let joined = dir.join(&*p);
            *p = std::path::absolute(&joined).unwrap_or(joined);
            if p.as_os_str().len() > MAX_CALIBRATION_PATH {
                bail!("calibration file {} is a path of more than {MAX_CALIBRATION_PATH} bytes", p.display());
            }
            Ok(())
        };
        if let Some(p) = &mut self.tcp {
            fix(p)?;
        }
        for (_, p) in &mut self.cameras {
            fix(p)?;
        }
        Ok(self)
    }
}

impl Default for RobotConfig {
    /// The shipped `robot-skill/config/robot.json`.
    fn default() -> Self {
        Self {
            profile: Profile::Simulation,
            default_freq_hz: 20.0,
            max_chunk_waypoints: MAX_CHUNK,
            max_joint_step_rad: 0.35,
            max_tcp_step_m: 0.05,
            max_tcp_step_rad: 0.35,
            reflexes: Reflexes {
                reflex_force_n: 30.0,
                operator_force_n: 80.0,
                window_s: 10.0,
                contact_torque_nm: [20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0],
                collision_torque_nm: [20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0],
                contact_force_n: [20.0; 6],
                collision_force_n: [20.0; 6],
            },
            calibration: CalibrationFiles::default(),
            gripper: Gripper::Sim,
            cameras: Vec::new(),
        }
    }
}

fn table<'a>(v: &'a Value, what: &str, keys: &[&str]) -> anyhow::Result<&'a Map<String, Value>> {
    let Some(m) = v.as_object() else { bail!("{what} must be a JSON object") };
    if let Some(k) = m.keys().find(|k| !keys.contains(&k.as_str())) {
        bail!("{what} has an unknown key \"{k}\"; accepted: {}", keys.join(", "));
    }
    Ok(m)
}

/// `N` numbers from `m[key]`, each within `lo..=hi`, or `default` when absent.
fn numbers<const N: usize>(
    m: &Map<String, Value>,
    what: &str,
    key: &str,
    default: [f64; N],
    lo: f64,
    hi: f64,
) -> anyhow::Result<[f64; N]> {
    let Some(v) = m.get(key) else { return Ok(default) };
    let Some(a) = v.as_array().filter(|a| a.len() == N) else {
        bail!("{what}.{key} must be a list of {N} numbers, got {v}")
    };
    let mut out = [0.0; N];
    for (o, x) in out.iter_mut().zip(a) {
        match x.as_f64() {
            Some(x) if x.is_finite() && (lo..=hi).contains(&x) => *o = x,
            _ => bail!("{what}.{key}: {x} is not a number in the accepted range [{lo}, {hi}]"),
        }
    }
    Ok(out)
}

/// A number from `m[key]` within `lo..=hi`, or `default` when absent.
fn number(m: &Map<String, Value>, what: &str, key: &str, default: f64, lo: f64, hi: f64) -> anyhow::Result<f64> {
    let Some(v) = m.get(key) else { return Ok(default) };
    let Some(x) = v.as_f64() else { bail!("{what}.{key} must be a number, got {v}") };
    if !(x.is_finite() && (lo..=hi).contains(&x)) {
        bail!("{what}.{key} = {x} is outside the accepted range [{lo}, {hi}]");
    }
    Ok(x)
}

impl RobotConfig {
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let root: Value = serde_json::from_str(text).context("not valid JSON")?;
        let top = table(&root, "robot.json", &["profile", "control", "franka", "calibration", "gripper", "cameras"])?;
        let d = Self::default();
        let profile = match top.get("profile") {
            None => bail!("robot.json has no \"profile\": use \"simulation\" or \"franka\""),
            Some(v) if v == "simulation" => Profile::Simulation,
            Some(v) if v == "franka" => Profile::Franka,
            Some(v) => bail!("robot.json \"profile\": {v} is unknown: use \"simulation\" or \"franka\""),
        };
        let empty = Value::Object(Map::new());
        let control = table(
            top.get("control").unwrap_or(&empty),
            "control",
            &["default_freq_hz", "max_chunk_waypoints", "max_joint_step_rad", "max_tcp_step_m", "max_tcp_step_rad"],
        )?;
        let franka = table(
            top.get("franka").unwrap_or(&empty),
            "franka",
            &[
                "reflex_force_n",
                "operator_force_n",
                "reflex_window_s",
                "contact_torque_nm",
                "collision_torque_nm",
                "contact_force_n",
                "collision_force_n",
            ],
        )?;
        let calibration = table(top.get("calibration").unwrap_or(&empty), "calibration", &["tcp", "cameras"])?;
        let r = &d.reflexes;
        let chunk =
            number(control, "control", "max_chunk_waypoints", d.max_chunk_waypoints as f64, 1.0, MAX_CHUNK as f64)?;
        if chunk.fract() != 0.0 {
            bail!("control.max_chunk_waypoints = {chunk} must be a whole number");
        }
        let c = Self {
            profile,
            default_freq_hz: number(control, "control", "default_freq_hz", d.default_freq_hz, 0.5, 1000.0)?,
            max_chunk_waypoints: chunk as usize,
            max_joint_step_rad: number(control, "control", "max_joint_step_rad", d.max_joint_step_rad, 1e-3, 10.0)?,
            max_tcp_step_m: number(control, "control", "max_tcp_step_m", d.max_tcp_step_m, 1e-4, 5.0)?,
            max_tcp_step_rad: number(control, "control", "max_tcp_step_rad", d.max_tcp_step_rad, 1e-3, 10.0)?,
            reflexes: Reflexes {
                reflex_force_n: number(franka, "franka", "reflex_force_n", d.reflexes.reflex_force_n, 1.0, 1000.0)?,
                operator_force_n: number(
                    franka,
                    "franka",
                    "operator_force_n",
                    d.reflexes.operator_force_n,
                    1.0,
                    1000.0,
                )?,
                window_s: number(franka, "franka", "reflex_window_s", r.window_s, 0.0, 3600.0)?,
                contact_torque_nm: numbers(franka, "franka", "contact_torque_nm", r.contact_torque_nm, 0.1, 200.0)?,
                collision_torque_nm: numbers(
                    franka,
                    "franka",
                    "collision_torque_nm",
                    r.collision_torque_nm,
                    0.1,
                    200.0,
                )?,
                contact_force_n: numbers(franka, "franka", "contact_force_n", r.contact_force_n, 0.1, 200.0)?,
                collision_force_n: numbers(franka, "franka", "collision_force_n", r.collision_force_n, 0.1, 200.0)?,
            },
            calibration: CalibrationFiles::parse(calibration)?,
            gripper: gripper(top.get("gripper"))?,
            cameras: Vec::new(),
        };
        let mut c = c;
        c.cameras = cameras(top.get("cameras"), &c.calibration)?;
        let r = &c.reflexes;
        let pairs = r
            .contact_torque_nm
            .iter()
            .zip(&r.collision_torque_nm)
            .chain(r.contact_force_n.iter().zip(&r.collision_force_n));
        if pairs.into_iter().any(|(lo, hi)| lo > hi) {
            bail!("franka: every contact_* threshold must be at most the matching collision_* threshold");
        }
        Ok(c)
    }

    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let mut c = Self::parse(&text).with_context(|| format!("robot config {}", path.display()))?;
        let dir = path.parent().unwrap_or(Path::new("."));
        c.calibration = c.calibration.resolved(dir).with_context(|| format!("robot config {}", path.display()))?;
        for cam in &mut c.cameras {
            if let CameraDriver::Replay { file, .. } = &mut cam.driver {
                let joined = dir.join(&*file);
                *file = std::path::absolute(&joined).unwrap_or(joined);
            }
        }
        Ok(c)
    }

    /// The limiter settings with this configuration's caps.
    pub fn limiter(&self) -> LimiterConfig {
        LimiterConfig {
            default_freq_hz: self.default_freq_hz,
            max_chunk: self.max_chunk_waypoints,
            max_joint_step_rad: self.max_joint_step_rad,
            max_tcp_step_m: self.max_tcp_step_m,
            max_tcp_step_rad: self.max_tcp_step_rad,
            ..LimiterConfig::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_file_is_the_default() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../robot-skill/config/robot.json");
        assert_eq!(RobotConfig::load(&path).unwrap(), RobotConfig::default());
    }

    #[test]
    fn franka_and_partial_files_fill_in_defaults() {
        let c = RobotConfig::parse(r#"{"profile": "franka", "franka": {"reflex_force_n": 12}}"#).unwrap();
        assert_eq!(c.profile, Profile::Franka);
        assert_eq!(c.reflexes.reflex_force_n, 12.0);
        assert_eq!(c.reflexes.operator_force_n, 80.0);
        assert_eq!(c.max_tcp_step_m, 0.05);
    }

    #[test]
    fn calibration_paths_resolve_against_the_config_folder() {
        let text = r#"{"profile": "franka", "calibration": {"tcp": "cal/tcp.json",
            "cameras": {"wrist": "/abs/wrist.json", "agentview": "agentview.json"}}}"#;
        let parsed = RobotConfig::parse(text).unwrap().calibration;
        assert_eq!(parsed.tcp.as_deref(), Some(Path::new("cal/tcp.json")));
        let dir = std::env::temp_dir().join(format!("r2g-robot-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("robot.json"), text).unwrap();
        let c = RobotConfig::load(&dir.join("robot.json")).unwrap().calibration;
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(c.tcp, Some(dir.join("cal/tcp.json")));
        let names: Vec<&str> = c.cameras.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["agentview", "wrist"]);
        assert_eq!(c.cameras[0].1, dir.join("agentview.json"));
        assert_eq!(c.cameras[1].1, Path::new("/abs/wrist.json"));
    }

    #[test]
    fn devices_parse() {
        let c = RobotConfig::parse(
            r#"{"profile": "franka",
                "gripper": {"driver": "robotiq_2f85", "port": "/dev/ttyUSB0", "force": 40},
                "calibration": {"cameras": {"wrist": "w.json", "front": "f.json"}},
                "cameras": {"wrist": {"driver": "realsense", "serial": "123456789012", "fps": 15},
                            "front": {"driver": "uvc", "device": "/dev/video2", "width": 320, "height": 240}}}"#,
        )
        .unwrap();
        let Gripper::Robotiq2f85(r) = &c.gripper else { panic!("{:?}", c.gripper) };
        assert_eq!((r.slave, r.baud, r.speed, r.force, r.closed_count), (9, 115200, 255, 40, 230));
        assert_eq!(c.cameras.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(), ["front", "wrist"]);
        assert!(!c.cameras[0].depth && c.cameras[1].depth);
        assert_eq!(
            c.cameras[1].host_args()[..6],
            ["--camera", "wrist", "--driver", "realsense", "--serial", "123456789012"]
        );
        assert!(c.cameras[0].host_args().contains(&"--no-depth".to_string()));
        let replay = RobotConfig::parse(
            r#"{"profile": "simulation", "calibration": {"cameras": {"a": "a.json"}},
                "cameras": {"a": {"driver": "replay", "file": "a.npz", "frames": 30}}}"#,
        )
        .unwrap();
        assert!(replay.cameras[0].host_args().windows(2).any(|w| w == ["--frames", "30"]));
        for (frames, want) in [("0", "at least 1"), ("1.5", "whole number"), ("\"x\"", "whole number")] {
            let text = format!(
                r#"{{"profile": "simulation", "calibration": {{"cameras": {{"a": "a.json"}}}},
                    "cameras": {{"a": {{"driver": "replay", "file": "a.npz", "frames": {frames}}}}}}}"#
            );
            let e = format!("{:#}", RobotConfig::parse(&text).unwrap_err());
            assert!(e.contains("cameras.a.frames") && e.contains(want), "{e}");
        }
        let hand = RobotConfig::parse(r#"{"profile": "franka", "gripper": {"driver": "franka_hand"}}"#).unwrap();
        assert_eq!(hand.gripper, Gripper::FrankaHand);
    }

    #[test]
    fn bad_files_name_the_key_and_what_is_accepted() {
        for (text, want) in [
            (r#"{"profile": "real"}"#, "\"profile\": \"real\" is unknown"),
            (r#"{}"#, "no \"profile\""),
            (r#"{"profile": "simulation", "speed": 2}"#, "unknown key \"speed\""),
            (
                r#"{"profile": "simulation", "control": {"max_chunk_waypoints": 1000}}"#,
                "outside the accepted range [1, 256]",
            ),
            (r#"{"profile": "simulation", "control": {"max_chunk_waypoints": 2.5}}"#, "whole number"),
            (r#"{"profile": "simulation", "control": {"max_tcp_step_m": "far"}}"#, "must be a number"),
            (r#"{"profile": "simulation", "franka": {"reflex_force_n": -3}}"#, "franka.reflex_force_n = -3"),
            (r#"{"profile": "simulation", "franka": {"torque": 3}}"#, "unknown key \"torque\""),
            (r#"{"profile": "franka", "franka": {"collision_torque_nm": [1, 2]}}"#, "list of 7 numbers"),
            (r#"{"profile": "franka", "franka": {"contact_force_n": [1, 2, 3, 4, 5, -6]}}"#, "-6"),
            (r#"{"profile": "#, "not valid JSON"),
            (r#"{"profile": "franka", "calibration": {"tool": "t.json"}}"#, "calibration has an unknown key \"tool\""),
            (r#"{"profile": "franka", "calibration": {"tcp": 3}}"#, "calibration.tcp must be a file path"),
            (r#"{"profile": "franka", "calibration": {"tcp": ""}}"#, "calibration.tcp must be a file path"),
            (
                r#"{"profile": "franka", "calibration": {"cameras": ["a.json"]}}"#,
                "calibration.cameras must be an object",
            ),
            (
                r#"{"profile": "franka", "calibration": {"cameras": {"wrist": null}}}"#,
                "calibration.cameras.wrist must be",
            ),
            (r#"{"profile": "franka", "calibration": {"cameras": {"a b": "x.json"}}}"#, "\"a b\" is not a camera name"),
            (
                r#"{"profile": "franka", "calibration": {"cameras": {"a": "1", "b": "2", "c": "3", "d": "4", "e": "5"}}}"#,
                "names 5 cameras, at most 4",
            ),
            (r#"{"profile": "franka", "gripper": {"driver": "robotiq"}}"#, "gripper.driver must be"),
            (
                r#"{"profile": "franka", "gripper": {"driver": "robotiq_2f85"}}"#,
                "gripper.port must be the absolute path",
            ),
            (
                r#"{"profile": "franka", "gripper": {"driver": "robotiq_2f85", "port": "/dev/ttyUSB0", "force": 300}}"#,
                "gripper.force = 300 is outside",
            ),
            (r#"{"profile": "franka", "gripper": {"driver": "sim", "port": "/dev/x"}}"#, "gripper.port does not apply"),
            (
                r#"{"profile": "franka", "cameras": {"wrist": {"driver": "realsense", "serial": "1"}}}"#,
                "no calibration file",
            ),
            (r#"{"profile": "franka", "cameras": {"wrist": {"driver": "kinect"}}}"#, "cameras.wrist.driver must be"),
            (r#"{"profile": "franka", "cameras": {"w": {"driver": "realsense", "serial": "a;b"}}}"#, "serial number"),
            (
                r#"{"profile": "franka", "cameras": {"w": {"driver": "uvc", "device": "/dev/video0", "depth": true}}}"#,
                "gives no depth",
            ),
            (
                r#"{"profile": "franka", "cameras": {"w": {"driver": "uvc", "serial": "1"}}}"#,
                "cameras.w.device must be",
            ),
        ] {
            let e = format!("{:#}", RobotConfig::parse(text).unwrap_err());
            assert!(e.contains(want), "{text}: {e}");
        }
    }
}
