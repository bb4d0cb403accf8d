#![doc = include_str!("../README.md")]

pub mod client;
pub mod image;

use std::cell::RefCell;
use std::ffi::{c_char, c_int, c_void, CStr};
use std::ptr::null_mut;
use std::rc::Rc;
use std::time::Duration;

use controllers::math;
use ipc_schema::{ControlType, Profile, RuntimeInfo, WAYPOINT_LEN};
use pyo3::exceptions::{PyBufferError, PyConnectionError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::ffi;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyBytes, PyDict, PyList, PyTuple};

pub use client::{Client, Frame, RoboError};

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

/// Pixels handed to Python: a read-only view of a frame in shared memory, or a copy.
enum Pixels {
    Rgb(Rc<Frame>),
    Depth(Rc<Frame>),
    OwnedRgb(Vec<u8>),
    OwnedDepth(Vec<f32>),
}

/// One image plane exposing the buffer protocol, so `numpy.asarray` wraps it without copying.
/// Holds the shared-memory sample alive for as long as any array uses it.
#[pyclass(unsendable, module = "robo")]
struct Plane {
    pixels: Pixels,
    shape: [isize; 3],
    strides: [isize; 3],
    ndim: usize,
}

impl Plane {
    fn new(pixels: Pixels, width: u32, height: u32) -> Self {
        let (w, h) = (width as isize, height as isize);
        let (shape, strides, ndim) = match pixels {
            Pixels::Rgb(_) | Pixels::OwnedRgb(_) => ([h, w, 3], [3 * w, 3, 1], 3),
            Pixels::Depth(_) | Pixels::OwnedDepth(_) => ([h, w, 0], [4 * w, 4, 0], 2),
        };
        Self { pixels, shape, strides, ndim }
    }

    /// (pointer, bytes, item size, format)
    fn raw(&self) -> (*const u8, usize, usize, &'static CStr) {
        match &self.pixels {
            Pixels::Rgb(f) => (f.rgb().as_ptr(), f.rgb().len(), 1, c"B"),
            Pixels::OwnedRgb(v) => (v.as_ptr(), v.len(), 1, c"B"),
            Pixels::Depth(f) => {
                let d = f.depth().unwrap_or(&[]);
                (d.as_ptr().cast(), 4 * d.len(), 4, c"f")
            }
            Pixels::OwnedDepth(v) => (v.as_ptr().cast(), 4 * v.len(), 4, c"f"),
        }
    }
}

#[pymethods]
impl Plane {
    /// # Safety
    /// Called by Python with a valid `Py_buffer`; the pointers handed out stay valid while the
    /// buffer holds a reference to this object.
    unsafe fn __getbuffer__(slf: Bound<'_, Self>, view: *mut ffi::Py_buffer, flags: c_int) -> PyResult<()> {
        if view.is_null() {
            return Err(PyBufferError::new_err("no buffer view to fill"));
        }
        if flags & ffi::PyBUF_WRITABLE == ffi::PyBUF_WRITABLE {
            return Err(PyBufferError::new_err(
                "robo images are read-only (they live in shared memory): copy with numpy.array(image)",
            ));
        }
        let me = slf.borrow();
        let (ptr, len, item, format) = me.raw();
        // SAFETY: `view` is non-null and ours to fill; shape and strides live inside this
        // object, which the view keeps alive through `obj`.
        unsafe {
            (*view).buf = ptr as *mut c_void;
            (*view).len = len as isize;
            (*view).readonly = 1;
            (*view).itemsize = item as isize;
            (*view).format = if flags & ffi::PyBUF_FORMAT == ffi::PyBUF_FORMAT {
                format.as_ptr() as *mut c_char
            } else {
                null_mut()
            };
            (*view).ndim = me.ndim as c_int;
            (*view).shape =
                if flags & ffi::PyBUF_ND == ffi::PyBUF_ND { me.shape.as_ptr() as *mut isize } else { null_mut() };
            (*view).strides = if flags & ffi::PyBUF_STRIDES == ffi::PyBUF_STRIDES {
                me.strides.as_ptr() as *mut isize
            } else {
                null_mut()
            };
            (*view).suboffsets = null_mut();
            (*view).internal = null_mut();
            drop(me);
            (*view).obj = slf.into_any().into_ptr();
        }
        Ok(())
    }

    unsafe fn __releasebuffer__(&self, _view: *mut ffi::Py_buffer) {}
}

static NUMPY_ASARRAY: PyOnceLock<Py<PyAny>> = PyOnceLock::new();

fn as_array<'py>(py: Python<'py>, plane: Plane) -> PyResult<Bound<'py, PyAny>> {
    let asarray = NUMPY_ASARRAY.get_or_try_init(py, || -> PyResult<Py<PyAny>> {
        let np = py
            .import("numpy")
            .map_err(|e| pyo3::exceptions::PyImportError::new_err(format!("get_state(raw=True) needs numpy: {e}")))?;
        Ok(np.getattr("asarray")?.unbind())
    })?;
    asarray.bind(py).call1((Bound::new(py, plane)?,))
}

/// Observes the robot: joints, TCP pose, gripper, external force, camera images (PNG, or numpy
/// arrays with depth when `raw`), image timestamps, calibration, control feedback and the
/// limits in force.
#[pyfunction]
#[pyo3(signature = (cameras=None, raw=false))]
fn get_state<'py>(py: Python<'py>, cameras: Option<&Bound<'py, PyAny>>, raw: bool) -> PyResult<Bound<'py, PyDict>> {
    let (state, info, feedback, names) = with_client(|c| {
        let s = c.refresh_state(Duration::from_secs(2))?;
        Ok((s, c.info, c.feedback.clone(), c.camera_names()))
    })
    .map_err(to_py)?;
    let wanted = parse_cameras(cameras, &names)?;
    let out = PyDict::new(py);
    out.set_item("joint", state.q_rad)?;
    let tcp = state.base_from_tcp;
    // The runtime's continuous axis-angle vector (nearest its previous report), never a flip.
    let aa = state.tcp_rotvec;
    out.set_item("ee_pose", [tcp.position_m[0], tcp.position_m[1], tcp.position_m[2], aa[0], aa[1], aa[2]])?;
    out.set_item("gripper", [state.gripper])?;
    out.set_item("timestamp", state.timestamp_s)?;
    out.set_item("joint_velocity", state.dq_rad_s)?;
    out.set_item("external_force_n", state.external_force_n)?;
    let profile = info.and_then(|i| Profile::from_u32(i.profile)).unwrap_or_default();
    out.set_item("backend", profile.name())?;
    out.set_item("mode", if state.mode == ipc_schema::Mode::Lockstep as u32 { "lockstep" } else { "wall" })?;
    out.set_item("control_type", ControlType::from_u32(state.control_type).map(ControlType::name))?;
    let fault = (state.fault != 0).then(|| {
        if state.fault & 2 != 0 {
            "the robot side publishes no state (it stopped or hangs): the arm holds its last command and chunks are refused until it is back".to_string()
        } else if state.fault & 12 == 12 && state.fault & 1 == 0 {
            format!(
                "the gripper cannot act now ({}): the arm holds and chunks are refused until it can; observe again later",
                state.gripper_error_str()
            )
        } else if state.fault & 4 != 0 && state.fault & 1 == 0 {
            format!(
                "the gripper reports a fault ({}): the arm holds and chunks are refused until the gripper is clear",
                state.gripper_error_str()
            )
        } else if feedback.status == "operator_required" {
            feedback.reason.clone()
        } else {
            format!("the arm is in a fault that needs an operator (`r2g clear --instance {}`)", instance())
        }
    });
    out.set_item("fault", fault)?;
    let images = PyDict::new(py);
    let stamps = PyDict::new(py);
    let intr = PyDict::new(py);
    let extr = PyDict::new(py);
    let depths = PyDict::new(py);
    // In lockstep simulated time stands still between requests: the frame of the settled state
    // always comes, however loaded the machine is, so it is waited for (an older one would make
    // the episode depend on the renderer's speed). In wall time a lagging renderer's newest
    // frame is taken after 1.5 s.
    let frame_wait = if state.mode == ipc_schema::Mode::Lockstep as u32 {
        Duration::from_secs(20)
    } else {
        Duration::from_millis(1500)
    };
    for (name, size) in wanted {
        let (frame, borrow) = with_client(|c| {
            let f = c.frame(&name, frame_wait)?;
            let b = raw && c.may_borrow(&f);
            Ok((f, b))
        })
        .map_err(to_py)?;
        let h = frame.header();
        let (w, hgt) = size.unwrap_or((h.width, h.height));
        let native = (w, hgt) == (h.width, h.height);
        if raw {
            let rgb = match (native, borrow) {
                (true, true) => Pixels::Rgb(frame.clone()),
                (true, false) => Pixels::OwnedRgb(frame.rgb().to_vec()),
                (false, _) => Pixels::OwnedRgb(image::resize_rgb(frame.rgb(), h.width, h.height, w, hgt)),
            };
            images.set_item(&name, as_array(py, Plane::new(rgb, w, hgt))?)?;
            if let Some(d) = frame.depth() {
                let depth = match (native, borrow) {
                    (true, true) => Pixels::Depth(frame.clone()),
                    (true, false) => Pixels::OwnedDepth(d.to_vec()),
                    (false, _) => Pixels::OwnedDepth(image::resize_depth(d, h.width, h.height, w, hgt)),
                };
                depths.set_item(&name, as_array(py, Plane::new(depth, w, hgt))?)?;
            }
        } else {
            let png = with_client(|c| c.png(&frame, w, hgt)).map_err(to_py)?;
            images.set_item(&name, PyBytes::new(py, &png))?;
        }
        stamps.set_item(&name, h.sim_time_s)?;
        let (sx, sy) = (w as f64 / h.width as f64, hgt as f64 / h.height as f64);
        let k = PyDict::new(py);
        k.set_item("fx", h.fx * sx)?;
        k.set_item("fy", h.fy * sy)?;
        // Pixel-index coordinates (pixel [v, u] is the point (u, v)): a scale acts on pixel
        // edges, which lie half a pixel from the centres, as image::resize_rgb samples.
        k.set_item("cx", (h.cx + 0.5) * sx - 0.5)?;
        k.set_item("cy", (h.cy + 0.5) * sy - 0.5)?;
        k.set_item("width", w)?;
        k.set_item("height", hgt)?;
        intr.set_item(&name, k)?;
        let m = math::homogeneous(h.base_from_camera.position_m, h.base_from_camera.quat_xyzw);
        extr.set_item(&name, m)?;
    }
    out.set_item("image", images)?;
    if raw {
        out.set_item("depth", depths)?;
    }
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
    fb.set_item("submit_to_accept_us", feedback.accepted_us)?;
    fb.set_item("submit_to_first_motion_us", feedback.first_motion_us)?;
    let contact = match feedback.contact {
        Some(c) => {
            let d = PyDict::new(py);
            d.set_item("start_n", c.start_n)?;
            d.set_item("peak_n", c.peak_n)?;
            d.set_item("mean_n", c.mean_n)?;
            d.set_item("peak_waypoint", c.peak_waypoint)?;
            Some(d)
        }
        None => None,
    };
    fb.set_item("contact", contact)?;
    // What the gripper knows about its fingers now: a Robotiq's own object detection, or for
    // grippers without one the fingers stopped short of a closing command.
    let grasp = PyDict::new(py);
    grasp.set_item("status", ipc_schema::grasp_name(state.grasp))?;
    grasp.set_item("object_detected", state.grasp == ipc_schema::GRASP_HOLDING)?;
    grasp.set_item("gripper_fault", (state.fault & 4 != 0).then(|| state.gripper_error_str().to_string()))?;
    fb.set_item("grasp", grasp)?;
    out.set_item("control_feedback", fb)?;
    out.set_item("effective_safety", effective_safety(py, info.as_ref())?)?;
    out.set_item("calibration", calibration(py, info.as_ref(), &names)?)?;
    out.set_item("setup", setup(py, info.as_ref())?)?;
    Ok(out)
}

/// What the runtime was started with (`gym`, `robot_config_sha256`); empty until it has
/// published its info.
fn setup<'py>(py: Python<'py>, info: Option<&RuntimeInfo>) -> PyResult<Bound<'py, PyDict>> {
    let Some(text) = info.map(|i| i.setup_str()).filter(|t| !t.is_empty()) else {
        return Ok(PyDict::new(py));
    };
    py.import("json")?
        .getattr("loads")?
        .call1((text,))?
        .cast_into::<PyDict>()
        .map_err(|_| PyRuntimeError::new_err("setup report is not an object"))
}

/// Where the TCP and camera calibrations come from: the runtime's report (the TCP, and every
/// camera the robot config names a file for), plus `{"source": "scene"}` for each camera that
/// sends frames without such a file (its frames carry the simulator's calibration). Empty until
/// the runtime has published its info.
fn calibration<'py>(py: Python<'py>, info: Option<&RuntimeInfo>, sending: &[String]) -> PyResult<Bound<'py, PyDict>> {
    let Some(text) = info.map(|i| i.calibration_str()).filter(|t| !t.is_empty()) else {
        return Ok(PyDict::new(py));
    };
    let report = py.import("json")?.getattr("loads")?.call1((text,))?;
    let report =
        report.cast_into::<PyDict>().map_err(|_| PyRuntimeError::new_err("calibration report is not an object"))?;
    let cameras = match report.get_item("cameras")? {
        Some(c) => {
            c.cast_into::<PyDict>().map_err(|_| PyRuntimeError::new_err("calibration cameras is not an object"))?
        }
        None => PyDict::new(py),
    };
    for name in sending {
        if !cameras.contains(name)? {
            let scene = PyDict::new(py);
            scene.set_item("source", "scene")?;
            cameras.set_item(name, scene)?;
        }
    }
    report.set_item("cameras", cameras)?;
    Ok(report)
}

/// The limits in force, as the runtime published them (empty until it has).
fn effective_safety<'py>(py: Python<'py>, info: Option<&RuntimeInfo>) -> PyResult<Bound<'py, PyDict>> {
    let safety = PyDict::new(py);
    let Some(i) = info else { return Ok(safety) };
    let finite = |v: f64| v.is_finite().then_some(v);
    let profile = Profile::from_u32(i.profile).unwrap_or_default();
    safety.set_item("profile", profile.name())?;
    safety.set_item("joint_position_min_rad", i.q_min_rad)?;
    safety.set_item("joint_position_max_rad", i.q_max_rad)?;
    safety.set_item("joint_position_margin_rad", i.q_margin_rad)?;
    safety.set_item("joint_velocity_max_rad_s", i.dq_max_rad_s)?;
    safety.set_item("joint_acceleration_max_rad_s2", i.ddq_max_rad_s2)?;
    safety.set_item("speed_scale", i.speed_scale)?;
    safety.set_item("max_chunk_len", i.max_chunk)?;
    safety.set_item("max_joint_step_rad", finite(i.max_joint_step_rad))?;
    safety.set_item("max_tcp_step_m", finite(i.max_tcp_step_m))?;
    safety.set_item("max_tcp_step_rad", finite(i.max_tcp_step_rad))?;
    safety.set_item("default_freq_hz", i.default_freq_hz)?;
    safety.set_item("tick_period_s", i.tick_period_ns as f64 * 1e-9)?;
    let (lo, hi) = if i.has_workspace == 1 {
        (Some(i.workspace_min_m.map(|v| v.max(-1e6))), Some(i.workspace_max_m.map(|v| v.min(1e6))))
    } else {
        (None, None)
    };
    safety.set_item("workspace_min_m", lo)?;
    safety.set_item("workspace_max_m", hi)?;
    safety.set_item("collision_margin_m", i.collision_margin_m)?;
    safety.set_item("reflex_force_n", finite(i.reflex_force_n))?;
    safety.set_item("operator_force_n", finite(i.operator_force_n))?;
    Ok(safety)
}

/// Why an action dict was refused: its structure (raises) or its content (returns 0).
enum Refusal {
    Structure(String),
    Content(String),
}

/// Parses the action dict.
fn parse_actions(cmd: &Bound<'_, PyAny>) -> Result<(ControlType, f64, Vec<[f64; WAYPOINT_LEN]>), Refusal> {
    use Refusal::{Content, Structure};
    let d = cmd.cast::<PyDict>().map_err(|_| {
        Structure(format!(
            "post_actions expects a dict {{\"actions\": [...], \"type\": \"joint\"|\"ee_pose\", \"freq\": \"\"}}, got {}",
            cmd.get_type().name().map(|n| n.to_string()).unwrap_or_else(|_| "?".into())
        ))
    })?;
    for k in d.keys() {
        let k: String = k.extract().map_err(|_| Structure("post_actions dict keys must be strings".into()))?;
        if !["actions", "type", "freq"].contains(&k.as_str()) {
            return Err(Structure(format!("unknown key '{k}': the dict takes actions, type and freq")));
        }
    }
    let ty: String = d
        .get_item("type")
        .ok()
        .flatten()
        .ok_or_else(|| Structure("missing key 'type': use \"joint\" or \"ee_pose\"".into()))?
        .extract()
        .map_err(|_| Structure("type must be the string \"joint\" or \"ee_pose\"".into()))?;
    let actions = d
        .get_item("actions")
        .ok()
        .flatten()
        .ok_or_else(|| Structure("missing key 'actions': a list of waypoints".into()))?;
    let rows: Vec<Bound<'_, PyAny>> =
        actions.extract().map_err(|_| Structure("actions must be a list of waypoints (lists of numbers)".into()))?;
    let mut values = Vec::with_capacity(rows.len());
    for (i, row) in rows.iter().enumerate() {
        let v: Vec<f64> = row.extract().map_err(|_| Structure(format!("actions[{i}] must be a list of numbers")))?;
        values.push(v);
    }
    let freq = match d.get_item("freq").ok().flatten() {
        None => 0.0,
        Some(f) if f.is_none() => 0.0,
        Some(f) => {
            if let Ok(s) = f.extract::<String>() {
                if s.trim().is_empty() {
                    0.0
                } else {
                    s.trim().parse::<f64>().map_err(|_| {
                        Content(format!("freq \"{s}\" is not a number: use \"\" for 20 Hz or a rate in Hz"))
                    })?
                }
            } else {
                let v = f.extract::<f64>().map_err(|_| Structure("freq must be \"\" or a number in Hz".into()))?;
                if v == 0.0 {
                    return Err(Content("freq 0 is not usable: use \"\" for 20 Hz or a positive rate in Hz".into()));
                }
                v
            }
        }
    };
    if !(freq.is_finite() && freq >= 0.0) {
        return Err(Content(format!("freq {freq} is not usable: use \"\" for 20 Hz or a positive rate in Hz")));
    }
    let (control, width) = match ty.as_str() {
        "joint" => (ControlType::Joint, 8),
        "ee_pose" => (ControlType::EePose, 7),
        other => return Err(Content(format!("type \"{other}\" is unknown: use \"joint\" or \"ee_pose\""))),
    };
    let mut out = Vec::with_capacity(values.len());
    for (i, vals) in values.iter().enumerate() {
        if vals.len() != width {
            let layout = if width == 8 { "[q1..q7, g]" } else { "[x, y, z, ax, ay, az, g]" };
            return Err(Content(format!(
                "actions[{i}] has {} values; a {ty} waypoint has {width}: {layout}",
                vals.len()
            )));
        }
        let mut w = [0.0; WAYPOINT_LEN];
        w[..width].copy_from_slice(vals);
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
/// 0 when rejected or failed (the reason is in `get_state()["control_feedback"]`). A dict of the
/// wrong structure raises TypeError (and is recorded as rejected too).
#[pyfunction]
fn post_actions(py: Python<'_>, cmd: &Bound<'_, PyAny>) -> PyResult<i32> {
    match parse_actions(cmd) {
        Ok((control, freq, actions)) => py.detach(|| with_client(|c| c.post(control, freq, &actions))).map_err(to_py),
        Err(Refusal::Content(reason)) => with_client(|c| Ok(c.reject_locally(reason))).map_err(to_py),
        Err(Refusal::Structure(reason)) => {
            with_client(|c| Ok(c.reject_locally(reason.clone()))).map_err(to_py)?;
            Err(PyTypeError::new_err(reason))
        }
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
    m.add_class::<Plane>()?;
    m.add("SCHEMA_VERSION", ipc_schema::SCHEMA_VERSION)?;
    Ok(())
}
