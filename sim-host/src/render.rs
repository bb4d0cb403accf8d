//! Camera rendering on its own thread, so physics keeps its rate. The physics thread hands over
//! joint positions through a snapshot it only ever `try_lock`s; this thread re-runs kinematics
//! on its own `MjData`, renders each camera with EGL (RGB, and depth in metres along the optical
//! axis), and publishes the images with their intrinsics and pose into a loaned iceoryx2
//! sample. Agents read frames in place.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use controllers::math;
use ipc_schema::{CameraFrame, FrameHeader, Pose, Qos, Services};
use mujoco_rs::mujoco_c::{mj_camlight, mj_kinematics, mjtObj, mjtRndFlag};
use mujoco_rs::prelude::*;
use mujoco_rs::renderer::MjRenderer;

use crate::scene::CameraSpec;

/// What physics last handed over.
#[derive(Debug, Default, Clone)]
pub struct Snapshot {
    pub qpos: Vec<f64>,
    pub sim_time_s: f64,
    pub state_seq: u64,
    pub reset_id: u64,
}

pub struct RenderConfig {
    pub services: Services,
    pub cameras: Vec<(CameraSpec, usize)>,
    pub base_body: usize,
    pub rate_hz: f64,
}

/// Pinhole intrinsics of a MuJoCo camera (square pixels), in pixel-index coordinates: pixel
/// `(u, v)` (array index `[v, u]`) is the point `(u, v)`, its centre, as OpenCV and RealSense
/// count. MuJoCo's frustum is centred on the image, whose centre lies between pixels
/// `w/2 - 1` and `w/2`: the principal point is `((w - 1) / 2, (h - 1) / 2)`. (Counting from
/// pixel edges, `w / 2`, put every back-projected ray half a pixel off.)
///
/// A camera given with `fx, fy, cx, cy` reports exactly those: the MJCF carries them to MuJoCo
/// ([`crate::mjcf`]), whose image then has that focal length and principal point.
pub fn intrinsics(spec: &CameraSpec) -> (f64, f64, f64, f64) {
    if let Some(k) = spec.given_intrinsics() {
        return k;
    }
    let fovy = spec.fovy_deg.unwrap_or(crate::scene::DEFAULT_FOVY_DEG);
    let f = 0.5 * spec.height as f64 / (0.5 * fovy.to_radians()).tan();
    (f, f, (spec.width as f64 - 1.0) / 2.0, (spec.height as f64 - 1.0) / 2.0)
}

/// Offscreen renderer with its own copy of the model's kinematics.
///
/// RGB is drawn with the model's multisampling (anti-aliased edges: each pixel the mean of its
/// samples, centred on the pixel). Depth comes from a second pass without multisampling: read
/// back from a multisampled buffer, a pixel's depth is one of its samples (llvmpipe: sample 0,
/// 0.375 px below and 0.125 px left of the centre), so a sloped surface read off its depth at
/// the pixel's centre (agentview's table 0.9 mm short on the median, the wrist's 0.3 mm long)
/// and back-projected surfaces moved (with the old principal point, agentview's table 1.7 mm
/// high, the wrist's 0.4-0.7 mm low). Without multisampling every depth is the surface at the
/// pixel's centre, whichever GL driver renders.
pub struct Cameras {
    /// Geom-id images (None until [`Cameras::segment`] is first asked).
    segmenter: Option<Segmenter>,
    width: u32,
    height: u32,
    renderer: MjRenderer,
    /// Depth, single-sampled (None: no depth wanted).
    depth: Option<MjRenderer>,
    data: MjData<Arc<MjModel>>,
    model: Arc<MjModel>,
}

fn egl_error(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("cannot start headless rendering (EGL): {e}; install Mesa's EGL (make deps)")
}

impl Cameras {
    /// A renderer for images of `width × height`, with depth when `depth` is set.
    pub fn new(model: Arc<MjModel>, width: u32, height: u32, depth: bool) -> anyhow::Result<Self> {
        let renderer = MjRenderer::builder()
            .width(width)
            .height(height)
            .rgb(true)
            .depth(false)
            .build(&model)
            .map_err(egl_error)?;
        let depth = if depth {
            // The same model but single-sampled and without shadow maps (they only colour). Its
            // layout equals the model's, so the pass draws from the same `MjData`.
            let mut single = MjModel::clone(&model);
            single.vis_mut().quality.offsamples = 0;
            single.light_castshadow_mut().iter_mut().for_each(|c| *c = false);
            single.light_active_mut().iter_mut().for_each(|c| *c = false);
            single.vis_mut().headlight.active = 0;
            Some(
                MjRenderer::builder()
                    .width(width)
                    .height(height)
                    .rgb(false)
                    .depth(true)
                    .build(&single)
                    .map_err(egl_error)?,
            )
        } else {
            None
        };
        let data = MjData::new(model.clone());
        Ok(Self { segmenter: None, width, height, renderer, depth, data, model })
    }

    /// Which geom each pixel of camera `cam_id` shows (row-major, top row first): the geom's
    /// id in the model, or -1 where no geom is drawn (the sky). The geoms are those the RGB image
    /// draws (groups 0-2), each pixel decided at its centre without multisampling, so a mask is
    /// exactly where the depth image holds that geom's surface. Uses MuJoCo's segmentation
    /// rendering (`mjRND_SEGMENT` with `mjRND_IDCOLOR`: every geom drawn flat in a colour that
    /// encodes its index in the visual scene), with a GL context of its own.
    pub fn segment(&mut self, cam_id: usize) -> anyhow::Result<Vec<i32>> {
        if self.segmenter.is_none() {
            self.segmenter = Some(Segmenter::new(&self.model, &mut self.data, self.width, self.height)?);
        }
        let Some(seg) = self.segmenter.as_mut() else { unreachable!("created above") };
        seg.render(&mut self.data, cam_id)
    }

    /// Poses the scene at `qpos` (from a model of the same size).
    pub fn set_state(&mut self, qpos: &[f64], time_s: f64) {
        // SAFETY: qpos holds nq values; the caller's qpos comes from the same model.
        unsafe {
            let d = self.data.ffi_mut();
            let n = (self.model.ffi().nq as usize).min(qpos.len());
            std::slice::from_raw_parts_mut(d.qpos, n).copy_from_slice(&qpos[..n]);
            d.time = time_s;
            mj_kinematics(self.model.ffi(), d);
            mj_camlight(self.model.ffi(), d);
        }
    }

    /// Renders camera `cam_id`: RGB bytes (row-major, top row first) and, when enabled, depth
    /// in metres along the optical axis.
    pub fn render(&mut self, cam_id: usize) -> anyhow::Result<(&[u8], Option<&[f32]>)> {
        for r in std::iter::once(&mut self.renderer).chain(self.depth.as_mut()) {
            r.set_camera(MjvCamera::new_fixed(cam_id));
            r.sync_data(&mut self.data).map_err(|e| anyhow::anyhow!("render sync: {e}"))?;
            r.render().map_err(|e| anyhow::anyhow!("render: {e}"))?;
        }
        let rgb = self.renderer.rgb_flat().ok_or_else(|| anyhow::anyhow!("renderer produced no RGB"))?;
        Ok((rgb, self.depth.as_ref().and_then(|r| r.depth_flat())))
    }

    /// World pose of a body: (position, quaternion x, y, z, w).
    pub fn body_pose(&self, body: usize) -> ([f64; 3], math::Quat) {
        let d = self.data.ffi();
        // SAFETY: body indexes xpos/xquat.
        unsafe {
            let p = std::slice::from_raw_parts(d.xpos.add(3 * body), 3);
            let q = std::slice::from_raw_parts(d.xquat.add(4 * body), 4);
            ([p[0], p[1], p[2]], [q[1], q[2], q[3], q[0]])
        }
    }

    /// World pose of the camera's optical frame (x right, y down, z forward).
    pub fn optical_pose(&self, cam_id: usize) -> ([f64; 3], math::Quat) {
        let d = self.data.ffi();
        // SAFETY: cam_id indexes cam_xpos/cam_xmat.
        let (p, m) = unsafe {
            let p = std::slice::from_raw_parts(d.cam_xpos.add(3 * cam_id), 3);
            let m = std::slice::from_raw_parts(d.cam_xmat.add(9 * cam_id), 9);
            let mut mm = [0.0; 9];
            mm.copy_from_slice(m);
            ([p[0], p[1], p[2]], mm)
        };
        // MuJoCo's camera frame has y up and z backwards; the optical frame has y down and z
        // forwards: a half turn about x.
        math::compose((p, math::quat_from_mat(&m)), ([0.0; 3], [1.0, 0.0, 0.0, 0.0]))
    }
}

/// MuJoCo's segmentation rendering. The `MjRenderer` of mujoco-rs keeps its scene's flags to
/// itself, so this draws with a scene and a rendering context of its own, in the GL context of a
/// renderer that shows nothing (every geom group hidden) and is only asked to render to make
/// that GL context current.
struct Segmenter {
    /// Dropped (in `Drop`) while `gl`'s context is current.
    context: Option<MjrContext>,
    scene: MjvScene,
    option: MjvOption,
    gl: MjRenderer,
    pixels: Vec<u8>,
    width: usize,
    height: usize,
}

impl Segmenter {
    fn new(model: &MjModel, data: &mut MjData<Arc<MjModel>>, width: u32, height: u32) -> anyhow::Result<Self> {
        // Single-sampled: a multisampled buffer is resolved by averaging, which mixes the colours
        // (the ids) of neighbouring geoms along every edge.
        let mut single = MjModel::clone(model);
        single.vis_mut().quality.offsamples = 0;
        let nothing = MjvOption { geomgroup: [0; 6], ..Default::default() };
        let mut gl = MjRenderer::builder()
            .width(width)
            .height(height)
            .rgb(true)
            .depth(false)
            .opts(nothing)
            .build(&single)
            .map_err(egl_error)?;
        gl.sync_data(data).map_err(|e| anyhow::anyhow!("segmentation sync: {e}"))?;
        gl.render().map_err(|e| anyhow::anyhow!("segmentation context: {e}"))?;
        // SAFETY: `gl.render()` just made its GL context current on this thread.
        let mut context = unsafe { MjrContext::new(&single) };
        context.offscreen();
        let ngeom = single.ffi().ngeom as usize;
        let scene = MjvScene::new(&single, ngeom + 100);
        let (w, h) = (width as usize, height as usize);
        Ok(Self {
            context: Some(context),
            scene,
            option: MjvOption::default(),
            gl,
            pixels: vec![0; w * h * 3],
            width: w,
            height: h,
        })
    }

    fn render(&mut self, data: &mut MjData<Arc<MjModel>>, cam_id: usize) -> anyhow::Result<Vec<i32>> {
        self.gl.render().map_err(|e| anyhow::anyhow!("segmentation context: {e}"))?;
        let Some(context) = self.context.as_mut() else { anyhow::bail!("segmentation context is gone") };
        let mut camera = MjvCamera::new_fixed(cam_id);
        self.scene.update(data, &self.option, &MjvPerturb::default(), &mut camera);
        // SAFETY: plain flags of the scene this struct owns.
        unsafe {
            let f = self.scene.ffi_mut();
            f.flags[mjtRndFlag::mjRND_SEGMENT as usize] = 1;
            f.flags[mjtRndFlag::mjRND_IDCOLOR as usize] = 1;
        }
        // Other contexts of this GL context may have bound their buffers since.
        context.offscreen();
        let vp = MjrRectangle::new(0, 0, self.width as i32, self.height as i32);
        self.scene.render(&vp, context);
        context
            .read_pixels(Some(&mut self.pixels), None, &vp)
            .map_err(|e| anyhow::anyhow!("segmentation read: {e:?}"))?;
        let geoms = self.scene.geoms();
        let (w, h) = (self.width, self.height);
        let mut out = vec![-1i32; w * h];
        // OpenGL's rows run bottom-up.
        for row in 0..h {
            let src = &self.pixels[(h - 1 - row) * w * 3..(h - row) * w * 3];
            for (col, px) in src.chunks_exact(3).enumerate() {
                let v = px[0] as usize | (px[1] as usize) << 8 | (px[2] as usize) << 16;
                if v == 0 {
                    continue;
                }
                if let Some(g) = geoms.get(v - 1) {
                    if g.objtype == mjtObj::mjOBJ_GEOM as i32 {
                        out[row * w + col] = g.objid;
                    }
                }
            }
        }
        Ok(out)
    }
}

impl Drop for Segmenter {
    fn drop(&mut self) {
        // Free the context's GL objects in its own GL context, not whichever is current.
        let _ = self.gl.render();
        self.context.take();
    }
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
    let camera_qos = Qos::CAMERA;
    let mut publishers = Vec::new();
    for (spec, _) in &cfg.cameras {
        let svc =
            ipc_schema::open_or_create_pubsub::<CameraFrame>(&node, &cfg.services.camera(&spec.name), camera_qos)?;
        publishers.push(svc.publisher_builder().max_loaned_samples(1).create()?);
    }
    let (w, h) = cfg.cameras.first().map(|(c, _)| (c.width, c.height)).unwrap_or((640, 480));
    let any_depth = cfg.cameras.iter().any(|(c, _)| c.depth);
    let mut cams = Cameras::new(model, w, h, any_depth)?;
    let period = Duration::from_secs_f64(1.0 / cfg.rate_hz.max(0.1));
    let mut last_seq = u64::MAX;
    let mut last_reset = u64::MAX;
    let first_frame_at_once = !ipc_schema::process::host_baseline();
    let mut next = Instant::now();
    let mut frame_seq = 0u64;
    let mut idle = 0u64;
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
            // Nothing new to draw (lockstep idles): hand the last frame to readers that joined
            // since, so they need not wait for the scene to change.
            idle += 1;
            if idle.is_multiple_of(10) {
                use iceoryx2::port::update_connections::UpdateConnections;
                for p in &publishers {
                    let _ = p.update_connections();
                }
                let _ = wake.notify();
            }
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        let now = Instant::now();
        // A new episode's first frame is drawn at once: whoever reset waits for it (an agent's
        // first observation), and its scene differs from the last frame's.
        if now < next && (snap.reset_id == last_reset || !first_frame_at_once) {
            std::thread::sleep(next - now);
        }
        next = Instant::now() + period;
        last_seq = snap.state_seq;
        last_reset = snap.reset_id;
        cams.set_state(&snap.qpos, snap.sim_time_s);
        let world_from_base = cams.body_pose(cfg.base_body);
        for ((spec, cam_id), publisher) in cfg.cameras.iter().zip(&publishers) {
            let (bp, bq) = math::compose(math::inverse(world_from_base), cams.optical_pose(*cam_id));
            let (fx, fy, cx, cy) = intrinsics(spec);
            let (rgb, depth) = cams.render(*cam_id)?;
            let depth = if spec.depth { depth } else { None };
            frame_seq += 1;
            let mut sample = publisher.loan_uninit()?;
            let header = FrameHeader {
                seq: frame_seq,
                sim_time_s: snap.sim_time_s,
                state_seq: snap.state_seq,
                rendered_ns: ipc_schema::monotonic_ns(),
                width: spec.width,
                height: spec.height,
                reset_id: snap.reset_id as u32,
                fx,
                fy,
                cx,
                cy,
                base_from_camera: Pose { position_m: bp, quat_xyzw: bq },
            };
            CameraFrame::fill(sample.payload_mut(), &header, rgb, depth);
            // SAFETY: `fill` wrote every byte of the sample.
            let sample = unsafe { sample.assume_init() };
            sample.send()?;
        }
        let _ = wake.notify();
    }
    Ok(())
}
