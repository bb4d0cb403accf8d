//! The Rust core of `robo`: connects to one instance's services and implements reset,
//! observation and chunk execution. The pyo3 layer only converts to and from Python.

use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use ipc_schema::process;
use ipc_schema::{
    CameraFrame, ControlType, Qos, Reply, Request, RequestKind, RobotState, RuntimeInfo, Services, SimInfo, Status,
    MAX_CHUNK, WAYPOINT_LEN,
};

type S = ipc::Service;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RoboError {
    #[error(
        "no r2g instance '{0}' is running: start one with `r2g up <gym> --instance {0}` \
         (robo reads the instance from R2G_INSTANCE)"
    )]
    NotRunning(String),
    #[error("{0}")]
    Ipc(String),
    #[error("the runtime of instance '{0}' stopped responding (no state for {1:.1} s)")]
    Stale(String, f64),
    #[error("unknown camera '{name}': this gym has {known}")]
    UnknownCamera { name: String, known: String },
    #[error("bad camera size for '{name}': {detail}")]
    BadSize { name: String, detail: String },
    #[error("no image from camera '{0}' within {1:.1} s (is rendering on?)")]
    NoFrame(String, f64),
}

fn ipc<E: std::fmt::Debug>(what: &'static str) -> impl Fn(E) -> RoboError {
    move |e| RoboError::Ipc(format!("{what}: {e:?}"))
}

/// What the last reset or post_actions did, as `control_feedback` reports it.
#[derive(Debug, Clone)]
pub struct Feedback {
    pub status: &'static str,
    pub reason: String,
    pub executed: u32,
    pub request_id: u64,
    pub final_joint_error_rad: f64,
}

impl Default for Feedback {
    fn default() -> Self {
        Self {
            status: "none",
            reason: "no command sent yet".into(),
            executed: 0,
            request_id: 0,
            final_joint_error_rad: 0.0,
        }
    }
}

/// One rendered image, borrowed from shared memory.
pub struct Frame {
    pub name: String,
    sample: Sample<S, CameraFrame, ()>,
}

impl Frame {
    pub fn header(&self) -> &CameraFrame {
        &self.sample
    }
    /// The used part of the RGB buffer, read in place.
    pub fn rgb(&self) -> &[u8] {
        let f: &CameraFrame = &self.sample;
        &f.rgb[..(f.width * f.height * 3) as usize]
    }
}

pub struct Client {
    pub instance: String,
    node: Node<S>,
    robot_sub: Subscriber<S, RobotState, ()>,
    info_sub: Subscriber<S, RuntimeInfo, ()>,
    req_pub: Publisher<S, Request, ()>,
    reply_sub: Subscriber<S, Reply, ()>,
    control_wake: Notifier<S>,
    agent_wake: Listener<S>,
    cameras: Vec<(String, Subscriber<S, CameraFrame, ()>)>,
    last_frames: Vec<Option<Sample<S, CameraFrame, ()>>>,
    client_id: u64,
    next_id: u64,
    pub last_state: Option<RobotState>,
    pub info: Option<RuntimeInfo>,
    pub feedback: Feedback,
    /// Gripper value of the last command, for holding it during arm-only moves.
    last_state_at: Instant,
}

impl Client {
    /// Connects to a running instance. Refuses instances whose runtime is not alive rather than
    /// creating empty services for them.
    pub fn connect(instance: &str) -> Result<Self, RoboError> {
        let services = Services::new(instance).map_err(|e| RoboError::Ipc(e.to_string()))?;
        if process::node_alive(&process::control_node(instance)) != Some(true) {
            return Err(RoboError::NotRunning(instance.into()));
        }
        let pid = std::process::id();
        let node = ipc_schema::node(&format!("robo-{instance}-{pid}")).map_err(|e| RoboError::Ipc(e.to_string()))?;
        let open = |e: ipc_schema::SchemaError| RoboError::Ipc(e.to_string());
        let robot_sub = ipc_schema::open_or_create_pubsub::<RobotState>(&node, &services.robot_state(), Qos::STREAM)
            .map_err(open)?
            .subscriber_builder()
            .create()
            .map_err(ipc("robot state subscriber"))?;
        let info_sub = ipc_schema::open_or_create_pubsub::<RuntimeInfo>(&node, &services.runtime_info(), Qos::STREAM)
            .map_err(open)?
            .subscriber_builder()
            .create()
            .map_err(ipc("runtime info subscriber"))?;
        let sim_info_sub = ipc_schema::open_or_create_pubsub::<SimInfo>(&node, &services.sim_info(), Qos::STREAM)
            .map_err(open)?
            .subscriber_builder()
            .create()
            .map_err(ipc("sim info subscriber"))?;
        let req_pub = ipc_schema::open_or_create_pubsub::<Request>(&node, &services.request(), Qos::REQUESTS)
            .map_err(open)?
            .publisher_builder()
            .create()
            .map_err(ipc("request publisher"))?;
        let reply_sub = ipc_schema::open_or_create_pubsub::<Reply>(&node, &services.reply(), Qos::REPLIES)
            .map_err(open)?
            .subscriber_builder()
            .create()
            .map_err(ipc("reply subscriber"))?;
        let control_wake = ipc_schema::open_or_create_event(&node, &services.control_wake())
            .map_err(open)?
            .notifier_builder()
            .create()
            .map_err(ipc("notifier"))?;
        let agent_wake = ipc_schema::open_or_create_event(&node, &services.agent_wake())
            .map_err(open)?
            .listener_builder()
            .create()
            .map_err(ipc("listener"))?;
        // Which cameras exist: the sim-host resends its info regularly.
        let t0 = Instant::now();
        let sim_info = loop {
            if let Some(s) = sim_info_sub.receive().map_err(ipc("sim info"))? {
                break *s;
            }
            if t0.elapsed() > Duration::from_secs(3) {
                return Err(RoboError::Ipc(format!(
                    "the sim-host of instance '{instance}' published no camera list within 3 s"
                )));
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        let mut cameras = Vec::new();
        for i in 0..(sim_info.camera_count as usize).min(ipc_schema::MAX_CAMERAS) {
            let name = sim_info.camera_name(i).to_string();
            let qos = Qos { history: 1, buffer: 1, max_publishers: 1, max_subscribers: 8 };
            let sub = ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, &services.camera(&name), qos)
                .map_err(open)?
                .subscriber_builder()
                .create()
                .map_err(ipc("camera subscriber"))?;
            cameras.push((name, sub));
        }
        let n = cameras.len();
        let mut c = Self {
            instance: instance.into(),
            node,
            robot_sub,
            info_sub,
            req_pub,
            reply_sub,
            control_wake,
            agent_wake,
            cameras,
            last_frames: (0..n).map(|_| None).collect(),
            client_id: ((pid as u64) << 32) ^ (ipc_schema::monotonic_ns() & 0xffff_ffff),
            next_id: 1,
            last_state: None,
            info: None,
            feedback: Feedback::default(),
            last_state_at: Instant::now(),
        };
        c.refresh_state(Duration::from_secs(3))?;
        Ok(c)
    }

    pub fn camera_names(&self) -> Vec<String> {
        self.cameras.iter().map(|c| c.0.clone()).collect()
    }

    /// Takes the newest robot state, waiting up to `wait` for a first one.
    pub fn refresh_state(&mut self, wait: Duration) -> Result<RobotState, RoboError> {
        let t0 = Instant::now();
        loop {
            while let Some(s) = self.robot_sub.receive().map_err(ipc("robot state"))? {
                self.last_state = Some(*s);
                self.last_state_at = Instant::now();
            }
            while let Some(i) = self.info_sub.receive().map_err(ipc("runtime info"))? {
                self.info = Some(*i);
            }
            if let Some(s) = self.last_state {
                let age_s = (ipc_schema::monotonic_ns().saturating_sub(s.published_ns)) as f64 * 1e-9;
                if age_s < 1.0 {
                    return Ok(s);
                }
                if t0.elapsed() >= wait {
                    return Err(RoboError::Stale(self.instance.clone(), age_s));
                }
            } else if t0.elapsed() >= wait {
                return Err(RoboError::NotRunning(self.instance.clone()));
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// The newest frame of a camera showing the scene at or after `not_before_s` (sim time);
    /// falls back to the newest frame after `wait`.
    pub fn frame(&mut self, name: &str, not_before_s: f64, wait: Duration) -> Result<Frame, RoboError> {
        let Some(i) = self.cameras.iter().position(|c| c.0 == name) else {
            let known = if self.cameras.is_empty() {
                "no cameras".to_string()
            } else {
                format!("cameras {}", self.camera_names().join(", "))
            };
            return Err(RoboError::UnknownCamera { name: name.into(), known });
        };
        let t0 = Instant::now();
        loop {
            while let Some(s) = self.cameras[i].1.receive().map_err(ipc("camera frame"))? {
                // Release the older sample before holding the newer one.
                self.last_frames[i] = None;
                self.last_frames[i] = Some(s);
            }
            if let Some(f) = &self.last_frames[i] {
                if f.sim_time_s >= not_before_s - 1e-9 || t0.elapsed() >= wait {
                    let sample = self.last_frames[i].take().ok_or_else(|| RoboError::NoFrame(name.into(), 0.0))?;
                    return Ok(Frame { name: name.into(), sample });
                }
            } else if t0.elapsed() >= wait {
                return Err(RoboError::NoFrame(name.into(), wait.as_secs_f64()));
            }
            let _ = self.agent_wake.timed_wait(|_| {}, Duration::from_millis(10));
        }
    }

    /// Puts a frame back so a later call can reuse it if nothing newer arrives.
    pub fn give_back(&mut self, frame: Frame) {
        if let Some(i) = self.cameras.iter().position(|c| c.0 == frame.name) {
            if self.last_frames[i].is_none() {
                self.last_frames[i] = Some(frame.sample);
            }
        }
    }

    fn send(&mut self, fill: impl FnOnce(&mut Request)) -> Result<u64, RoboError> {
        let id = self.next_id;
        self.next_id += 1;
        let mut sample = self.req_pub.loan_uninit().map_err(ipc("loan request"))?;
        let p = sample.payload_mut().as_mut_ptr();
        // SAFETY: p points at a Request-sized sample we own; every field is written before
        // assume_init (actions zeroed in place, then filled).
        let sample = unsafe {
            std::ptr::write_bytes(p, 0, 1);
            (*p).id = id;
            (*p).client = self.client_id;
            fill(&mut *p);
            sample.assume_init()
        };
        sample.send().map_err(ipc("send request"))?;
        self.control_wake.notify().map_err(ipc("notify runtime"))?;
        Ok(id)
    }

    /// Waits for the reply to request `id`; watches the runtime's liveness meanwhile.
    fn wait_reply(&mut self, id: u64, timeout: Duration) -> Result<Reply, RoboError> {
        let t0 = Instant::now();
        loop {
            while let Some(r) = self.reply_sub.receive().map_err(ipc("reply"))? {
                if r.id == id && r.client == self.client_id {
                    return Ok(*r);
                }
            }
            while let Some(s) = self.robot_sub.receive().map_err(ipc("robot state"))? {
                self.last_state = Some(*s);
                self.last_state_at = Instant::now();
            }
            if self.last_state_at.elapsed() > Duration::from_secs(2) {
                return Err(RoboError::Stale(self.instance.clone(), self.last_state_at.elapsed().as_secs_f64()));
            }
            if t0.elapsed() > timeout {
                return Err(RoboError::Ipc(format!("no reply to request {id} within {:.0} s", timeout.as_secs_f64())));
            }
            let _ = self.agent_wake.timed_wait(|_| {}, Duration::from_millis(20));
        }
    }

    fn finish(&mut self, reply: Reply) -> i32 {
        let status = Status::from_u32(reply.status).unwrap_or(Status::Failed);
        self.feedback = Feedback {
            status: status.name(),
            reason: reply.reason_str().to_string(),
            executed: reply.executed,
            request_id: reply.id,
            final_joint_error_rad: reply.final_joint_error_rad,
        };
        i32::from(status == Status::Executed)
    }

    /// Records a rejection that never left this process.
    pub fn reject_locally(&mut self, reason: String) -> i32 {
        self.feedback = Feedback {
            status: Status::Rejected.name(),
            reason,
            executed: 0,
            request_id: 0,
            final_joint_error_rad: 0.0,
        };
        0
    }

    pub fn reset(&mut self) -> Result<i32, RoboError> {
        let id = self.send(|r| r.kind = RequestKind::Reset as u32)?;
        let reply = self.wait_reply(id, Duration::from_secs(30))?;
        let ok = self.finish(reply);
        // Drop frames from before the reset.
        for f in &mut self.last_frames {
            *f = None;
        }
        self.refresh_state(Duration::from_secs(2))?;
        Ok(ok)
    }

    /// Sends a chunk of absolute targets and blocks until it executed or failed.
    pub fn post(
        &mut self,
        control: ControlType,
        freq_hz: f64,
        actions: &[[f64; WAYPOINT_LEN]],
    ) -> Result<i32, RoboError> {
        if actions.len() > MAX_CHUNK {
            return Ok(self
                .reject_locally(format!("actions has {} waypoints, at most {MAX_CHUNK} are accepted", actions.len())));
        }
        let id = self.send(|r| {
            r.kind = RequestKind::Chunk as u32;
            r.control_type = control as u32;
            r.len = actions.len() as u32;
            r.freq_hz = freq_hz;
            r.actions[..actions.len()].copy_from_slice(actions);
        })?;
        let f = if freq_hz > 0.0 { freq_hz } else { 20.0 };
        // The runtime caps a chunk's duration; this only bounds the wait if it never answers.
        let nominal_s = (actions.len() as f64 / f).clamp(0.0, 600.0);
        let reply = self.wait_reply(id, Duration::from_secs_f64(60.0 + 4.0 * nominal_s))?;
        Ok(self.finish(reply))
    }

    pub fn node_name(&self) -> String {
        self.node.name().as_str().to_string()
    }
}
