//! A gym's compiled scene for Blender (`r2g blender`, `r2g compare`): every body's pose keyframed
//! from a native trace, optionally rendered with Cycles on the CPU.
//!
//! The scene is compiled by sim-host (the same MJCF MuJoCo simulates); what MuJoCo draws (geoms
//! of groups 0-2, with the pixels of a 2-D texture on a plane), its cameras and its lights (with
//! a spot light's cone and exponent) are read from the compiled model and written to a JSON
//! document ([`export`]). Every trace sample's state (objects, fixture joints, arm joints,
//! fingers) is set on the model and MuJoCo's forward kinematics gives each body's and camera's
//! world pose. The document goes to `real2sim/blender/build_scene.py`, run by the Python of
//! `.venv-blender` (Blender as a Python module, [`run_blender`]), which builds the scene with bpy,
//! keyframes it, saves the `.blend` and renders the instants asked for ([`render_pairs`]: a BOP
//! folder with RGB images and per-object masks). Cameras are the scene's own, or the ones of a BOP
//! `scene_camera.json` compiled into the scene as `r2g render --cameras` does ([`with_bop_cameras`]).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context};
use serde_json::{json, Value};
use sim_host::trace::{Sample, Trace};
use sim_host::Sim;

/// Geom groups MuJoCo's renderer draws by default (the hidden collision shapes are group 3).
const DRAWN_GROUPS: i32 = 3;
/// Keyframes per second of simulated time: the native trace's sample rate (every 10 ms).
pub const FPS: f64 = 100.0;

/// Where the states came from, and the trace holding them.
pub struct Motion {
    pub source: String,
    pub trace: Trace,
}

impl Motion {
    pub fn states(&self) -> &[Sample] {
        &self.trace.samples
    }
}

/// Reads a native trace of `sim`'s scene, checking that it names the scene's objects and
/// fixture joints and that every sample holds the arm's joint angles.
pub fn read_trace(sim: &Sim, path: &Path) -> anyhow::Result<Motion> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading trace {}", path.display()))?;
    let at = |what: String| format!("trace {}: {what}", path.display());
    let trace: Trace = serde_json::from_str(&text).with_context(|| at("not a native trace".into()))?;
    if trace.gym != sim.scene.name {
        bail!(at(format!("recorded in gym '{}', not in '{}'", trace.gym, sim.scene.name)));
    }
    let want_objects: Vec<String> = sim.scene.objects.iter().map(|o| o.name.clone()).collect();
    if trace.objects != want_objects {
        bail!(at(format!("names objects {:?}, the scene has {want_objects:?}", trace.objects)));
    }
    let want_joints: Vec<String> = sim.layout.fixture_joints.iter().map(|j| j.0.clone()).collect();
    if trace.joints != want_joints {
        bail!(at(format!("names fixture joints {:?}, the scene has {want_joints:?}", trace.joints)));
    }
    if trace.samples.is_empty() {
        bail!(at("has no samples".into()));
    }
    for (i, s) in trace.samples.iter().enumerate() {
        let here = |what: String| at(format!("sample {i} (t = {} s): {what}", s.t_s));
        if s.objects.len() != want_objects.len() || s.joints.len() != want_joints.len() {
            bail!(here(format!(
                "{} object poses and {} joint values for {} objects and {} fixture joints",
                s.objects.len(),
                s.joints.len(),
                want_objects.len(),
                want_joints.len()
            )));
        }
        if s.arm_rad.len() != sim.layout.arm_qpos.len() {
            bail!(here(format!(
                "{} arm joint angles (arm_rad), the robot has {} joints; a trace written before traces held \
                 them cannot pose the arm: write it again with `r2g replay` or `r2g validate --keep-trace`",
                s.arm_rad.len(),
                sim.layout.arm_qpos.len()
            )));
        }
        if !s.t_s.is_finite() || i > 0 && s.t_s < trace.samples[i - 1].t_s {
            bail!(here("its time is not finite or earlier than the sample before".into()));
        }
    }
    Ok(Motion { source: format!("trace {}", path.display()), trace })
}

/// The states to show: the trace given, else the demonstration replayed in lockstep (seed 0),
/// else the scene at rest.
pub fn motion(sim: &Sim, scene_path: &Path, trace: Option<&Path>) -> anyhow::Result<Motion> {
    if let Some(t) = trace {
        return read_trace(sim, t);
    }
    if sim.scene.task.demonstration.is_none() {
        let mut trace = sim.new_trace();
        trace.samples.push(sim.sample());
        return Ok(Motion { source: "the scene at rest (it has no demonstration)".into(), trace });
    }
    let dir = std::env::temp_dir().join(format!("r2g-blender-replay-{}-{}", std::process::id(), unique()));
    let r = lockstep::replay(scene_path, 0, false, Some(&dir));
    let out = r.and_then(|r| {
        let p = r.trace_path.context("the replay wrote no trace")?;
        let m = read_trace(sim, &p)?;
        Ok((m, r.evaluation.success, r.failures.len()))
    });
    let _ = std::fs::remove_dir_all(&dir);
    let (mut m, success, failures) = out.context("replaying the demonstration in lockstep")?;
    m.source = format!(
        "the demonstration replayed in lockstep (seed 0; native verdict: {}{})",
        if success { "success" } else { "failure" },
        if failures > 0 { format!(", {failures} chunk(s) not executed") } else { String::new() }
    );
    Ok(m)
}

/// Raw model arrays.
/// SAFETY (callers): `p` points at `n` valid values of the live model.
unsafe fn arr<'a, T>(p: *const T, n: usize) -> &'a [T] {
    if n == 0 || p.is_null() {
        &[]
    } else {
        // SAFETY: the caller's promise above.
        unsafe { std::slice::from_raw_parts(p, n) }
    }
}

const B64: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// Standard base64 (with padding) of `bytes`.
pub fn base64(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16 | (*c.get(1).unwrap_or(&0) as u32) << 8 | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                s.push(B64[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn round6(v: f64) -> f64 {
    (v * 1e6).round() / 1e6
}

fn geom_type(t: i32) -> Option<&'static str> {
    // mjtGeom: plane, hfield, sphere, capsule, ellipsoid, cylinder, box, mesh, sdf.
    match t {
        0 => Some("plane"),
        2 => Some("sphere"),
        3 => Some("capsule"),
        4 => Some("ellipsoid"),
        5 => Some("cylinder"),
        6 => Some("box"),
        7 => Some("mesh"),
        _ => None,
    }
}

/// The scene for Blender: drawn geoms, meshes, cameras, lights, and per state every moving
/// body's and camera's world pose. Object `k` of the scene is `"object": k` on its geoms.
pub fn export(sim: &mut Sim, motion: &Motion) -> anyhow::Result<Value> {
    let model = sim.model.clone();
    let m = model.ffi();
    let (nbody, ngeom, ncam, nlight, nmesh) =
        (m.nbody as usize, m.ngeom as usize, m.ncam as usize, m.nlight as usize, m.nmesh as usize);
    let name = |kind, i| model.id_to_name(kind, i).unwrap_or_default().to_string();
    use mujoco_rs::prelude::MjtObjBase as Obj;
    // SAFETY: every array below is sized by the model counts it is read with.
    let (gtype, gbody, gdata, gmat, ggroup, gsize, gpos, gquat, grgba) = unsafe {
        (
            arr(m.geom_type, ngeom),
            arr(m.geom_bodyid, ngeom),
            arr(m.geom_dataid, ngeom),
            arr(m.geom_matid, ngeom),
            arr(m.geom_group, ngeom),
            arr(m.geom_size, 3 * ngeom),
            arr(m.geom_pos, 3 * ngeom),
            arr(m.geom_quat, 4 * ngeom),
            arr(m.geom_rgba, 4 * ngeom),
        )
    };
    // SAFETY: as above.
    let (mat_rgba, mat_texid, mat_texuniform, mat_texrepeat, ntex) = unsafe {
        (
            arr(m.mat_rgba, 4 * m.nmat as usize),
            arr(m.mat_texid, 10 * m.nmat as usize),
            arr(m.mat_texuniform, m.nmat as usize),
            arr(m.mat_texrepeat, 2 * m.nmat as usize),
            m.ntex as usize,
        )
    };
    let n_roles = if m.nmat > 0 { mat_texid.len() / m.nmat as usize } else { 0 };
    // SAFETY: as above.
    let (tex_type, tex_space, tex_adr, tex_w, tex_h, tex_nc, tex_data) = unsafe {
        (
            arr(m.tex_type, ntex),
            arr(m.tex_colorspace, ntex),
            arr(m.tex_adr, ntex),
            arr(m.tex_width, ntex),
            arr(m.tex_height, ntex),
            arr(m.tex_nchannel, ntex),
            arr(m.tex_data, m.ntexdata as usize),
        )
    };
    // Mean colour of a texture (0-1 per channel).
    let tex_mean = |t: usize| -> [f64; 3] {
        let (adr, n, nc) = (tex_adr[t] as usize, (tex_w[t] * tex_h[t]) as usize, tex_nc[t].max(1) as usize);
        let mut acc = [0.0f64; 3];
        let mut count = 0usize;
        // (Cube and skybox textures stack their faces in the height.)
        let px = tex_data.get(adr..adr + n * nc).unwrap_or(&[]);
        for p in px.chunks(nc) {
            for c in 0..3.min(nc) {
                acc[c] += p[c] as f64 / 255.0;
            }
            count += 1;
        }
        acc.map(|a| round6(a / count.max(1) as f64))
    };
    // A 2-D texture's pixels as RGB bytes, rows in MuJoCo's order (the first row is texture
    // coordinate t = 0), with what MuJoCo's renderer needs to map it on a plane.
    let tex_image = |t: usize, mi: usize| -> anyhow::Result<Value> {
        let (adr, w, h, nc) = (tex_adr[t] as usize, tex_w[t] as usize, tex_h[t] as usize, tex_nc[t] as usize);
        let len = w.checked_mul(h).and_then(|n| n.checked_mul(nc)).filter(|&n| n > 0 && (1..=4).contains(&nc));
        let Some(px) = len.and_then(|n| tex_data.get(adr..adr.checked_add(n)?)) else {
            bail!(
                "texture {t} ('{}'): {w}x{h} pixels of {nc} channels do not fit the model's texture data",
                name(Obj::mjOBJ_TEXTURE, t)
            );
        };
        let rgb: Vec<u8> =
            px.chunks(nc).flat_map(|p| if nc >= 3 { [p[0], p[1], p[2]] } else { [p[0], p[0], p[0]] }).collect();
        Ok(json!({
            "name": name(Obj::mjOBJ_TEXTURE, t),
            "width": w,
            "height": h,
            "rgb_b64": base64(&rgb),
            // mjtColorSpace: auto and linear are drawn as they are, sRGB is decoded first.
            "srgb": tex_space[t] == 2,
            "repeat": [round6(mat_texrepeat[2 * mi] as f64), round6(mat_texrepeat[2 * mi + 1] as f64)],
            "uniform": mat_texuniform[mi],
        }))
    };
    // SAFETY: as above.
    let (mvadr, mvnum, mfadr, mfnum, mvert, mface) = unsafe {
        (
            arr(m.mesh_vertadr, nmesh),
            arr(m.mesh_vertnum, nmesh),
            arr(m.mesh_faceadr, nmesh),
            arr(m.mesh_facenum, nmesh),
            arr(m.mesh_vert, 3 * m.nmeshvert as usize),
            arr(m.mesh_face, 3 * m.nmeshface as usize),
        )
    };
    let owners = &sim.layout.geom_owner;
    let n_objects = sim.scene.objects.len();
    let mut geoms = Vec::new();
    let mut meshes: Vec<Value> = Vec::new();
    let mut mesh_index: std::collections::HashMap<usize, usize> = Default::default();
    let mut moving = vec![false; nbody];
    for g in 0..ngeom {
        if ggroup[g] >= DRAWN_GROUPS {
            continue;
        }
        let gname = name(Obj::mjOBJ_GEOM, g);
        let b = gbody[g] as usize;
        let Some(kind) = geom_type(gtype[g]) else {
            bail!("geom {g} ('{gname}', body '{}') is of MuJoCo type {}, which the Blender export does not draw (height fields and SDFs)", name(Obj::mjOBJ_BODY, b), gtype[g]);
        };
        // MuJoCo draws a material's colour (and its texture's) unless the geom sets its own.
        let mut rgba: Vec<f64> = grgba[4 * g..4 * g + 4].iter().map(|&c| round6(c as f64)).collect();
        let mut texture_mean = None;
        let mut texture = None;
        if gmat[g] >= 0 {
            let mi = gmat[g] as usize;
            let default_rgba = rgba == [0.5, 0.5, 0.5, 1.0];
            if default_rgba {
                rgba = mat_rgba[4 * mi..4 * mi + 4].iter().map(|&c| round6(c as f64)).collect();
            }
            // The RGB role (index 1) or the legacy first slot.
            let tex = (0..n_roles).map(|r| mat_texid[n_roles * mi + r]).find(|&t| t >= 0);
            if let Some(t) = tex {
                let t = t as usize;
                let mean = tex_mean(t);
                texture_mean = Some(mean);
                // A 2-D texture on a plane is drawn as MuJoCo maps it (build_scene.py); on
                // anything else, and for cube and skybox textures, its mean colour tints rgba.
                if kind == "plane" && tex_type[t] == 0 {
                    texture = Some(tex_image(t, mi)?);
                } else if default_rgba {
                    for c in 0..3 {
                        rgba[c] = round6(rgba[c] * mean[c]);
                    }
                }
            }
        }
        let owner = owners.get(g).copied().unwrap_or(u16::MAX) as usize;
        let object = (owner < n_objects).then_some(owner);
        let mut e = json!({
            "name": gname,
            "body": b,
            "type": kind,
            "size": gsize[3 * g..3 * g + 3].iter().map(|&v| round6(v)).collect::<Vec<_>>(),
            "pos": gpos[3 * g..3 * g + 3].iter().map(|&v| round6(v)).collect::<Vec<_>>(),
            "quat_wxyz": gquat[4 * g..4 * g + 4].iter().map(|&v| round6(v)).collect::<Vec<_>>(),
            "rgba": rgba,
            "object": object,
            "owner": sim.owners.get(owner).cloned(),
        });
        if let Some(t) = texture_mean {
            e["texture_mean_rgb"] = json!(t);
        }
        if let Some(t) = texture {
            e["texture"] = t;
        }
        if kind == "mesh" {
            let id = gdata[g] as usize;
            let idx = *mesh_index.entry(id).or_insert_with(|| {
                let (va, vn, fa, fnum) =
                    (mvadr[id] as usize, mvnum[id] as usize, mfadr[id] as usize, mfnum[id] as usize);
                let v: Vec<u8> = mvert[3 * va..3 * (va + vn)].iter().flat_map(|x| x.to_le_bytes()).collect();
                let f: Vec<u8> = mface[3 * fa..3 * (fa + fnum)].iter().flat_map(|x| x.to_le_bytes()).collect();
                meshes.push(json!({
                    "name": name(Obj::mjOBJ_MESH, id),
                    "vertices": vn,
                    "faces": fnum,
                    "vertices_f32le_b64": base64(&v),
                    "faces_i32le_b64": base64(&f),
                }));
                meshes.len() - 1
            });
            e["mesh"] = json!(idx);
        }
        if b != 0 {
            moving[b] = true;
        }
        geoms.push(e);
    }
    let bodies: Vec<usize> = (1..nbody).filter(|&b| moving[b]).collect();
    // Cameras: intrinsics from the scene's spec, poses from kinematics.
    let cams: Vec<(String, usize)> = sim.layout.cameras.clone();
    let mut camera_json = Vec::new();
    for (cname, _) in &cams {
        let spec = sim.scene.cameras.iter().find(|c| &c.name == cname).context("camera spec")?;
        let (fx, fy, cx, cy) = sim_host::render::intrinsics(spec);
        camera_json.push(json!({
            "name": cname,
            "width": spec.width,
            "height": spec.height,
            "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "mounted_on": spec.link,
        }));
    }
    let mut body_poses: Vec<Vec<Vec<f64>>> = vec![Vec::new(); bodies.len()];
    let mut cam_poses: Vec<Vec<Vec<f64>>> = vec![Vec::new(); cams.len()];
    let mut times = Vec::new();
    for st in motion.states() {
        sim.set_state_from_sample(st).map_err(|e| anyhow::anyhow!(e))?;
        let d = sim.data.ffi();
        // SAFETY: xpos/xquat hold nbody entries, cam_xpos/cam_xmat ncam.
        let (xpos, xquat, cpos, cmat) = unsafe {
            (arr(d.xpos, 3 * nbody), arr(d.xquat, 4 * nbody), arr(d.cam_xpos, 3 * ncam), arr(d.cam_xmat, 9 * ncam))
        };
        for (k, &b) in bodies.iter().enumerate() {
            let mut p: Vec<f64> = xpos[3 * b..3 * b + 3].to_vec();
            p.extend_from_slice(&xquat[4 * b..4 * b + 4]);
            body_poses[k].push(p.into_iter().map(round6).collect());
        }
        for (k, (_, c)) in cams.iter().enumerate() {
            let mut mat = [0.0; 9];
            mat.copy_from_slice(&cmat[9 * c..9 * c + 9]);
            let q = controllers::math::quat_from_mat(&mat);
            let p = &cpos[3 * c..3 * c + 3];
            cam_poses[k].push([p[0], p[1], p[2], q[3], q[0], q[1], q[2]].into_iter().map(round6).collect());
        }
        times.push(round6(st.t_s));
    }
    for (c, poses) in camera_json.iter_mut().zip(cam_poses) {
        c["poses"] = json!(poses);
    }
    // SAFETY: light arrays hold nlight entries.
    let (lpos, ldir, ltype, ldiff, lamb, lshadow, lactive, lcut, lexp, latt) = unsafe {
        let d = sim.data.ffi();
        (
            arr(d.light_xpos, 3 * nlight),
            arr(d.light_xdir, 3 * nlight),
            arr(m.light_type, nlight),
            arr(m.light_diffuse, 3 * nlight),
            arr(m.light_ambient, 3 * nlight),
            arr(m.light_castshadow, nlight),
            arr(m.light_active, nlight),
            arr(m.light_cutoff, nlight),
            arr(m.light_exponent, nlight),
            arr(m.light_attenuation, 3 * nlight),
        )
    };
    let lights: Vec<Value> = (0..nlight)
        .filter(|&i| lactive[i])
        .map(|i| {
            // mjtLightType: spot, directional, point, image.
            let kind = ["spot", "directional", "point", "image"].get(ltype[i] as usize).copied().unwrap_or("spot");
            json!({
                "name": name(Obj::mjOBJ_LIGHT, i),
                "pos": lpos[3 * i..3 * i + 3].iter().map(|&v| round6(v)).collect::<Vec<_>>(),
                "dir": ldir[3 * i..3 * i + 3].iter().map(|&v| round6(v)).collect::<Vec<_>>(),
                "type": kind,
                "diffuse": ldiff[3 * i..3 * i + 3].iter().map(|&v| round6(v as f64)).collect::<Vec<_>>(),
                "ambient": lamb[3 * i..3 * i + 3].iter().map(|&v| round6(v as f64)).collect::<Vec<_>>(),
                "cast_shadow": lshadow[i],
                // A spot light's cone (degrees from its axis), the power of the cosine that
                // dims it off the axis, and its attenuation (constant, linear, quadratic).
                "cutoff_deg": round6(lcut[i] as f64),
                "exponent": round6(lexp[i] as f64),
                "attenuation": latt[3 * i..3 * i + 3].iter().map(|&v| round6(v as f64)).collect::<Vec<_>>(),
            })
        })
        .collect();
    let vis = &m.vis;
    let head = &vis.headlight;
    let sky = (0..ntex).find(|&t| tex_type[t] == 2).map(tex_mean);
    let (bp, bq) = sim.world_from_base();
    Ok(json!({
        "gym": sim.scene.name,
        "source": motion.source,
        "fps": FPS,
        "times_s": times,
        "objects": sim.scene.objects.iter().map(|o| o.name.clone()).collect::<Vec<_>>(),
        "bodies": bodies.iter().zip(body_poses).map(|(&b, poses)| json!({
            "id": b, "name": name(Obj::mjOBJ_BODY, b), "poses": poses,
        })).collect::<Vec<_>>(),
        "geoms": geoms,
        "meshes": meshes,
        "cameras": camera_json,
        "lights": lights,
        "headlight": {
            "active": head.active != 0,
            "ambient": head.ambient.map(|v| round6(v as f64)),
            "diffuse": head.diffuse.map(|v| round6(v as f64)),
        },
        "sky_mean_rgb": sky,
        // BOP's world is the robot base: the cameras written beside Blender's renders are posed
        // in it through this.
        "world_from_base": {"position_m": bp, "quat_wxyz": [bq[3], bq[0], bq[1], bq[2]]},
    }))
}

/// The checkout holding the gyms (and `.venv-blender`, `real2sim/blender`).
fn checkout() -> PathBuf {
    runtime::launch::gyms_dir().parent().map(Path::to_path_buf).unwrap_or_default()
}

/// The Python that has `bpy`: `$R2G_BLENDER_PYTHON`, else the checkout's `.venv-blender`,
/// installed by `scripts/setup-blender.sh` first when it is missing or out of date.
pub fn blender_python() -> anyhow::Result<PathBuf> {
    if let Some(p) = std::env::var_os("R2G_BLENDER_PYTHON") {
        return Ok(PathBuf::from(p));
    }
    let root = checkout();
    let script = root.join("scripts/setup-blender.sh");
    // The script returns at once when its stamp matches requirements-blender.txt.
    let status = Command::new(&script)
        .status()
        .with_context(|| format!("running {} (installs Blender as a Python module)", script.display()))?;
    if !status.success() {
        bail!("{} failed ({status}): Blender's environment is not installed", script.display());
    }
    Ok(root.join(".venv-blender/bin/python"))
}

/// What Blender is asked to do besides saving the .blend.
pub struct RenderJob {
    /// Folder to render into (made by the caller, empty).
    pub dir: PathBuf,
    /// (image id, frame index into the states, camera name).
    pub shots: Vec<(usize, usize, String)>,
    pub samples: u32,
    pub percent: u32,
}

/// Index of the state nearest `t_s`; an instant outside the states' span (by more than half a
/// sample) is an error.
pub fn nearest(states: &[Sample], t_s: f64) -> anyhow::Result<usize> {
    let (first, last) = (states[0].t_s, states[states.len() - 1].t_s);
    let slack = 0.5 / FPS;
    if !t_s.is_finite() || t_s < first - slack || t_s > last + slack {
        bail!("--at {t_s}: outside the motion's span, {first} to {last} s of simulated time");
    }
    Ok(states
        .iter()
        .enumerate()
        .min_by(|a, b| (a.1.t_s - t_s).abs().total_cmp(&(b.1.t_s - t_s).abs()))
        .map(|(i, _)| i)
        .unwrap_or(0))
}

/// Runs `build_scene.py` in Blender's Python on the exported document: saves `blend` (when
/// given) and renders `job` (when given). Returns the script's summary JSON.
pub fn run_blender(doc: &Value, blend: Option<&Path>, job: Option<&RenderJob>) -> anyhow::Result<Value> {
    let py = blender_python()?;
    let script = checkout().join("real2sim/blender/build_scene.py");
    let work = std::env::temp_dir().join(format!("r2g-blender-{}-{}", std::process::id(), unique()));
    std::fs::create_dir_all(&work).with_context(|| format!("creating {}", work.display()))?;
    let result = (|| {
        let scene_json = work.join("scene.json");
        std::fs::write(&scene_json, serde_json::to_vec(doc)?)
            .with_context(|| format!("writing {}", scene_json.display()))?;
        let summary = work.join("summary.json");
        let mut cmd = Command::new(&py);
        cmd.arg(&script).arg("--scene").arg(&scene_json).arg("--summary").arg(&summary);
        if let Some(b) = blend {
            cmd.arg("--blend").arg(std::path::absolute(b)?);
        }
        if let Some(j) = job {
            cmd.arg("--render").arg(&j.dir);
            cmd.arg("--samples").arg(j.samples.to_string()).arg("--percent").arg(j.percent.to_string());
            for (id, frame, cam) in &j.shots {
                cmd.arg("--shot").arg(format!("{id}:{frame}:{cam}"));
            }
        }
        let out = cmd.output().with_context(|| format!("running {} {}", py.display(), script.display()))?;
        if !out.status.success() {
            let err = String::from_utf8_lossy(&out.stderr);
            let tail: Vec<&str> = err.trim().lines().rev().take(12).collect();
            bail!(
                "Blender ({} {}) failed ({}):\n{}",
                py.display(),
                script.display(),
                out.status,
                tail.into_iter().rev().collect::<Vec<_>>().join("\n")
            );
        }
        let text =
            std::fs::read_to_string(&summary).with_context(|| format!("Blender wrote no {}", summary.display()))?;
        Ok(serde_json::from_str::<Value>(&text)?)
    })();
    let _ = std::fs::remove_dir_all(&work);
    result
}

fn unique() -> u128 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0)
}

/// A folder beside `dest` to fill before renaming it to `dest`.
pub fn temp_beside(dest: &Path) -> anyhow::Result<PathBuf> {
    let name = dest.file_name().with_context(|| format!("{} is not a folder path", dest.display()))?;
    let parent = dest.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    let tmp = parent.join(format!(".{}.tmp{}", name.to_string_lossy(), std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    Ok(tmp)
}

/// Renames a filled temporary folder to `dest`, replacing an earlier one.
pub fn commit_dir(tmp: &Path, dest: &Path) -> anyhow::Result<()> {
    if dest.exists() {
        std::fs::remove_dir_all(dest).with_context(|| format!("replacing {}", dest.display()))?;
    }
    std::fs::rename(tmp, dest).with_context(|| format!("renaming {} to {}", tmp.display(), dest.display()))
}

/// A BOP rotation (row-major, world to camera, OpenCV axes: x right, y down, z forward) and
/// translation (mm) from a camera's world pose as MuJoCo keeps it (position, quaternion w, x,
/// y, z of a frame looking along its −z with image up along +y).
pub fn bop_pose(p: &[f64], q_wxyz: &[f64]) -> ([f64; 9], [f64; 3]) {
    let q = [q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]];
    // Columns of world_from_cam (MuJoCo axes), then flip y and z for OpenCV's.
    let x = controllers::math::rotate(q, [1.0, 0.0, 0.0]);
    let y = controllers::math::rotate(q, [0.0, -1.0, 0.0]);
    let z = controllers::math::rotate(q, [0.0, 0.0, -1.0]);
    // cam_from_world = transpose: rows are the camera axes in the world.
    let r = [x[0], x[1], x[2], y[0], y[1], y[2], z[0], z[1], z[2]];
    let t = [
        -(r[0] * p[0] + r[1] * p[1] + r[2] * p[2]) * 1000.0,
        -(r[3] * p[0] + r[4] * p[1] + r[5] * p[2]) * 1000.0,
        -(r[6] * p[0] + r[7] * p[1] + r[8] * p[2]) * 1000.0,
    ];
    (r, t)
}

/// [`bop_pose`] of a camera's world pose `[x, y, z, qw, qx, qy, qz]`, taken into the robot base
/// frame (BOP's world) with the export's `world_from_base`.
pub(crate) fn bop_pose_in_base(doc: &Value, pose: &[f64]) -> anyhow::Result<([f64; 9], [f64; 3])> {
    use controllers::math;
    if pose.len() != 7 {
        bail!("camera pose: {} numbers, not 7", pose.len());
    }
    let wb = &doc["world_from_base"];
    let v = |x: &Value| -> Vec<f64> { x.as_array().into_iter().flatten().filter_map(Value::as_f64).collect() };
    let (bp, bq) = (v(&wb["position_m"]), v(&wb["quat_wxyz"]));
    if bp.len() != 3 || bq.len() != 4 {
        bail!("the export has no world_from_base pose");
    }
    let world_from_base = ([bp[0], bp[1], bp[2]], [bq[1], bq[2], bq[3], bq[0]]);
    let (p, q) = math::compose(
        math::inverse(world_from_base),
        ([pose[0], pose[1], pose[2]], [pose[4], pose[5], pose[6], pose[3]]),
    );
    Ok(bop_pose(&p, &[q[3], q[0], q[1], q[2]]))
}

/// Renders every instant of `at` from every camera named in `cameras` (default: all of the
/// document's) into `dest` (BOP layout), whole or not at all. Returns Blender's summary
/// (per-frame times).
#[allow(clippy::too_many_arguments)]
pub fn render_to(
    doc: &Value,
    blend: Option<&Path>,
    states: &[Sample],
    cameras: &[String],
    at: &[f64],
    samples: u32,
    percent: u32,
    dest: &Path,
) -> anyhow::Result<Value> {
    if at.is_empty() {
        bail!("--render needs --at <t_s>[,<t_s>...]: the instants to render");
    }
    let chosen = if cameras.is_empty() { camera_names(doc) } else { cameras.to_vec() };
    let pairs: Vec<(f64, String)> = at.iter().flat_map(|&t| chosen.iter().map(move |c| (t, c.clone()))).collect();
    render_pairs(doc, blend, states, &pairs, samples, percent, dest)
}

/// `sim`'s scene compiled again with the cameras of a BOP `scene_camera.json` in place of its own,
/// as `r2g render --cameras` does (`sim_host::bop::camera_spec`: pinhole intrinsics, fixed pose
/// with the robot base as BOP's world, named `bop_<id>`), and the image ids they came from in
/// file order.
pub fn with_bop_cameras(sim: &Sim, file: &Path) -> anyhow::Result<(Sim, Vec<String>)> {
    let bop = sim_host::bop::read_scene_camera(file).map_err(|e| anyhow::anyhow!(e))?;
    let world_from_base = sim.world_from_base();
    let mut scene = sim.scene.clone();
    scene.cameras = bop
        .iter()
        .map(|c| sim_host::bop::camera_spec(c, world_from_base))
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!(e))?;
    let sim = Sim::from_scene(scene)
        .with_context(|| format!("compiling scene '{}' with the cameras of {}", sim.scene.name, file.display()))?;
    Ok((sim, bop.into_iter().map(|c| c.id).collect()))
}

/// Names the document's cameras in the rendered `scene_camera.json` (`r2g_camera`) by `labels`
/// (in camera order) instead of their scene names: the image ids of a BOP camera file, as `r2g
/// render --cameras` names them.
pub fn label_cameras(doc: &mut Value, labels: &[String]) -> anyhow::Result<()> {
    let cams = doc["cameras"].as_array_mut().context("the export has no cameras")?;
    if cams.len() != labels.len() {
        bail!("{} cameras exported for {} labels", cams.len(), labels.len());
    }
    for (c, l) in cams.iter_mut().zip(labels) {
        c["r2g_label"] = json!(l);
    }
    Ok(())
}

/// The names of the document's cameras, in order.
pub fn camera_names(doc: &Value) -> Vec<String> {
    doc["cameras"].as_array().into_iter().flatten().filter_map(|c| c["name"].as_str().map(String::from)).collect()
}

/// Renders one image per (instant, camera) pair, image ids in order, into `dest` (BOP layout:
/// scene_camera.json, rgb/, label/, mask_visib/, timing.json), whole or not at all.
pub fn render_pairs(
    doc: &Value,
    blend: Option<&Path>,
    states: &[Sample],
    pairs: &[(f64, String)],
    samples: u32,
    percent: u32,
    dest: &Path,
) -> anyhow::Result<Value> {
    if !(1..=100).contains(&percent) {
        bail!("--percent {percent}: give 1 to 100");
    }
    if samples == 0 {
        bail!("--samples 0: Cycles needs at least one sample per pixel");
    }
    let cams = doc["cameras"].as_array().cloned().unwrap_or_default();
    let known: Vec<&str> = cams.iter().filter_map(|c| c["name"].as_str()).collect();
    let mut shots = Vec::new();
    let mut camera_json = serde_json::Map::new();
    for (t, c) in pairs {
        let Some(cam) = cams.iter().find(|x| x["name"] == c.as_str()) else {
            bail!("--camera {c}: the scene has no such camera (it has {})", known.join(", "));
        };
        let f = nearest(states, *t)?;
        let id = shots.len();
        let (w, h) = (cam["width"].as_u64().unwrap_or(0), cam["height"].as_u64().unwrap_or(0));
        let (rw, rh) = (w * percent as u64 / 100, h * percent as u64 / 100);
        if rw == 0 || rh == 0 {
            bail!("camera {c}: {w}x{h} at {percent}% leaves no pixels");
        }
        let (sx, sy) = (rw as f64 / w as f64, rh as f64 / h as f64);
        let g = |k: &str| cam[k].as_f64().unwrap_or(0.0);
        let pose: Vec<f64> =
            cam["poses"][f].as_array().context("camera pose")?.iter().filter_map(Value::as_f64).collect();
        let (r, tr) = bop_pose_in_base(doc, &pose)?;
        // Pixel centres at integer coordinates: scaling maps edges, so centres move by half a pixel.
        let k = [
            g("fx") * sx,
            0.0,
            (g("cx") + 0.5) * sx - 0.5,
            0.0,
            g("fy") * sy,
            (g("cy") + 0.5) * sy - 0.5,
            0.0,
            0.0,
            1.0,
        ];
        camera_json.insert(
            id.to_string(),
            json!({
                "cam_K": k,
                "cam_R_w2c": r,
                "cam_t_w2c": tr,
                "depth_scale": 0.1,
                "width": rw,
                "height": rh,
                "r2g_camera": cam["r2g_label"].as_str().unwrap_or(c),
                "r2g_t_s": states[f].t_s,
            }),
        );
        shots.push((id, f, c.clone()));
    }
    let tmp = temp_beside(dest)?;
    let result = (|| {
        let job = RenderJob { dir: tmp.clone(), shots: shots.clone(), samples, percent };
        let summary = run_blender(doc, blend, Some(&job))?;
        // Flat per-object colours → one mask per (image, object), as BOP's mask_visib.
        let n_obj = doc["objects"].as_array().map(Vec::len).unwrap_or(0);
        std::fs::create_dir_all(tmp.join("mask_visib"))?;
        for (id, _, _) in &shots {
            let (lab, w, h) = read_png_rgb(&tmp.join(format!("label/{id:06}.png")))?;
            for k in 0..n_obj {
                let mask: Vec<u8> = lab.chunks(3).map(|p| if label_of(p) == Some(k) { 255 } else { 0 }).collect();
                write_png(&tmp.join(format!("mask_visib/{id:06}_{k:06}.png")), &mask, w, h, png::ColorType::Grayscale)?;
            }
        }
        std::fs::write(tmp.join("scene_camera.json"), serde_json::to_vec_pretty(&camera_json)?)?;
        std::fs::write(tmp.join("timing.json"), serde_json::to_vec_pretty(&summary)?)?;
        commit_dir(&tmp, dest)?;
        Ok(summary)
    })();
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result
}

/// The label render's encoding (build_scene.py): object k is red = LABEL_STEP × (k + 1), green
/// and blue 0; anything else black.
const LABEL_STEP: u32 = 8;

fn label_of(p: &[u8]) -> Option<usize> {
    let r = p[0] as u32;
    if r < LABEL_STEP / 2 || p[1] > 8 || p[2] > 8 {
        return None;
    }
    Some(((r + LABEL_STEP / 2) / LABEL_STEP) as usize - 1)
}

/// Reads an 8-bit PNG as RGB (grey and RGBA converted).
pub fn read_png_rgb(path: &Path) -> anyhow::Result<(Vec<u8>, usize, usize)> {
    let f = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut dec = png::Decoder::new(std::io::BufReader::new(f));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut r = dec.read_info().with_context(|| format!("{}: not a PNG", path.display()))?;
    let mut buf = vec![0; r.output_buffer_size().context("PNG too large")?];
    let info = r.next_frame(&mut buf).with_context(|| format!("{}: bad PNG data", path.display()))?;
    let (w, h) = (info.width as usize, info.height as usize);
    let px = &buf[..info.buffer_size()];
    let rgb = match info.color_type {
        png::ColorType::Rgb => px.to_vec(),
        png::ColorType::Rgba => px.chunks(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
        png::ColorType::Grayscale => px.iter().flat_map(|&g| [g, g, g]).collect(),
        png::ColorType::GrayscaleAlpha => px.chunks(2).flat_map(|p| [p[0], p[0], p[0]]).collect(),
        png::ColorType::Indexed => bail!("{}: indexed PNG after expansion", path.display()),
    };
    Ok((rgb, w, h))
}

/// Writes an 8-bit PNG.
pub fn write_png(path: &Path, px: &[u8], w: usize, h: usize, color: png::ColorType) -> anyhow::Result<()> {
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, w as u32, h as u32);
        enc.set_color(color);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header()?;
        wr.write_image_data(px)?;
    }
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_the_standard_alphabet_and_padding() {
        assert_eq!(base64(b""), "");
        assert_eq!(base64(b"f"), "Zg==");
        assert_eq!(base64(b"fo"), "Zm8=");
        assert_eq!(base64(b"foo"), "Zm9v");
        assert_eq!(base64(b"foobar"), "Zm9vYmFy");
        assert_eq!(base64(&[0xff, 0xfe, 0x00]), "//4A");
    }

    #[test]
    fn labels_decode_to_object_indices_and_nothing_else() {
        assert_eq!(label_of(&[0, 0, 0]), None);
        assert_eq!(label_of(&[8, 0, 0]), Some(0));
        assert_eq!(label_of(&[16, 0, 0]), Some(1));
        assert_eq!(label_of(&[17, 1, 0]), Some(1));
        // A colour that is not a label (green or blue present) is no object.
        assert_eq!(label_of(&[16, 200, 0]), None);
    }

    #[test]
    fn a_camera_looking_down_has_the_bop_pose_of_opencv_axes() {
        // One metre above the origin with the identity orientation: MuJoCo's camera looks
        // along its −z, so straight down, image up along world +y.
        let (r, t) = bop_pose(&[0.0, 0.0, 1.0], &[1.0, 0.0, 0.0, 0.0]);
        // OpenCV x = world x, y = −world y, z = −world z.
        assert_eq!(r, [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0]);
        // The world origin is 1000 mm in front of the camera.
        assert!((t[0]).abs() < 1e-12 && (t[1]).abs() < 1e-12 && (t[2] - 1000.0).abs() < 1e-9, "{t:?}");
    }
}
