//! Placement perturbation: free objects start somewhere else, drawn from the episode seed.
//!
//! The shipped gyms jitter their objects by millimetres (`jitter_xy_m`, `jitter_yaw_deg`); a
//! [`Perturbation`] moves them by centimetres and tens of degrees to test whether a behaviour
//! transfers to layouts it never saw (skills, `r2g skills run`) and to place objects for
//! augmentation (Real2Sim). A draw is accepted only when every moved object keeps
//! [`CLEARANCE_M`] from every other collision geometry (objects, fixtures, the robot at its
//! start pose), its centre stays on the table and within [`REACH_M`] of the robot base; MuJoCo's
//! own distance query decides, on the compiled geometry. After [`TRIES`] rejected draws the
//! scene keeps its written placement and [`Placed::note`] says so.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::scene::Scene;

/// Least distance between a moved object and any other collision geometry, m.
pub const CLEARANCE_M: f64 = 0.01;
/// Farthest a moved object's centre may be from the robot base in the table plane, m.
pub const REACH_M: f64 = 0.80;
/// Draws tried before the written placement is kept.
pub const TRIES: usize = 200;

/// How far objects may move. Parsed from `xy=0.05,yaw=30[,objects=block+plate]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Perturbation {
    /// Each moved object's start x and y move by up to this much, m.
    pub xy_m: f64,
    /// Each moved object's start yaw turns by up to this much about the vertical, degrees.
    pub yaw_deg: f64,
    /// The objects moved; empty: every free object of the scene.
    #[serde(default)]
    pub objects: Vec<String>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum PerturbationError {
    #[error("perturbation '{text}': {why} (accepted: xy=<m in [0, 0.3]>,yaw=<deg in [0, 180]>[,objects=a+b])")]
    Syntax { text: String, why: String },
    #[error("perturbation: {0}")]
    Scene(String),
}

impl FromStr for Perturbation {
    type Err = PerturbationError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = |why: String| PerturbationError::Syntax { text: text.to_string(), why };
        let (mut xy, mut yaw, mut objects) = (None, None, Vec::new());
        for item in text.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (k, v) = item.split_once('=').ok_or_else(|| bad(format!("'{item}' is not key=value")))?;
            let num = || v.trim().parse::<f64>().map_err(|_| bad(format!("{k}: '{v}' is not a number")));
            match k.trim() {
                "xy" => xy = Some(num()?),
                "yaw" => yaw = Some(num()?),
                "objects" => objects = v.split('+').map(|s| s.trim().to_string()).filter(|s| !s.is_empty()).collect(),
                other => return Err(bad(format!("unknown key '{other}'"))),
            }
        }
        let (Some(xy_m), Some(yaw_deg)) = (xy, yaw) else {
            return Err(bad("both xy and yaw are needed".into()));
        };
        let p = Perturbation { xy_m, yaw_deg, objects };
        p.check_ranges().map_err(bad)?;
        Ok(p)
    }
}

impl fmt::Display for Perturbation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "xy={},yaw={}", self.xy_m, self.yaw_deg)?;
        if !self.objects.is_empty() {
            write!(f, ",objects={}", self.objects.join("+"))?;
        }
        Ok(())
    }
}

impl Perturbation {
    fn check_ranges(&self) -> Result<(), String> {
        if !(self.xy_m.is_finite() && (0.0..=0.3).contains(&self.xy_m)) {
            return Err(format!("xy must be in [0, 0.3] m, not {}", self.xy_m));
        }
        if !(self.yaw_deg.is_finite() && (0.0..=180.0).contains(&self.yaw_deg)) {
            return Err(format!("yaw must be in [0, 180] degrees, not {}", self.yaw_deg));
        }
        Ok(())
    }

    /// Indices into `scene.objects` of the objects this moves; every named one must be a free
    /// object of the scene.
    pub fn moved(&self, scene: &Scene) -> Result<Vec<usize>, PerturbationError> {
        self.check_ranges().map_err(PerturbationError::Scene)?;
        if self.objects.is_empty() {
            return Ok((0..scene.objects.len()).filter(|&i| scene.objects[i].free).collect());
        }
        self.objects
            .iter()
            .map(|name| match scene.objects.iter().position(|o| &o.name == name) {
                Some(i) if scene.objects[i].free => Ok(i),
                Some(_) => {
                    Err(PerturbationError::Scene(format!("object '{name}' is welded to the world (free = false)")))
                }
                None => Err(PerturbationError::Scene(format!(
                    "scene '{}' has no object '{name}' (it has: {})",
                    scene.name,
                    scene.objects.iter().map(|o| o.name.as_str()).collect::<Vec<_>>().join(", ")
                ))),
            })
            .collect()
    }
}

/// Where a perturbed reset put the moved objects.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Placed {
    /// Per moved object: name, start position (m, world) and orientation (w, x, y, z).
    pub objects: Vec<(String, [f64; 3], [f64; 4])>,
    /// Draws rejected before this one (0: the first draw fitted).
    pub rejected: usize,
    /// Set when no draw fitted and the written placement was kept.
    pub note: Option<String>,
}

/// Uniform in [-1, 1).
pub(crate) fn symmetric(rng: &mut controllers::ik::SplitMix64) -> f64 {
    2.0 * rng.next_f64() - 1.0
}

/// `q' = rz(yaw) · q` for a (w, x, y, z) quaternion.
pub(crate) fn turn_about_z(q: [f64; 4], yaw_rad: f64) -> [f64; 4] {
    let (s, c) = (0.5 * yaw_rad).sin_cos();
    [c * q[0] - s * q[3], c * q[1] - s * q[2], c * q[2] + s * q[1], c * q[3] + s * q[0]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_prints_the_same_text() {
        let p: Perturbation = "xy=0.05,yaw=30,objects=block+plate".parse().expect("parse");
        assert_eq!(p, Perturbation { xy_m: 0.05, yaw_deg: 30.0, objects: vec!["block".into(), "plate".into()] });
        assert_eq!(p.to_string().parse::<Perturbation>().expect("again"), p);
        let q: Perturbation = " yaw=10 , xy=0 ".parse().expect("parse");
        assert!(q.objects.is_empty() && q.xy_m == 0.0 && q.yaw_deg == 10.0);
    }

    #[test]
    fn refuses_what_it_cannot_use_with_the_reason() {
        for (text, says) in [
            ("xy=0.05", "both xy and yaw"),
            ("xy=0.5,yaw=3", "xy must be in [0, 0.3]"),
            ("xy=0.05,yaw=-1", "yaw must be in [0, 180]"),
            ("xy=NaN,yaw=3", "xy must be"),
            ("xy=abc,yaw=3", "'abc' is not a number"),
            ("xy=0.1,yaw=3,spin=2", "unknown key 'spin'"),
            ("xy0.1", "not key=value"),
        ] {
            let e = text.parse::<Perturbation>().expect_err(text).to_string();
            assert!(e.contains(says), "{text}: {e}");
        }
    }
}
