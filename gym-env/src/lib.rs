#![doc = include_str!("../README.md")]
//! The native half of `r2g_gym`: one episode driven step by step, in this process
//! ([`Local`], `lockstep::Episode`, no shared memory) or through a live instance ([`Live`],
//! `robo`'s client beside the sim-host's `env/` services). The Python half (`r2g_gym.env`)
//! declares the spaces, checks actions and speaks gymnasium.

mod live;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use controllers::LimiterConfig;
use ipc_schema::{ControlType, Reply, RobotState, Status, N_JOINTS, WAYPOINT_LEN};
use pyo3::exceptions::{PyConnectionError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};
use runtime::controller::{REACH_TOL_M, REACH_TOL_RAD, REACH_TOL_TCP_RAD};
use sim_host::render::Cameras;

pub use live::Live;

fn runtime_err(e: impl std::fmt::Display) -> PyErr {
    PyRuntimeError::new_err(e.to_string())
}

fn control_type(name: &str) -> PyResult<ControlType> {
    match name {
        "joint" => Ok(ControlType::Joint),
        "ee_pose" => Ok(ControlType::EePose),
        other => Err(PyValueError::new_err(format!("control must be 'joint' or 'ee_pose', not '{other}'"))),
    }
}

/// The robot configuration's limiter settings (`robot.json`; none: the shipped defaults), so an
/// episode here is limited exactly as `r2g-control` limits one.
fn limits(robot_config: Option<&str>) -> PyResult<LimiterConfig> {
    let cfg = match robot_config {
        Some(p) => runtime::RobotConfig::load(Path::new(p)).map_err(|e| PyValueError::new_err(format!("{e:#}")))?,
        None => runtime::RobotConfig::default(),
    };
    Ok(cfg.limiter())
}

/// What the spaces are made of: the robot's joint limits, its limiter margin, the cameras.
fn spec<'py>(py: Python<'py>, scene: &Path, margin_rad: f64) -> PyResult<Bound<'py, PyDict>> {
    let (robot, _) = runtime::scene_robot(scene).map_err(|e| PyValueError::new_err(format!("{e:#}")))?;
    let s = sim_host::Scene::load(scene).map_err(|e| PyValueError::new_err(format!("{e:#}")))?;
    let d = PyDict::new(py);
    d.set_item("gym", &s.name)?;
    d.set_item("q_min", robot.joints.iter().map(|j| j.q_min_rad).collect::<Vec<_>>())?;
    d.set_item("q_max", robot.joints.iter().map(|j| j.q_max_rad).collect::<Vec<_>>())?;
    d.set_item("dq_max", robot.joints.iter().map(|j| j.dq_max_rad_s).collect::<Vec<_>>())?;
    d.set_item("q_margin", margin_rad)?;
    d.set_item("timestep_s", s.timestep_s)?;
    let cams: HashMap<String, (u32, u32)> = s.cameras.iter().map(|c| (c.name.clone(), (c.width, c.height))).collect();
    d.set_item("cameras", cams)?;
    Ok(d)
}

/// The observation's numbers of an agent-facing state (what `robo.get_state` reports).
fn state_dict<'py>(py: Python<'py>, s: &RobotState) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("joint", s.q_rad.to_vec())?;
    d.set_item("joint_vel", s.dq_rad_s.to_vec())?;
    let p = s.base_from_tcp.position_m;
    let r = s.tcp_rotvec;
    d.set_item("ee_pose", vec![p[0], p[1], p[2], r[0], r[1], r[2]])?;
    d.set_item("gripper", vec![s.gripper])?;
    d.set_item("sim_time_s", s.timestamp_s)?;
    Ok(d)
}

/// Quaternion (x, y, z, w) of an axis-angle vector.
fn quat_of_rotvec(v: [f64; 3]) -> [f64; 4] {
    let a = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if a < 1e-12 {
        return [0.0, 0.0, 0.0, 1.0];
    }
    let s = (0.5 * a).sin() / a;
    [v[0] * s, v[1] * s, v[2] * s, (0.5 * a).cos()]
}

/// How a step's target went: `refused` (the runtime took none of it: the reason says why),
/// `reached` (the measured arm ends the period within the reach tolerance of the target:
/// joints within 5 mrad, or the TCP within 5 mm and 0.02 rad), or `limited` (accepted, but the
/// limits, a safety stop or contact kept the arm from it within the period).
fn outcome<'py>(
    py: Python<'py>,
    control: ControlType,
    target: &[f64; WAYPOINT_LEN],
    replies: &[Reply],
    end: &RobotState,
) -> PyResult<Bound<'py, PyDict>> {
    let refused = replies.iter().find(|r| {
        [Status::Rejected, Status::OperatorRequired].iter().any(|s| *s as u32 == r.status) && r.accepted_ns == 0
    });
    let stopped = replies.iter().find(|r| r.status == Status::Failed as u32 && r.accepted_ns != 0);
    let error = match control {
        ControlType::Joint => (0..N_JOINTS).map(|j| (end.q_rad[j] - target[j]).abs()).fold(0.0, f64::max),
        ControlType::EePose => {
            let p = end.base_from_tcp.position_m;
            (0..3).map(|k| (p[k] - target[k]).powi(2)).sum::<f64>().sqrt()
        }
    };
    let rot_error = match control {
        ControlType::Joint => 0.0,
        ControlType::EePose => {
            let (a, b) = (quat_of_rotvec([target[3], target[4], target[5]]), end.base_from_tcp.quat_xyzw);
            let dot = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]).abs().min(1.0);
            2.0 * dot.acos()
        }
    };
    let reached = match control {
        ControlType::Joint => error <= REACH_TOL_RAD,
        ControlType::EePose => error <= REACH_TOL_M && rot_error <= REACH_TOL_TCP_RAD,
    };
    let (status, reason) = match (refused, stopped) {
        (Some(r), _) => ("refused", r.reason_str().to_string()),
        (None, Some(r)) => ("limited", r.reason_str().to_string()),
        (None, None) if reached => ("reached", String::new()),
        (None, None) => {
            let unit = if control == ControlType::Joint { "rad (largest joint)" } else { "m (TCP)" };
            ("limited", format!("still {error:.4} {unit} from the target at the end of the period: the limits stretch the motion past one step"))
        }
    };
    let d = PyDict::new(py);
    d.set_item("status", status)?;
    d.set_item("reason", reason)?;
    d.set_item("error", error)?;
    if control == ControlType::EePose {
        d.set_item("rotation_error", rot_error)?;
    }
    Ok(d)
}

type StepResult<'py> = (Bound<'py, PyDict>, Bound<'py, PyDict>);

/// The state a step ended on and its outcome; an error when its period never ended.
fn step_result<'py>(
    py: Python<'py>,
    control: ControlType,
    target: &[f64; WAYPOINT_LEN],
    replies: &[Reply],
    end: &RobotState,
) -> Result<StepResult<'py>, String> {
    if replies.last().is_none_or(|r| r.status != Status::Stepped as u32) {
        return Err("the step's period did not end".into());
    }
    let state = state_dict(py, end).map_err(|e| e.to_string())?;
    Ok((state, outcome(py, control, target, replies, end).map_err(|e| e.to_string())?))
}

fn waypoint(action: &[f64]) -> PyResult<[f64; WAYPOINT_LEN]> {
    let n = match action.len() {
        8 => 8,
        7 => 7,
        other => {
            return Err(PyValueError::new_err(format!(
                "an action has 8 numbers (7 joints + gripper) or 7 (xyz, axis-angle, gripper), not {other}"
            )))
        }
    };
    let mut w = [0.0; WAYPOINT_LEN];
    w[..n].copy_from_slice(action);
    if n == 7 {
        // ee_pose: [x, y, z, ax, ay, az, g] travels as [.., 0.0 padding, g].
        w[7] = w[6];
        w[6] = 0.0;
    }
    if w.iter().any(|v| !v.is_finite()) {
        return Err(PyValueError::new_err(format!("the action holds a NaN or an infinity: {action:?}")));
    }
    Ok(w)
}

/// One episode at a time of a gym, in this process: the runtime's controller and the
/// simulator in lockstep, exactly as `r2g-control` and `r2g-sim` run it, without shared memory.
#[pyclass(unsendable, module = "r2g_gym._native")]
pub struct Local {
    episode: lockstep::Episode,
    control: ControlType,
    /// Renderers by (width, height), made on first use (EGL).
    cameras: HashMap<(u32, u32), Cameras>,
    scene: PathBuf,
    margin_rad: f64,
}

#[pymethods]
impl Local {
    #[new]
    #[pyo3(signature = (scene, control, robot_config=None))]
    fn new(scene: &str, control: &str, robot_config: Option<&str>) -> PyResult<Self> {
        let control = control_type(control)?;
        let lim = limits(robot_config)?;
        let episode = lockstep::Episode::with_limits(Path::new(scene), 0, lim)
            .map_err(|e| PyValueError::new_err(format!("{e:#}")))?;
        Ok(Self { episode, control, cameras: HashMap::new(), scene: scene.into(), margin_rad: lim.q_margin_rad })
    }

    /// Limits and cameras the spaces are built from.
    fn spec<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        spec(py, &self.scene, self.margin_rad)
    }

    /// A new episode augmented by `seed`; the first state.
    fn reset<'py>(&mut self, py: Python<'py>, seed: u64) -> PyResult<Bound<'py, PyDict>> {
        self.episode.reset(seed).map_err(runtime_err)?;
        let s = self.episode.robot_state();
        state_dict(py, &s)
    }

    /// One period of `ticks` ticks towards `action`; the state at its end and the outcome.
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        action: Vec<f64>,
        ticks: u32,
    ) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
        let target = waypoint(&action)?;
        let freq_hz = 1.0 / (f64::from(ticks) * self.episode.sim.scene.timestep_s);
        let replies = self.episode.step(self.control, &[target], freq_hz, ticks);
        let end = self.episode.robot_state();
        step_result(py, self.control, &target, &replies, &end).map_err(runtime_err)
    }

    /// The evaluator's verdict on the episode so far: (success, the verdict as JSON).
    fn evaluate(&self) -> PyResult<(bool, String)> {
        let e = self.episode.evaluate();
        Ok((e.success, serde_json::to_string(&e).map_err(runtime_err)?))
    }

    /// RGB of camera `name` at `width` × `height`, row-major, top row first.
    fn render<'py>(&mut self, py: Python<'py>, name: &str, width: u32, height: u32) -> PyResult<Bound<'py, PyBytes>> {
        let sim = &self.episode.sim;
        let Some(&(_, cam)) = sim.layout.cameras.iter().find(|(n, _)| n == name) else {
            let known: Vec<&str> = sim.layout.cameras.iter().map(|(n, _)| n.as_str()).collect();
            return Err(PyValueError::new_err(format!("no camera '{name}': this gym has {}", known.join(", "))));
        };
        if !(1..=ipc_schema::MAX_IMAGE_WIDTH as u32).contains(&width)
            || !(1..=ipc_schema::MAX_IMAGE_HEIGHT as u32).contains(&height)
        {
            return Err(PyValueError::new_err(format!(
                "images are 1..{} × 1..{} pixels, not {width} × {height}",
                ipc_schema::MAX_IMAGE_WIDTH,
                ipc_schema::MAX_IMAGE_HEIGHT
            )));
        }
        let r = match self.cameras.entry((width, height)) {
            std::collections::hash_map::Entry::Occupied(o) => o.into_mut(),
            std::collections::hash_map::Entry::Vacant(v) => {
                v.insert(Cameras::new(sim.model.clone(), width, height, false).map_err(runtime_err)?)
            }
        };
        r.set_state(sim.qpos(), sim.time_s());
        let (rgb, _) = r.render(cam).map_err(runtime_err)?;
        Ok(PyBytes::new(py, rgb))
    }
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Local>()?;
    m.add_class::<Live>()?;
    m.add("InstanceGone", m.py().get_type::<PyConnectionError>())?;
    Ok(())
}
