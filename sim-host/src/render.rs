//! Camera rendering on its own thread, so physics keeps its rate. The physics thread hands over
//! joint positions through a snapshot it only ever `try_lock`s; this thread re-runs kinematics
//! on its own `MjData`, renders each camera with EGL, and publishes the image into a loaned
//! iceoryx2 sample. Agents read frames in place.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use controllers::math;
use ipc_schema::{CameraFrame, Pose, Qos, Services};
use mujoco_rs::mujoco_c::{mj_camlight, mj_kinematics};
use mujoco_rs::prelude::*;
use mujoco_rs::renderer::MjRenderer;

use crate::scene::CameraSpec;

const MAX_PIXELS: usize = ipc_schema::MAX_IMAGE_WIDTH * ipc_schema::MAX_IMAGE_HEIGHT;
const MAX_RGB: usize = MAX_PIXELS * 3;

/// What physics last handed over.
#[derive(Debug, Default, Clone)]
pub struct Snapshot {
    pub qpos: Vec<f64>,
    pub sim_time_s: f64,
    pub state_seq: u64,
}

pub struct RenderConfig {
    pub services: Services,
    pub cameras: Vec<(CameraSpec, usize)>,
    pub base_body: usize,
    pub rate_hz: f64,
}

/// Runs until `stop` is set. Errors end the thread with a message; physics continues.
pub fn run(
    model: Arc<MjModel>,
    snapshot: Arc<Mutex<Snapshot>>,
    cfg: RenderConfig,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<()> {
    let node = ipc_schema::node(&format!("r2g-render-{}", cfg.services.instance))?;
    let wake = ipc_schema::open_or_create_event(&node, &cfg.services.agent_wake())?.notifier_builder().create()?;
    let camera_qos = Qos { history: 1, buffer: 1, max_publishers: 1, max_subscribers: 8 };
    let mut publishers = Vec::new();
    for (spec, _) in &cfg.cameras {
        let svc =
            ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, &cfg.services.camera(&spec.name), camera_qos)?;
        publishers.push(svc.publisher_builder().max_loaned_samples(1).create()?);
    }
    let (w, h) = cfg.cameras.first().map(|(c, _)| (c.width, c.height)).unwrap_or((640, 480));
    let mut renderer =
        MjRenderer::builder().width(w).height(h).rgb(true).depth(false).build(&model).map_err(|e| {
            anyhow::anyhow!("cannot start headless rendering (EGL): {e}; install Mesa's EGL (make deps)")
        })?;
    let mut data = MjData::new(model.clone());
    let period = Duration::from_secs_f64(1.0 / cfg.rate_hz.max(0.1));
    let mut last_seq = u64::MAX;
    let mut next = Instant::now();
    let mut frame_seq = 0u64;
    while !stop.load(Ordering::Relaxed) {
        let snap = {
            let Ok(s) = snapshot.lock() else { break };
            if s.state_seq == last_seq || s.qpos.is_empty() {
                None
            } else {
                Some(s.clone())
            }
        };
        let Some(snap) = snap else {
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        let now = Instant::now();
        if now < next {
            std::thread::sleep(next - now);
        }
        next = Instant::now() + period;
        last_seq = snap.state_seq;
        // SAFETY: qpos holds nq values, and snap.qpos was taken from a model of the same size.
        unsafe {
            let d = data.ffi_mut();
            std::slice::from_raw_parts_mut(d.qpos, snap.qpos.len()).copy_from_slice(&snap.qpos);
            d.time = snap.sim_time_s;
            mj_kinematics(model.ffi(), d);
            mj_camlight(model.ffi(), d);
        }
        let world_from_base = {
            let d = data.ffi();
            // SAFETY: base_body indexes xpos/xquat.
            unsafe {
                let p = std::slice::from_raw_parts(d.xpos.add(3 * cfg.base_body), 3);
                let q = std::slice::from_raw_parts(d.xquat.add(4 * cfg.base_body), 4);
                ([p[0], p[1], p[2]], [q[1], q[2], q[3], q[0]])
            }
        };
        for ((spec, cam_id), publisher) in cfg.cameras.iter().zip(&publishers) {
            renderer.set_camera(MjvCamera::new_fixed(*cam_id));
            renderer.sync_data(&mut data).map_err(|e| anyhow::anyhow!("render sync: {e}"))?;
            renderer.render().map_err(|e| anyhow::anyhow!("render: {e}"))?;
            let Some(rgb) = renderer.rgb_flat() else { continue };
            let (cam_p, cam_m) = {
                let d = data.ffi();
                // SAFETY: cam_id indexes cam_xpos/cam_xmat.
                unsafe {
                    let p = std::slice::from_raw_parts(d.cam_xpos.add(3 * cam_id), 3);
                    let m = std::slice::from_raw_parts(d.cam_xmat.add(9 * cam_id), 9);
                    let mut mm = [0.0; 9];
                    mm.copy_from_slice(m);
                    ([p[0], p[1], p[2]], mm)
                }
            };
            // MuJoCo's camera frame has y up and z backwards; the optical frame has y down and
            // z forwards: a half turn about x.
            let world_from_optical =
                math::compose((cam_p, math::quat_from_mat(&cam_m)), ([0.0; 3], [1.0, 0.0, 0.0, 0.0]));
            let (bp, bq) = math::compose(math::inverse(world_from_base), world_from_optical);
            let fy = 0.5 * spec.height as f64 / (0.5 * spec.fovy_deg.to_radians()).tan();
            frame_seq += 1;
            let mut sample = publisher.loan_uninit()?;
            let p = sample.payload_mut().as_mut_ptr();
            let n = (spec.width * spec.height * 3) as usize;
            // SAFETY: p points at a CameraFrame-sized sample we own. Every header field is written
            // below and the used part of `rgb`; the rest of the pixel buffers is plain bytes/floats
            // that readers never look at beyond width × height.
            let sample = unsafe {
                (*p).seq = frame_seq;
                (*p).sim_time_s = snap.sim_time_s;
                (*p).state_seq = snap.state_seq;
                (*p).rendered_ns = ipc_schema::monotonic_ns();
                (*p).width = spec.width;
                (*p).height = spec.height;
                (*p).has_depth = 0;
                (*p)._pad = 0;
                (*p).fx = fy;
                (*p).fy = fy;
                (*p).cx = spec.width as f64 / 2.0;
                (*p).cy = spec.height as f64 / 2.0;
                (*p).base_from_camera = Pose { position_m: bp, quat_xyzw: bq };
                let rgb_dst = std::ptr::addr_of_mut!((*p).rgb).cast::<u8>();
                let used = n.min(rgb.len());
                std::ptr::copy_nonoverlapping(rgb.as_ptr(), rgb_dst, used);
                // Every byte initialised before assume_init: the unused tail and the depth plane
                // (not rendered yet) are zeroed.
                std::ptr::write_bytes(rgb_dst.add(used), 0, MAX_RGB - used);
                std::ptr::write_bytes(std::ptr::addr_of_mut!((*p).depth_m).cast::<f32>(), 0, MAX_PIXELS);
                sample.assume_init()
            };
            sample.send()?;
        }
        let _ = wake.notify();
    }
    Ok(())
}
