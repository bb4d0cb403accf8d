//! Measured calibrations named in `config/robot.json` (its `calibration` table): the
//! flange-to-TCP transform and, per camera, intrinsics and the camera's pose. Each lives in its
//! own JSON file (formats in runtime/README.md, "Calibration"), read once at start and checked
//! strictly; every error names the file and the field.
//!
//! A named TCP file that cannot be read or is invalid stops the start: motion planned with a
//! wrong TCP is unsafe. A camera file that cannot be read or is invalid does not: that camera is
//! reported `missing` with the reason, and nothing is made up in its place. [`Calibration::report`]
//! is what `get_state()["calibration"]` shows (through [`ipc_schema::RuntimeInfo::calibration`]).

use std::path::{Path, PathBuf};

use serde_json::{json, Map, Value};

use crate::robot_config::CalibrationFiles;

/// Row-major 4×4 homogeneous transform, metres.
pub type Matrix = [[f64; 4]; 4];

/// Largest |RᵀR − I| element (and |det R − 1|) accepted for a rotation.
pub const ROTATION_TOLERANCE: f64 = 1e-4;
/// Farthest a TCP may sit from the flange, m.
pub const MAX_TCP_OFFSET_M: f64 = 0.5;
/// Farthest a camera may sit from the base (or the flange), m.
pub const MAX_CAMERA_OFFSET_M: f64 = 10.0;
/// Largest image side accepted, px.
pub const MAX_IMAGE_SIDE: u64 = 16384;
/// Longest reason kept for a missing camera, bytes.
const MAX_REASON: usize = 400;

/// Where a camera is mounted: fixed in the robot base frame, or on the flange (hand-eye).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mount {
    /// `base_from_camera`: camera optical frame → base frame.
    Base(Matrix),
    /// `flange_from_camera`: camera optical frame → flange frame.
    Flange(Matrix),
}

/// One camera's calibration as its file gives it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraCalibration {
    /// None: the file gives no intrinsics; the camera host takes the device's own.
    pub intrinsics: Option<Intrinsics>,
    pub mount: Mount,
}

/// A camera's measured pinhole model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// OpenCV order: k1, k2, p1, p2, k3. None: the file gives none (undistorted images).
    pub distortion: Option<[f64; 5]>,
}

/// A camera named in the config: its file and what came of reading it.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraEntry {
    pub name: String,
    pub path: PathBuf,
    /// The calibration, or why it is missing.
    pub calibration: Result<CameraCalibration, String>,
}

/// The calibrations read at start.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Calibration {
    /// The measured flange-to-TCP transform and its file; None: the description's TCP.
    pub tcp: Option<(PathBuf, Matrix)>,
    pub cameras: Vec<CameraEntry>,
}

impl Calibration {
    /// Reads every named file. Fails only for the TCP (unreadable or invalid: the runtime must
    /// not move with a wrong TCP); a camera's problem is kept as its reason.
    pub fn load(files: &CalibrationFiles) -> anyhow::Result<Self> {
        let tcp = match &files.tcp {
            Some(path) => {
                let m = read(path).and_then(|text| parse_tcp(&text)).map_err(|e| {
                    anyhow::anyhow!(
                        "calibration file {} (calibration.tcp in the robot config): {e}; a measured TCP that \
                         cannot be used stops the start (motion with a wrong TCP is unsafe): fix the file, or \
                         remove calibration.tcp to use the robot description's TCP",
                        path.display()
                    )
                })?;
                Some((path.clone(), m))
            }
            None => None,
        };
        let cameras = files
            .cameras
            .iter()
            .map(|(name, path)| CameraEntry {
                name: name.clone(),
                path: path.clone(),
                calibration: read(path)
                    .and_then(|text| parse_camera(&text))
                    .map_err(|e| cut(format!("calibration file {}: {e}", path.display()))),
            })
            .collect();
        Ok(Self { tcp, cameras })
    }

    /// The `calibration` entry of `get_state()`, as one JSON object: the TCP in use
    /// (`flange_from_tcp`, whatever its source) and every configured camera.
    pub fn report(&self, flange_from_tcp: &Matrix) -> String {
        let source = match &self.tcp {
            Some((path, _)) => format!("file: {}", path.display()),
            None => "description".into(),
        };
        let mut cameras = Map::new();
        for c in &self.cameras {
            let entry = match &c.calibration {
                Ok(k) => {
                    let (key, m) = match k.mount {
                        Mount::Base(m) => ("base_from_camera", m),
                        Mount::Flange(m) => ("flange_from_camera", m),
                    };
                    let mut e = json!({"source": format!("file: {}", c.path.display()), key: m});
                    match k.intrinsics {
                        Some(i) => {
                            let more = json!({"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy,
                                "cx": i.cx, "cy": i.cy, "distortion": i.distortion});
                            e.as_object_mut().into_iter().zip(more.as_object()).for_each(|(e, more)| {
                                e.extend(more.clone());
                            });
                        }
                        None => e["intrinsics"] = json!("device"),
                    }
                    e
                }
                Err(reason) => json!({"source": "missing", "reason": reason}),
            };
            cameras.insert(c.name.clone(), entry);
        }
        json!({
            "tcp": {"source": source, "flange_from_tcp": flange_from_tcp},
            "cameras": cameras,
        })
        .to_string()
    }
}

fn read(path: &Path) -> Result<String, String> {
    std::fs::read_to_string(path).map_err(|e| format!("cannot be read: {e}"))
}

/// A reason cut to [`MAX_REASON`] bytes at a character boundary.
fn cut(mut s: String) -> String {
    if s.len() > MAX_REASON {
        let mut n = MAX_REASON - 3;
        while !s.is_char_boundary(n) {
            n -= 1;
        }
        s.truncate(n);
        s.push_str("...");
    }
    s
}

/// A value for an error message, shortened.
fn shown(v: &Value) -> String {
    let s = v.to_string();
    if s.len() > 60 {
        format!("{}...", &s[..s.char_indices().nth(57).map_or(s.len(), |(i, _)| i)])
    } else {
        s
    }
}

fn object<'a>(v: &'a Value, keys: &[&str]) -> Result<&'a Map<String, Value>, String> {
    let Some(m) = v.as_object() else { return Err("must hold a JSON object".into()) };
    if let Some(k) = m.keys().find(|k| !keys.contains(&k.as_str())) {
        return Err(format!("unknown key \"{k}\"; accepted: {}", keys.join(", ")));
    }
    if let Some(n) = m.get("note") {
        if !n.is_string() {
            return Err(format!("note must be a string, got {}", shown(n)));
        }
    }
    Ok(m)
}

fn number(m: &Map<String, Value>, key: &str) -> Result<f64, String> {
    let v = m.get(key).ok_or_else(|| format!("{key} is missing"))?;
    match v.as_f64() {
        Some(x) if x.is_finite() => Ok(x),
        _ => Err(format!("{key} must be a finite number, got {}", shown(v))),
    }
}

/// A rigid transform: 4 rows of 4 finite numbers, last row 0 0 0 1, an orthonormal right-handed
/// rotation, and a translation of at most `max_m`.
fn transform(m: &Map<String, Value>, key: &str, max_m: f64) -> Result<Matrix, String> {
    let v = m.get(key).ok_or_else(|| format!("{key} is missing"))?;
    let rows = v.as_array().filter(|r| r.len() == 4).ok_or_else(|| {
        format!("{key} must be a 4x4 matrix (a list of 4 rows of 4 numbers, row-major), got {}", shown(v))
    })?;
    let mut t = [[0.0; 4]; 4];
    for (i, row) in rows.iter().enumerate() {
        let r = row
            .as_array()
            .filter(|r| r.len() == 4)
            .ok_or_else(|| format!("{key} row {} must be a list of 4 numbers, got {}", i + 1, shown(row)))?;
        for (j, x) in r.iter().enumerate() {
            t[i][j] = x.as_f64().filter(|x| x.is_finite()).ok_or_else(|| {
                format!("{key} row {} column {} must be a finite number, got {}", i + 1, j + 1, shown(x))
            })?;
        }
    }
    if t[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(format!("{key} row 4 must be [0, 0, 0, 1], got {:?}", t[3]));
    }
    let mut worst: f64 = 0.0;
    for a in 0..3 {
        for b in 0..3 {
            let dot: f64 = (0..3).map(|k| t[k][a] * t[k][b]).sum();
            worst = worst.max((dot - if a == b { 1.0 } else { 0.0 }).abs());
        }
    }
    let det = t[0][0] * (t[1][1] * t[2][2] - t[1][2] * t[2][1]) - t[0][1] * (t[1][0] * t[2][2] - t[1][2] * t[2][0])
        + t[0][2] * (t[1][0] * t[2][1] - t[1][1] * t[2][0]);
    if worst > ROTATION_TOLERANCE {
        return Err(format!(
            "{key}: the rotation (upper-left 3x3) is not orthonormal: |RᵀR − I| reaches {worst:.2e}, more than {ROTATION_TOLERANCE:e}"
        ));
    }
    if (det - 1.0).abs() > ROTATION_TOLERANCE {
        return Err(format!("{key}: the rotation (upper-left 3x3) has determinant {det:.6}, not +1 (a reflection)"));
    }
    let d = (t[0][3].powi(2) + t[1][3].powi(2) + t[2][3].powi(2)).sqrt();
    if d > max_m {
        return Err(format!(
            "{key}: the translation is {d:.3} m long, more than the {max_m} m accepted (units are metres)"
        ));
    }
    Ok(t)
}

/// A flange-to-TCP file: `{"flange_from_tcp": 4x4, "note": "..."}`.
pub fn parse_tcp(text: &str) -> Result<Matrix, String> {
    let v: Value = serde_json::from_str(text).map_err(|e| format!("not valid JSON: {e}"))?;
    let m = object(&v, &["flange_from_tcp", "note"])?;
    transform(m, "flange_from_tcp", MAX_TCP_OFFSET_M)
}

/// A camera file: intrinsics, optional distortion, and exactly one of `base_from_camera`
/// (fixed camera) or `flange_from_camera` (on the hand).
pub fn parse_camera(text: &str) -> Result<CameraCalibration, String> {
    let v: Value = serde_json::from_str(text).map_err(|e| format!("not valid JSON: {e}"))?;
    let m = object(
        &v,
        &["width", "height", "fx", "fy", "cx", "cy", "distortion", "base_from_camera", "flange_from_camera", "note"],
    )?;
    let side = |key: &str| -> Result<u32, String> {
        let v = m.get(key).ok_or_else(|| format!("{key} is missing"))?;
        match v.as_u64() {
            Some(n) if (1..=MAX_IMAGE_SIDE).contains(&n) => Ok(n as u32),
            _ => Err(format!("{key} must be a whole number of pixels, 1 to {MAX_IMAGE_SIDE}, got {}", shown(v))),
        }
    };
    const INTRINSICS: [&str; 7] = ["width", "height", "fx", "fy", "cx", "cy", "distortion"];
    let given = INTRINSICS.iter().filter(|k| m.contains_key(**k)).count();
    let mount =
        match (m.contains_key("base_from_camera"), m.contains_key("flange_from_camera")) {
            (true, false) => Mount::Base(transform(m, "base_from_camera", MAX_CAMERA_OFFSET_M)?),
            (false, true) => Mount::Flange(transform(m, "flange_from_camera", MAX_CAMERA_OFFSET_M)?),
            _ => return Err(
                "needs exactly one of base_from_camera (a fixed camera) or flange_from_camera (a camera on the hand)"
                    .into(),
            ),
        };
    if given == 0 {
        // The device's own intrinsics (the camera host reads them).
        return Ok(CameraCalibration { intrinsics: None, mount });
    }
    let (width, height) = (side("width")?, side("height")?);
    let focal = |key: &str| -> Result<f64, String> {
        let x = number(m, key)?;
        if x > 0.0 {
            Ok(x)
        } else {
            Err(format!("{key} = {x} must be positive (pixels)"))
        }
    };
    let (fx, fy) = (focal("fx")?, focal("fy")?);
    let centre = |key: &str, size: u32| -> Result<f64, String> {
        let x = number(m, key)?;
        if (0.0..=f64::from(size)).contains(&x) {
            Ok(x)
        } else {
            Err(format!("{key} = {x} must lie on the image (0 to {size} pixels)"))
        }
    };
    let (cx, cy) = (centre("cx", width)?, centre("cy", height)?);
    let distortion = match m.get("distortion") {
        None | Some(Value::Null) => None,
        Some(v) => {
            let a = v.as_array().filter(|a| a.len() == 5).ok_or_else(|| {
                format!("distortion must be 5 numbers (k1, k2, p1, p2, k3) or null, got {}", shown(v))
            })?;
            let mut d = [0.0; 5];
            for (o, x) in d.iter_mut().zip(a) {
                *o = x
                    .as_f64()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| format!("distortion must hold finite numbers, got {}", shown(x)))?;
            }
            Some(d)
        }
    };
    Ok(CameraCalibration { intrinsics: Some(Intrinsics { width, height, fx, fy, cx, cy, distortion }), mount })
}

#[cfg(test)]
mod tests {
    use super::*;

    const TCP: &str = r#"{"flange_from_tcp": [[0.7071067811865476, 0.7071067811865476, 0, 0],
        [-0.7071067811865476, 0.7071067811865476, 0, 0], [0, 0, 1, 0.1074], [0, 0, 0, 1]],
        "note": "measured 2025-01-01"}"#;
    const CAMERA: &str = r#"{"width": 640, "height": 480, "fx": 600.5, "fy": 601, "cx": 320.2, "cy": 239.8,
        "distortion": [0.1, -0.2, 0, 0, 0.05],
        "flange_from_camera": [[0, -1, 0, 0.05], [1, 0, 0, 0], [0, 0, 1, 0.02], [0, 0, 0, 1]]}"#;

    #[test]
    fn valid_files_parse() {
        let t = parse_tcp(TCP).unwrap();
        assert_eq!(t[2][3], 0.1074);
        let c = parse_camera(CAMERA).unwrap();
        let k = c.intrinsics.unwrap();
        assert_eq!((k.width, k.height, k.fx, k.cy), (640, 480, 600.5, 239.8));
        assert_eq!(k.distortion, Some([0.1, -0.2, 0.0, 0.0, 0.05]));
        assert!(matches!(c.mount, Mount::Flange(m) if m[0][3] == 0.05));
        let fixed = CAMERA
            .replace("flange_from_camera", "base_from_camera")
            .replace(r#""distortion": [0.1, -0.2, 0, 0, 0.05],"#, "");
        let c = parse_camera(&fixed).unwrap();
        assert!(matches!(c.mount, Mount::Base(_)) && c.intrinsics.unwrap().distortion.is_none());
        // Without intrinsics: the device's own are used.
        let device = r#"{"base_from_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]]}"#;
        assert_eq!(parse_camera(device).unwrap().intrinsics, None);
    }

    #[test]
    fn invalid_files_name_the_field() {
        for (text, want) in [
            ("{", "not valid JSON"),
            ("[1]", "must hold a JSON object"),
            (r#"{"flange_from_tcp": [[1,0,0,0],[0,1,0,0],[0,0,1,0.1]]}"#, "flange_from_tcp must be a 4x4 matrix"),
            (
                r#"{"flange_from_tcp": [[1,0,0,0],[0,1,0,0],[0,0,1],[0,0,0,1]]}"#,
                "flange_from_tcp row 3 must be a list of 4",
            ),
            (
                r#"{"flange_from_tcp": [[1,0,0,0],[0,1,0,"x"],[0,0,1,0],[0,0,0,1]]}"#,
                "row 2 column 4 must be a finite number",
            ),
            (r#"{"flange_from_tcp": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]}"#, "row 4 must be [0, 0, 0, 1]"),
            (r#"{"flange_from_tcp": [[1,0.01,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#, "not orthonormal"),
            (r#"{"flange_from_tcp": [[-1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#, "determinant -1"),
            (r#"{"flange_from_tcp": [[1,0,0,0],[0,1,0,0],[0,0,1,103.4],[0,0,0,1]]}"#, "103.400 m long"),
            (r#"{"tcp": 1}"#, "unknown key \"tcp\""),
            (r#"{"note": "x"}"#, "flange_from_tcp is missing"),
            (r#"{"flange_from_tcp": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "note": 3}"#, "note must be a string"),
        ] {
            let e = parse_tcp(text).unwrap_err();
            assert!(e.contains(want), "{text}: {e}");
        }
        for (from, to, want) in [
            (r#""width": 640"#, r#""width": 0"#, "width must be a whole number of pixels"),
            (r#""height": 480"#, r#""height": 480.5"#, "height must be a whole number"),
            (r#""fx": 600.5"#, r#""fx": -600.5"#, "fx = -600.5 must be positive"),
            (r#""fy": 601"#, r#""fy": "601""#, "fy must be a finite number"),
            (r#""cx": 320.2"#, r#""cx": 700"#, "cx = 700 must lie on the image (0 to 640"),
            (r#""cy": 239.8"#, r#""cy": -1"#, "cy = -1 must lie on the image"),
            (r#""distortion": [0.1, -0.2, 0, 0, 0.05]"#, r#""distortion": [0.1]"#, "distortion must be 5 numbers"),
            ("flange_from_camera", "hand_from_camera", "unknown key \"hand_from_camera\""),
            (
                r#""cy": 239.8,"#,
                r#""cy": 239.8, "base_from_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],"#,
                "exactly one of",
            ),
            ("[0, 0, 1, 0.02]", "[0, 0, 0.9, 0.02]", "flange_from_camera: the rotation"),
        ] {
            let text = CAMERA.replace(from, to);
            assert_ne!(text, CAMERA, "{from}");
            let e = parse_camera(&text).unwrap_err();
            assert!(e.contains(want), "{to}: {e}");
        }
    }

    #[test]
    fn a_bad_tcp_file_stops_the_start_and_a_bad_camera_file_is_reported_missing() {
        let dir = std::env::temp_dir().join(format!("r2g-calibration-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("tcp.json"), TCP).unwrap();
        std::fs::write(dir.join("wrist.json"), CAMERA).unwrap();
        std::fs::write(dir.join("bad.json"), CAMERA.replace(r#""fx": 600.5"#, r#""fx": 0"#)).unwrap();
        std::fs::write(dir.join("badtcp.json"), r#"{"flange_from_tcp": 1}"#).unwrap();
        let files = CalibrationFiles {
            tcp: Some(dir.join("tcp.json")),
            cameras: vec![
                ("agentview".into(), dir.join("absent.json")),
                ("side".into(), dir.join("bad.json")),
                ("wrist".into(), dir.join("wrist.json")),
            ],
        };
        let c = Calibration::load(&files).unwrap();
        assert_eq!(c.tcp.as_ref().map(|t| t.1[2][3]), Some(0.1074));
        let absent = c.cameras[0].calibration.as_ref().unwrap_err();
        assert!(absent.contains("absent.json: cannot be read"), "{absent}");
        let bad = c.cameras[1].calibration.as_ref().unwrap_err();
        assert!(bad.contains("bad.json: fx = 0 must be positive"), "{bad}");
        assert!(c.cameras[2].calibration.is_ok());
        let report: Value = serde_json::from_str(&c.report(&c.tcp.as_ref().unwrap().1)).unwrap();
        assert_eq!(report["tcp"]["source"], format!("file: {}", dir.join("tcp.json").display()));
        assert_eq!(report["tcp"]["flange_from_tcp"][2][3], 0.1074);
        assert_eq!(report["cameras"]["agentview"]["source"], "missing");
        assert_eq!(report["cameras"]["side"]["source"], "missing");
        assert_eq!(report["cameras"]["wrist"]["fx"], 600.5);
        assert_eq!(report["cameras"]["wrist"]["flange_from_camera"][0][3], 0.05);
        for (tcp, want) in [("badtcp.json", "flange_from_tcp must be a 4x4 matrix"), ("none.json", "cannot be read")] {
            let files = CalibrationFiles { tcp: Some(dir.join(tcp)), cameras: vec![] };
            let e = format!("{:#}", Calibration::load(&files).unwrap_err());
            assert!(e.contains(&format!("{tcp} (calibration.tcp in the robot config): {want}")), "{e}");
            assert!(e.contains("stops the start"), "{e}");
        }
        let none = Calibration::load(&CalibrationFiles::default()).unwrap();
        let report: Value = serde_json::from_str(&none.report(&[[1.0, 0.0, 0.0, 0.0]; 4])).unwrap();
        assert_eq!(report["tcp"]["source"], "description");
        assert_eq!(report["cameras"], json!({}));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_largest_report_fits_the_shared_buffer() {
        // Quotes and backslashes double in JSON; control characters are refused in paths.
        let long = PathBuf::from(format!("/{}", "\\".repeat(crate::robot_config::MAX_CALIBRATION_PATH - 1)));
        let worst = [[-1.234_567_890_123_456_7e-300; 4]; 4];
        let k = CameraCalibration {
            intrinsics: Some(Intrinsics {
                width: 16384,
                height: 16384,
                fx: -1.234_567_890_123_456_7e-300,
                fy: -1.234_567_890_123_456_7e-300,
                cx: -1.234_567_890_123_456_7e-300,
                cy: -1.234_567_890_123_456_7e-300,
                distortion: Some([-1.234_567_890_123_456_7e-300; 5]),
            }),
            mount: Mount::Flange(worst),
        };
        let cameras = (0..ipc_schema::MAX_CAMERAS)
            .map(|i| CameraEntry {
                name: format!("{i}").repeat(ipc_schema::NAME_LEN),
                path: long.clone(),
                calibration: if i % 2 == 0 { Ok(k) } else { Err("\"".repeat(2 * MAX_REASON)) },
            })
            .map(|mut e| {
                if let Err(r) = &e.calibration {
                    e.calibration = Err(cut(r.clone()));
                }
                e
            })
            .collect();
        let c = Calibration { tcp: Some((long, worst)), cameras };
        let all_ok = Calibration {
            cameras: c.cameras.iter().cloned().map(|e| CameraEntry { calibration: Ok(k), ..e }).collect(),
            ..c.clone()
        };
        for c in [c, all_ok] {
            let text = c.report(&worst);
            assert!(text.len() <= ipc_schema::CALIBRATION_LEN, "{} bytes", text.len());
        }
    }
}
