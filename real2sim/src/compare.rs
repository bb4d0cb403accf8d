//! `r2g compare`: the same instants drawn by MuJoCo (`r2g render`) and by Blender ([`crate::blender`]'s
//! Cycles renders), and the source frames when given, side by side in one PNG sheet, with
//! per-object silhouette IoU between the two renderers.
//!
//! The MuJoCo renders are made by the caller ([`MujocoRenderFn`]: `cli` runs its own `r2g
//! render`), so that this crate stays free of the renderer's process setup.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use controllers::math;
use serde_json::{json, Value};
use sim_host::Sim;

use crate::blender::{self, read_png_rgb};

/// What `r2g compare` is asked (the command's arguments).
#[derive(Debug, Clone)]
pub struct Options {
    /// Gym name, gym folder, or scene file (as given: passed on to the MuJoCo renderer).
    pub gym: String,
    /// Instants to compare, s of simulated time; with `frames`, the instant of every source
    /// image that does not carry its own (`r2g_t_s`), default 0.
    pub at: Vec<f64>,
    /// Scene cameras to compare (default: all). Not with `frames`.
    pub cameras: Vec<String>,
    /// A native trace of this gym (default: its demonstration replayed in lockstep).
    pub trace: Option<PathBuf>,
    /// Source frames in the BOP scene layout.
    pub frames: Option<PathBuf>,
    /// The sheet to write (PNG); beside it `<stem>.json` and `<stem>.renders/`.
    pub out: PathBuf,
    /// Cycles samples per pixel of Blender's images.
    pub samples: u32,
    /// Blender's image size as a percentage of the camera's.
    pub percent: u32,
}

/// Renders the gym `gym` with MuJoCo into the BOP folder `out`: the trace's states at the
/// instants given, from the scene cameras named (all when empty) or from the cameras of a BOP
/// `scene_camera.json` (image ids 0, 1, … in the file's order; `r2g_camera` and `r2g_t_s` set).
pub type MujocoRenderFn<'a> = &'a dyn Fn(&str, &Path, &[f64], &[String], Option<&Path>, &Path) -> anyhow::Result<()>;

/// One BOP camera: intrinsics, world-to-camera pose (mm), image size.
#[derive(Debug, Clone)]
pub struct BopCam {
    pub k: [f64; 9],
    pub r_w2c: [f64; 9],
    pub t_w2c_mm: [f64; 3],
    pub width: usize,
    pub height: usize,
    pub t_s: Option<f64>,
}

fn arr<const N: usize>(v: &Value, what: &str) -> anyhow::Result<[f64; N]> {
    let a = v.as_array().with_context(|| format!("{what} is missing or not a list"))?;
    if a.len() != N {
        bail!("{what} has {} numbers, not {N}", a.len());
    }
    let mut out = [0.0; N];
    for (o, x) in out.iter_mut().zip(a) {
        *o = x
            .as_f64()
            .filter(|f| f.is_finite())
            .with_context(|| format!("{what} holds a value that is not a finite number"))?;
    }
    Ok(out)
}

/// Reads `scene_camera.json` of a BOP scene folder (image sizes from `width`/`height`, else
/// from `rgb/<id>.png`).
pub fn read_bop_cameras(dir: &Path) -> anyhow::Result<Vec<(u64, BopCam)>> {
    let path = dir.join("scene_camera.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let v: Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let obj = v.as_object().with_context(|| format!("{}: not an object of image ids", path.display()))?;
    let mut out = Vec::new();
    for (id, c) in obj {
        let at = |what: &str| format!("{} image {id}: {what}", path.display());
        let n: u64 = id.parse().map_err(|_| anyhow::anyhow!(at("the key is not an image id (a number)")))?;
        let k = arr::<9>(&c["cam_K"], "cam_K").with_context(|| at("no intrinsics"))?;
        if k[0] <= 0.0 || k[4] <= 0.0 {
            bail!(at("cam_K's focal lengths must be positive"));
        }
        let r = arr::<9>(&c["cam_R_w2c"], "cam_R_w2c").with_context(|| at("no pose"))?;
        let t = arr::<3>(&c["cam_t_w2c"], "cam_t_w2c").with_context(|| at("no pose"))?;
        let (width, height) = match (c["width"].as_u64(), c["height"].as_u64()) {
            (Some(w), Some(h)) => (w as usize, h as usize),
            _ => {
                let img = dir.join(format!("rgb/{n:06}.png"));
                let (_, w, h) = read_png_rgb(&img).with_context(|| at("no width/height and no readable rgb image"))?;
                (w, h)
            }
        };
        out.push((n, BopCam { k, r_w2c: r, t_w2c_mm: t, width, height, t_s: c["r2g_t_s"].as_f64() }));
    }
    if out.is_empty() {
        bail!("{}: no images", path.display());
    }
    out.sort_by_key(|c| c.0);
    Ok(out)
}

/// A BOP camera as `r2g blender` exports cameras: position and quaternion (w, x, y, z) in the
/// scene's world of a frame looking along its −z with image up along +y, intrinsics and size.
/// BOP's world is the robot base, placed in the scene's world by `world_from_base`.
fn bop_to_export(name: &str, c: &BopCam, n_states: usize, world_from_base: ([f64; 3], math::Quat)) -> Value {
    let r = c.r_w2c;
    let t = c.t_w2c_mm.map(|v| v / 1000.0);
    // Camera centre: −Rᵀt.
    let p = [
        -(r[0] * t[0] + r[3] * t[1] + r[6] * t[2]),
        -(r[1] * t[0] + r[4] * t[1] + r[7] * t[2]),
        -(r[2] * t[0] + r[5] * t[1] + r[8] * t[2]),
    ];
    // World-from-camera columns: OpenCV's x, −y, −z (the rows of R).
    let m = [r[0], -r[3], -r[6], r[1], -r[4], -r[7], r[2], -r[5], -r[8]];
    let (p, q) = math::compose(world_from_base, (p, math::quat_from_mat(&m)));
    let pose = vec![p[0], p[1], p[2], q[3], q[0], q[1], q[2]];
    json!({
        "name": name,
        "width": c.width,
        "height": c.height,
        "fx": c.k[0], "fy": c.k[4], "cx": c.k[2], "cy": c.k[5],
        "mounted_on": null,
        "poses": vec![pose; n_states],
    })
}

/// A mask (0/255 grey PNG) resampled to `w × h`: a pixel is in when at least half of the area
/// it covers in the source is.
fn mask_at(path: &Path, w: usize, h: usize) -> anyhow::Result<Vec<bool>> {
    let (px, sw, sh) = read_png_rgb(path)?;
    let on: Vec<bool> = px.chunks(3).map(|p| p[0] >= 128).collect();
    if (sw, sh) == (w, h) {
        return Ok(on);
    }
    let mut out = vec![false; w * h];
    for v in 0..h {
        let (y0, y1) = (v * sh / h, ((v + 1) * sh / h).max(v * sh / h + 1).min(sh));
        for u in 0..w {
            let (x0, x1) = (u * sw / w, ((u + 1) * sw / w).max(u * sw / w + 1).min(sw));
            let mut n = 0;
            for y in y0..y1 {
                n += on[y * sw + x0..y * sw + x1].iter().filter(|&&b| b).count();
            }
            out[v * w + u] = 2 * n >= (y1 - y0) * (x1 - x0);
        }
    }
    Ok(out)
}

/// Intersection over union (None when both are empty), and the two pixel counts.
fn iou(a: &[bool], b: &[bool]) -> (Option<f64>, usize, usize) {
    let (mut i, mut u, mut na, mut nb) = (0usize, 0usize, 0usize, 0usize);
    for (&x, &y) in a.iter().zip(b) {
        i += usize::from(x && y);
        u += usize::from(x || y);
        na += usize::from(x);
        nb += usize::from(y);
    }
    ((u > 0).then(|| i as f64 / u as f64), na, nb)
}

/// One row of the sheet.
struct Row {
    t_s: f64,
    camera: String,
    /// The `r2g render` folder holding this row's MuJoCo image.
    mujoco_dir: PathBuf,
    /// Image ids in the MuJoCo and Blender folders, and in the source folder.
    mujoco: u64,
    blender: u64,
    source: Option<u64>,
}

/// (image id, camera name, instant) of every image of an `r2g render` folder, by id.
fn read_mujoco_index(dir: &Path) -> anyhow::Result<Vec<(u64, String, f64)>> {
    let path = dir.join("scene_camera.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading r2g render's {}", path.display()))?;
    let v: Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let mut out: Vec<(u64, String, f64)> = v
        .as_object()
        .into_iter()
        .flatten()
        .filter_map(|(id, c)| {
            Some((id.parse().ok()?, c["r2g_camera"].as_str().unwrap_or("").to_string(), c["r2g_t_s"].as_f64()?))
        })
        .collect();
    out.sort_by_key(|x| x.0);
    Ok(out)
}

/// Renders, measures and writes the sheet, `<stem>.json` and `<stem>.renders/` (each whole or not
/// at all; the sheet last). Returns the report written to `<stem>.json`.
pub fn run(a: &Options, mujoco_render: MujocoRenderFn) -> anyhow::Result<Value> {
    if a.out.extension().and_then(|e| e.to_str()) != Some("png") {
        bail!("--out {}: name a .png file", a.out.display());
    }
    if a.frames.is_some() && !a.cameras.is_empty() {
        bail!("--camera and --frames: the source frames bring their own cameras; give one or the other");
    }
    if let Some(parent) = a.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    if a.frames.is_none() && a.at.is_empty() {
        bail!("--at <t_s>[,<t_s>...]: the instants to compare");
    }
    // Source frames are read before anything is simulated or rendered.
    let bop = match &a.frames {
        Some(dir) => Some(read_bop_cameras(dir)?),
        None => None,
    };
    let scene_path = runtime::launch::resolve_scene(&a.gym)?;
    let mut sim = Sim::load(&scene_path).with_context(|| format!("compiling {}", scene_path.display()))?;
    let motion = blender::motion(&sim, &scene_path, a.trace.as_deref())?;
    let states = motion.states();
    let mut doc = blender::export(&mut sim, &motion)?;
    let objects: Vec<String> = sim.scene.objects.iter().map(|o| o.name.clone()).collect();

    // Instants: the nearest sample's own time, so both renderers pose the same sample.
    let sample_t = |t: f64| blender::nearest(states, t).map(|i| states[i].t_s);
    let stem = a.out.with_extension("");
    let renders = PathBuf::from(format!("{}.renders", stem.display()));
    let tmp = blender::temp_beside(&renders)?;
    let result = (|| -> anyhow::Result<Value> {
        // The trace both renderers pose from.
        let trace_path = match &a.trace {
            Some(t) => t.clone(),
            None => {
                let p = tmp.join("trace.json");
                std::fs::write(&p, serde_json::to_vec(&motion.trace)?)?;
                p
            }
        };
        let mut rows = Vec::new();
        let (mj_dir, bl_dir) = (tmp.join("mujoco"), tmp.join("blender"));
        match &bop {
            None => {
                let at: Vec<f64> = a.at.iter().map(|&t| sample_t(t)).collect::<anyhow::Result<_>>()?;
                let known: Vec<String> = doc["cameras"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(|c| c["name"].as_str().map(String::from))
                    .collect();
                let cams = if a.cameras.is_empty() { known.clone() } else { a.cameras.clone() };
                for c in &cams {
                    if !known.contains(c) {
                        bail!("--camera {c}: the scene has no such camera (it has {})", known.join(", "));
                    }
                }
                mujoco_render(&a.gym, &trace_path, &at, &cams, None, &mj_dir)?;
                let mj = read_mujoco_index(&mj_dir)?;
                for &t in &at {
                    for c in &cams {
                        let m = mj
                            .iter()
                            .find(|(_, name, mt)| name == c && (mt - t).abs() < 1e-9)
                            .map(|x| x.0)
                            .with_context(|| format!("r2g render wrote no image of camera {c} at {t} s"))?;
                        let id = rows.len() as u64;
                        rows.push(Row {
                            t_s: t,
                            camera: c.clone(),
                            mujoco_dir: mj_dir.clone(),
                            mujoco: m,
                            blender: id,
                            source: None,
                        });
                    }
                }
            }
            Some(frames) => {
                let default_t = sample_t(a.at.first().copied().unwrap_or(states[0].t_s))?;
                let world_from_base = sim.world_from_base();
                let cams = doc["cameras"].as_array_mut().context("cameras")?;
                cams.clear();
                let mut by_time: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
                for (id, c) in frames {
                    let t = match c.t_s {
                        Some(t) => sample_t(t)?,
                        None => default_t,
                    };
                    cams.push(bop_to_export(&format!("frame{id:06}"), c, states.len(), world_from_base));
                    by_time.entry(t.to_bits()).or_default().push(*id);
                }
                // MuJoCo: one render per instant, from the source cameras of that instant.
                let src = a.frames.as_deref().context("frames")?;
                let all: Value = serde_json::from_slice(&std::fs::read(src.join("scene_camera.json"))?)?;
                std::fs::create_dir_all(&mj_dir)?;
                for (k, (bits, ids)) in by_time.iter().enumerate() {
                    let t = f64::from_bits(*bits);
                    let only: serde_json::Map<String, Value> =
                        ids.iter().map(|id| (id.to_string(), all[id.to_string()].clone())).collect();
                    let cams_file = tmp.join(format!("cameras{k}.json"));
                    std::fs::write(&cams_file, serde_json::to_vec(&Value::Object(only))?)?;
                    let out = mj_dir.join(k.to_string());
                    mujoco_render(&a.gym, &trace_path, &[t], &[], Some(&cams_file), &out)?;
                    let _ = std::fs::remove_file(&cams_file);
                    let mj = read_mujoco_index(&out)?;
                    if mj.len() != ids.len() {
                        bail!("r2g render wrote {} images for {} source cameras", mj.len(), ids.len());
                    }
                    // r2g render writes the cameras of a scene_camera.json in its order.
                    for ((mid, _, _), sid) in mj.iter().zip(ids) {
                        let id = rows.len() as u64;
                        rows.push(Row {
                            t_s: t,
                            camera: format!("frame{sid:06}"),
                            mujoco_dir: out.clone(),
                            mujoco: *mid,
                            blender: id,
                            source: Some(*sid),
                        });
                    }
                }
            }
        }
        // Blender: one shot per row, image ids in row order.
        let pairs: Vec<(f64, String)> = rows.iter().map(|r| (r.t_s, r.camera.clone())).collect();
        let summary = blender::render_pairs(&doc, None, states, &pairs, a.samples, a.percent, &bl_dir)?;
        sheet(a, &tmp, &rows, &objects, &summary, &motion.source)
    })();
    match result {
        Ok(report) => {
            blender::commit_dir(&tmp, &renders)?;
            let json_path = stem.with_extension("json");
            lockstep::demo::write_atomic(&json_path, &serde_json::to_vec_pretty(&report)?)?;
            // The sheet was written into the temporary folder; it goes last, whole.
            std::fs::rename(renders.join("sheet.png"), &a.out)
                .with_context(|| format!("moving the sheet to {}", a.out.display()))?;
            Ok(report)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            Err(e)
        }
    }
}

fn sheet(
    a: &Options,
    tmp: &Path,
    rows: &[Row],
    objects: &[String],
    summary: &Value,
    source: &str,
) -> anyhow::Result<Value> {
    let bl_dir = tmp.join("blender");
    let mut tiles = Vec::new();
    let mut report_rows = Vec::new();
    let frames_dir = a.frames.as_deref();
    for (k, r) in rows.iter().enumerate() {
        let mj_dir = &r.mujoco_dir;
        let (bl_rgb, w, h) = read_png_rgb(&bl_dir.join(format!("rgb/{:06}.png", r.blender)))?;
        let (mj_rgb, mw, mh) = read_png_rgb(&mj_dir.join(format!("rgb/{:06}.png", r.mujoco)))?;
        if let (Some(dir), Some(sid)) = (frames_dir, r.source) {
            let (src, sw, sh) = read_png_rgb(&dir.join(format!("rgb/{sid:06}.png")))?;
            tiles.push(crate::sheet::shrink(&src, sw, sh));
        }
        tiles.push(crate::sheet::shrink(&mj_rgb, mw, mh));
        tiles.push(crate::sheet::shrink(&bl_rgb, w, h));
        // Silhouettes: green where both renderers draw the object, red MuJoCo only, blue Blender only.
        let mut overlay: Vec<u8> = bl_rgb.iter().map(|&c| c / 4).collect();
        let mut ious = serde_json::Map::new();
        for (i, name) in objects.iter().enumerate() {
            let mm = mask_at(&mj_dir.join(format!("mask_visib/{:06}_{i:06}.png", r.mujoco)), w, h)
                .with_context(|| format!("MuJoCo's mask of '{name}'"))?;
            let bm = mask_at(&bl_dir.join(format!("mask_visib/{:06}_{i:06}.png", r.blender)), w, h)
                .with_context(|| format!("Blender's mask of '{name}'"))?;
            for (p, (&x, &y)) in overlay.chunks_mut(3).zip(mm.iter().zip(&bm)) {
                let c = match (x, y) {
                    (true, true) => [60, 200, 60],
                    (true, false) => [220, 50, 50],
                    (false, true) => [60, 90, 240],
                    _ => continue,
                };
                p.copy_from_slice(&c);
            }
            let (v, nm, nb) = iou(&mm, &bm);
            ious.insert(
                name.clone(),
                json!({"iou": v.map(|x| (x * 1e4).round() / 1e4), "mujoco_px": nm, "blender_px": nb}),
            );
        }
        tiles.push(crate::sheet::shrink(&overlay, w, h));
        report_rows.push(json!({
            "row": k,
            "t_s": r.t_s,
            "camera": r.camera,
            "source_image": r.source,
            "mujoco_image": r.mujoco,
            "blender_image": r.blender,
            "size": [w, h],
            "objects": ious,
        }));
    }
    let columns: Vec<&str> = if frames_dir.is_some() {
        vec!["source", "mujoco", "blender", "silhouettes"]
    } else {
        vec!["mujoco", "blender", "silhouettes"]
    };
    crate::sheet::write_tiles(&tiles, columns.len(), &tmp.join("sheet.png"))?;
    let ious: Vec<f64> = report_rows
        .iter()
        .flat_map(|r| r["objects"].as_object().into_iter().flatten().filter_map(|(_, o)| o["iou"].as_f64()))
        .collect();
    Ok(json!({
        "gym": a.gym,
        "sheet": a.out,
        "renders": format!("{}.renders", a.out.with_extension("").display()),
        "source": source,
        "columns": columns,
        "silhouettes": "green: both renderers draw the object there; red: MuJoCo only; blue: Blender only",
        "rows": report_rows,
        "min_iou": ious.iter().copied().reduce(f64::min),
        "mean_iou": if ious.is_empty() { None } else { Some(ious.iter().sum::<f64>() / ious.len() as f64) },
        "blender": summary,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bop_camera_exported_for_blender_comes_back_as_the_same_bop_pose() {
        // A camera at (1.2, -0.3, 0.8) m looking at the origin, written as BOP (OpenCV axes).
        let p: [f64; 3] = [1.2, -0.3, 0.8];
        let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        let z = [-p[0] / n, -p[1] / n, -p[2] / n];
        let up = [0.0, 0.0, 1.0];
        let x = {
            let c = [z[1] * up[2] - z[2] * up[1], z[2] * up[0] - z[0] * up[2], z[0] * up[1] - z[1] * up[0]];
            let m = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            [c[0] / m, c[1] / m, c[2] / m]
        };
        let y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]];
        let r = [x[0], x[1], x[2], y[0], y[1], y[2], z[0], z[1], z[2]];
        let t = [
            -(r[0] * p[0] + r[1] * p[1] + r[2] * p[2]) * 1000.0,
            -(r[3] * p[0] + r[4] * p[1] + r[5] * p[2]) * 1000.0,
            -(r[6] * p[0] + r[7] * p[1] + r[8] * p[2]) * 1000.0,
        ];
        let cam = BopCam {
            k: [500.0, 0.0, 300.0, 0.0, 510.0, 250.0, 0.0, 0.0, 1.0],
            r_w2c: r,
            t_w2c_mm: t,
            width: 640,
            height: 480,
            t_s: None,
        };
        let e = bop_to_export("c", &cam, 2, ([0.0; 3], [0.0, 0.0, 0.0, 1.0]));
        let pose: Vec<f64> = e["poses"][1].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        for k in 0..3 {
            assert!((pose[k] - p[k]).abs() < 1e-9, "{pose:?}");
        }
        let (r2, t2) = crate::blender::bop_pose(&pose[0..3], &pose[3..7]);
        for k in 0..9 {
            assert!((r2[k] - r[k]).abs() < 1e-9, "{r2:?} {r:?}");
        }
        for k in 0..3 {
            assert!((t2[k] - t[k]).abs() < 1e-6, "{t2:?} {t:?}");
        }
        assert_eq!((e["fx"].as_f64(), e["cy"].as_f64()), (Some(500.0), Some(250.0)));

        // A robot base away from the scene's origin (moved and turned a quarter about z): the
        // exported camera is placed in the scene's world, and the BOP pose written beside
        // Blender's renders (taken back into the base frame) is the source's again.
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let wb = ([0.3, -0.2, 0.05], [0.0, 0.0, s, s]);
        let e = bop_to_export("c", &cam, 1, wb);
        let pose: Vec<f64> = e["poses"][0].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        // Base point p in the world: rotate by 90° about z (x, y) -> (-y, x), then translate.
        let pw = [0.3 + 0.3, -0.2 + 1.2, 0.05 + 0.8];
        for k in 0..3 {
            assert!((pose[k] - pw[k]).abs() < 1e-9, "{pose:?} {pw:?}");
        }
        let doc = json!({"world_from_base": {"position_m": wb.0, "quat_wxyz": [s, 0.0, 0.0, s]}});
        let (r3, t3) = crate::blender::bop_pose_in_base(&doc, &pose).unwrap();
        for k in 0..9 {
            assert!((r3[k] - r[k]).abs() < 1e-9, "{r3:?} {r:?}");
        }
        for k in 0..3 {
            assert!((t3[k] - t[k]).abs() < 1e-6, "{t3:?} {t:?}");
        }
    }

    #[test]
    fn iou_counts_overlap_and_treats_two_empty_masks_as_no_measure() {
        let a = [true, true, false, false];
        let b = [true, false, true, false];
        assert_eq!(iou(&a, &b), (Some(1.0 / 3.0), 2, 2));
        assert_eq!(iou(&[false; 4], &[false; 4]).0, None);
    }
}
