//! The Rust core of `robo`: connects to one instance's services and implements reset,
//! observation and chunk execution. The pyo3 layer only converts to and from Python.

use std::rc::{Rc, Weak};
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
    #[error("no image from camera '{0}' within {1:.1} s (is rendering on, and is its camera host delivering frames?)")]
    NoFrame(String, f64),
}

/// On the wall clock, a frame made longer ago than this (CLOCK_MONOTONIC) is never shown: its
/// camera (or its camera host, or the renderer) stopped. Rendering runs at 0.5 Hz or more.
const STALE_FRAME_NS: u64 = 2_000_000_000;

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
    /// Submission → acceptance by the runtime, µs.
    pub accepted_us: Option<f64>,
    /// Submission → first measured motion, µs.
    pub first_motion_us: Option<f64>,
    /// The force felt over the chunk (on its first tick, largest and mean magnitude, N; the
    /// waypoint at the largest); None for a request that never ran (a rejection, a reset).
    pub contact: Option<Contact>,
}

/// [`Feedback::contact`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    /// On the chunk's first tick: what was already felt.
    pub start_n: f64,
    pub peak_n: f64,
    pub mean_n: f64,
    /// None when nothing was felt (`peak_n` 0).
    pub peak_waypoint: Option<u32>,
}

impl Default for Feedback {
    fn default() -> Self {
        Self {
            status: "none",
            reason: "no command sent yet".into(),
            executed: 0,
            request_id: 0,
            final_joint_error_rad: 0.0,
            accepted_us: None,
            first_motion_us: None,
            contact: None,
        }
    }
}

/// Frames of one camera a subscriber may hold at once (see [`Qos::CAMERA`]).
const BORROWED: usize = Qos::CAMERA.borrowed;

/// One camera's subscription and the frames handed out from it.
struct Camera {
    name: String,
    sub: Subscriber<S, CameraFrame, ()>,
    /// The newest frame received.
    last: Option<Rc<Frame>>,
    /// Every frame received that may still be alive (held by `last` or by views in Python).
    issued: Vec<Weak<Frame>>,
    /// The last PNG encoded: frame seq, width, height, bytes. An idle scene is encoded once.
    png: Option<(u64, u32, u32, Rc<Vec<u8>>)>,
}

impl Camera {
    /// Distinct frames of this camera still borrowed from shared memory.
    fn alive(&mut self) -> usize {
        self.issued.retain(|w| w.strong_count() > 0);
        self.issued.len()
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
    /// The used part of the depth buffer (metres, planar), read in place; None without depth.
    pub fn depth(&self) -> Option<&[f32]> {
        let f: &CameraFrame = &self.sample;
        (f.has_depth == 1).then(|| &f.depth_m[..(f.width * f.height) as usize])
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
    cameras: Vec<Camera>,
    client_id: u64,
    next_id: u64,
    pub last_state: Option<RobotState>,
    pub info: Option<RuntimeInfo>,
    pub feedback: Feedback,
    last_state_at: Instant,
    /// Simulated time at which the last request finished: images must show the scene from then
    /// on, never mid-motion.
    settled_s: f64,
    /// The reset_id of the episode that settle saw (frames of earlier episodes are stale).
    settled_reset: u32,
    /// CLOCK_MONOTONIC when the last chunk was sent, ns.
    submitted_ns: u64,
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
        let robot_sub =
            ipc_schema::open_or_create_pubsub::<RobotState>(&node, &services.robot_state(), Qos::ROBOT_STATE)
                .map_err(open)?
                .subscriber_builder()
                .buffer_size(1)
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
            let qos = Qos::CAMERA;
            let sub = ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, &services.camera(&name), qos)
                .map_err(open)?
                .subscriber_builder()
                .create()
                .map_err(ipc("camera subscriber"))?;
            cameras.push(Camera { name, sub, last: None, issued: Vec::new(), png: None });
        }
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
            client_id: ((pid as u64) << 32) ^ (ipc_schema::monotonic_ns() & 0xffff_ffff),
            next_id: 1,
            last_state: None,
            info: None,
            feedback: Feedback::default(),
            last_state_at: Instant::now(),
            settled_s: 0.0,
            settled_reset: 0,
            submitted_ns: 0,
        };
        c.refresh_state(Duration::from_secs(3))?;
        // The limits in force: the runtime resends them at least every 200 ms.
        let t0 = Instant::now();
        while c.info.is_none() && t0.elapsed() < Duration::from_secs(2) {
            std::thread::sleep(Duration::from_millis(5));
            c.refresh_state(Duration::from_secs(1))?;
        }
        Ok(c)
    }

    pub fn camera_names(&self) -> Vec<String> {
        self.cameras.iter().map(|c| c.name.clone()).collect()
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

    /// The newest frame of a camera showing the scene after the last request finished; falls
    /// back to the newest frame after `wait` (rendering lags or is off).
    pub fn frame(&mut self, name: &str, wait: Duration) -> Result<Rc<Frame>, RoboError> {
        let Some(i) = self.cameras.iter().position(|c| c.name == name) else {
            let known = if self.cameras.is_empty() {
                "no cameras".to_string()
            } else {
                format!("cameras {}", self.camera_names().join(", "))
            };
            return Err(RoboError::UnknownCamera { name: name.into(), known });
        };
        let (mut not_before_reset, mut not_before_s) = (self.settled_reset, self.settled_s);
        let submitted_ns = self.submitted_ns;
        // Lockstep time stands still while nothing moves, so a frame may be old and current;
        // on the wall clock every frame is rendered or captured continually.
        let wall = self.last_state.is_none_or(|s| s.mode != ipc_schema::Mode::Lockstep as u32);
        if let (false, Some(s)) = (wall, self.last_state.as_ref()) {
            // Nothing moves between requests in lockstep: the frame must show the state as it is
            // now, also for a client that moved nothing itself (another process did: a program's
            // proxy, then the host that observes after it), whose own `settled_s` says nothing.
            let ahead = (s.reset_id as u32).wrapping_sub(not_before_reset) as i32;
            if ahead > 0 || (ahead == 0 && s.timestamp_s > not_before_s) {
                (not_before_reset, not_before_s) = (s.reset_id as u32, s.timestamp_s);
            }
        }
        let t0 = Instant::now();
        loop {
            let cam = &mut self.cameras[i];
            // Receive only while another frame can still be borrowed: programs may hold views.
            while cam.alive() < BORROWED {
                let Some(s) = cam.sub.receive().map_err(ipc("camera frame"))? else { break };
                let f = Rc::new(Frame { name: cam.name.clone(), sample: s });
                cam.issued.push(Rc::downgrade(&f));
                cam.last = Some(f);
            }
            if let Some(f) = &cam.last {
                let h = f.header();
                // Reset ids grow by one per reset; compared modulo 2^32.
                let episodes_ahead = h.reset_id.wrapping_sub(not_before_reset) as i32;
                let young = ipc_schema::monotonic_ns().saturating_sub(h.rendered_ns) < STALE_FRAME_NS;
                // A camera (host) that stopped delivering gives no frame, moved or not.
                let fresh = (episodes_ahead > 0 || (episodes_ahead == 0 && h.sim_time_s >= not_before_s - 1e-9))
                    && (young || !wall);
                // After the wait, an older frame of this episode only if it was made after the
                // last chunk was sent, and recently: a renderer that lags behind the motion.
                let recent = h.rendered_ns > submitted_ns && young;
                if fresh || (episodes_ahead == 0 && recent && t0.elapsed() >= wait) {
                    return Ok(f.clone());
                }
                if t0.elapsed() >= wait {
                    // Only a frame of an earlier episode: showing it would show a scene that no
                    // longer exists.
                    return Err(RoboError::NoFrame(name.into(), wait.as_secs_f64()));
                }
            } else if t0.elapsed() >= wait {
                return Err(RoboError::NoFrame(name.into(), wait.as_secs_f64()));
            }
            let _ = self.agent_wake.timed_wait(|_| {}, Duration::from_millis(10));
        }
    }

    /// `frame` as PNG at `width` × `height` (resized if needed), encoded once per frame and size.
    pub fn png(&mut self, frame: &Frame, width: u32, height: u32) -> Result<Rc<Vec<u8>>, RoboError> {
        let h = frame.header();
        let cam = self.cameras.iter_mut().find(|c| c.name == frame.name);
        if let Some((_, _, _, png)) =
            cam.as_ref().and_then(|c| c.png.as_ref()).filter(|p| (p.0, p.1, p.2) == (h.seq, width, height))
        {
            return Ok(png.clone());
        }
        let encoded = if (width, height) == (h.width, h.height) {
            crate::image::encode_png(frame.rgb(), width, height)
        } else {
            crate::image::encode_png(
                &crate::image::resize_rgb(frame.rgb(), h.width, h.height, width, height),
                width,
                height,
            )
        }
        .map_err(|e| RoboError::Ipc(format!("PNG encoding of '{}' failed: {e}", frame.name)))?;
        let png = Rc::new(encoded);
        if let Some(c) = cam {
            c.png = Some((h.seq, width, height, png.clone()));
        }
        Ok(png)
    }

    /// Whether a program may keep `frame` as a view into shared memory: true while this camera
    /// has room for it and for receiving the next frame; otherwise the caller copies.
    pub fn may_borrow(&mut self, frame: &Rc<Frame>) -> bool {
        let Some(cam) = self.cameras.iter_mut().find(|c| c.name == frame.name) else { return false };
        let alive = cam.alive();
        let held_elsewhere = alive - usize::from(cam.last.as_ref().is_some_and(|l| Rc::ptr_eq(l, frame)));
        held_elsewhere < BORROWED - 2
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

    /// Waits for the final reply to request `id` (an `accepted` one is noted on the way);
    /// watches the runtime's liveness meanwhile.
    fn wait_reply(&mut self, id: u64, timeout: Duration) -> Result<Reply, RoboError> {
        let replies = self.replies_until(id, timeout, |r| r.status != Status::Accepted as u32)?;
        let Some((last, accepted)) = replies.split_last() else { unreachable!("ends with the final reply") };
        for r in accepted {
            self.finish(*r);
        }
        Ok(*last)
    }

    /// Every reply to request `id` until one that `done` accepts (the last one returned);
    /// watches the runtime's liveness meanwhile.
    fn replies_until(
        &mut self,
        id: u64,
        timeout: Duration,
        done: impl Fn(&Reply) -> bool,
    ) -> Result<Vec<Reply>, RoboError> {
        let t0 = Instant::now();
        let mut replies = Vec::new();
        loop {
            while let Some(r) = self.reply_sub.receive().map_err(ipc("reply"))? {
                if r.id == id && r.client == self.client_id {
                    replies.push(*r);
                    if done(&r) {
                        return Ok(replies);
                    }
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
        let since = |ns: u64| (ns > 0).then(|| ns.saturating_sub(self.submitted_ns) as f64 * 1e-3);
        let mut reason = reply.reason_str().to_string();
        if status == Status::OperatorRequired {
            reason.push_str(&format!(" (an operator clears it with `r2g clear --instance {}`)", self.instance));
        }
        self.feedback = Feedback {
            status: status.name(),
            reason,
            executed: reply.executed,
            request_id: reply.id,
            final_joint_error_rad: reply.final_joint_error_rad,
            accepted_us: since(reply.accepted_ns),
            first_motion_us: since(reply.first_motion_ns),
            contact: (reply.contact_ticks > 0).then_some(Contact {
                start_n: reply.contact_start_n,
                peak_n: reply.contact_peak_n,
                mean_n: reply.contact_mean_n,
                // nothing felt at all: no waypoint to name
                peak_waypoint: (reply.contact_peak_n > 0.0).then_some(reply.contact_peak_waypoint),
            }),
        };
        i32::from(status == Status::Executed)
    }

    /// The request finished: images from now on must show the scene after it.
    fn settle(&mut self) -> Result<(), RoboError> {
        let s = self.refresh_state(Duration::from_secs(2))?;
        self.settled_s = s.timestamp_s;
        self.settled_reset = s.reset_id as u32;
        Ok(())
    }

    /// Records a rejection that never left this process.
    pub fn reject_locally(&mut self, reason: String) -> i32 {
        self.feedback = Feedback {
            status: Status::Rejected.name(),
            reason,
            executed: 0,
            request_id: 0,
            final_joint_error_rad: 0.0,
            accepted_us: None,
            first_motion_us: None,
            contact: None,
        };
        0
    }

    pub fn reset(&mut self) -> Result<i32, RoboError> {
        let id = self.send(|r| r.kind = RequestKind::Reset as u32)?;
        let reply = self.wait_reply(id, Duration::from_secs(30))?;
        let ok = self.finish(reply);
        self.settle()?;
        Ok(ok)
    }

    /// Sends a chunk of absolute targets and blocks until it executed or failed.
    pub fn post(
        &mut self,
        control: ControlType,
        freq_hz: f64,
        actions: &[[f64; WAYPOINT_LEN]],
    ) -> Result<i32, RoboError> {
        let max = self.info.map_or(MAX_CHUNK, |i| (i.max_chunk as usize).clamp(1, MAX_CHUNK));
        if actions.len() > max {
            return Ok(self.reject_locally(format!(
                "actions has {} waypoints, at most {max} are accepted: split the chunk",
                actions.len()
            )));
        }
        self.submitted_ns = ipc_schema::monotonic_ns();
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
        let ok = self.finish(reply);
        if reply.status != Status::Rejected as u32 {
            // Something may have moved: images must show the scene after it.
            self.settle()?;
        }
        Ok(ok)
    }

    /// One step of a fixed period (a gymnasium environment's, see [`RequestKind::Step`]):
    /// `actions` (none: time only passes) as the step's chunk, then `ticks` ticks. Blocks until
    /// the period is over; returns every reply to the step in order, the last `stepped`.
    pub fn step(
        &mut self,
        control: ControlType,
        freq_hz: f64,
        actions: &[[f64; WAYPOINT_LEN]],
        ticks: u32,
    ) -> Result<Vec<Reply>, RoboError> {
        let id = self.send(|r| {
            r.kind = RequestKind::Step as u32;
            r.control_type = control as u32;
            r.len = actions.len().min(MAX_CHUNK) as u32;
            r.step_ticks = ticks;
            r.freq_hz = freq_hz;
            r.actions[..actions.len().min(MAX_CHUNK)].copy_from_slice(&actions[..actions.len().min(MAX_CHUNK)]);
        })?;
        let period_s = f64::from(ticks) * self.info.map_or(1e-3, |i| i.tick_period_ns as f64 * 1e-9);
        let timeout = Duration::from_secs_f64(10.0 + 2.0 * period_s);
        let replies = self.replies_until(id, timeout, |r| r.status == Status::Stepped as u32)?;
        self.settle()?;
        Ok(replies)
    }

    pub fn node_name(&self) -> String {
        self.node.name().as_str().to_string()
    }
}
