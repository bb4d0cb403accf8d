//! Augmentation: a validated gym expanded into a pool of task-conditioned variants, every one of
//! them re-executed natively and kept only when it passes the gate.
//!
//! **Factors** (each about the task's object and its target, `gym::roles`):
//! - `object_size`: the object scaled uniformly about its origin (geometry, cavity; its bottom
//!   stays on its support; the mass is its own factor);
//! - `object_pose`: the object moved in x, y and yaw by `sim_host::placement` (a seeded draw
//!   that keeps 1 cm from all other collision geometry, on the table, within reach), the moved
//!   pose written into the variant's scene; an object that starts in a holder fixture (a plate
//!   in its stand) is drawn without the holder, and the holder moves with it;
//! - `support_height`: the table top and everything standing on it raised or lowered relative to
//!   the robot's mount (success rules in world heights rise with it);
//! - `friction_mass`: the object's friction and mass scaled (MuJoCo takes the larger friction of
//!   the two geoms in contact, so lowering it below the fingers' 1.2 and the table's 0.8 does
//!   little);
//! - `distractors`: one to three small objects placed by the same placement draw, redrawn
//!   (bounded) while one would stand within 6 cm of the demonstration's low TCP path;
//! - `visual`: light intensity and position, the objects' hue and the table's shade. Visual
//!   only: such a variant must reproduce its parent's trace hash exactly, or it is dropped.
//!
//! **Sweeps** first: each factor alone, level by level outward from the parent's value; its
//! feasible range ends before the first level that fails the gate. **Candidates** then combine
//! one to three factors (drawn uniformly among those with a feasible range), each value drawn
//! uniformly within its feasible range.
//!
//! **The demonstration is adapted**: every anchor of the motion (`events::anchors`: the object
//! up to its grasp, its support from the release, the thing pushed) is moved with its entity
//! (for a scaled object: its grasp point scaled about the origin; at a release, the held
//! object's scaled height below the TCP is kept), the rows between anchors take the change
//! blended by path length (the first row never moves), and the moved rows are re-solved with IK
//! under the joint limits and the scene's collision checks. Rows no anchor moves keep their
//! joints. For rigid moves this is public as [`reanchor`] (with [`Demonstration::recorded_in`]
//! and [`planar_move`]); `r2g reconstruct` uses it to carry a demonstration to reconstructed
//! objects.
//!
//! **A failed candidate is shrunk** toward its parent (every deviation halved, one distractor
//! fewer) up to `shrink_tries` times before it is dropped.
//!
//! **Near-duplicates**: two kept variants whose every parameter differs by less than
//! `dedupe_tolerance` of that parameter's feasible width (absent parameters count as the
//! parent's value, distractor counts must match and their positions lie within 3 cm); the later
//! one is removed.
//!
//! Each candidate is one self-contained unit of work over its own folder (build, then
//! [`crate::validate::validate`]); `--jobs` runs several on threads.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use controllers::ik::SplitMix64;
use controllers::safety::SafetyChecks;
use controllers::RobotModel;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use serde_json::json;
use sim_host::placement::Perturbation;
use sim_host::Scene;

use crate::events::{self, Anchor, EventsFile};
use crate::gym::{self, Staging};
use crate::validate::{self, Evidence};
use crate::{Error, Result};

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Factor {
    ObjectSize,
    ObjectPose,
    SupportHeight,
    FrictionMass,
    Distractors,
    Visual,
}

pub const FACTORS: [Factor; 6] = [
    Factor::ObjectSize,
    Factor::ObjectPose,
    Factor::SupportHeight,
    Factor::FrictionMass,
    Factor::Distractors,
    Factor::Visual,
];

impl Factor {
    pub fn name(self) -> &'static str {
        match self {
            Factor::ObjectSize => "object_size",
            Factor::ObjectPose => "object_pose",
            Factor::SupportHeight => "support_height",
            Factor::FrictionMass => "friction_mass",
            Factor::Distractors => "distractors",
            Factor::Visual => "visual",
        }
    }
}

/// A variant's parameters; `None`: the parent's.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Params {
    pub size_scale: Option<f64>,
    /// Placement ranges (m, degrees) and the seed of the draw.
    pub pose: Option<PoseDraw>,
    pub support_dz_m: Option<f64>,
    pub friction_scale: Option<f64>,
    pub mass_scale: Option<f64>,
    /// Count and the seed of their placement.
    pub distractors: Option<(usize, u64)>,
    pub light_scale: Option<f64>,
    pub light_shift_m: Option<[f64; 2]>,
    pub hue_deg: Option<f64>,
    pub table_shade: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseDraw {
    pub xy_m: f64,
    pub yaw_deg: f64,
    pub seed: u64,
    /// The share of the drawn move applied (1; halved by each shrink).
    pub fraction: f64,
}

impl Params {
    pub fn factors(&self) -> Vec<Factor> {
        let mut f = Vec::new();
        if self.size_scale.is_some() {
            f.push(Factor::ObjectSize);
        }
        if self.pose.is_some() {
            f.push(Factor::ObjectPose);
        }
        if self.support_dz_m.is_some() {
            f.push(Factor::SupportHeight);
        }
        if self.friction_scale.is_some() || self.mass_scale.is_some() {
            f.push(Factor::FrictionMass);
        }
        if self.distractors.is_some() {
            f.push(Factor::Distractors);
        }
        if self.light_scale.is_some()
            || self.light_shift_m.is_some()
            || self.hue_deg.is_some()
            || self.table_shade.is_some()
        {
            f.push(Factor::Visual);
        }
        f
    }

    pub fn visual_only(&self) -> bool {
        self.factors() == [Factor::Visual]
    }

    /// Halfway back to the parent: every deviation halved, one distractor fewer.
    pub fn shrunk(&self) -> Params {
        let half = |v: Option<f64>, parent: f64| v.map(|x| parent + 0.5 * (x - parent));
        Params {
            size_scale: half(self.size_scale, 1.0),
            pose: self.pose.clone().map(|p| PoseDraw { fraction: 0.5 * p.fraction, ..p }),
            support_dz_m: half(self.support_dz_m, 0.0),
            friction_scale: half(self.friction_scale, 1.0),
            mass_scale: half(self.mass_scale, 1.0),
            distractors: self.distractors.and_then(|(n, s)| (n > 1).then_some((n - 1, s))),
            light_scale: half(self.light_scale, 1.0),
            light_shift_m: self.light_shift_m.map(|v| [0.5 * v[0], 0.5 * v[1]]),
            hue_deg: half(self.hue_deg, 0.0),
            table_shade: half(self.table_shade, 0.0),
        }
    }
}

/// The sweeps: per parameter and side, the levels tried outward from the parent's value (the
/// last one is the edge of the search).
const SWEEPS: [(Factor, &str, &[f64]); 14] = [
    (Factor::ObjectSize, "size_scale-", &[0.9, 0.8, 0.7, 0.6]),
    (Factor::ObjectSize, "size_scale+", &[1.1, 1.2, 1.35, 1.5]),
    (Factor::ObjectPose, "pose_xy_m", &[0.02, 0.05, 0.1, 0.15, 0.2]),
    (Factor::ObjectPose, "pose_yaw_deg", &[10.0, 25.0, 45.0, 90.0]),
    (Factor::SupportHeight, "support_dz_m-", &[-0.025, -0.05, -0.1]),
    (Factor::SupportHeight, "support_dz_m+", &[0.025, 0.05, 0.1]),
    (Factor::FrictionMass, "friction_scale-", &[0.6, 0.3, 0.1]),
    (Factor::FrictionMass, "friction_scale+", &[1.5, 2.0]),
    (Factor::FrictionMass, "mass_scale-", &[0.6, 0.3]),
    (Factor::FrictionMass, "mass_scale+", &[1.5, 3.0, 10.0]),
    (Factor::Distractors, "distractors", &[1.0, 2.0, 3.0]),
    (Factor::Visual, "light_scale-", &[0.4]),
    (Factor::Visual, "light_scale+", &[1.6]),
    (Factor::Visual, "hue_deg", &[90.0, 180.0]),
];

/// One sweep level as params: `axis` (without its side) at `x`, everything else the parent's.
fn level(axis: &str, x: f64) -> Params {
    let pose = |xy_m: f64, yaw_deg: f64| Some(PoseDraw { xy_m, yaw_deg, seed: 1, fraction: 1.0 });
    let mut p = Params::default();
    match axis.trim_end_matches(['-', '+']) {
        "size_scale" => p.size_scale = Some(x),
        "pose_xy_m" => p.pose = pose(x, 0.0),
        "pose_yaw_deg" => p.pose = pose(0.0, x),
        "support_dz_m" => p.support_dz_m = Some(x),
        "friction_scale" => p.friction_scale = Some(x),
        "mass_scale" => p.mass_scale = Some(x),
        "distractors" => p.distractors = Some((x as usize, 1)),
        "light_scale" => p.light_scale = Some(x),
        "hue_deg" => p.hue_deg = Some(x),
        _ => {}
    }
    p
}

fn sweep_levels() -> Vec<(Factor, &'static str, Vec<Params>)> {
    SWEEPS.iter().map(|(f, axis, v)| (*f, *axis, v.iter().map(|x| level(axis, *x)).collect())).collect()
}

/// The value a sweep varies, read back from its params.
fn swept_value(axis: &str, p: &Params) -> f64 {
    match axis.trim_end_matches(['-', '+']) {
        "size_scale" => p.size_scale.unwrap_or(1.0),
        "pose_xy_m" => p.pose.as_ref().map(|d| d.xy_m).unwrap_or(0.0),
        "pose_yaw_deg" => p.pose.as_ref().map(|d| d.yaw_deg).unwrap_or(0.0),
        "support_dz_m" => p.support_dz_m.unwrap_or(0.0),
        "friction_scale" => p.friction_scale.unwrap_or(1.0),
        "mass_scale" => p.mass_scale.unwrap_or(1.0),
        "distractors" => p.distractors.map(|d| d.0 as f64).unwrap_or(0.0),
        "light_scale" => p.light_scale.unwrap_or(1.0),
        "hue_deg" => p.hue_deg.unwrap_or(0.0),
        _ => f64::NAN,
    }
}

/// Feasible ranges found by the sweeps: parameter → [low, high] (the parent's value inside).
pub type Ranges = BTreeMap<String, [f64; 2]>;

fn parent_value(param: &str) -> f64 {
    match param {
        "size_scale" | "friction_scale" | "mass_scale" | "light_scale" => 1.0,
        _ => 0.0,
    }
}

#[derive(Clone)]
pub struct Options {
    pub candidates: usize,
    pub seed: u64,
    pub out: PathBuf,
    pub jobs: usize,
    pub shrink_tries: usize,
    pub dedupe_tolerance: f64,
    pub sheet: bool,
    /// The factors varied (default: all of [`FACTORS`]).
    pub factors: Vec<Factor>,
    /// At most this many sweep levels per parameter and side, nearest the parent first.
    pub max_levels: usize,
    /// How each candidate folder is judged (default: [`in_process`]).
    pub validator: Validator,
}

impl Options {
    pub fn new(out: PathBuf) -> Self {
        Self {
            candidates: 50,
            seed: 1,
            out,
            jobs: 1,
            shrink_tries: 2,
            dedupe_tolerance: 0.05,
            sheet: true,
            factors: FACTORS.to_vec(),
            max_levels: usize::MAX,
            validator: in_process(),
        }
    }
}

/// A demonstration with what its re-anchoring needs: the scene it was recorded in, its rows,
/// the robot, the anchors of its motion (`events::anchors`, from the demonstration's native
/// replay in that scene) and the TCP pose of every row.
pub struct Demonstration {
    /// The scene the demonstration was recorded in (where its anchors' entities stand).
    pub scene: Scene,
    /// The demonstration's rows: 7 joint angles (rad) and the gripper command.
    pub rows: Vec<[f64; 8]>,
    pub robot: RobotModel,
    pub anchors: Vec<Anchor>,
    /// TCP per row, world frame.
    pub tcp_world: Vec<Isometry3<f64>>,
    pub world_from_base: Isometry3<f64>,
}

impl Demonstration {
    /// From a scene whose demonstration passed the gate: `pev` and `native` are what
    /// [`validate::validate_native`] returned for `scene_path`.
    fn from_native(scene_path: &Path, scene: Scene, pev: &Evidence, native: &crate::replay::Native) -> Result<Self> {
        let rows = lockstep::read_demo(scene.task.demonstration.as_deref().ok_or_else(|| err("no demonstration"))?)?;
        let row_at = |t: f64| native.row_at(t);
        let anchors = events::anchors(&pev.native_events, &row_at);
        let (robot, _) = runtime::scene_robot(scene_path)?;
        let world_from_base = Isometry3::from_parts(
            Translation3::new(
                scene.robot.base_position_m[0],
                scene.robot.base_position_m[1],
                scene.robot.base_position_m[2],
            ),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), scene.robot.base_yaw_rad),
        );
        let tcp_world = rows
            .iter()
            .map(|r| world_from_base * robot.kin.fk(&std::array::from_fn(|j| r[j]), robot.kin.tcp))
            .collect();
        Ok(Self { scene, rows, robot, anchors, tcp_world, world_from_base })
    }

    /// The demonstration of the gym at `scene_path`, with its anchors: the gym is validated
    /// natively (the gate's replay, its evidence written under `out`) and must pass, since the
    /// anchors come from the events of a successful run.
    pub fn recorded_in(scene_path: &Path, out: &Path) -> Result<(Self, Evidence)> {
        let scene = Scene::load(scene_path).map_err(|e| Error::Episode(e.into()))?;
        let (pev, _, native) = validate::validate_native(scene_path, &validate::Options::new(out.to_path_buf()))?;
        if !pev.success {
            return Err(err(format!(
                "the demonstration's own scene {} fails the gate ({}): its anchors cannot be trusted",
                scene_path.display(),
                failed_checks(&pev)
            )));
        }
        Ok((Self::from_native(scene_path, scene, &pev, &native)?, pev))
    }
}

/// Re-anchors a demonstration to entities that stand elsewhere: `moves` gives, per entity of
/// the demonstration's scene (by its name there), the rigid move (world frame) that carries its
/// recorded pose to its new one. Every anchor of the motion on a moved entity follows it, the
/// rows between anchors take the change blended by path length (row 0 never moves), and the
/// moved rows are re-solved by IK under the joint limits and the collision checks of the scene
/// at `target_scene` (the scene the rows will run in). Rows that no anchor moves keep their
/// joints. Entities absent from `moves` stay where they were. This is the adaptation
/// `r2g augment` applies to every variant; `r2g reconstruct` uses it for a demonstration
/// recorded in another arrangement of the reconstructed objects.
pub fn reanchor(
    demo: &Demonstration,
    moves: &BTreeMap<String, Isometry3<f64>>,
    target_scene: &Path,
) -> Result<Vec<[f64; 8]>> {
    let (_, safety) = runtime::scene_robot(target_scene)?;
    let changes: BTreeMap<String, Change> =
        moves.iter().map(|(k, m)| (k.clone(), Change { moved: *m, scale: None })).collect();
    adapt(demo, &changes, &safety)
        .map_err(|(row, why)| err(format!("the demonstration cannot follow: row {row}: {why}")))
}

/// The rigid move (world frame) that carries the point `from_m` to `to_m` and turns what is
/// around it by `yaw_rad` about the vertical through it: an entity's move from its recorded
/// reference point to its new one, in the form [`reanchor`] takes.
pub fn planar_move(from_m: [f64; 3], to_m: [f64; 3], yaw_rad: f64) -> Isometry3<f64> {
    Isometry3::translation(to_m[0], to_m[1], to_m[2])
        * Isometry3::rotation(Vector3::z() * yaw_rad)
        * Isometry3::translation(-from_m[0], -from_m[1], -from_m[2])
}

/// What the parent gives every variant.
struct Parent {
    scene_path: PathBuf,
    dir_name: String,
    /// The parent's scene, rows, robot, anchors and TCP path.
    demo: Demonstration,
    source: Vec<events::SourceGrasp>,
    source_kind: String,
    /// The parent's native grasps: each variant must grasp as it did (`events.json`'s `native`).
    grasps: Vec<events::Interval>,
    trace_sha256: String,
    object: String,
    /// A fixture the object starts in (a holder), moved along with it.
    carrier: Option<String>,
}

/// How an entity changes: a rigid move of its start pose, and for a scaled object its scale,
/// origin and lowest point (object frame z).
#[derive(Debug, Clone, Copy)]
struct Change {
    moved: Isometry3<f64>,
    scale: Option<(f64, Point3<f64>, f64)>,
}

impl Change {
    fn none() -> Self {
        Self { moved: Isometry3::identity(), scale: None }
    }

    /// The rigid change that carries the point `p` (world) with the entity.
    fn at(&self, p: &Point3<f64>) -> Isometry3<f64> {
        match self.scale {
            None => self.moved,
            Some((s, origin, _)) => {
                let scaled = origin + s * (p - origin);
                let q = self.moved * scaled;
                Isometry3::from_parts(Translation3::from(q - p), UnitQuaternion::identity())
            }
        }
    }
}

/// One candidate's outcome.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    pub name: String,
    pub factors: Vec<Factor>,
    /// Every attempt: its params, whether it passed and, when not, why.
    pub attempts: Vec<(Params, bool, String)>,
    pub kept: bool,
    pub shrinks: usize,
    pub diff: serde_json::Value,
    pub trace_sha256: Option<String>,
    #[serde(skip)]
    pub staged: Option<PathBuf>,
    /// Normalised parameter vector for the near-duplicate test.
    #[serde(skip)]
    pub signature: Vec<f64>,
    #[serde(skip)]
    pub distractor_xy: Vec<[f64; 2]>,
}

fn err(why: impl Into<String>) -> Error {
    Error::Episode(anyhow::anyhow!(why.into()))
}

fn arr3(v: &toml::Value) -> Option<[f64; 3]> {
    let a = v.as_array()?;
    let f = |i: usize| a.get(i).and_then(|x| x.as_float().or_else(|| x.as_integer().map(|n| n as f64)));
    Some([f(0)?, f(1)?, f(2)?])
}

fn farr(v: &[f64]) -> toml::Value {
    toml::Value::Array(v.iter().map(|x| toml::Value::Float(*x)).collect())
}

fn object_mut<'a>(t: &'a mut toml::Table, name: &str) -> Option<&'a mut toml::Table> {
    t.get_mut("objects")?
        .as_array_mut()?
        .iter_mut()
        .filter_map(|o| o.as_table_mut())
        .find(|o| o.get("name").and_then(|n| n.as_str()) == Some(name))
}

fn scale_array(v: &mut toml::Value, s: f64) {
    if let Some(a) = v.as_array_mut() {
        for x in a.iter_mut() {
            if let Some(f) = x.as_float().or_else(|| x.as_integer().map(|n| n as f64)) {
                *x = toml::Value::Float(f * s);
            }
        }
    }
}

/// Rotates an RGBA colour's hue by `deg` (about the grey axis).
fn hue(rgba: [f64; 4], deg: f64) -> [f64; 4] {
    let (c, s) = (deg.to_radians().cos(), deg.to_radians().sin());
    let k = 1.0 / 3.0f64.sqrt();
    let v = Vector3::new(rgba[0], rgba[1], rgba[2]);
    let axis = Vector3::new(k, k, k);
    let r = v * c + axis.cross(&v) * s + axis * axis.dot(&v) * (1.0 - c);
    [r.x.clamp(0.0, 1.0), r.y.clamp(0.0, 1.0), r.z.clamp(0.0, 1.0), rgba[3]]
}

fn rgba_of(v: Option<&toml::Value>, default: [f64; 4]) -> [f64; 4] {
    v.and_then(|v| v.as_array())
        .map(|a| {
            std::array::from_fn(|i| {
                a.get(i).and_then(|x| x.as_float().or_else(|| x.as_integer().map(|n| n as f64))).unwrap_or(default[i])
            })
        })
        .unwrap_or(default)
}

/// A variant built in a staging folder, before validation.
struct Built {
    staging: Staging,
    diff: serde_json::Value,
    distractor_xy: Vec<[f64; 2]>,
    pose_move: Option<[f64; 3]>,
}

fn draw_placement(
    staging: &Staging,
    table: &toml::Table,
    objects: Vec<String>,
    xy_m: f64,
    yaw_deg: f64,
    seed: u64,
) -> Result<Vec<(String, [f64; 3], [f64; 4])>> {
    let path = staging.write("scene.toml", toml::to_string(table).map_err(|e| err(e.to_string()))?.as_bytes())?;
    let mut sim = sim_host::Sim::load(&path).map_err(|e| Error::Episode(e.into()))?;
    sim.seed = seed.max(1);
    sim.set_perturbation(Some(Perturbation { xy_m, yaw_deg, objects })).map_err(|e| err(e.to_string()))?;
    let placed = sim.placed.clone().ok_or_else(|| err("the placement draw placed nothing"))?;
    if let Some(note) = placed.note {
        return Err(err(note));
    }
    Ok(placed.objects)
}

fn yaw_of(q: [f64; 4]) -> f64 {
    let r = gym::pose_wxyz([0.0; 3], q).rotation;
    r.euler_angles().2
}

/// Builds a variant of the parent with `params` in a staging folder beside `out`.
fn build(parent: &Parent, params: &Params, out: &Path) -> Result<Built> {
    let staging = Staging::new(out)?;
    let mut t = gym::rebased_scene(&parent.scene_path, &staging.dir)?;
    // The parent's demonstration first: the scene must load for the placement draws.
    lockstep::write_demo(&staging.dir.join("demo.csv"), &parent.demo.rows)?;
    let obj = parent.object.clone();
    let spec =
        parent.demo.scene.objects.iter().find(|o| o.name == obj).ok_or_else(|| err(format!("no object '{obj}'")))?;
    let old_pose = gym::pose_wxyz(spec.position_m, spec.quat_wxyz);
    let mut changes: BTreeMap<String, Change> = BTreeMap::new();
    let mut diff = serde_json::Map::new();
    let mut obj_change = Change::none();
    if let Some(s) = params.size_scale {
        // The lowest point (world vertical) stays where it was: the object still stands on its support.
        let (lo, _) = gym::vertical_extent(spec)
            .ok_or_else(|| err(format!("object '{obj}' has no primitive bounds to scale")))?;
        let o = object_mut(&mut t, &obj).ok_or_else(|| err("object vanished"))?;
        if let Some(v) = o.get_mut("size_m") {
            scale_array(v, s);
        }
        for part in o.get_mut("parts").and_then(|p| p.as_array_mut()).into_iter().flatten() {
            for key in ["size_m", "position_m", "mesh_scale"] {
                if let Some(v) = part.get_mut(key) {
                    scale_array(v, s);
                }
            }
        }
        for key in ["cavity_min_m", "cavity_max_m"] {
            if let Some(v) = o.get_mut(key) {
                scale_array(v, s);
            }
        }
        let mut p = spec.position_m;
        p[2] += (1.0 - s) * lo;
        o.insert("position_m".into(), farr(&p));
        obj_change = Change {
            moved: Isometry3::translation(0.0, 0.0, (1.0 - s) * lo),
            scale: Some((s, Point3::from(spec.position_m), lo)),
        };
        diff.insert("size_scale".into(), json!({"parent": 1.0, "value": s}));
    }
    if let Some(dz) = params.support_dz_m {
        if let Some(top) = t.get_mut("table").and_then(|v| v.get_mut("top_center_m")) {
            if let Some(mut a) = arr3(top) {
                a[2] += dz;
                *top = farr(&a);
            }
        }
        // Success rules in world heights (`past` along z, `inside` a world box) rise with the
        // table: the task is the same relative to it.
        let mut shifted = 0;
        for rule in t
            .get_mut("task")
            .and_then(|v| v.get_mut("success"))
            .and_then(|v| v.as_array_mut())
            .into_iter()
            .flatten()
            .filter_map(|r| r.as_table_mut())
        {
            match rule.get("kind").and_then(|k| k.as_str()) {
                Some("past") if rule.get("axis").and_then(|a| a.as_integer()) == Some(2) => {
                    for key in ["above", "below"] {
                        if let Some(v) =
                            rule.get(key).and_then(|v| v.as_float().or_else(|| v.as_integer().map(|n| n as f64)))
                        {
                            rule.insert(key.into(), toml::Value::Float(v + dz));
                            shifted += 1;
                        }
                    }
                }
                Some("inside") => {
                    for key in ["min_m", "max_m"] {
                        if let Some(mut a) = rule.get(key).and_then(arr3) {
                            a[2] += dz;
                            rule.insert(key.into(), farr(&a));
                            shifted += 1;
                        }
                    }
                }
                _ => {}
            }
        }
        if shifted > 0 {
            diff.insert("success_heights_shifted_m".into(), json!({"values": shifted, "by": dz}));
        }
        for key in ["objects", "fixtures"] {
            for item in t.get_mut(key).and_then(|v| v.as_array_mut()).into_iter().flatten() {
                if let Some(p) = item.get_mut("position_m") {
                    if let Some(mut a) = arr3(p) {
                        a[2] += dz;
                        *p = farr(&a);
                    }
                }
            }
        }
        if let Some(s) = t.get_mut("safety").and_then(|v| v.as_table_mut()) {
            for key in ["workspace_min_m", "workspace_max_m"] {
                if let Some(p) = s.get_mut(key) {
                    if let Some(mut a) = arr3(p) {
                        a[2] += dz;
                        *p = farr(&a);
                    }
                }
            }
        }
        let up = Isometry3::translation(0.0, 0.0, dz);
        for e in
            parent.demo.scene.objects.iter().map(|o| &o.name).chain(parent.demo.scene.fixtures.iter().map(|f| &f.name))
        {
            changes.insert(e.clone(), Change { moved: up, scale: None });
        }
        obj_change.moved = up * obj_change.moved;
        diff.insert("support_dz_m".into(), json!({"parent": 0.0, "value": dz}));
    }
    let mut pose_move = None;
    if let Some(d) = &params.pose {
        // An object that starts in a holder moves with it: the draw is made without the holder
        // (it would otherwise be within the clearance of any place), the holder follows.
        let mut draw_scene = t.clone();
        if let Some(c) = &parent.carrier {
            if let Some(fx) = draw_scene.get_mut("fixtures").and_then(|v| v.as_array_mut()) {
                fx.retain(|f| f.get("name").and_then(|n| n.as_str()) != Some(c.as_str()));
            }
        }
        let placed = draw_placement(&staging, &draw_scene, vec![obj.clone()], d.xy_m, d.yaw_deg, d.seed)?;
        let (_, pos, quat) =
            placed.into_iter().find(|p| p.0 == obj).ok_or_else(|| err("the draw did not move the object"))?;
        let o = object_mut(&mut t, &obj).ok_or_else(|| err("object vanished"))?;
        let written = o.get("position_m").and_then(arr3).unwrap_or(spec.position_m);
        let f = d.fraction;
        let new_p = [written[0] + f * (pos[0] - written[0]), written[1] + f * (pos[1] - written[1]), written[2]];
        let dyaw = f * (yaw_of(quat) - yaw_of(spec.quat_wxyz));
        let new_q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), dyaw) * old_pose.rotation;
        o.insert("position_m".into(), farr(&new_p));
        o.insert("quat_wxyz".into(), farr(&[new_q.w, new_q.i, new_q.j, new_q.k]));
        // About the object's (possibly already moved) origin.
        let origin = Point3::from(written);
        let turn = Isometry3::from_parts(
            Translation3::from(origin.coords),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), dyaw),
        ) * Isometry3::from_parts(Translation3::from(-origin.coords), UnitQuaternion::identity());
        let shift = Isometry3::translation(new_p[0] - written[0], new_p[1] - written[1], 0.0);
        obj_change.moved = shift * turn * obj_change.moved;
        if let Some(c) = &parent.carrier {
            let moved = shift * turn;
            let fx = t
                .get_mut("fixtures")
                .and_then(|v| v.as_array_mut())
                .and_then(|a| a.iter_mut().find(|f| f.get("name").and_then(|n| n.as_str()) == Some(c.as_str())))
                .and_then(|f| f.as_table_mut())
                .ok_or_else(|| err(format!("holder '{c}' vanished")))?;
            let fp = fx.get("position_m").and_then(arr3).unwrap_or([0.0; 3]);
            let fq = rgba_of(fx.get("quat_wxyz"), [1.0, 0.0, 0.0, 0.0]);
            let new = moved * gym::pose_wxyz(fp, fq);
            let (v, q) = (new.translation.vector, new.rotation);
            fx.insert("position_m".into(), farr(&[v.x, v.y, v.z]));
            fx.insert("quat_wxyz".into(), farr(&[q.w, q.i, q.j, q.k]));
            let prior = changes.get(c).map(|ch| ch.moved).unwrap_or(Isometry3::identity());
            changes.insert(c.clone(), Change { moved: moved * prior, scale: None });
            diff.insert("holder_moved_with_object".into(), json!(c));
        }
        pose_move = Some([new_p[0] - written[0], new_p[1] - written[1], dyaw.to_degrees()]);
        diff.insert(
            "object_pose".into(),
            json!({"parent": {"position_m": written, "yaw_deg": yaw_of(spec.quat_wxyz).to_degrees()},
                   "value": {"position_m": new_p, "yaw_deg": yaw_of([new_q.w, new_q.i, new_q.j, new_q.k]).to_degrees()},
                   "draw": {"xy_m": d.xy_m, "yaw_deg": d.yaw_deg, "seed": d.seed, "fraction": f}}),
        );
    }
    changes.insert(obj.clone(), obj_change);
    if let Some(fs) = params.friction_scale {
        let o = object_mut(&mut t, &obj).ok_or_else(|| err("object vanished"))?;
        o.insert("friction".into(), toml::Value::Float(spec.friction * fs));
        diff.insert("friction".into(), json!({"parent": spec.friction, "value": spec.friction * fs}));
    }
    if let Some(ms) = params.mass_scale {
        let o = object_mut(&mut t, &obj).ok_or_else(|| err("object vanished"))?;
        o.insert("mass_kg".into(), toml::Value::Float(spec.mass_kg * ms));
        diff.insert("mass_kg".into(), json!({"parent": spec.mass_kg, "value": spec.mass_kg * ms}));
    }
    let mut distractor_xy = Vec::new();
    if let Some((n, seed)) = params.distractors {
        let centre = parent.demo.scene.table.as_ref().map(|tb| tb.top_center_m).unwrap_or([0.45, 0.0, 0.0]);
        let top_z = centre[2] + params.support_dz_m.unwrap_or(0.0);
        let mut rng = SplitMix64::new(seed ^ 0xD157_AC70);
        let names: Vec<String> = (0..n).map(|k| format!("distractor{k}")).collect();
        let mut added = Vec::new();
        for name in &names {
            let box_shape = rng.next_f64() < 0.5;
            let half = 0.012 + 0.01 * rng.next_f64();
            let rgba = [rng.next_f64(), rng.next_f64(), rng.next_f64(), 1.0];
            let mut o = toml::Table::new();
            o.insert("name".into(), toml::Value::String(name.clone()));
            o.insert("shape".into(), toml::Value::String(if box_shape { "box" } else { "cylinder" }.into()));
            o.insert("size_m".into(), farr(&if box_shape { vec![half, half, half] } else { vec![half, half] }));
            o.insert("position_m".into(), farr(&[centre[0], centre[1], top_z + half]));
            o.insert("mass_kg".into(), toml::Value::Float(0.05));
            o.insert("rgba".into(), farr(&rgba));
            added.push(json!({"name": name, "shape": if box_shape { "box" } else { "cylinder" }, "half_size_m": half}));
            t.get_mut("objects")
                .and_then(|v| v.as_array_mut())
                .ok_or_else(|| err("scene has no objects"))?
                .push(toml::Value::Table(o));
        }
        // Placed by the shared draw; redrawn while one would stand on the demonstration's low path.
        let low_path: Vec<[f64; 2]> = parent
            .demo
            .tcp_world
            .iter()
            .filter(|p| p.translation.vector.z < top_z + 0.15)
            .map(|p| [p.translation.vector.x, p.translation.vector.y])
            .collect();
        let mut placed = None;
        for attempt in 0..10u64 {
            let p = draw_placement(
                &staging,
                &t,
                names.clone(),
                0.3,
                180.0,
                seed.wrapping_mul(31).wrapping_add(attempt + 1),
            )?;
            let clear =
                p.iter().all(|(_, pos, _)| low_path.iter().all(|q| (q[0] - pos[0]).hypot(q[1] - pos[1]) > 0.06));
            if clear {
                placed = Some(p);
                break;
            }
        }
        let placed =
            placed.ok_or_else(|| err("no distractor placement clear of the demonstration's path in 10 draws"))?;
        for (name, pos, quat) in &placed {
            let o = object_mut(&mut t, name).ok_or_else(|| err("distractor vanished"))?;
            o.insert("position_m".into(), farr(pos));
            o.insert("quat_wxyz".into(), farr(quat));
            distractor_xy.push([pos[0], pos[1]]);
        }
        diff.insert("distractors".into(), json!({"parent": 0, "value": n, "objects": added, "placed": placed}));
    }
    if params.light_scale.is_some() || params.light_shift_m.is_some() {
        let k = params.light_scale.unwrap_or(1.0);
        let d = params.light_shift_m.unwrap_or([0.0, 0.0]);
        let mut l = toml::Table::new();
        // The default key light (sim-host's MJCF when a scene names none), changed.
        l.insert("position_m".into(), farr(&[0.4 + d[0], -0.6 + d[1], 2.0]));
        l.insert("direction".into(), farr(&[-0.1, 0.3, -1.0]));
        l.insert("diffuse".into(), farr(&[(0.6 * k).min(1.0); 3]));
        if t.get("lights").and_then(|v| v.as_array()).is_none_or(|a| a.is_empty()) {
            t.insert("lights".into(), toml::Value::Array(vec![toml::Value::Table(l)]));
        } else {
            for light in t.get_mut("lights").and_then(|v| v.as_array_mut()).into_iter().flatten() {
                if let Some(v) = light.get_mut("diffuse") {
                    scale_array(v, k);
                }
                if let Some(p) = light.get_mut("position_m") {
                    if let Some(mut a) = arr3(p) {
                        a[0] += d[0];
                        a[1] += d[1];
                        *p = farr(&a);
                    }
                }
            }
        }
        diff.insert(
            "light".into(),
            json!({"parent": {"scale": 1.0, "shift_m": [0.0, 0.0]}, "value": {"scale": k, "shift_m": d}}),
        );
    }
    if let Some(h) = params.hue_deg {
        for o in t.get_mut("objects").and_then(|v| v.as_array_mut()).into_iter().flatten() {
            let rgba = rgba_of(o.get("rgba"), [0.8, 0.2, 0.2, 1.0]);
            if let Some(tb) = o.as_table_mut() {
                tb.insert("rgba".into(), farr(&hue(rgba, h)));
                for part in tb.get_mut("parts").and_then(|p| p.as_array_mut()).into_iter().flatten() {
                    if let Some(pt) = part.as_table_mut() {
                        if let Some(c) = pt.get("rgba").cloned() {
                            pt.insert("rgba".into(), farr(&hue(rgba_of(Some(&c), [0.8, 0.2, 0.2, 1.0]), h)));
                        }
                    }
                }
            }
        }
        diff.insert("hue_deg".into(), json!({"parent": 0.0, "value": h}));
    }
    if let Some(sh) = params.table_shade {
        if let Some(tb) = t.get_mut("table").and_then(|v| v.as_table_mut()) {
            let c = rgba_of(tb.get("rgba"), [0.55, 0.42, 0.30, 1.0]);
            tb.insert(
                "rgba".into(),
                farr(&[(c[0] + sh).clamp(0.0, 1.0), (c[1] + sh).clamp(0.0, 1.0), (c[2] + sh).clamp(0.0, 1.0), c[3]]),
            );
        }
        diff.insert("table_shade".into(), json!({"parent": 0.0, "value": sh}));
    }
    // The demonstration, adapted to the moved anchors, checked against this variant's table.
    let path = staging.write("scene.toml", toml::to_string(&t).map_err(|e| err(e.to_string()))?.as_bytes())?;
    let (_, safety) = runtime::scene_robot(&path)?;
    let rows = adapt(&parent.demo, &changes, &safety)
        .map_err(|(row, why)| err(format!("the demonstration cannot follow: row {row}: {why}")))?;
    let moved_rows = rows.iter().zip(&parent.demo.rows).filter(|(a, b)| a != b).count();
    diff.insert("demonstration".into(), json!({"rows": rows.len(), "rows_re_solved": moved_rows}));
    let text = format!(
        "# Variant of {} made by `r2g augment` (see variant.json).\n{}",
        parent.dir_name,
        toml::to_string(&t).map_err(|e| err(e.to_string()))?
    );
    staging.write("scene.toml", text.as_bytes())?;
    lockstep::write_demo(&staging.dir.join("demo.csv"), &rows)?;
    let events = EventsFile {
        params: events::Params::default(),
        source_kind: format!("{} (from {})", parent.source_kind, parent.dir_name),
        source: parent.source.clone(),
        native: parent.grasps.clone(),
        anchors: parent.demo.anchors.clone(),
    };
    staging.write("events.json", &serde_json::to_vec_pretty(&events).map_err(|e| err(e.to_string()))?)?;
    Ok(Built { staging, diff: serde_json::Value::Object(diff), distractor_xy, pose_move })
}

/// The parent's rows with every anchor's change applied and the moved rows re-solved.
fn adapt(
    demo: &Demonstration,
    changes: &BTreeMap<String, Change>,
    safety: &SafetyChecks,
) -> std::result::Result<Vec<[f64; 8]>, (usize, String)> {
    let n = demo.rows.len();
    let tcp = &demo.tcp_world;
    // The change at each anchor row.
    let mut keys: Vec<(usize, Isometry3<f64>)> = Vec::new();
    let mut grasp_height: BTreeMap<String, f64> = BTreeMap::new();
    for a in &demo.anchors {
        let p = Point3::from(tcp[a.row].translation.vector);
        let change = changes.get(&a.entity).copied().unwrap_or(Change::none());
        let mut delta = change.at(&p);
        if a.released.is_none() {
            if let Some(spec) = demo.scene.objects.iter().find(|o| o.name == a.entity) {
                grasp_height.insert(a.entity.clone(), p.z - spec.position_m[2]);
            }
        }
        if let Some(held) = &a.released {
            // The held object's part below the TCP grows or shrinks with it.
            if let (Some(Change { scale: Some((s, _, lo)), .. }), Some(h)) = (changes.get(held), grasp_height.get(held))
            {
                delta = Isometry3::translation(0.0, 0.0, (s - 1.0) * (h - lo)) * delta;
            }
        }
        keys.push((a.row, delta));
    }
    if keys.iter().all(|(_, d)| d.translation.vector.norm() < 1e-12 && d.rotation.angle() < 1e-12) {
        return Ok(demo.rows.clone());
    }
    // Path length from row 0, for blending between keys.
    let mut s = vec![0.0; n];
    for k in 1..n {
        s[k] = s[k - 1] + (tcp[k].translation.vector - tcp[k - 1].translation.vector).norm();
    }
    let smooth = |x: f64| {
        let x = x.clamp(0.0, 1.0);
        x * x * x * (10.0 - 15.0 * x + 6.0 * x * x)
    };
    let blend = |a: &Isometry3<f64>, b: &Isometry3<f64>, w: f64| {
        Isometry3::from_parts(
            Translation3::from(a.translation.vector.lerp(&b.translation.vector, w)),
            a.rotation.slerp(&b.rotation, w),
        )
    };
    let mut chain: Vec<(usize, Isometry3<f64>)> = vec![(0, Isometry3::identity())];
    chain.extend(keys.iter().copied());
    let delta_at = |r: usize| -> Isometry3<f64> {
        let i = chain.iter().rposition(|(row, _)| *row <= r).unwrap_or(0);
        if i + 1 >= chain.len() {
            return chain[i].1;
        }
        let ((r0, d0), (r1, d1)) = (chain[i], chain[i + 1]);
        let span = s[r1] - s[r0];
        let w = if span > 1e-9 {
            (s[r] - s[r0]) / span
        } else if r1 > r0 {
            (r - r0) as f64 / (r1 - r0) as f64
        } else {
            1.0
        };
        blend(&d0, &d1, smooth(w))
    };
    let base_from_world = demo.world_from_base.inverse();
    let mut out = demo.rows.clone();
    let mut targets = Vec::new();
    let mut idx = Vec::new();
    for r in 0..n {
        let d = delta_at(r);
        if d.translation.vector.norm() < 1e-9 && d.rotation.angle() < 1e-9 {
            continue;
        }
        targets.push(base_from_world * d * tcp[r]);
        idx.push(r);
    }
    // Solve the moved rows as one path (consecutive moved rows seed each other).
    let mut start = 0;
    while start < idx.len() {
        let mut end = start + 1;
        while end < idx.len() && idx[end] == idx[end - 1] + 1 {
            end += 1;
        }
        let seed: [f64; 7] = std::array::from_fn(|j| demo.rows[idx[start]][j]);
        let (sol, _) = crate::retarget::solve_path(&demo.robot, safety, &targets[start..end], seed, 0.0)
            .map_err(|(k, why)| (idx[start + k], why))?;
        for (k, qs) in sol.iter().enumerate() {
            let r = idx[start + k];
            out[r] = [qs[0], qs[1], qs[2], qs[3], qs[4], qs[5], qs[6], demo.rows[r][7]];
        }
        start = end;
    }
    Ok(out)
}

/// Builds and validates one candidate, shrinking it toward the parent on failure.
fn run_candidate(
    parent: &Parent,
    name: String,
    params: Params,
    tries: usize,
    pool_dir: &Path,
    validator: &Validator,
) -> Outcome {
    let mut attempts = Vec::new();
    let mut p = params.clone();
    let factors = params.factors();
    for shrinks in 0..=tries {
        // Built beside where it stays: its scene's relative paths are rebased for that folder.
        let dir = pool_dir.join(&name);
        let _ = std::fs::remove_dir_all(&dir);
        let result = build(parent, &p, &dir).and_then(|b| {
            let ev = validator(&b.staging.dir)?;
            Ok((b, ev))
        });
        match result {
            Ok((b, ev)) => {
                let visual_ok = !p.visual_only() || ev.trace_sha256 == parent.trace_sha256;
                if ev.success && visual_ok {
                    let variant = json!({"parent": parent.dir_name, "parent_scene": parent.scene_path.display().to_string(),
                        "factors": factors, "params": p, "diff": b.diff, "shrinks": shrinks,
                        "trace_sha256": ev.trace_sha256, "inputs_sha256": ev.inputs_sha256,
                        "visual_only_trace_matches_parent": p.visual_only().then_some(visual_ok)});
                    let staged =
                        b.staging.write("variant.json", &serde_json::to_vec_pretty(&variant).unwrap_or_default()).ok();
                    let committed = staged.and_then(|_| b.staging.commit().ok());
                    attempts.push((p.clone(), true, String::new()));
                    return Outcome {
                        name,
                        factors,
                        attempts,
                        kept: committed.is_some(),
                        shrinks,
                        diff: b.diff,
                        trace_sha256: Some(ev.trace_sha256),
                        staged: committed,
                        signature: Vec::new(),
                        distractor_xy: b.distractor_xy,
                    }
                    .with_pose(b.pose_move, &p);
                }
                let why = if !visual_ok {
                    "visual-only variant changed the physics (trace hash differs from the parent's)".to_string()
                } else {
                    ev.failed.clone()
                };
                attempts.push((p.clone(), false, why));
            }
            Err(e) => attempts.push((p.clone(), false, format!("{e:#}"))),
        }
        p = p.shrunk();
        if p.factors().is_empty() {
            break;
        }
    }
    Outcome {
        name,
        factors,
        attempts,
        kept: false,
        shrinks: tries,
        diff: json!(null),
        trace_sha256: None,
        staged: None,
        signature: Vec::new(),
        distractor_xy: Vec::new(),
    }
}

impl Outcome {
    fn with_pose(mut self, pose_move: Option<[f64; 3]>, p: &Params) -> Self {
        // Raw values; normalised against the feasible ranges when deduplicating.
        let m = pose_move.unwrap_or([0.0; 3]);
        self.signature = vec![
            p.size_scale.unwrap_or(1.0),
            m[0],
            m[1],
            m[2],
            p.support_dz_m.unwrap_or(0.0),
            p.friction_scale.unwrap_or(1.0),
            p.mass_scale.unwrap_or(1.0),
            p.distractors.map(|d| d.0 as f64).unwrap_or(0.0),
            p.light_scale.unwrap_or(1.0),
            p.light_shift_m.map(|v| v[0]).unwrap_or(0.0),
            p.light_shift_m.map(|v| v[1]).unwrap_or(0.0),
            p.hue_deg.unwrap_or(0.0),
            p.table_shade.unwrap_or(0.0),
        ];
        self
    }
}

/// What a validator reports of a variant folder.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    pub success: bool,
    pub trace_sha256: String,
    pub inputs_sha256: String,
    /// The failed checks and their values, `; `-separated.
    pub failed: String,
}

impl Verdict {
    /// From an `evidence.json` (what `r2g validate <dir> --out <dir>` writes), for validators
    /// that run elsewhere.
    pub fn from_evidence(v: &serde_json::Value) -> Self {
        let failed = v["checks"]
            .as_object()
            .map(|c| {
                c.iter()
                    .filter(|(_, c)| c["pass"] != true)
                    .map(|(k, c)| format!("{k}: {}", c["value"]))
                    .collect::<Vec<_>>()
                    .join("; ")
            })
            .unwrap_or_default();
        Self {
            success: v["success"] == true,
            trace_sha256: v["trace_sha256"].as_str().unwrap_or_default().into(),
            inputs_sha256: v["inputs_sha256"].as_str().unwrap_or_default().into(),
            failed,
        }
    }
}

/// The gate as augmentation calls it: a variant folder in, its verdict out (its evidence
/// written into the folder). One unit of work, no state shared between calls.
pub type Validator = std::sync::Arc<dyn Fn(&Path) -> Result<Verdict> + Send + Sync>;

/// [`validate::validate`] in this process, seed 0, evidence into the folder.
pub fn in_process() -> Validator {
    std::sync::Arc::new(|dir: &Path| {
        let (ev, _) = validate::validate(&dir.join("scene.toml"), &validate::Options::new(dir.to_path_buf()))?;
        Ok(Verdict {
            success: ev.success,
            trace_sha256: ev.trace_sha256.clone(),
            inputs_sha256: ev.inputs_sha256.clone(),
            failed: failed_checks(&ev),
        })
    })
}

fn failed_checks(ev: &Evidence) -> String {
    ev.checks.iter().filter(|(_, c)| !c.pass).map(|(k, c)| format!("{k}: {}", c.value)).collect::<Vec<_>>().join("; ")
}

/// Widths of the signature's entries for the near-duplicate test.
fn widths(r: &Ranges) -> Vec<f64> {
    let w = |k: &str, fallback: f64| r.get(k).map(|v| v[1] - v[0]).filter(|v| *v > 1e-9).unwrap_or(fallback);
    let xy = 2.0 * w("pose_xy_m", 0.2);
    vec![
        w("size_scale", 0.9),
        xy,
        xy,
        2.0 * w("pose_yaw_deg", 90.0),
        w("support_dz_m", 0.2),
        w("friction_scale", 1.9),
        w("mass_scale", 9.7),
        3.0,
        w("light_scale", 1.2),
        1.2,
        1.2,
        360.0,
        0.5,
    ]
}

/// Runs units of work on `jobs` threads in index order of completion-independent results.
fn parallel<T: Send, R: Send>(items: Vec<T>, jobs: usize, f: impl Fn(T) -> R + Sync) -> Vec<R> {
    let n = items.len();
    let queue: Mutex<Vec<(usize, T)>> = Mutex::new(items.into_iter().enumerate().rev().collect());
    let results: Mutex<Vec<Option<R>>> = Mutex::new((0..n).map(|_| None).collect());
    let done = AtomicUsize::new(0);
    std::thread::scope(|s| {
        for _ in 0..jobs.max(1).min(n.max(1)) {
            s.spawn(|| loop {
                let next = queue.lock().ok().and_then(|mut q| q.pop());
                let Some((i, item)) = next else { break };
                let r = f(item);
                if let Ok(mut res) = results.lock() {
                    res[i] = Some(r);
                }
                done.fetch_add(1, Ordering::Relaxed);
            });
        }
    });
    results.into_inner().unwrap_or_default().into_iter().flatten().collect()
}

/// The pool's report.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub parent: String,
    pub seed: u64,
    pub candidates: usize,
    pub sweeps: Vec<serde_json::Value>,
    pub feasible: Ranges,
    pub per_factor: BTreeMap<String, BTreeMap<String, usize>>,
    pub kept: Vec<String>,
    pub deduplicated: Vec<String>,
    pub dropped: Vec<serde_json::Value>,
    pub near_duplicate: String,
    pub wall_s: f64,
    pub sweep_wall_s: f64,
    pub candidate_wall_s: f64,
    pub gate_runs: usize,
    /// Kept (gate-passing) candidates per minute of the candidate phase.
    pub validated_per_minute: f64,
    /// The same over the whole run (the parent, the sweeps and the sheet included).
    pub validated_per_minute_overall: f64,
    pub gate_runs_per_minute: f64,
    pub contact_sheet: Option<String>,
    pub jobs: usize,
}

/// Augments the gym at `scene_path` into the pool folder `o.out`.
pub fn augment(scene_path: &Path, o: &Options, progress: &(dyn Fn(&str) + Sync)) -> Result<Report> {
    let started = Instant::now();
    // The pool is built in a hidden sibling and renamed into place at the end: a failing parent
    // or an I/O error leaves no pool, not part of one.
    let staging = Staging::new(&o.out)?;
    let pool_dir = staging.dir.clone();
    let scene = Scene::load(scene_path).map_err(|e| Error::Episode(e.into()))?;
    let dir_name =
        scene_path.parent().and_then(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let roles = gym::roles(&scene);
    let object = roles.object.clone().ok_or_else(|| {
        err(format!("{}: the success rules name no free object to vary; augmentation needs one", scene_path.display()))
    })?;
    // The parent must pass the gate itself; its native events give the motion's anchors.
    progress(&format!("validating the parent {dir_name}"));
    let parent_out = pool_dir.join("parent");
    let (pev, _, native) = validate::validate_native(scene_path, &validate::Options::new(parent_out))?;
    if !pev.success {
        return Err(err(format!("the parent {} fails the gate: {}", scene_path.display(), failed_checks(&pev))));
    }
    let carrier = pev
        .native_events
        .iter()
        .find(|e| {
            e.kind == events::Kind::Support
                && e.subject == object
                && e.onset_s < 0.05
                && scene.fixtures.iter().any(|f| f.name == e.other && f.joint.is_none())
        })
        .map(|e| e.other.clone());
    let demo = Demonstration::from_native(scene_path, scene, &pev, &native)?;
    let recorded = std::fs::read_to_string(scene_path.parent().unwrap_or(Path::new(".")).join("events.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<EventsFile>(&t).ok());
    let (source, source_kind) = match recorded {
        Some(r) => (r.source, r.source_kind),
        None => (
            events::source_grasps(&demo.rows, demo.scene.task.demonstration_hz),
            "demonstration gripper column".to_string(),
        ),
    };
    let parent = Parent {
        scene_path: scene_path.to_path_buf(),
        dir_name: dir_name.clone(),
        demo,
        source,
        source_kind,
        grasps: pev.native_events.iter().filter(|e| e.kind == events::Kind::Grasp).cloned().collect(),
        trace_sha256: pev.trace_sha256.clone(),
        object,
        carrier,
    };
    let gate_runs = AtomicUsize::new(1);

    // 1. Sweeps: each factor alone, outward from the parent.
    let sweep_started = Instant::now();
    let plan: Vec<(Factor, &str, Vec<Params>)> = sweep_levels()
        .into_iter()
        .filter(|(f, _, _)| o.factors.contains(f))
        .map(|(f, axis, levels)| (f, axis, levels.into_iter().take(o.max_levels).collect()))
        .collect();
    let lines: Vec<(usize, usize, Params)> = plan
        .iter()
        .enumerate()
        .flat_map(|(i, (_, _, levels))| levels.iter().cloned().enumerate().map(move |(k, p)| (i, k, p)))
        .collect();
    progress(&format!("sweeping {} single-factor levels", lines.len()));
    let results = parallel(lines, o.jobs, |(i, k, p)| {
        let name = format!(
            "{}_{}_{k}",
            plan[i].0.name(),
            plan[i].1.replace(['-', '+'], if plan[i].1.ends_with('-') { "lo" } else { "hi" })
        );
        let r = run_candidate(&parent, name, p.clone(), 0, &pool_dir.join("sweeps"), &o.validator);
        gate_runs.fetch_add(r.attempts.len(), Ordering::Relaxed);
        (i, k, p, r)
    });
    let mut feasible: Ranges = BTreeMap::new();
    let mut sweeps = Vec::new();
    for (i, (factor, axis, levels)) in plan.iter().enumerate() {
        let param = axis.trim_end_matches(['-', '+']).to_string();
        let mut best = parent_value(&param);
        let mut open = true;
        let mut tried = Vec::new();
        for (k, p) in levels.iter().enumerate() {
            let Some((_, _, _, r)) = results.iter().find(|(a, b, _, _)| *a == i && *b == k) else { continue };
            let v = swept_value(axis, p);
            let pass = r.kept;
            tried.push(
                json!({"value": v, "pass": pass, "why": r.attempts.last().map(|a| a.2.clone()).unwrap_or_default()}),
            );
            if open && pass {
                best = v;
            } else {
                open = false;
            }
        }
        let e = feasible.entry(param.clone()).or_insert([parent_value(&param); 2]);
        if best < e[0] {
            e[0] = best;
        }
        if best > e[1] {
            e[1] = best;
        }
        sweeps.push(json!({"factor": factor, "axis": axis, "levels": tried, "feasible_to": best}));
    }
    let sweep_wall_s = sweep_started.elapsed().as_secs_f64();
    let available: Vec<Factor> = FACTORS
        .iter()
        .copied()
        .filter(|f| o.factors.contains(f))
        .filter(|f| match f {
            Factor::ObjectSize => feasible.get("size_scale").is_some_and(|r| r[1] - r[0] > 1e-9),
            Factor::ObjectPose => {
                feasible.get("pose_xy_m").is_some_and(|r| r[1] > 0.0)
                    || feasible.get("pose_yaw_deg").is_some_and(|r| r[1] > 0.0)
            }
            Factor::SupportHeight => feasible.get("support_dz_m").is_some_and(|r| r[1] - r[0] > 1e-9),
            Factor::FrictionMass => {
                feasible.get("friction_scale").is_some_and(|r| r[1] - r[0] > 1e-9)
                    || feasible.get("mass_scale").is_some_and(|r| r[1] - r[0] > 1e-9)
            }
            Factor::Distractors => feasible.get("distractors").is_some_and(|r| r[1] >= 1.0),
            Factor::Visual => true,
        })
        .collect();
    progress(&format!(
        "feasible: {feasible:?}; combining {:?}",
        available.iter().map(|f| f.name()).collect::<Vec<_>>()
    ));

    // 2. Candidates: one to three factors, values within the feasible ranges.
    let cand_started = Instant::now();
    let mut rng = SplitMix64::new(o.seed);
    let mut candidates = Vec::new();
    for i in 0..o.candidates {
        let k = 1 + (rng.next_u64() % 3) as usize;
        let mut pool = available.clone();
        let mut p = Params::default();
        for _ in 0..k.min(pool.len()) {
            let f = pool.remove((rng.next_u64() % pool.len() as u64) as usize);
            let mut u = |r: Option<&[f64; 2]>, parent: f64| {
                let r = r.copied().unwrap_or([parent, parent]);
                r[0] + rng.next_f64() * (r[1] - r[0])
            };
            match f {
                Factor::ObjectSize => p.size_scale = Some(u(feasible.get("size_scale"), 1.0)),
                Factor::ObjectPose => {
                    let xy = feasible.get("pose_xy_m").map(|r| r[1]).unwrap_or(0.0);
                    let yaw = feasible.get("pose_yaw_deg").map(|r| r[1]).unwrap_or(0.0);
                    p.pose = Some(PoseDraw { xy_m: xy, yaw_deg: yaw, seed: rng.next_u64() | 1, fraction: 1.0 });
                }
                Factor::SupportHeight => p.support_dz_m = Some(u(feasible.get("support_dz_m"), 0.0)),
                Factor::FrictionMass => {
                    p.friction_scale = Some(u(feasible.get("friction_scale"), 1.0));
                    p.mass_scale = Some(u(feasible.get("mass_scale"), 1.0));
                }
                Factor::Distractors => {
                    let max = feasible.get("distractors").map(|r| r[1]).unwrap_or(0.0).max(1.0) as u64;
                    p.distractors = Some((1 + (rng.next_u64() % max) as usize, rng.next_u64()));
                }
                Factor::Visual => {
                    p.light_scale = Some(u(feasible.get("light_scale"), 1.0));
                    p.light_shift_m = Some([u(Some(&[-0.5, 0.5]), 0.0), u(Some(&[-0.5, 0.5]), 0.0)]);
                    p.hue_deg = Some(u(feasible.get("hue_deg"), 0.0));
                    p.table_shade = Some(u(Some(&[-0.2, 0.2]), 0.0));
                }
            }
        }
        candidates.push((format!("{dir_name}_v{i:03}"), p));
    }
    progress(&format!("validating {} candidates on {} job(s)", candidates.len(), o.jobs));
    let outcomes = parallel(candidates, o.jobs, |(name, p)| {
        let r = run_candidate(&parent, name, p, o.shrink_tries, &pool_dir, &o.validator);
        gate_runs.fetch_add(r.attempts.len(), Ordering::Relaxed);
        progress(&format!(
            "{}: {} after {} attempt(s)",
            r.name,
            if r.kept { "kept" } else { "dropped" },
            r.attempts.len()
        ));
        r
    });
    let candidate_wall_s = cand_started.elapsed().as_secs_f64();

    // 3. Near-duplicates, in candidate order.
    let w = widths(&feasible);
    let mut kept: Vec<&Outcome> = Vec::new();
    let mut dedup = Vec::new();
    for r in outcomes.iter().filter(|r| r.kept) {
        let dup = kept.iter().any(|k| {
            k.signature.iter().zip(&r.signature).zip(&w).all(|((a, b), w)| (a - b).abs() / w < o.dedupe_tolerance)
                && k.distractor_xy.len() == r.distractor_xy.len()
                && k.distractor_xy.iter().zip(&r.distractor_xy).all(|(a, b)| (a[0] - b[0]).hypot(a[1] - b[1]) < 0.03)
        });
        if dup {
            dedup.push(r.name.clone());
        } else {
            kept.push(r);
        }
    }
    // The pool keeps the distinct variants; the near-duplicates' folders go.
    for r in outcomes.iter().filter(|r| dedup.contains(&r.name)) {
        if let Some(d) = &r.staged {
            std::fs::remove_dir_all(d).map_err(Error::io(d))?;
        }
    }
    let kept_names: Vec<String> = kept.iter().filter(|r| r.staged.is_some()).map(|r| r.name.clone()).collect();
    let mut per_factor: BTreeMap<String, BTreeMap<String, usize>> = BTreeMap::new();
    for r in &outcomes {
        for f in &r.factors {
            let e = per_factor.entry(f.name().into()).or_default();
            *e.entry("attempted".into()).or_default() += 1;
            let key = if !r.kept {
                "dropped"
            } else if dedup.contains(&r.name) {
                "deduplicated"
            } else if r.shrinks > 0 {
                "shrunk_then_validated"
            } else {
                "validated"
            };
            *e.entry(key.into()).or_default() += 1;
        }
    }
    let dropped: Vec<serde_json::Value> = outcomes
        .iter()
        .filter(|r| !r.kept)
        .map(|r| json!({"name": r.name, "factors": r.factors, "attempts": r.attempts.iter().map(|a| json!({"params": a.0, "why": a.2})).collect::<Vec<_>>()}))
        .collect();
    let mut contact_sheet = None;
    if o.sheet && !kept_names.is_empty() {
        progress("rendering the contact sheet");
        // The parent first, then every kept variant.
        let scenes: Vec<PathBuf> = std::iter::once(scene_path.to_path_buf())
            .chain(kept_names.iter().map(|n| pool_dir.join(n).join("scene.toml")))
            .collect();
        let refs: Vec<&Path> = scenes.iter().map(PathBuf::as_path).collect();
        match crate::sheet::write(&refs, 8, &pool_dir.join("contact_sheet.png")) {
            Ok(_) => contact_sheet = Some(o.out.join("contact_sheet.png").display().to_string()),
            Err(e) => progress(&format!("no contact sheet: {e:#}")),
        }
    }
    let wall_s = started.elapsed().as_secs_f64();
    let validated = outcomes.iter().filter(|r| r.kept).count();
    let runs = gate_runs.load(Ordering::Relaxed);
    let report = Report {
        parent: scene_path.display().to_string(),
        seed: o.seed,
        candidates: o.candidates,
        sweeps,
        feasible,
        per_factor,
        kept: kept_names,
        deduplicated: dedup,
        dropped,
        near_duplicate: format!(
            "every parameter within {} of its feasible width of an earlier kept variant's (absent = the parent's value), \
             the same number of distractors, each within 3 cm",
            o.dedupe_tolerance
        ),
        wall_s,
        sweep_wall_s,
        candidate_wall_s,
        gate_runs: runs,
        validated_per_minute: validated as f64 / (candidate_wall_s / 60.0).max(1e-9),
        validated_per_minute_overall: validated as f64 / (wall_s / 60.0).max(1e-9),
        gate_runs_per_minute: runs as f64 / (wall_s / 60.0).max(1e-9),
        contact_sheet,
        jobs: o.jobs,
    };
    lockstep::demo::write_atomic(
        &pool_dir.join("report.json"),
        &serde_json::to_vec_pretty(&report).map_err(|e| err(e.to_string()))?,
    )?;
    staging.commit()?;
    Ok(report)
}
