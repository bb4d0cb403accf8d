#![doc = include_str!("../README.md")]

pub mod client;
pub mod image;

use std::cell::RefCell;
use std::time::Duration;

use controllers::math;
use ipc_schema::{ControlType, WAYPOINT_LEN};
use pyo3::exceptions::{PyConnectionError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyList, PyTuple};

pub use client::{Client, RoboError};

thread_local! {
    static CLIENT: RefCell<Option<Client>> = const { RefCell::new(None) };
}

fn instance() -> String {
    std::env::var("R2G_INSTANCE").unwrap_or_else(|_| "default".into())
}

fn to_py(e: RoboError) -> PyErr {
    match e {
        RoboError::NotRunning(_) | RoboError::Stale(..) => PyConnectionError::new_err(e.to_string()),
        RoboError::UnknownCamera { .. } | RoboError::BadSize { .. } => PyValueError::new_err(e.to_string()),
        _ => PyRuntimeError::new_err(e.to_string()),
    }
}

/// Runs `f` with the connected client, connecting first if needed. A connection that turned
/// out dead is dropped, so the next call reconnects (e.g. after `r2g up` was restarted).
fn with_client<T>(f: impl FnOnce(&mut Client) -> Result<T, RoboError>) -> Result<T, RoboError> {
    CLIENT.with(|cell| {
        let mut slot = cell.borrow_mut();
        let wanted = instance();
        if slot.as_ref().is_some_and(|c| c.instance != wanted) {
            *slot = None;
        }
        if slot.is_none() {
            *slot = Some(Client::connect(&wanted)?);
        }
        let Some(client) = slot.as_mut() else { unreachable!("connected above") };
        let r = f(client);
        if matches!(r, Err(RoboError::Stale(..)) | Err(RoboError::NotRunning(_)) | Err(RoboError::Ipc(_))) {
            *slot = None;
        }
        r
    })
}

/// Restores the scene (simulation profile). Returns 1 on success, 0 on failure; see
/// `get_state()["control_feedback"]` for the reason.
#[pyfunction]
fn reset(py: Python<'_>) -> PyResult<i32> {
    py.detach(|| with_client(|c| c.reset())).map_err(to_py)
}

/// Which cameras, at which size: None for the native size.
type CameraRequest = Vec<(String, Option<(u32, u32)>)>;

fn parse_cameras(arg: Option<&Bound<'_, PyAny>>, all: &[String]) -> PyResult<CameraRequest> {
    let Some(arg) = arg.filter(|a| !a.is_none()) else {
        return Ok(all.iter().map(|n| (n.clone(), None)).collect());
    };
    if let Ok(name) = arg.extract::<String>() {
        return Ok(vec![(name, None)]);
    }
    if let Ok(d) = arg.cast::<PyDict>() {
        let mut out = Vec::new();
        for (k, v) in d.iter() {
            let name: String =
                k.extract().map_err(|_| PyTypeError::new_err("cameras dict keys must be camera names (str)"))?;
            let size: (i64, i64) = v.extract().map_err(|_| {
                PyTypeError::new_err(format!("cameras['{name}'] must be a (width, height) pair of integers"))
            })?;
            if !(1..=4096).contains(&size.0) || !(1..=4096).contains(&size.1) {
                return Err(PyValueError::new_err(format!(
                    "cameras['{name}'] = {size:?}: width and height must be 1..4096"
                )));
            }
            out.push((name, Some((size.0 as u32, size.1 as u32))));
        }
        return Ok(out);
    }
    if arg.cast::<PyList>().is_ok() || arg.cast::<PyTuple>().is_ok() {
        let names: Vec<String> =
            arg.extract().map_err(|_| PyTypeError::new_err("cameras list must hold camera names (str)"))?;
        return Ok(names.into_iter().map(|n| (n, None)).collect());
    }
    Err(PyTypeError::new_err(
        "cameras must be None (all), a camera name, a list of names, a dict name -> (width, height), or [] (no images)",
    ))
}

/// Observes the robot: joints, TCP pose, gripper, camera images (PNG), timestamps,
/// calibration, control feedback and the limits in force.
#[pyfunction]
#[pyo3(signature = (cameras=None))]
fn get_state<'py>(py: Python<'py>, cameras: Option<&Bound<'py, PyAny>>) -> PyResult<Bound<'py, PyDict>> {
    let (state, info, feedback, names) = with_client(|c| {
        let s = c.refresh_state(Duration::from_secs(2))?;
        Ok((s, c.info, c.feedback.clone(), c.camera_names()))
    })
    .map_err(to_py)?;
    let wanted = parse_cameras(cameras, &names)?;
    let out = PyDict::new(py);
    out.set_item("joint", state.q_rad.to_vec())?;
    let tcp = state.base_from_tcp;
    let aa = math::axis_angle(tcp.quat_xyzw);
    out.set_item("ee_pose", vec![tcp.position_m[0], tcp.position_m[1], tcp.position_m[2], aa[0], aa[1], aa[2]])?;
    out.set_item("gripper", vec![state.gripper])?;
    out.set_item("timestamp", state.timestamp_s)?;
    out.set_item("joint_velocity", state.dq_rad_s.to_vec())?;
    out.set_item("backend", "simulation")?;
    out.set_item("mode", if state.mode == ipc_schema::Mode::Lockstep as u32 { "lockstep" } else { "wall" })?;
    out.set_item("control_type", ControlType::from_u32(state.control_type).map(ControlType::name))?;
    let images = PyDict::new(py);
    let stamps = PyDict::new(py);
    let intr = PyDict::new(py);
    let extr = PyDict::new(py);
    for (name, size) in wanted {
        let frame = with_client(|c| c.frame(&name, state.timestamp_s, Duration::from_millis(1500))).map_err(to_py)?;
        let h = frame.header();
        let (w, hgt) = size.unwrap_or((h.width, h.height));
        let png = if (w, hgt) == (h.width, h.height) {
            image::encode_png(frame.rgb(), w, hgt)
        } else {
            let resized = image::resize_rgb(frame.rgb(), h.width, h.height, w, hgt);
            image::encode_png(&resized, w, hgt)
        }
        .map_err(|e| PyRuntimeError::new_err(format!("PNG encoding of '{name}' failed: {e}")))?;
        images.set_item(&name, PyBytes::new(py, &png))?;
        stamps.set_item(&name, h.sim_time_s)?;
        let (sx, sy) = (w as f64 / h.width as f64, hgt as f64 / h.height as f64);
        let k = PyDict::new(py);
        k.set_item("fx", h.fx * sx)?;
        k.set_item("fy", h.fy * sy)?;
        k.set_item("cx", h.cx * sx)?;
        k.set_item("cy", h.cy * sy)?;
        k.set_item("width", w)?;
        k.set_item("height", hgt)?;
        intr.set_item(&name, k)?;
        let m = math::homogeneous(h.base_from_camera.position_m, h.base_from_camera.quat_xyzw);
        extr.set_item(&name, m.iter().map(|r| r.to_vec()).collect::<Vec<_>>())?;
        with_client(|c| {
            c.give_back(frame);
            Ok(())
        })
        .map_err(to_py)?;
    }
    out.set_item("image", images)?;
    out.set_item("image_timestamp", stamps)?;
    out.set_item("camera_intrinsics", intr)?;
    // base_from_camera: camera optical frame (x right, y down, z forward) in the robot base.
    out.set_item("camera_extrinsics", extr)?;
    let fb = PyDict::new(py);
    fb.set_item("status", feedback.status)?;
    fb.set_item("reason", feedback.reason)?;
    fb.set_item("executed", feedback.executed)?;
    fb.set_item("request_id", feedback.request_id)?;
    fb.set_item("final_joint_error_rad", feedback.final_joint_error_rad)?;
    out.set_item("control_feedback", fb)?;
    let safety = PyDict::new(py);
    if let Some(i) = info {
        safety.set_item("joint_position_min_rad", i.q_min_rad.to_vec())?;
        safety.set_item("joint_position_max_rad", i.q_max_rad.to_vec())?;
        safety.set_item("joint_position_margin_rad", i.q_margin_rad)?;
        safety.set_item("joint_velocity_max_rad_s", i.dq_max_rad_s.to_vec())?;
        safety.set_item("joint_acceleration_max_rad_s2", i.ddq_max_rad_s2.to_vec())?;
        safety.set_item("speed_scale", i.speed_scale)?;
        safety.set_item("max_chunk_len", i.max_chunk)?;
        safety.set_item("default_freq_hz", i.default_freq_hz)?;
        safety.set_item("tick_period_s", i.tick_period_ns as f64 * 1e-9)?;
    }
    out.set_item("effective_safety", safety)?;
    Ok(out)
}

/// Parses the action dict; Err carries a rejection reason for control_feedback.
fn parse_actions(cmd: &Bound<'_, PyAny>) -> Result<(ControlType, f64, Vec<[f64; WAYPOINT_LEN]>), String> {
    let d = cmd.cast::<PyDict>().map_err(|_| {
        "post_actions expects a dict {\"actions\": [...], \"type\": \"joint\"|\"ee_pose\", \"freq\": \"\"}".to_string()
    })?;
    for k in d.keys() {
        let k: String = k.extract().unwrap_or_default();
        if !["actions", "type", "freq"].contains(&k.as_str()) {
            return Err(format!("unknown key '{k}': the dict takes actions, type and freq"));
        }
    }
    let ty: String = d
        .get_item("type")
        .ok()
        .flatten()
        .ok_or("missing key 'type': use \"joint\" or \"ee_pose\"")?
        .extract()
        .map_err(|_| "type must be the string \"joint\" or \"ee_pose\"")?;
    let (control, width) = match ty.as_str() {
        "joint" => (ControlType::Joint, 8),
        "ee_pose" => (ControlType::EePose, 7),
        other => return Err(format!("type \"{other}\" is unknown: use \"joint\" or \"ee_pose\"")),
    };
    let freq = match d.get_item("freq").ok().flatten() {
        None => 0.0,
        Some(f) if f.is_none() => 0.0,
        Some(f) => {
            if let Ok(s) = f.extract::<String>() {
                if s.trim().is_empty() {
                    0.0
                } else {
                    s.trim()
                        .parse::<f64>()
                        .map_err(|_| format!("freq \"{s}\" is not a number: use \"\" for 20 Hz or a rate in Hz"))?
                }
            } else {
                f.extract::<f64>().map_err(|_| "freq must be \"\" or a number in Hz".to_string())?
            }
        }
    };
    if !(freq.is_finite() && freq >= 0.0) {
        return Err(format!("freq {freq} is not usable: use \"\" for 20 Hz or a positive rate in Hz"));
    }
    let actions = d.get_item("actions").ok().flatten().ok_or("missing key 'actions': a list of waypoints")?;
    let rows: Vec<Bound<'_, PyAny>> =
        actions.extract().map_err(|_| "actions must be a list of waypoints (lists of numbers)".to_string())?;
    let mut out = Vec::with_capacity(rows.len());
    for (i, row) in rows.iter().enumerate() {
        let vals: Vec<f64> = row.extract().map_err(|_| format!("actions[{i}] must be a list of {width} numbers"))?;
        if vals.len() != width {
            let layout = if width == 8 { "[q1..q7, g]" } else { "[x, y, z, ax, ay, az, g]" };
            return Err(format!("actions[{i}] has {} values; a {ty} waypoint has {width}: {layout}", vals.len()));
        }
        let mut w = [0.0; WAYPOINT_LEN];
        w[..width].copy_from_slice(&vals);
        if width == 7 {
            // ee_pose keeps the gripper in the last slot, like joint waypoints.
            w[7] = vals[6];
            w[6] = 0.0;
        }
        out.push(w);
    }
    Ok((control, freq, out))
}

/// Executes a chunk of absolute targets and blocks until it finished. Returns 1 when executed,
/// 0 when rejected or failed (the reason is in `get_state()["control_feedback"]`).
#[pyfunction]
fn post_actions(py: Python<'_>, cmd: &Bound<'_, PyAny>) -> PyResult<i32> {
    match parse_actions(cmd) {
        Ok((control, freq, actions)) => py.detach(|| with_client(|c| c.post(control, freq, &actions))).map_err(to_py),
        Err(reason) => with_client(|c| Ok(c.reject_locally(reason))).map_err(to_py),
    }
}

/// The instance this process talks to (from R2G_INSTANCE, default "default").
#[pyfunction(name = "instance")]
fn instance_name() -> String {
    instance()
}

#[pymodule]
fn robo(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(reset, m)?)?;
    m.add_function(wrap_pyfunction!(get_state, m)?)?;
    m.add_function(wrap_pyfunction!(post_actions, m)?)?;
    m.add_function(wrap_pyfunction!(instance_name, m)?)?;
    m.add("SCHEMA_VERSION", ipc_schema::SCHEMA_VERSION)?;
    Ok(())
}
