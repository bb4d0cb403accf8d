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
        let top = table(&root, "robot.json", &["profile", "control", "franka", "calibration"])?;
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
        };
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
        ] {
            let e = format!("{:#}", RobotConfig::parse(text).unwrap_err());
            assert!(e.contains(want), "{text}: {e}");
        }
    }
}
