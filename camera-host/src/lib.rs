//! `r2g_camera`: the publisher a camera host uses to put real frames into an instance's camera
//! services, as [`ipc_schema::CameraFrame`]s exactly like the ones sim-host renders, so that
//! `robo` and the perception helpers read them unchanged. Payload types live in `ipc-schema`
//! only; this module is not `robo` and never enters the agent's sandbox.
//!
//! What it adds to the pixels the host hands it:
//! - **time on the runtime's clock**: the host gives the exposure time on CLOCK_MONOTONIC; the
//!   frame carries the robot time of that instant, interpolated between the runtime's two states
//!   published around it (`place`), so `robo`'s "not older than the last motion" check works
//!   as for rendered frames;
//! - **the camera's pose** from the robot config's calibration (as the runtime read and reported
//!   it, [`ipc_schema::RuntimeInfo::calibration`]): fixed (`base_from_camera`), or on the hand
//!   (`flange_from_camera`), composed with the TCP pose at the exposure, interpolated the same way;
//! - **intrinsics** from the calibration file when it gives them (the image size must then
//!   match), else the device's, as the host passes them.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use controllers::math;
use ipc_schema::process;
use ipc_schema::{
    CameraFrame, FrameHeader, Pose, Qos, RobotState, RuntimeInfo, Services, MAX_IMAGE_HEIGHT, MAX_IMAGE_WIDTH,
};
use pyo3::buffer::PyBuffer;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

type Service = iceoryx2::prelude::ipc::Service;

/// Runtime states kept to place an exposure between two of them: 256 ms of 1 kHz ticks, more
/// than a camera's capture-to-publish latency.
const KEPT_STATES: usize = 256;
/// The states the subscriber holds between two publishes (every tick's, drained per frame;
/// [`Qos::ROBOT_STATE`] allows up to 128).
const STATE_BUFFER: usize = 128;

type Transform = ([f64; 3], [f64; 4]);

fn from_matrix(v: &serde_json::Value) -> Option<Transform> {
    let rows: Vec<Vec<f64>> = serde_json::from_value(v.clone()).ok()?;
    if rows.len() != 4 || rows.iter().any(|r| r.len() != 4) {
        return None;
    }
    let r =
        [rows[0][0], rows[0][1], rows[0][2], rows[1][0], rows[1][1], rows[1][2], rows[2][0], rows[2][1], rows[2][2]];
    Some(([rows[0][3], rows[1][3], rows[2][3]], math::quat_from_mat(&r)))
}

enum Mount {
    Base(Transform),
    /// flange_from_camera, and tcp_from_flange (the runtime's TCP in use).
    Flange(Transform, Transform),
}

#[pyclass(unsendable)]
struct Publisher {
    camera: String,
    node: Option<iceoryx2::prelude::Node<Service>>,
    publisher: Option<iceoryx2::port::publisher::Publisher<Service, CameraFrame, ()>>,
    robot: Option<iceoryx2::port::subscriber::Subscriber<Service, RobotState, ()>>,
    wake: Option<iceoryx2::port::notifier::Notifier<Service>>,
    states: VecDeque<RobotState>,
    mount: Mount,
    #[pyo3(get)]
    width: Option<u32>,
    #[pyo3(get)]
    height: Option<u32>,
    #[pyo3(get)]
    intrinsics: Option<(f64, f64, f64, f64)>,
    seq: u64,
}

fn ipc<E: std::fmt::Display>(what: &'static str) -> impl Fn(E) -> PyErr {
    move |e| PyRuntimeError::new_err(format!("{what}: {e}"))
}

#[pymethods]
impl Publisher {
    #[new]
    fn new(instance: &str, camera: &str) -> PyResult<Self> {
        let services = Services::new(instance).map_err(|e| PyValueError::new_err(e.to_string()))?;
        if process::node_alive(&process::control_node(instance)) != Some(true) {
            return Err(PyRuntimeError::new_err(format!(
                "the runtime of instance '{instance}' is not running (start it with `r2g up`)"
            )));
        }
        let node = ipc_schema::node(&format!("r2g-camera-{instance}-{camera}")).map_err(ipc("iceoryx2 node"))?;
        let open = |e: ipc_schema::SchemaError| PyRuntimeError::new_err(e.to_string());
        let info = ipc_schema::open_or_create_pubsub::<RuntimeInfo>(&node, &services.runtime_info(), Qos::STREAM)
            .map_err(open)?
            .subscriber_builder()
            .create()
            .map_err(ipc("runtime info subscriber"))?;
        let robot = ipc_schema::open_or_create_pubsub::<RobotState>(&node, &services.robot_state(), Qos::ROBOT_STATE)
            .map_err(open)?
            .subscriber_builder()
            .buffer_size(STATE_BUFFER)
            .create()
            .map_err(ipc("robot state subscriber"))?;
        // The calibration as the runtime read it: the runtime resends its info every 200 ms.
        let t0 = Instant::now();
        let report = loop {
            if let Some(i) = info.receive().map_err(ipc("runtime info"))? {
                break i.calibration_str().to_string();
            }
            if t0.elapsed() > Duration::from_secs(3) {
                return Err(PyRuntimeError::new_err(format!(
                    "the runtime of instance '{instance}' published no info within 3 s"
                )));
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        let report: serde_json::Value = serde_json::from_str(&report)
            .map_err(|e| PyRuntimeError::new_err(format!("the runtime's calibration report: {e}")))?;
        let entry = &report["cameras"][camera];
        if entry.is_null() {
            return Err(PyValueError::new_err(format!(
                "the robot config names no calibration file for camera '{camera}' (calibration.cameras.{camera}): \
                 its pose is unknown, so its frames could not be related to the robot"
            )));
        }
        if entry["source"] == "missing" {
            return Err(PyValueError::new_err(format!(
                "camera '{camera}': {}",
                entry["reason"].as_str().unwrap_or("its calibration file is unusable")
            )));
        }
        let bad = |what: &str| {
            PyValueError::new_err(format!("camera '{camera}': the calibration report's {what} is unusable"))
        };
        let mount = if let Some(m) = entry.get("base_from_camera") {
            Mount::Base(from_matrix(m).ok_or_else(|| bad("base_from_camera"))?)
        } else {
            let fc = from_matrix(&entry["flange_from_camera"]).ok_or_else(|| bad("flange_from_camera"))?;
            let ft = from_matrix(&report["tcp"]["flange_from_tcp"]).ok_or_else(|| bad("flange_from_tcp"))?;
            Mount::Flange(fc, math::inverse(ft))
        };
        let (width, height, intrinsics) = match entry.get("fx") {
            Some(_) => {
                let f = |k: &str| entry[k].as_f64().ok_or_else(|| bad(k));
                (Some(f("width")? as u32), Some(f("height")? as u32), Some((f("fx")?, f("fy")?, f("cx")?, f("cy")?)))
            }
            None => (None, None, None),
        };
        if width.is_some_and(|w| w as usize > MAX_IMAGE_WIDTH) || height.is_some_and(|h| h as usize > MAX_IMAGE_HEIGHT)
        {
            return Err(PyValueError::new_err(format!(
                "camera '{camera}': its calibration is for {}×{} images; frames are at most {MAX_IMAGE_WIDTH}×{MAX_IMAGE_HEIGHT}",
                width.unwrap_or(0),
                height.unwrap_or(0)
            )));
        }
        let publisher = ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, &services.camera(camera), Qos::CAMERA)
            .map_err(open)?
            .publisher_builder()
            .create()
            .map_err(|e| {
                PyRuntimeError::new_err(format!(
                    "camera service '{}' has a publisher already ({e}): another camera host, or the sim-host rendering a \
                     scene camera of that name",
                    services.camera(camera)
                ))
            })?;
        let wake = ipc_schema::open_or_create_event(&node, &services.agent_wake())
            .map_err(open)?
            .notifier_builder()
            .create()
            .map_err(ipc("agent wake notifier"))?;
        Ok(Self {
            camera: camera.into(),
            node: Some(node),
            publisher: Some(publisher),
            robot: Some(robot),
            wake: Some(wake),
            states: VecDeque::with_capacity(KEPT_STATES),
            mount,
            width,
            height,
            intrinsics,
            seq: 0,
        })
    }

    /// Publishes one frame: `rgb` uint8 (H, W, 3), `depth_m` float32 (H, W) in metres aligned to
    /// it or None, the pinhole intrinsics in pixels, and the exposure time on CLOCK_MONOTONIC.
    #[pyo3(signature = (rgb, depth_m, fx, fy, cx, cy, captured_ns))]
    #[allow(clippy::too_many_arguments)]
    fn publish<'py>(
        &mut self,
        py: Python<'py>,
        rgb: &Bound<'py, PyAny>,
        depth_m: Option<&Bound<'py, PyAny>>,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        captured_ns: u64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let cam = self.camera.clone();
        let err = |m: String| PyValueError::new_err(format!("camera '{cam}': {m}"));
        let rgb = PyBuffer::<u8>::get(rgb).map_err(|e| err(format!("rgb must be a uint8 array: {e}")))?;
        let shape = rgb.shape().to_vec();
        if shape.len() != 3 || shape[2] != 3 || !rgb.is_c_contiguous() {
            return Err(err(format!("rgb must be a C-contiguous (height, width, 3) uint8 array, got shape {shape:?}")));
        }
        let (h, w) = (shape[0], shape[1]);
        if w == 0 || h == 0 || w > MAX_IMAGE_WIDTH || h > MAX_IMAGE_HEIGHT {
            return Err(err(format!(
                "a {w}×{h} image does not fit a frame (at most {MAX_IMAGE_WIDTH}×{MAX_IMAGE_HEIGHT})"
            )));
        }
        if let (Some(cw), Some(ch)) = (self.width, self.height) {
            if (w as u32, h as u32) != (cw, ch) {
                return Err(err(format!(
                    "the image is {w}×{h} but its calibration is for {cw}×{ch}: the device changed resolution, or the \
                     calibration belongs to another mode"
                )));
            }
        }
        let depth = match depth_m {
            Some(d) if !d.is_none() => {
                let d = PyBuffer::<f32>::get(d).map_err(|e| err(format!("depth_m must be a float32 array: {e}")))?;
                if d.shape() != [h, w] || !d.is_c_contiguous() {
                    return Err(err(format!(
                        "depth_m must be a C-contiguous float32 array of the image's shape ({h}, {w}), got {:?}",
                        d.shape()
                    )));
                }
                Some(d)
            }
            _ => None,
        };
        let (fx, fy, cx, cy) = self.intrinsics.unwrap_or((fx, fy, cx, cy));
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0 && cx.is_finite() && cy.is_finite()) {
            return Err(err(format!("intrinsics fx={fx} fy={fy} cx={cx} cy={cy} are not usable")));
        }
        // The runtime's states, newest last, to place the exposure on its clock.
        let robot = self.robot.as_ref().ok_or_else(|| PyRuntimeError::new_err("the publisher is closed"))?;
        while let Some(s) = robot.receive().map_err(ipc("robot state"))? {
            if self.states.len() == KEPT_STATES {
                self.states.pop_front();
            }
            self.states.push_back(*s);
        }
        let Some(newest) = self.states.back() else {
            return Err(PyRuntimeError::new_err(format!(
                "camera '{cam}': no state from the runtime yet, so the frame cannot be placed on its clock"
            )));
        };
        if newest.published_ns + 1_000_000_000 < ipc_schema::monotonic_ns() {
            return Err(PyRuntimeError::new_err(format!(
                "camera '{cam}': the runtime's newest state is more than 1 s old (the runtime stopped or hangs)"
            )));
        }
        let at = place(&self.states, captured_ns);
        let base_from_camera = match self.mount {
            Mount::Base(t) => t,
            Mount::Flange(flange_from_camera, tcp_from_flange) => {
                math::compose(math::compose(at.base_from_tcp, tcp_from_flange), flange_from_camera)
            }
        };
        let (state, sim_time_s) = (at.state, at.sim_time_s);
        let publisher = self.publisher.as_ref().ok_or_else(|| PyRuntimeError::new_err("the publisher is closed"))?;
        let mut sample = publisher.loan_uninit().map_err(ipc("camera sample"))?;
        let n = w * h;
        self.seq += 1;
        let header = FrameHeader {
            seq: self.seq,
            sim_time_s,
            state_seq: state.seq,
            rendered_ns: captured_ns,
            width: w as u32,
            height: h as u32,
            reset_id: state.reset_id as u32,
            fx,
            fy,
            cx,
            cy,
            base_from_camera: Pose { position_m: base_from_camera.0, quat_xyzw: base_from_camera.1 },
        };
        // SAFETY: both buffers were checked above to be C-contiguous with exactly these many
        // elements (3 × w × h bytes, w × h floats), and they stay alive and unchanged while the
        // GIL is held, which it is for this call.
        let (rgb, depth) = unsafe {
            (
                std::slice::from_raw_parts(rgb.buf_ptr().cast::<u8>(), 3 * n),
                depth.as_ref().map(|d| std::slice::from_raw_parts(d.buf_ptr().cast::<f32>(), n)),
            )
        };
        CameraFrame::fill(sample.payload_mut(), &header, rgb, depth);
        // SAFETY: `fill` wrote every byte of the sample.
        let sample = unsafe { sample.assume_init() };
        sample.send().map_err(ipc("camera frame"))?;
        if let Some(w) = &self.wake {
            let _ = w.notify();
        }
        let published_ns = ipc_schema::monotonic_ns();
        let out = PyDict::new(py);
        out.set_item("seq", self.seq)?;
        out.set_item("sim_time_s", sim_time_s)?;
        out.set_item("reset_id", state.reset_id)?;
        out.set_item("published_ns", published_ns)?;
        Ok(out)
    }

    /// Removes this publisher from the instance's services.
    fn close(&mut self) {
        self.publisher = None;
        self.robot = None;
        self.wake = None;
        self.node = None;
    }
}

/// An exposure on the runtime's clock and the TCP pose then.
struct Placed {
    /// The state nearest the exposure (its seq and reset_id go into the frame).
    state: RobotState,
    sim_time_s: f64,
    base_from_tcp: Transform,
}

/// Places an exposure at `captured_ns` (CLOCK_MONOTONIC) among the runtime's states, oldest
/// first: between the two published around it, robot time and TCP pose interpolated (linear,
/// and normalised linear for the rotation: 1 ms apart they differ by little); before the oldest
/// or after the newest, that state's pose and its time shifted by the difference. `states` is
/// not empty.
fn place(states: &VecDeque<RobotState>, captured_ns: u64) -> Placed {
    let pose = |s: &RobotState| (s.base_from_tcp.position_m, s.base_from_tcp.quat_xyzw);
    let between = states
        .iter()
        .zip(states.iter().skip(1))
        .find(|(a, b)| a.published_ns <= captured_ns && captured_ns <= b.published_ns && a.reset_id == b.reset_id);
    if let Some((a, b)) = between.filter(|(a, b)| b.published_ns > a.published_ns) {
        let f = (captured_ns - a.published_ns) as f64 / (b.published_ns - a.published_ns) as f64;
        let ((pa, qa), (pb, mut qb)) = (pose(a), pose(b));
        if qa.iter().zip(&qb).map(|(x, y)| x * y).sum::<f64>() < 0.0 {
            qb = qb.map(|v| -v); // the same rotation, on qa's side
        }
        let lerp = |x: f64, y: f64| x + f * (y - x);
        let p = std::array::from_fn(|i| lerp(pa[i], pb[i]));
        let q = math::normalize(std::array::from_fn(|i| lerp(qa[i], qb[i])));
        return Placed {
            state: if f < 0.5 { *a } else { *b },
            sim_time_s: lerp(a.timestamp_s, b.timestamp_s),
            base_from_tcp: (p, q),
        };
    }
    let nearest = states.iter().min_by_key(|s| s.published_ns.abs_diff(captured_ns)).copied().unwrap_or_default();
    let dt_s = (captured_ns as f64 - nearest.published_ns as f64) * 1e-9;
    Placed { state: nearest, sim_time_s: nearest.timestamp_s + dt_s, base_from_tcp: pose(&nearest) }
}

#[pymodule]
fn r2g_camera(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Publisher>()?;
    Ok(())
}
