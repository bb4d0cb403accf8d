//! Demonstrations authored from a gym's hand-written TCP keyframes (`r2g author-demo`): a joint +
//! gripper trajectory at the scene's demonstration rate. The TCP moves on straight lines
//! (orientation by slerp) with a quintic time law between keyframes; every row is solved by
//! the project's IK, seeded with the previous row, so the joint path is continuous.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use controllers::kinematics::{from_arrays, to_arrays};
use controllers::math::{self, Quat};
use controllers::{IkConfig, IkSolver};
use serde::Deserialize;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Keyframes {
    keyframes: Vec<Keyframe>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Keyframe {
    /// TCP position in the robot base frame; default: the previous keyframe's.
    #[serde(default)]
    position_m: Option<[f64; 3]>,
    /// Gripper pointing straight down, turned this much about the vertical.
    #[serde(default)]
    yaw_deg: Option<f64>,
    /// Absolute TCP orientation (URDF roll, pitch, yaw); default: the previous keyframe's.
    #[serde(default)]
    rpy_deg: Option<[f64; 3]>,
    /// −1 open … +1 closed, held from the start of this segment.
    #[serde(default)]
    gripper: Option<f64>,
    /// Time to reach this keyframe from the previous one.
    duration_s: f64,
    /// A note on what this step does (documentation only).
    #[serde(default)]
    #[allow(dead_code)]
    note: String,
}

fn rpy_quat(r: f64, p: f64, y: f64) -> Quat {
    let q = |axis: usize, a: f64| {
        let (s, c) = (0.5 * a).sin_cos();
        let mut v = [0.0, 0.0, 0.0, c];
        v[axis] = s;
        v
    };
    math::mul(q(2, y), math::mul(q(1, p), q(0, r)))
}

fn slerp(a: Quat, b: Quat, s: f64) -> Quat {
    let mut dot: f64 = (0..4).map(|k| a[k] * b[k]).sum();
    let b = if dot < 0.0 {
        dot = -dot;
        [-b[0], -b[1], -b[2], -b[3]]
    } else {
        b
    };
    if dot > 0.9995 {
        return math::normalize([0, 1, 2, 3].map(|k| a[k] + s * (b[k] - a[k])));
    }
    let th = dot.clamp(-1.0, 1.0).acos();
    let (wa, wb) = (((1.0 - s) * th).sin() / th.sin(), (s * th).sin() / th.sin());
    [0, 1, 2, 3].map(|k| wa * a[k] + wb * b[k])
}

/// What [`author_demo`] wrote.
#[derive(Debug, Clone)]
pub struct AuthoredDemo {
    pub path: PathBuf,
    pub rows: usize,
    pub hz: f64,
}

/// Writes `task.demonstration` of the scene file `scene_path` from `<scene folder>/keyframes.toml`.
pub fn author_demo(scene_path: &Path) -> anyhow::Result<AuthoredDemo> {
    let scene = sim_host::Scene::load(scene_path).or_else(|e| {
        // The demonstration may not exist yet: that is what we are about to write.
        if e.to_string().contains("task.demonstration") {
            let text = std::fs::read_to_string(scene_path)?;
            let mut t: toml::Table = toml::from_str(&text)?;
            if let Some(task) = t.get_mut("task").and_then(|v| v.as_table_mut()) {
                task.remove("demonstration");
            }
            let tmp = scene_path.with_extension("authoring.toml");
            std::fs::write(&tmp, toml::to_string(&t)?)?;
            let s = sim_host::Scene::load(&tmp);
            let _ = std::fs::remove_file(&tmp);
            Ok(s?)
        } else {
            Err(anyhow::Error::from(e))
        }
    })?;
    let dir = scene_path.parent().unwrap_or(Path::new("."));
    let kf_path = dir.join("keyframes.toml");
    let text = std::fs::read_to_string(&kf_path).with_context(|| format!("reading {}", kf_path.display()))?;
    let kf: Keyframes = toml::from_str(&text).with_context(|| format!("parsing {}", kf_path.display()))?;
    let (robot, _) = runtime::scene_robot(scene_path)?;
    let ik = IkSolver::new(&robot, IkConfig { limit_margin_rad: 0.05, ..IkConfig::default() })?;
    let hz = scene.task.demonstration_hz;
    let mut q = scene.robot.initial_joints_rad;
    let (mut pos, mut rot) = to_arrays(&robot.kin.fk(&q, robot.kin.tcp));
    let mut grip = scene.robot.initial_gripper;
    let mut rows = vec![[q[0], q[1], q[2], q[3], q[4], q[5], q[6], grip]];
    for (i, k) in kf.keyframes.iter().enumerate() {
        let target_p = k.position_m.unwrap_or(pos);
        let target_r = match (k.yaw_deg, k.rpy_deg) {
            (Some(_), Some(_)) => bail!("keyframes[{i}]: give yaw_deg or rpy_deg, not both"),
            (Some(y), None) => rpy_quat(std::f64::consts::PI, 0.0, y.to_radians()),
            (None, Some(r)) => rpy_quat(r[0].to_radians(), r[1].to_radians(), r[2].to_radians()),
            (None, None) => rot,
        };
        grip = k.gripper.unwrap_or(grip);
        if !(k.duration_s.is_finite() && k.duration_s > 0.0) {
            bail!("keyframes[{i}]: duration_s must be positive");
        }
        let n = ((k.duration_s * hz).round() as usize).max(1);
        for step in 1..=n {
            let t = step as f64 / n as f64;
            let s = t * t * t * (10.0 - 15.0 * t + 6.0 * t * t);
            let p = [0, 1, 2].map(|a| pos[a] + s * (target_p[a] - pos[a]));
            let r = slerp(rot, target_r, s);
            let sol = ik.solve(&from_arrays(p, r), &q)?;
            if !sol.ok {
                bail!(
                    "keyframes[{i}] ({}) at {:.0}%: no IK solution for {p:?} (best {:.1} mm, {:.2} deg away)",
                    k.note,
                    100.0 * t,
                    sol.position_error_m * 1e3,
                    sol.rotation_error_rad.to_degrees()
                );
            }
            let jump = (0..7).map(|j| (sol.q[j] - q[j]).abs()).fold(0.0, f64::max);
            if jump > 0.25 {
                bail!(
                    "keyframes[{i}] ({}) at {:.0}%: the IK solution jumps {jump:.2} rad; add a keyframe",
                    k.note,
                    100.0 * t
                );
            }
            q = sol.q;
            rows.push([q[0], q[1], q[2], q[3], q[4], q[5], q[6], grip]);
        }
        pos = target_p;
        rot = target_r;
    }
    let out = scene.task.demonstration.clone().unwrap_or_else(|| dir.join("demo.csv"));
    crate::demo::write_demo(&out, &rows)?;
    Ok(AuthoredDemo { path: out, rows: rows.len(), hz })
}
