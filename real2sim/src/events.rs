//! Interaction events of an episode, from its native trace: intervals of contact (the robot
//! touching an object or fixture), grasp (the fingers closed on something and held still by it),
//! support (a free object resting on something while not held) and containment (an object's
//! origin inside a cavity). Each kind is a yes/no per trace sample (every 10 ms) turned into
//! intervals with hysteresis in time: runs (of either state) shorter than `min_duration_s` are
//! ignored. Every interval carries three keyframes: `before` (`keyframe_margin_s` before its
//! onset), `onset`, and `after` (the margin after it ends), each with the demonstration row, the
//! TCP, the fingers and the subject's pose.
//!
//! The source's own events are the gripper's: grasp intervals of the commanded gripper
//! (closed above +0.5, open again below 0; from the demonstration's rows, or from the hand's
//! aperture for EgoDex). [`timing`] compares them with the native grasps.

use serde::{Deserialize, Serialize};
use sim_host::trace::Trace;
use sim_host::Scene;

use crate::resample;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Params {
    pub min_duration_s: f64,
    pub keyframe_margin_s: f64,
    /// Fingers moving slower than this (per finger) are held still by what they grip.
    pub finger_still_m_s: f64,
    /// Largest gap between a source grasp switch and the native one.
    pub timing_tolerance_s: f64,
}

impl Default for Params {
    fn default() -> Self {
        Self { min_duration_s: 0.05, keyframe_margin_s: 0.2, finger_still_m_s: 0.01, timing_tolerance_s: 0.5 }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    Contact,
    Grasp,
    Support,
    Containment,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    /// `before`, `onset` or `after`.
    pub at: String,
    pub t_s: f64,
    /// Demonstration row nearest `t_s` (clamped to the last row).
    pub row: usize,
    /// TCP position in the world.
    pub tcp_m: [f64; 3],
    pub finger_m: f64,
    /// The subject's world pose (position, quaternion w x y z) when it is an object.
    pub subject_pose: Option<[f64; 7]>,
}

/// One interval. Contact: subject `robot`, other the thing touched. Grasp: subject the thing
/// held, other `robot`. Support: subject the object, other what it rests on. Containment:
/// subject the object, other the container.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub kind: Kind,
    pub subject: String,
    pub other: String,
    pub onset_s: f64,
    /// End of the interval (the trace's end when it lasts until then).
    pub offset_s: f64,
    pub keyframes: Vec<Keyframe>,
}

/// A grasp as the source commanded it, in demonstration time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourceGrasp {
    pub close_s: f64,
    pub open_s: Option<f64>,
}

/// The demonstration row at which the TCP is held relative to an object or fixture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Anchor {
    pub row: usize,
    pub entity: String,
    /// At a release: the object let go of here.
    #[serde(default)]
    pub released: Option<String>,
}

/// `events.json` of a gym.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EventsFile {
    pub params: Params,
    /// Where `source` came from.
    pub source_kind: String,
    pub source: Vec<SourceGrasp>,
    pub native: Vec<Interval>,
    /// From the native grasps and contacts: the object up to each grasp, the support it ends on
    /// from each release, the thing pushed during a contact.
    pub anchors: Vec<Anchor>,
}

/// The source's grasps from demonstration rows (gripper in column 8, −1 open … +1 closed).
pub fn source_grasps(rows: &[[f64; 8]], hz: f64) -> Vec<SourceGrasp> {
    let g: Vec<f64> = rows.iter().map(|r| r[7]).collect();
    let t: Vec<f64> = (0..rows.len()).map(|k| k as f64 / hz).collect();
    grasps_of(&resample::hysteresis(&g, 0.5, 0.0), &t)
}

/// Grasp intervals of a closed/open series; switch times halfway between the frames.
pub fn grasps_of(closed: &[bool], t_s: &[f64]) -> Vec<SourceGrasp> {
    let mut out: Vec<SourceGrasp> = Vec::new();
    for (t, c) in resample::switches(closed, t_s) {
        if c {
            out.push(SourceGrasp { close_s: t, open_s: None });
        } else if let Some(last) = out.last_mut().filter(|g| g.open_s.is_none()) {
            last.open_s = Some(t);
        }
    }
    out
}

fn runs(on: &[bool], t: &[f64], min_s: f64) -> Vec<(usize, usize)> {
    let s = resample::debounce(on, t, min_s);
    let mut out = Vec::new();
    let mut k = 0;
    while k < s.len() {
        if s[k] {
            let start = k;
            while k + 1 < s.len() && s[k + 1] {
                k += 1;
            }
            if t[k] - t[start] + 1e-9 >= min_s {
                out.push((start, k));
            }
        }
        k += 1;
    }
    out
}

/// Is the point (world) inside the cavity of `container` at sample `s`?
fn inside(scene: &Scene, trace: &Trace, s: usize, container: &str, p: [f64; 3]) -> Option<bool> {
    let (pose, lo, hi) = if let Some(i) = trace.objects.iter().position(|o| o == container) {
        let spec = scene.objects.iter().find(|o| o.name == container)?;
        let o = trace.samples[s].objects[i];
        (crate::gym::pose_wxyz([o[0], o[1], o[2]], [o[3], o[4], o[5], o[6]]), spec.cavity_min_m?, spec.cavity_max_m?)
    } else {
        let f = scene.fixtures.iter().find(|f| f.name == container)?;
        (crate::gym::pose_wxyz(f.position_m, f.quat_wxyz), f.cavity_min_m?, f.cavity_max_m?)
    };
    let local = pose.inverse() * nalgebra::Point3::from(p);
    Some((0..3).all(|k| local[k] >= lo[k] && local[k] <= hi[k]))
}

/// The events of a native trace. `row_at`: the demonstration row being played at a native time.
pub fn from_trace(scene: &Scene, trace: &Trace, row_at: &dyn Fn(f64) -> usize, p: Params) -> Vec<Interval> {
    let n = trace.samples.len();
    if n == 0 {
        return Vec::new();
    }
    let t: Vec<f64> = trace.samples.iter().map(|s| s.t_s).collect();
    let owner = |name: &str| trace.owners.iter().position(|o| o == name).map(|i| i as u16);
    let touching = |s: usize, a: u16, b: u16| trace.samples[s].contacts.contains(&[a.min(b), a.max(b)]);
    let robot = owner("robot");
    let things: Vec<(String, u16)> = trace
        .owners
        .iter()
        .enumerate()
        .filter(|(_, o)| !["robot", "table", "floor"].contains(&o.as_str()))
        .map(|(i, o)| (o.clone(), i as u16))
        .collect();
    let finger_max = trace.finger_max_m;
    let still: Vec<bool> = (0..n)
        .map(|s| {
            let prev = trace.samples[s.saturating_sub(1)].finger_m;
            let cur = trace.samples[s].finger_m;
            let dt = (t[s] - t[s.saturating_sub(1)]).max(1e-9);
            let speed = if s == 0 { 0.0 } else { (cur - prev).abs() / dt };
            speed < p.finger_still_m_s && cur < 0.97 * finger_max && cur > 5e-4
        })
        .collect();
    let mut out = Vec::new();
    let mut grasped_by_sample: Vec<Vec<String>> = vec![Vec::new(); n];
    if let Some(r) = robot {
        for (name, id) in &things {
            let contact: Vec<bool> = (0..n).map(|s| touching(s, r, *id)).collect();
            for (a, b) in runs(&contact, &t, p.min_duration_s) {
                out.push((Kind::Contact, "robot".to_string(), name.clone(), a, b));
            }
            let grasp: Vec<bool> = (0..n).map(|s| contact[s] && still[s]).collect();
            for (a, b) in runs(&grasp, &t, p.min_duration_s) {
                out.push((Kind::Grasp, name.clone(), "robot".to_string(), a, b));
                grasped_by_sample[a..=b].iter_mut().for_each(|g| g.push(name.clone()));
            }
        }
    }
    for (i, obj) in trace.objects.iter().enumerate() {
        if !scene.objects.iter().any(|o| &o.name == obj && o.free) {
            continue;
        }
        let Some(oid) = owner(obj) else { continue };
        let mut others: Vec<(String, u16)> = things.iter().filter(|(n, _)| n != obj).cloned().collect();
        if let Some(tid) = owner(Scene::TABLE) {
            others.push((Scene::TABLE.into(), tid));
        }
        for (other, id) in &others {
            let other_obj = trace.objects.iter().position(|o| o == other);
            let support: Vec<bool> = (0..n)
                .map(|s| {
                    let above =
                        other_obj.is_none_or(|j| trace.samples[s].objects[i][2] >= trace.samples[s].objects[j][2]);
                    touching(s, oid, *id) && above && !grasped_by_sample[s].contains(obj)
                })
                .collect();
            for (a, b) in runs(&support, &t, p.min_duration_s) {
                out.push((Kind::Support, obj.clone(), other.clone(), a, b));
            }
            let contained: Vec<bool> = (0..n)
                .map(|s| {
                    let o = trace.samples[s].objects[i];
                    inside(scene, trace, s, other, [o[0], o[1], o[2]]).unwrap_or(false)
                })
                .collect();
            for (a, b) in runs(&contained, &t, p.min_duration_s) {
                out.push((Kind::Containment, obj.clone(), other.clone(), a, b));
            }
        }
    }
    let frame = |at: &str, s: usize, subject: &str| {
        let sample = &trace.samples[s];
        Keyframe {
            at: at.into(),
            t_s: sample.t_s,
            row: row_at(sample.t_s),
            tcp_m: sample.tcp_m,
            finger_m: sample.finger_m,
            subject_pose: trace.objects.iter().position(|o| o == subject).map(|j| sample.objects[j]),
        }
    };
    let at_time = |target: f64| t.partition_point(|x| *x < target - 1e-9).min(n - 1);
    let mut intervals: Vec<Interval> = out
        .into_iter()
        .map(|(kind, subject, other, a, b)| {
            let thing = if kind == Kind::Contact { &other } else { &subject };
            let ends = b + 1 >= n;
            Interval {
                kind,
                onset_s: t[a],
                offset_s: if ends { t[n - 1] } else { t[b + 1] },
                keyframes: vec![
                    frame("before", at_time(t[a] - p.keyframe_margin_s), thing),
                    frame("onset", a, thing),
                    frame("after", at_time(t[b.min(n - 1)] + p.keyframe_margin_s), thing),
                ],
                subject,
                other,
            }
        })
        .collect();
    intervals.sort_by(|x, y| x.onset_s.total_cmp(&y.onset_s).then(x.kind.cmp(&y.kind)));
    intervals
}

/// Anchors of the motion from its events: each grasp's object from the grasp's onset, the
/// object's support after the release from its end; a contact without a grasp anchors on the
/// thing touched for its length.
pub fn anchors(events: &[Interval], row_at: &dyn Fn(f64) -> usize) -> Vec<Anchor> {
    let row = |t: f64| row_at(t);
    let mut out = Vec::new();
    for g in events.iter().filter(|e| e.kind == Kind::Grasp) {
        out.push(Anchor { row: row(g.onset_s), entity: g.subject.clone(), released: None });
        let after = events
            .iter()
            .filter(|e| e.kind == Kind::Support && e.subject == g.subject && e.onset_s >= g.offset_s - 0.3)
            .min_by(|a, b| a.onset_s.total_cmp(&b.onset_s));
        let target = after.map(|e| e.other.clone()).filter(|o| o != Scene::TABLE).unwrap_or_else(|| g.subject.clone());
        out.push(Anchor { row: row(g.offset_s), entity: target, released: Some(g.subject.clone()) });
    }
    let held = |e: &Interval| {
        events.iter().any(|g| {
            g.kind == Kind::Grasp && g.subject == e.other && g.onset_s <= e.offset_s && e.onset_s <= g.offset_s + 0.5
        })
    };
    for c in events.iter().filter(|e| e.kind == Kind::Contact && !held(e)) {
        if c.offset_s - c.onset_s < 0.3 {
            continue;
        }
        out.push(Anchor { row: row(c.onset_s), entity: c.other.clone(), released: None });
        out.push(Anchor { row: row(c.offset_s), entity: c.other.clone(), released: None });
    }
    out.sort_by_key(|a| a.row);
    out
}

/// The source grasps against the native ones, on the native clock.
#[derive(Debug, Clone, Serialize)]
pub struct Timing {
    /// Per source grasp: (source close in native time, native grasp onset, error), s.
    pub close: Vec<(f64, Option<f64>, Option<f64>)>,
    /// Per source release: (source open in native time, native grasp end, error), s.
    pub open: Vec<(f64, Option<f64>, Option<f64>)>,
    /// Source closes after which the fingers shut on nothing (no grasp to time), native time.
    pub closed_on_nothing: Vec<f64>,
    pub max_abs_error_s: f64,
    pub tolerance_s: f64,
    pub pass: bool,
}

/// `to_native`: a source time (demonstration time, row / rate) on the native clock.
/// `recorded`: the native events recorded with the gym (its import's replay, or for a variant its
/// parent's grasps). A source close after which the fingers shut on nothing is excused only when
/// the recorded run held nothing there either (a close to push, say); with no recorded run (a
/// hand-written demonstration) the demonstration is its own reference.
pub fn timing(
    source: &[SourceGrasp],
    native: &[Interval],
    recorded: Option<&[Interval]>,
    trace: &Trace,
    to_native: &dyn Fn(f64) -> f64,
    tolerance_s: f64,
) -> Timing {
    let grasps: Vec<&Interval> = native.iter().filter(|e| e.kind == Kind::Grasp).collect();
    let nearest = |t: f64, pick: &dyn Fn(&Interval) -> f64| {
        grasps.iter().map(|g| pick(g)).min_by(|a, b| (a - t).abs().total_cmp(&(b - t).abs()))
    };
    let grasp_near = |events: &[Interval], t: f64| {
        events.iter().any(|g| g.kind == Kind::Grasp && (g.onset_s - t).abs() <= tolerance_s)
    };
    // Fingers fully shut within a second of the command, no grasp near, and none in the
    // recorded run: nothing was held, nor meant to be.
    let shut_on_nothing = |t: f64| {
        let shut = trace.samples.iter().any(|s| s.t_s >= t && s.t_s <= t + 1.0 && s.finger_m < 1e-3);
        shut && nearest(t, &|g| g.onset_s).is_none_or(|n| (n - t).abs() > tolerance_s)
            && !recorded.is_some_and(|r| grasp_near(r, t))
    };
    let r = |v: f64| (v * 1e4).round() / 1e4;
    let mut t = Timing {
        close: vec![],
        open: vec![],
        closed_on_nothing: vec![],
        max_abs_error_s: 0.0,
        tolerance_s,
        pass: true,
    };
    for s in source {
        let close = to_native(s.close_s);
        if shut_on_nothing(close) {
            t.closed_on_nothing.push(r(close));
            continue;
        }
        let mut pairs: Vec<(f64, fn(&Interval) -> f64, bool)> = vec![(close, |g| g.onset_s, true)];
        if let Some(o) = s.open_s {
            pairs.push((to_native(o), |g| g.offset_s, false));
        }
        for (at, pick, is_close) in pairs {
            let n = nearest(at, &pick);
            let e = n.map(|v| v - at);
            t.pass &= e.is_some_and(|e| e.abs() <= tolerance_s);
            t.max_abs_error_s = t.max_abs_error_s.max(e.map(f64::abs).unwrap_or(f64::INFINITY));
            let entry = (r(at), n.map(r), e.map(r));
            if is_close {
                t.close.push(entry);
            } else {
                t.open.push(entry);
            }
        }
    }
    if !t.max_abs_error_s.is_finite() {
        t.max_abs_error_s = f64::MAX;
    }
    t
}

/// Recorded intervals (grasps, robot contacts, containment) missing from a new run: those with
/// no interval of the same kind and subjects whose onset is within `tolerance_s`.
pub fn missing(recorded: &[Interval], now: &[Interval], tolerance_s: f64) -> Vec<String> {
    recorded
        .iter()
        .filter(|r| r.kind != Kind::Support)
        .filter(|r| {
            !now.iter().any(|e| {
                e.kind == r.kind
                    && e.subject == r.subject
                    && e.other == r.other
                    && (e.onset_s - r.onset_s).abs() <= tolerance_s
            })
        })
        .map(|r| format!("{:?} {}:{} at {:.2} s", r.kind, r.subject, r.other, r.onset_s).to_lowercase())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim_host::trace::Sample;

    fn grasp_at(onset_s: f64) -> Interval {
        Interval {
            kind: Kind::Grasp,
            subject: "block".into(),
            other: "robot".into(),
            onset_s,
            offset_s: onset_s + 1.0,
            keyframes: Vec::new(),
        }
    }

    #[test]
    fn a_close_on_nothing_is_excused_only_when_the_recorded_run_held_nothing_there() {
        // Fingers open, shut fully at 1 s and stay shut: nothing between them.
        let samples = (0..300)
            .map(|k| {
                let t_s = k as f64 * 0.01;
                Sample {
                    t_s,
                    objects: Vec::new(),
                    joints: Vec::new(),
                    tcp_m: [0.0; 3],
                    finger_m: if t_s < 1.0 { 0.04 } else { 0.0 },
                    arm_rad: Vec::new(),
                    contacts: Vec::new(),
                    penetration_m: 0.0,
                    penetration_pair: [0, 0],
                }
            })
            .collect();
        let trace = Trace { finger_max_m: 0.04, samples, ..Default::default() };
        let source = [SourceGrasp { close_s: 0.9, open_s: Some(2.0) }];
        let same = |t: f64| t;
        // No recorded run (a hand-written demonstration), or one that held nothing: excused.
        for recorded in [None, Some(&[][..])] {
            let t = timing(&source, &[], recorded, &trace, &same, 0.5);
            assert!(t.pass && t.closed_on_nothing == [0.9], "{recorded:?}: {t:?}");
        }
        // The recorded run (the parent) grasped there: shutting on nothing is a missed grasp.
        let parent = [grasp_at(1.0)];
        let t = timing(&source, &[], Some(&parent), &trace, &same, 0.5);
        assert!(!t.pass && t.closed_on_nothing.is_empty(), "{t:?}");
        // And a native grasp where the parent had one passes.
        let t = timing(&source, &parent, Some(&parent), &trace, &same, 0.5);
        assert!(t.pass, "{t:?}");
    }
}
