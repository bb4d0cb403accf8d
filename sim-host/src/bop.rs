//! Rendered views of a scene in the BOP scene layout (`r2g render`): RGB, depth, per-object
//! visible masks, camera intrinsics and poses, the objects' true poses and the arm's joints.
//!
//! "World" in every file is the robot base frame. Depth PNGs are z-depth along the optical axis
//! in units of [`DEPTH_SCALE_MM`] millimetres (0: no surface, or farther than 6.5535 m); masks
//! are 0/255 images of where each object (in scene order) is seen. A folder is written under a
//! temporary name and renamed into place only once every file is written.
//!
//! Cameras are the scene's own (a link-mounted one posed by forward kinematics), or the ones of a
//! BOP `scene_camera.json` ([`read_scene_camera`]), which [`camera_spec`] turns into fixed scene
//! cameras with the same pinhole intrinsics and pose, compiled with the gym ([`crate::Sim::from_scene`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context;
use controllers::math::{self, Quat};
use mujoco_rs::prelude::*;
use serde_json::{json, Value};

use crate::render::{intrinsics, Cameras};
use crate::scene::CameraSpec;
use crate::Sim;

/// Millimetres per unit of a depth PNG (BOP's `depth_scale`): 0.1 mm, up to 6.5535 m.
pub const DEPTH_SCALE_MM: f64 = 0.1;

type Pose = ([f64; 3], Quat);

/// One image's camera from a BOP `scene_camera.json`, with the image size r2g needs beside it.
#[derive(Debug, Clone, PartialEq)]
pub struct BopCamera {
    /// The image id as the file writes it.
    pub id: String,
    /// Row-major 3×3 intrinsics.
    pub k: [f64; 9],
    /// World (robot base) to camera: row-major rotation and translation in millimetres.
    pub r_w2c: [f64; 9],
    pub t_w2c_mm: [f64; 3],
    pub width: u32,
    pub height: u32,
}

impl BopCamera {
    /// Pose of the camera's optical frame (x right, y down, z forward) in the base frame, m.
    pub fn base_from_camera(&self) -> Pose {
        let r = &self.r_w2c;
        // c_from_w = (R, t) → w_from_c = (Rᵀ, −Rᵀ t).
        let rt = [r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8]];
        let t = self.t_w2c_mm.map(|v| v / 1000.0);
        let p = [
            -(rt[0] * t[0] + rt[1] * t[1] + rt[2] * t[2]),
            -(rt[3] * t[0] + rt[4] * t[1] + rt[5] * t[2]),
            -(rt[6] * t[0] + rt[7] * t[1] + rt[8] * t[2]),
        ];
        (p, math::quat_from_mat(&rt))
    }
}

fn numbers(v: Option<&Value>, n: usize, at: &str, what: &str) -> Result<Vec<f64>, String> {
    let Some(v) = v else { return Err(format!("{at}: no \"{what}\"")) };
    let list = v.as_array().ok_or_else(|| format!("{at}: \"{what}\" is not a list of numbers"))?;
    let out: Vec<f64> = list.iter().filter_map(|x| x.as_f64()).collect();
    if out.len() != list.len() || out.len() != n || !out.iter().all(|x| x.is_finite()) {
        let shape = if n == 9 { " (a 3x3 matrix, row-major)" } else { "" };
        return Err(format!("{at}: \"{what}\" holds {} entries; accepted are {n} finite numbers{shape}", list.len()));
    }
    Ok(out)
}

/// Reads a BOP `scene_camera.json` whose entries also give `"width"` and `"height"` (BOP keeps
/// the image size elsewhere; r2g needs it to render). Entries are returned in numeric id order.
/// Refused, naming the image and the key: a missing size, a `cam_K` that is not 3×3 or not a
/// pinhole matrix (no skew, last row 0 0 1), a rotation that is not one, a principal point off
/// the image.
pub fn read_scene_camera(path: &Path) -> Result<Vec<BopCamera>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let doc: Value = serde_json::from_str(&text).map_err(|e| format!("{} is not JSON: {e}", path.display()))?;
    let map = doc.as_object().ok_or_else(|| format!("{}: accepted is an object keyed by image id", path.display()))?;
    if map.is_empty() {
        return Err(format!("{}: no images", path.display()));
    }
    let mut out = Vec::new();
    for (id, entry) in map {
        let at = format!("{} image '{id}'", path.display());
        let size = |key: &str| -> Result<u32, String> {
            match entry.get(key).and_then(|v| v.as_u64()) {
                Some(v) if (1..=4096).contains(&v) => Ok(v as u32),
                Some(v) => Err(format!("{at}: \"{key}\" = {v}: accepted is a size from 1 to 4096 pixels")),
                None => Err(format!(
                    "{at}: no \"{key}\" (an integer, pixels): r2g needs the image size beside cam_K to render"
                )),
            }
        };
        let (width, height) = (size("width")?, size("height")?);
        let k = numbers(entry.get("cam_K"), 9, &at, "cam_K")?;
        if k[1] != 0.0 || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || (k[8] - 1.0).abs() > 1e-9 {
            return Err(format!(
                "{at}: cam_K = {k:?}: accepted is a pinhole matrix [fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew)"
            ));
        }
        let r = numbers(entry.get("cam_R_w2c"), 9, &at, "cam_R_w2c")?;
        let t = numbers(entry.get("cam_t_w2c"), 3, &at, "cam_t_w2c")?;
        let dot = |a: usize, b: usize| r[3 * a] * r[3 * b] + r[3 * a + 1] * r[3 * b + 1] + r[3 * a + 2] * r[3 * b + 2];
        let det = r[0] * (r[4] * r[8] - r[5] * r[7]) - r[1] * (r[3] * r[8] - r[5] * r[6])
            + r[2] * (r[3] * r[7] - r[4] * r[6]);
        let orthonormal = (0..3).all(|a| (0..3).all(|b| (dot(a, b) - if a == b { 1.0 } else { 0.0 }).abs() < 1e-4));
        if !orthonormal || (det - 1.0).abs() > 1e-4 {
            return Err(format!("{at}: cam_R_w2c is not a rotation (orthonormal rows, determinant 1)"));
        }
        let cam = BopCamera {
            id: id.clone(),
            k: k.try_into().map_err(|_| format!("{at}: cam_K"))?,
            r_w2c: r.try_into().map_err(|_| format!("{at}: cam_R_w2c"))?,
            t_w2c_mm: t.try_into().map_err(|_| format!("{at}: cam_t_w2c"))?,
            width,
            height,
        };
        let spec = camera_spec(&cam, ([0.0; 3], [0.0, 0.0, 0.0, 1.0]))?;
        crate::scene::check_intrinsics(&at, &spec)?;
        out.push(cam);
    }
    out.sort_by(|a, b| match (a.id.parse::<u64>(), b.id.parse::<u64>()) {
        (Ok(x), Ok(y)) => x.cmp(&y),
        _ => a.id.cmp(&b.id),
    });
    Ok(out)
}

/// A fixed scene camera with the BOP camera's intrinsics and pose (`world_from_base`: the
/// robot base in the scene's world), named `bop_<index>`-style by the caller through `name`.
pub fn camera_spec(c: &BopCamera, world_from_base: Pose) -> Result<CameraSpec, String> {
    let (p, q) = math::compose(world_from_base, c.base_from_camera());
    let z = math::rotate(q, [0.0, 0.0, 1.0]);
    let y = math::rotate(q, [0.0, 1.0, 0.0]);
    let name: String = c.id.chars().map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '_' }).collect();
    Ok(CameraSpec {
        name: format!("bop_{name}"),
        link: None,
        position_m: p,
        look_at_m: [p[0] + z[0], p[1] + z[1], p[2] + z[2]],
        up: Some([-y[0], -y[1], -y[2]]),
        fovy_deg: None,
        fx: Some(c.k[0]),
        fy: Some(c.k[4]),
        cx: Some(c.k[2]),
        cy: Some(c.k[5]),
        width: c.width,
        height: c.height,
        depth: true,
    })
}

/// One rendered image and the truth that goes with it.
#[derive(Debug, Clone)]
pub struct Image {
    /// The scene camera's name, or the id of the `scene_camera.json` entry it came from.
    pub camera: String,
    pub t_s: f64,
    pub width: u32,
    pub height: u32,
    /// fx, fy, cx, cy in pixels.
    pub k: (f64, f64, f64, f64),
    /// The optical frame in the robot base frame.
    pub base_from_camera: Pose,
    /// RGB, row-major, top row first.
    pub rgb: Vec<u8>,
    /// Z-depth in metres (MuJoCo's far plane where nothing is drawn).
    pub depth_m: Vec<f32>,
    /// Per pixel: the index of the scene object seen there, -1 for anything else, -2 for no
    /// surface (the sky).
    pub object: Vec<i32>,
    /// Per object (scene order): its frame in the camera's optical frame.
    pub camera_from_object: Vec<Pose>,
    pub joints_rad: [f64; 7],
    pub finger_m: f64,
}

/// Renders a [`Sim`]'s present state from its cameras: one [`Cameras`] per image size.
pub struct Shooter {
    renderers: Vec<((u32, u32), Cameras)>,
    model: Arc<MjModel>,
}

impl Shooter {
    pub fn new(sim: &Sim) -> Self {
        Self { renderers: Vec::new(), model: sim.model.clone() }
    }

    /// Images of the sim's present state from the scene cameras at `cameras` (indices into
    /// `sim.scene.cameras`); `labels` name them in the output (default: the cameras' names).
    pub fn shoot(&mut self, sim: &Sim, cameras: &[usize], labels: Option<&[String]>) -> anyhow::Result<Vec<Image>> {
        anyhow::ensure!(Arc::ptr_eq(&self.model, &sim.model), "the renderer belongs to another compiled scene");
        let n_objects = sim.scene.objects.len();
        let mut out = Vec::new();
        for (n, &ci) in cameras.iter().enumerate() {
            let spec = &sim.scene.cameras[ci];
            let cam_id = sim.layout.cameras[ci].1;
            let size = (spec.width, spec.height);
            let r = match self.renderers.iter().position(|(s, _)| *s == size) {
                Some(i) => i,
                None => {
                    self.renderers.push((size, Cameras::new(sim.model.clone(), size.0, size.1, true)?));
                    self.renderers.len() - 1
                }
            };
            let cams = &mut self.renderers[r].1;
            cams.set_state(sim.qpos(), sim.time_s());
            let (rgb, depth) = cams.render(cam_id)?;
            let rgb = rgb.to_vec();
            let depth_m = depth.context("the renderer produced no depth")?.to_vec();
            let geoms = cams.segment(cam_id)?;
            let object = geoms
                .iter()
                .map(|&g| {
                    if g < 0 {
                        return -2;
                    }
                    match sim.layout.geom_owner.get(g as usize) {
                        Some(&o) if (o as usize) < n_objects => o as i32,
                        _ => -1,
                    }
                })
                .collect();
            let world_from_base = cams.body_pose(sim.layout.base_body);
            let world_from_camera = cams.optical_pose(cam_id);
            let base_from_camera = math::compose(math::inverse(world_from_base), world_from_camera);
            let camera_from_world = math::inverse(world_from_camera);
            let camera_from_object =
                sim.layout.objects.iter().map(|&(b, _)| math::compose(camera_from_world, cams.body_pose(b))).collect();
            let qpos = sim.qpos();
            out.push(Image {
                camera: labels.and_then(|l| l.get(n).cloned()).unwrap_or_else(|| spec.name.clone()),
                t_s: sim.time_s(),
                width: spec.width,
                height: spec.height,
                k: intrinsics(spec),
                base_from_camera,
                rgb,
                depth_m,
                object,
                camera_from_object,
                joints_rad: sim.layout.arm_qpos.map(|a| qpos[a]),
                finger_m: sim.layout.finger_qpos.first().map(|&a| qpos[a]).unwrap_or(0.0),
            });
        }
        Ok(out)
    }
}

fn mat(q: Quat) -> [f64; 9] {
    let x = math::rotate(q, [1.0, 0.0, 0.0]);
    let y = math::rotate(q, [0.0, 1.0, 0.0]);
    let z = math::rotate(q, [0.0, 0.0, 1.0]);
    [x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]]
}

fn png(path: &Path, w: u32, h: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) -> anyhow::Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    enc.set_color(color);
    enc.set_depth(depth);
    enc.set_compression(png::Compression::Fast);
    let mut writer = enc.write_header().with_context(|| format!("writing {}", path.display()))?;
    writer.write_image_data(data).with_context(|| format!("writing {}", path.display()))?;
    writer.finish().with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

fn round(v: f64, digits: i32) -> f64 {
    let s = 10f64.powi(digits);
    (v * s).round() / s
}

/// The depth PNG value of a depth in metres: units of [`DEPTH_SCALE_MM`], 0 beyond the range.
pub fn depth_units(depth_m: f32) -> u16 {
    let v = (depth_m as f64 * 1000.0 / DEPTH_SCALE_MM).round();
    if v.is_finite() && v > 0.0 && v <= u16::MAX as f64 {
        v as u16
    } else {
        0
    }
}

/// Writes `images` (image ids 0, 1, … in order) as a BOP scene folder at `out`: written under a
/// temporary name beside it and renamed into place when complete. An existing `out` is
/// replaced only when it is an earlier output (it holds `scene_camera.json`) or empty.
pub fn write(out: &Path, object_names: &[String], images: &[Image]) -> anyhow::Result<()> {
    if out.exists() {
        let empty = out.read_dir().map(|mut d| d.next().is_none()).unwrap_or(false);
        anyhow::ensure!(
            out.is_dir() && (empty || out.join("scene_camera.json").is_file()),
            "--out {}: exists and is not an earlier render (no scene_camera.json); choose another folder",
            out.display()
        );
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).with_context(|| format!("cannot create {}", parent.display()))?;
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "render".into());
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let result = write_into(&tmp, object_names, images);
    if let Err(e) = result {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    if out.exists() {
        let old = parent.join(format!(".{name}.old-{}", std::process::id()));
        std::fs::rename(out, &old).with_context(|| format!("cannot move the earlier {} aside", out.display()))?;
        if let Err(e) = std::fs::rename(&tmp, out) {
            let _ = std::fs::rename(&old, out);
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e).with_context(|| format!("cannot rename into {}", out.display()));
        }
        let _ = std::fs::remove_dir_all(&old);
    } else {
        std::fs::rename(&tmp, out).with_context(|| format!("cannot rename into {}", out.display()))?;
    }
    Ok(())
}

fn write_into(dir: &Path, object_names: &[String], images: &[Image]) -> anyhow::Result<()> {
    for sub in ["rgb", "depth", "mask_visib"] {
        std::fs::create_dir_all(dir.join(sub)).with_context(|| format!("cannot create {}", dir.join(sub).display()))?;
    }
    let mut cameras = BTreeMap::new();
    let mut gt = BTreeMap::new();
    let mut gt_info = BTreeMap::new();
    let mut joints = BTreeMap::new();
    for (id, im) in images.iter().enumerate() {
        let (w, h) = (im.width, im.height);
        let n = (w * h) as usize;
        anyhow::ensure!(
            im.rgb.len() == 3 * n && im.depth_m.len() == n && im.object.len() == n,
            "image {id}: buffers of another size than {w}x{h}"
        );
        png(&dir.join(format!("rgb/{id:06}.png")), w, h, png::ColorType::Rgb, png::BitDepth::Eight, &im.rgb)?;
        let depth: Vec<u8> = im
            .depth_m
            .iter()
            .zip(&im.object)
            .flat_map(|(&d, &o)| if o == -2 { 0 } else { depth_units(d) }.to_be_bytes())
            .collect();
        png(&dir.join(format!("depth/{id:06}.png")), w, h, png::ColorType::Grayscale, png::BitDepth::Sixteen, &depth)?;
        let (fx, fy, cx, cy) = im.k;
        let c_from_b = math::inverse(im.base_from_camera);
        cameras.insert(
            id,
            json!({
                "cam_K": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
                "cam_R_w2c": mat(c_from_b.1),
                "cam_t_w2c": c_from_b.0.map(|v| v * 1000.0),
                "depth_scale": DEPTH_SCALE_MM,
                "width": w,
                "height": h,
                "r2g_camera": im.camera,
                "r2g_t_s": round(im.t_s, 6),
            }),
        );
        let mut objs = Vec::new();
        let mut infos = Vec::new();
        for (k, name) in object_names.iter().enumerate() {
            let mask: Vec<u8> = im.object.iter().map(|&o| if o == k as i32 { 255 } else { 0 }).collect();
            let visible = mask.iter().filter(|&&m| m != 0).count();
            png(
                &dir.join(format!("mask_visib/{id:06}_{k:06}.png")),
                w,
                h,
                png::ColorType::Grayscale,
                png::BitDepth::Eight,
                &mask,
            )?;
            let (t, q) = im.camera_from_object.get(k).copied().unwrap_or(([0.0; 3], [0.0, 0.0, 0.0, 1.0]));
            objs.push(json!({
                "obj_id": k + 1,
                "r2g_name": name,
                "cam_R_m2c": mat(q),
                "cam_t_m2c": t.map(|v| v * 1000.0),
            }));
            infos.push(json!({"obj_id": k + 1, "r2g_name": name, "px_count_visib": visible}));
        }
        gt.insert(id, Value::Array(objs));
        gt_info.insert(id, Value::Array(infos));
        joints.insert(id, json!({"joints_rad": im.joints_rad, "finger_m": im.finger_m}));
    }
    let keyed = |m: BTreeMap<usize, Value>| -> Value {
        Value::Object(m.into_iter().map(|(k, v)| (k.to_string(), v)).collect())
    };
    for (file, doc) in [
        ("scene_camera.json", keyed(cameras)),
        ("scene_gt.json", keyed(gt)),
        ("scene_gt_info.json", keyed(gt_info)),
        ("joints.json", keyed(joints)),
    ] {
        let text = serde_json::to_string_pretty(&doc)?;
        std::fs::write(dir.join(file), text).with_context(|| format!("cannot write {}", dir.join(file).display()))?;
    }
    Ok(())
}
