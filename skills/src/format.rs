//! The skill format (one JSON file per version; robot-skill/skills/README.md explains it to the
//! model, this module is its schema): applicability, object roles, object-relative motion
//! rules, the procedure, recovery guidance, evidence and status. [`Skill::validate`] refuses
//! what a skill must never hold — above all, anything that is a position in the robot's base
//! frame: a rule is always relative to an object's anchor, its offset is bounded, and its
//! anchor must be a declared object role.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

/// The format's version new skills are written in: files of a schema not in [`READS`] are
/// refused, not guessed at. Schema 2 binds a long thin anchor (a line, a bar: short side under
/// half the long one) with its y toward the TCP when the TCP faces it across its length (the
/// "line" frame, robot-skill/skills/README.md); schema 1 files, written before, keep the frame
/// they were extracted and admitted with (robo_skills reads the schema when it binds).
pub const SCHEMA: u32 = 2;
/// The schemas this build reads.
pub const READS: [u32; 2] = [1, 2];
/// How far a rule's target may be from its anchor: further is not "about" that object.
pub const MAX_OFFSET_M: f64 = 0.40;

#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum FormatError {
    #[error("skill {id} v{version}: {field}: {why}")]
    Invalid { id: String, version: u32, field: String, why: String },
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    /// Extracted, not yet proven by fresh execution.
    Candidate,
    /// Passed admission: checks, re-instantiation and held-out execution.
    Validated,
    /// No longer selected (its evidence stays).
    Retired,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum Backend {
    Sim,
    Real,
}

/// What a skill depends on, hashed (not the bytes of config/robot.json: unrelated keys change
/// nothing). Equal fingerprints: the skill's motions mean the same on this robot.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Eq, Default)]
#[serde(deny_unknown_fields)]
pub struct Fingerprint {
    /// SHA-256 over the arm's forward kinematics at fixed configurations, its joint limits and
    /// TCP (see `fingerprint::of`).
    pub kinematics: String,
    /// The gripper: `franka_hand` or `robotiq_2f85`.
    pub gripper: String,
    /// `simulation` or `franka`.
    pub profile: String,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Applicability {
    /// A verb class of the instruction: pick_place, stack, push, open, close, hang, insert, ...
    pub task_kind: String,
    /// Words of the instructions it was learned from (selection's text relevance).
    #[serde(default)]
    pub keywords: Vec<String>,
    /// Shape classes of the objects it needs, as perception names them (block, disc, bowl, ...).
    pub object_classes: Vec<String>,
    pub fingerprint: Fingerprint,
    pub backend: Backend,
    /// A narrower context after a split (e.g. {"object_classes": "cylinder"}); empty: none.
    #[serde(default)]
    pub context: BTreeMap<String, String>,
}

/// An object the skill acts on or relative to, found by a perception prompt.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ObjectRole {
    /// The robo_perception prompt that finds it ("red block", "left blue bowl").
    pub prompt: String,
    /// Its shape class.
    pub class: String,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum Actor {
    Tcp,
    Fingertips,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum Feature {
    Centre,
    TopFace,
    SupportPlane,
    MajorAxis,
    /// The object as the hand holds it: the TCP's frame when the stage begins, laid level (a
    /// handle being pulled; bound only while the gripper holds something).
    InHand,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AnchorRef {
    /// An object role of the skill.
    pub object: String,
    pub feature: Feature,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct Approach {
    /// Direction of the final motion in the target's TCP frame ([0, 0, 1]: along the fingers).
    #[serde(default)]
    pub axis: Option<[f64; 3]>,
    /// With `axis`: start this far back along it (a pre-pose), m.
    #[serde(default)]
    pub distance_m: f64,
    /// Waypoint spacing of the final motion, m.
    pub step_m: f64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum StopKind {
    /// The chunk executed (the runtime's "reached").
    Reached,
    /// Stop early once the measured external force exceeds `force_n`.
    Contact,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Stop {
    pub kind: StopKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub force_n: Option<f64>,
}

/// An axis of a rule's anchor frame.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    X,
    Y,
    Z,
}

/// A second object (or marking) the target is also about: along the named axes of the rule's
/// anchor frame, the actor's coordinate is measured from this feature instead of from the
/// anchor ("3 cm past the line, level with the block": anchor the line, `along: {"x": 0.0}`
/// from the block). Without it a rule could only say where the target is from one object.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SecondAnchor {
    /// An object role of the skill (a marking included).
    pub object: String,
    pub feature: Feature,
    /// Axis of the anchor frame → the actor's coordinate along it from this feature, m.
    pub along: BTreeMap<Axis, f64>,
}

/// Put the actor at `offset_m` from the anchor, turned `yaw_rad` about the anchor's z, tilted by
/// `tilt_rad`; approach and stop as given; `gripper` is commanded while moving.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MotionRule {
    pub id: String,
    pub actor: Actor,
    pub anchor: AnchorRef,
    pub offset_m: [f64; 3],
    pub yaw_rad: f64,
    pub tilt_rad: [f64; 3],
    pub approach: Approach,
    pub gripper: f64,
    pub stop: Stop,
    /// Optional: the coordinates along some axes taken from a second object (see [`SecondAnchor`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub second_anchor: Option<SecondAnchor>,
}

/// One step of a stage, told apart by its key.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum Step {
    Move {
        #[serde(rename = "move")]
        rule: String,
    },
    Gripper {
        gripper: GripperAction,
        #[serde(default = "default_settle")]
        settle_s: f64,
    },
    Hold {
        hold_s: f64,
    },
}

fn default_settle() -> f64 {
    0.6
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum GripperAction {
    Open,
    Close,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum CheckKind {
    /// The gripper stopped on something.
    Holding,
    /// The gripper is open.
    Released,
    /// `object` rose at least `min_m` since the stage began.
    Lifted,
    /// `object` moved at least `min_m` since the stage began.
    Moved,
    /// `object` rests on or in `support` (over its footprint, its bottom at the support's top or
    /// between its top and bottom, within `tolerance_m`).
    On,
}

/// An effect a stage must have, checked on a fresh observation after it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Check {
    pub kind: CheckKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub support: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_m: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Stage {
    /// A short name (a few words as an id: the rule ids of the stage start with it).
    pub name: String,
    /// What the stage does, in the words of whoever named it (extraction keeps the model's whole
    /// stage text here). Absent in files written before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    pub steps: Vec<Step>,
    #[serde(default)]
    pub checks: Vec<Check>,
    /// Tries after the first when a check fails (from a fresh observation).
    #[serde(default = "default_retries")]
    pub retries: u32,
    /// Optional stage code (Python using robo/robo_perception/robo_skills); linted for
    /// base-frame numbers before a skill is admitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub code: Option<String>,
    /// The evidence this stage's motions were computed from (an evidence id).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
}

fn default_retries() -> u32 {
    1
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Recovery {
    /// The situation, as feedback or checks show it.
    pub when: String,
    /// What to do instead.
    pub action: String,
    #[serde(default)]
    pub evidence: Vec<String>,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// A round whose local effect was what it should be.
    Positive,
    Negative,
    Unknown,
    /// A whole natively judged run of the skill (validation) or episode that used it.
    Success,
    Failure,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// A round of an agent episode, labelled by extraction.
    Extraction,
    /// A model-free run of the skill (`r2g skills run`), natively judged.
    Validation,
    /// An episode that was given the skill, natively judged.
    Use,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Evidence {
    /// `<episode>#<round>`; unique per (episode, round).
    pub id: String,
    /// The run (episode) it comes from: the run folder's name.
    pub episode: String,
    /// The round within that episode (0 for a whole run).
    pub round: u32,
    pub outcome: Outcome,
    pub source: Source,
    #[serde(default)]
    pub seed: u64,
    /// The run folder, when it is still there (re-instantiation reads its observations).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record: Option<String>,
    #[serde(default)]
    pub note: String,
}

impl Evidence {
    pub fn key(&self) -> (String, u32) {
        (self.episode.clone(), self.round)
    }
}

/// What one version did, in order of versions.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Change {
    pub version: u32,
    pub op: String,
    pub reason: String,
    #[serde(default)]
    pub evidence: Vec<String>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Skill {
    pub schema: u32,
    pub id: String,
    pub version: u32,
    pub status: Status,
    pub name: String,
    pub summary: String,
    pub applicability: Applicability,
    pub objects: BTreeMap<String, ObjectRole>,
    pub rules: Vec<MotionRule>,
    pub procedure: Vec<Stage>,
    #[serde(default)]
    pub recovery: Vec<Recovery>,
    #[serde(default)]
    pub evidence: Vec<Evidence>,
    #[serde(default)]
    pub history: Vec<Change>,
}

/// The longest id (skill, rule, object role), bytes.
pub const ID_MAX: usize = 64;

/// Whether `s` is a valid id: 1 to [`ID_MAX`] of a-z, 0-9, '_' and '-'.
pub fn id_ok(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= ID_MAX
        && s.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_' || b == b'-')
}

/// A lowercase slug of `text` usable as an id ("Pick & place!" -> "pick-place"), at most
/// [`ID_MAX`] bytes; "skill" when nothing of it is usable.
pub fn slug(text: &str) -> String {
    let s = slug_within(text, ID_MAX, '-');
    if s.is_empty() {
        "skill".into()
    } else {
        s
    }
}

/// `text` as an id of at most `max` bytes: lowercase ASCII letters and digits kept, accents
/// dropped from Latin letters (é -> e), '-' and '_' kept, every other run of characters one
/// `sep`; cut at a separator where one falls in the last third, so a
/// long text ends on a whole word. Empty when nothing of it is usable.
pub fn slug_within(text: &str, max: usize, sep: char) -> String {
    let mut out = String::new();
    for c in text.chars().flat_map(char::to_lowercase) {
        let c = fold_accent(c);
        if c.is_ascii_alphanumeric() {
            out.push(c);
        } else if !out.is_empty() && !out.ends_with(['-', '_']) {
            // A separator the text already has stays what it was ("pick_place" is an id).
            out.push(if c == '-' || c == '_' { c } else { sep });
        }
    }
    let out = out.trim_end_matches(['-', '_']);
    if out.len() <= max {
        return out.to_string();
    }
    let cut = &out[..max];
    let at = cut.rfind(['-', '_']).filter(|&i| i >= max * 2 / 3).unwrap_or(max);
    out[..at].trim_end_matches(['-', '_']).to_string()
}

/// The unaccented ASCII letter of a Latin letter with a diacritic (the common ones); others as given.
fn fold_accent(c: char) -> char {
    const FROM: &str = "àáâãäåāçćčďèéêëēěìíîïīñńňòóôõöøōřśšťùúûüūůýÿžźż";
    const TO: &str = "aaaaaaacccdeeeeeeiiiiinnnooooooorsstuuuuuuyyzzz";
    FROM.chars().position(|f| f == c).and_then(|i| TO.chars().nth(i)).unwrap_or(c)
}

impl Skill {
    fn err(&self, field: impl Into<String>, why: impl Into<String>) -> FormatError {
        FormatError::Invalid { id: self.id.clone(), version: self.version, field: field.into(), why: why.into() }
    }

    /// Parses one version file's text and checks it.
    pub fn parse(text: &str) -> Result<Self, String> {
        let s: Skill = serde_json::from_str(text).map_err(|e| format!("not a skill (schema {SCHEMA}): {e}"))?;
        s.validate().map_err(|e| e.to_string())?;
        Ok(s)
    }

    /// Everything a skill must satisfy; the first violation is returned.
    pub fn validate(&self) -> Result<(), FormatError> {
        if !READS.contains(&self.schema) {
            return Err(self.err("schema", format!("is {}, this build reads {READS:?}", self.schema)));
        }
        if !id_ok(&self.id) {
            return Err(self.err("id", "1 to 64 of a-z, 0-9, '_' and '-'"));
        }
        if self.version == 0 {
            return Err(self.err("version", "versions start at 1"));
        }
        if self.name.trim().is_empty() {
            return Err(self.err("name", "empty"));
        }
        if self.applicability.object_classes.is_empty() {
            return Err(self.err("applicability.object_classes", "a skill acts on at least one object"));
        }
        for (role, o) in &self.objects {
            if !id_ok(role) {
                return Err(self.err(format!("objects.{role}"), "a role name is 1 to 64 of a-z, 0-9, '_' and '-'"));
            }
            if o.prompt.trim().is_empty() {
                return Err(self.err(format!("objects.{role}.prompt"), "empty"));
            }
        }
        let mut ids = BTreeSet::new();
        for r in &self.rules {
            let at = format!("rules.{}", r.id);
            if !id_ok(&r.id) || !ids.insert(r.id.as_str()) {
                return Err(self.err(at, "a rule id is unique and 1 to 64 of a-z, 0-9, '_' and '-'"));
            }
            if !self.objects.contains_key(&r.anchor.object) {
                return Err(self.err(
                    format!("{at}.anchor.object"),
                    format!(
                        "'{}' is no object role of the skill (roles: {}); a rule is always relative to an object, never to the robot base",
                        r.anchor.object,
                        self.objects.keys().cloned().collect::<Vec<_>>().join(", ")
                    ),
                ));
            }
            let nums = r
                .offset_m
                .iter()
                .chain(&r.tilt_rad)
                .chain(std::iter::once(&r.yaw_rad))
                .chain(std::iter::once(&r.gripper));
            if nums.clone().any(|v| !v.is_finite()) {
                return Err(self.err(at, "offset, yaw, tilt and gripper must be finite numbers"));
            }
            let reach = r.offset_m.iter().map(|v| v * v).sum::<f64>().sqrt();
            if reach > MAX_OFFSET_M {
                return Err(self.err(
                    format!("{at}.offset_m"),
                    format!(
                        "{reach:.3} m from its anchor: more than {MAX_OFFSET_M} m is a base-frame position in disguise"
                    ),
                ));
            }
            if !(-1.0..=1.0).contains(&r.gripper) {
                return Err(self.err(format!("{at}.gripper"), "in [-1, 1] (-1 open, +1 closed)"));
            }
            let a = &r.approach;
            if !(a.step_m.is_finite() && a.step_m > 0.0 && a.step_m <= 0.05) {
                return Err(self.err(format!("{at}.approach.step_m"), "in (0, 0.05] m"));
            }
            if !(a.distance_m.is_finite() && (0.0..=0.3).contains(&a.distance_m)) {
                return Err(self.err(format!("{at}.approach.distance_m"), "in [0, 0.3] m"));
            }
            if let Some(ax) = a.axis {
                let n = ax.iter().map(|v| v * v).sum::<f64>().sqrt();
                if !(n.is_finite() && n > 1e-6) {
                    return Err(self.err(format!("{at}.approach.axis"), "a non-zero direction"));
                }
            }
            if r.stop.kind == StopKind::Contact
                && !r.stop.force_n.is_some_and(|f| f.is_finite() && f > 0.0 && f <= 60.0)
            {
                return Err(self.err(format!("{at}.stop.force_n"), "a contact stop needs force_n in (0, 60] N"));
            }
            if let Some(second) = &r.second_anchor {
                if !self.objects.contains_key(&second.object) {
                    return Err(self.err(
                        format!("{at}.second_anchor.object"),
                        format!("'{}' is no object role of the skill", second.object),
                    ));
                }
                if second.along.is_empty() {
                    return Err(self.err(
                        format!("{at}.second_anchor.along"),
                        "names at least one axis of the anchor frame (x, y, z) with its distance from the second object",
                    ));
                }
                if second.along.values().any(|v| !(v.is_finite() && v.abs() <= MAX_OFFSET_M)) {
                    return Err(self.err(
                        format!("{at}.second_anchor.along"),
                        format!("each distance is finite and at most {MAX_OFFSET_M} m from the second object"),
                    ));
                }
            }
        }
        if self.procedure.is_empty() {
            return Err(self.err("procedure", "at least one stage"));
        }
        for st in &self.procedure {
            let at = format!("procedure.{}", st.name);
            if st.steps.is_empty() && st.code.is_none() {
                return Err(self.err(at, "a stage has steps or code"));
            }
            if st.retries > 3 {
                return Err(self.err(format!("{at}.retries"), "at most 3"));
            }
            for step in &st.steps {
                match step {
                    Step::Move { rule } if !ids.contains(rule.as_str()) => {
                        return Err(self.err(
                            format!("{at}.steps"),
                            format!("moves by rule '{rule}', which the skill does not have"),
                        ));
                    }
                    Step::Gripper { settle_s, .. } | Step::Hold { hold_s: settle_s }
                        if !(settle_s.is_finite() && *settle_s > 0.0 && *settle_s <= 5.0) =>
                    {
                        return Err(self.err(format!("{at}.steps"), "gripper settle_s and hold_s in (0, 5] s"));
                    }
                    _ => {}
                }
            }
            for c in &st.checks {
                let needs_object = matches!(c.kind, CheckKind::Lifted | CheckKind::Moved | CheckKind::On);
                let known = |r: &Option<String>| r.as_ref().is_none_or(|r| self.objects.contains_key(r));
                if (needs_object && c.object.is_none()) || (c.kind == CheckKind::On && c.support.is_none()) {
                    return Err(
                        self.err(format!("{at}.checks"), format!("{:?} needs its object (and support)", c.kind))
                    );
                }
                if !known(&c.object) || !known(&c.support) {
                    return Err(self.err(format!("{at}.checks"), "names an object role the skill does not have"));
                }
            }
        }
        let mut seen = BTreeSet::new();
        for e in &self.evidence {
            if !seen.insert(e.key()) {
                return Err(self.err("evidence", format!("({}, round {}) is listed twice", e.episode, e.round)));
            }
        }
        Ok(())
    }

    /// Successes and trials among natively judged runs (validation and use).
    pub fn record(&self) -> (u32, u32) {
        let judged = self.evidence.iter().filter(|e| matches!(e.outcome, Outcome::Success | Outcome::Failure));
        let (mut k, mut n) = (0, 0);
        for e in judged {
            n += 1;
            k += u32::from(e.outcome == Outcome::Success);
        }
        (k, n)
    }
}

/// Lower bound of the Wilson score interval (z = 1.96) of k successes in n trials; 0 for none.
pub fn wilson_lower(k: u32, n: u32) -> f64 {
    if n == 0 {
        return 0.0;
    }
    let (k, n, z) = (f64::from(k), f64::from(n), 1.96f64);
    let p = k / n;
    let d = 1.0 + z * z / n;
    ((p + z * z / (2.0 * n)) - z * ((p * (1.0 - p) + z * z / (4.0 * n)) / n).sqrt()) / d
}
