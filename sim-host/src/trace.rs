//! The native trace of an episode and the evaluator that judges it. Physics records what
//! happened (object poses, fixture joints, TCP, gripper, contacts, penetration) every 10 ms of
//! simulated time; after the episode the task's success rules are checked against that record
//! alone. Nothing here ever crosses to the agent.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use controllers::math;

use crate::scene::{Criterion, Scene};

/// One sample of the trace.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Sample {
    pub t_s: f64,
    /// Per object: world position (3) and orientation quaternion w, x, y, z (4).
    pub objects: Vec<[f64; 7]>,
    /// Per fixture joint, in the scene's units (m for slides, degrees for hinges).
    pub joints: Vec<f64>,
    /// TCP position in the world.
    pub tcp_m: [f64; 3],
    /// Opening of one finger, m.
    pub finger_m: f64,
    /// The arm's joint angles, rad (empty in traces written before they were recorded). Not
    /// part of [`Trace::sha256`]: the hash of a run stays what it was before they were added.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub arm_rad: Vec<f64>,
    /// Pairs of owners in contact (indices into [`Trace::owners`], smaller first), sorted.
    pub contacts: Vec<[u16; 2]>,
    /// Deepest penetration between different owners, m (0 when none).
    pub penetration_m: f64,
    pub penetration_pair: [u16; 2],
}

/// Everything recorded in one episode.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Trace {
    pub gym: String,
    pub seed: u64,
    /// The placement perturbation of the episode (`xy=..,yaw=..`), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub perturbation: Option<String>,
    /// Names of what can touch: the objects, the fixtures, then `table`, `robot`, `floor`.
    pub owners: Vec<String>,
    pub objects: Vec<String>,
    /// Fixture names, one per recorded joint.
    pub joints: Vec<String>,
    pub finger_max_m: f64,
    pub samples: Vec<Sample>,
}

impl Trace {
    /// SHA-256 over every recorded number (little-endian f64) and contact pair, in order; the
    /// arm's joint angles (`arm_rad`, added later) are left out, so a run hashes as it did before.
    pub fn sha256(&self) -> String {
        let mut h = Sha256::new();
        for s in &self.samples {
            h.update(s.t_s.to_le_bytes());
            for o in &s.objects {
                o.iter().for_each(|v| h.update(v.to_le_bytes()));
            }
            s.joints.iter().for_each(|v| h.update(v.to_le_bytes()));
            s.tcp_m.iter().for_each(|v| h.update(v.to_le_bytes()));
            h.update(s.finger_m.to_le_bytes());
            for c in &s.contacts {
                h.update(c[0].to_le_bytes());
                h.update(c[1].to_le_bytes());
            }
            h.update([0xff]);
            h.update(s.penetration_m.to_le_bytes());
        }
        hex(&h.finalize())
    }

    fn owner(&self, name: &str) -> Option<u16> {
        self.owners.iter().position(|o| o == name).map(|i| i as u16)
    }

    fn object(&self, name: &str) -> Option<usize> {
        self.objects.iter().position(|o| o == name)
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The value and verdict of one check.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Check {
    pub value: serde_json::Value,
    pub pass: bool,
}

/// The evaluator's verdict on one episode.
#[derive(Debug, Clone, Serialize)]
pub struct Evaluation {
    pub gym: String,
    pub success: bool,
    pub checks: BTreeMap<String, Check>,
    pub trace_sha256: String,
    pub criteria_sha256: String,
    pub samples: usize,
    pub sim_time_s: f64,
}

/// SHA-256 of the success rules as JSON: which rules judged an episode.
pub fn criteria_sha256(scene: &Scene) -> String {
    let json = serde_json::to_string(&(&scene.task.success, scene.task.max_penetration_m)).unwrap_or_default();
    hex(&Sha256::digest(json.as_bytes()))
}

/// A quaternion stored (w, x, y, z), as MuJoCo and the trace keep it, in the (x, y, z, w)
/// order of `controllers::math`.
fn xyzw(q: [f64; 4]) -> math::Quat {
    [q[1], q[2], q[3], q[0]]
}

/// World poses of the fixtures (they never move), for cavity checks: name → (pos, quat wxyz).
fn fixture_pose(scene: &Scene, name: &str) -> Option<([f64; 3], [f64; 4])> {
    scene.fixtures.iter().find(|f| f.name == name).map(|f| (f.position_m, f.quat_wxyz))
}

fn round(v: f64) -> f64 {
    (v * 1e4).round() / 1e4
}

/// Judges a trace against the scene's success rules. Each rule is checked on the final sample
/// (or, for `stable`, over the final window); penetration is checked over the whole episode.
pub fn evaluate(scene: &Scene, trace: &Trace) -> Evaluation {
    let mut checks = BTreeMap::new();
    let last = trace.samples.last();
    let fail = |why: &str| Check { value: serde_json::json!(why), pass: false };
    for c in &scene.task.success {
        let check = match last {
            None => fail("the trace is empty"),
            Some(s) => judge(scene, trace, s, c),
        };
        // Two rules of the same kind on the same things must not hide each other.
        let mut label = c.label();
        let mut n = 1;
        while checks.contains_key(&label) {
            n += 1;
            label = format!("{}#{n}", c.label());
        }
        checks.insert(label, check);
    }
    // Penetration beyond the limit must not persist for more than 0.1 s.
    let limit = scene.task.max_penetration_m;
    let (mut longest, mut run_start, mut deepest, mut pair) = (0.0f64, None::<f64>, 0.0f64, [0u16; 2]);
    for s in &trace.samples {
        if s.penetration_m > deepest {
            deepest = s.penetration_m;
            pair = s.penetration_pair;
        }
        if s.penetration_m > limit {
            let start = *run_start.get_or_insert(s.t_s);
            longest = longest.max(s.t_s - start);
        } else {
            run_start = None;
        }
    }
    let name = |i: u16| trace.owners.get(i as usize).cloned().unwrap_or_default();
    checks.insert(
        "no_persistent_penetration".into(),
        Check {
            value: serde_json::json!({
                "deepest_m": (deepest * 1e5).round() / 1e5,
                "between": [name(pair[0]), name(pair[1])],
                "longest_over_limit_s": round(longest),
            }),
            pass: longest <= 0.1,
        },
    );
    let success = !scene.task.success.is_empty() && checks.values().all(|c| c.pass);
    Evaluation {
        gym: trace.gym.clone(),
        success,
        checks,
        trace_sha256: trace.sha256(),
        criteria_sha256: criteria_sha256(scene),
        samples: trace.samples.len(),
        sim_time_s: last.map(|s| s.t_s).unwrap_or(0.0),
    }
}

fn judge(scene: &Scene, trace: &Trace, s: &Sample, c: &Criterion) -> Check {
    let missing = |what: &str| Check { value: serde_json::json!(format!("{what} is not in the trace")), pass: false };
    let touching = |a: u16, b: u16| s.contacts.contains(&[a.min(b), a.max(b)]);
    match c {
        Criterion::Inside { object, container, min_m, max_m } => {
            let Some(i) = trace.object(object) else { return missing(object) };
            let o = s.objects[i];
            let p = [o[0], o[1], o[2]];
            let (local, lo, hi) = match container {
                Some(cn) => {
                    let (frame, lo, hi) = if let Some(k) = trace.object(cn) {
                        let c = s.objects[k];
                        let spec = scene.objects.iter().find(|x| &x.name == cn);
                        (
                            ([c[0], c[1], c[2]], [c[3], c[4], c[5], c[6]]),
                            spec.and_then(|x| x.cavity_min_m),
                            spec.and_then(|x| x.cavity_max_m),
                        )
                    } else if let Some(f) = fixture_pose(scene, cn) {
                        let spec = scene.fixtures.iter().find(|x| &x.name == cn);
                        (f, spec.and_then(|x| x.cavity_min_m), spec.and_then(|x| x.cavity_max_m))
                    } else {
                        return missing(cn);
                    };
                    let d = [p[0] - frame.0[0], p[1] - frame.0[1], p[2] - frame.0[2]];
                    (
                        math::rotate(math::conj(math::normalize(xyzw(frame.1))), d),
                        lo.unwrap_or([0.0; 3]),
                        hi.unwrap_or([0.0; 3]),
                    )
                }
                None => (p, min_m.unwrap_or([0.0; 3]), max_m.unwrap_or([0.0; 3])),
            };
            let inside = (0..3).all(|k| local[k] >= lo[k] && local[k] <= hi[k]);
            Check { value: serde_json::json!({"position_m": local.map(round)}), pass: inside }
        }
        Criterion::On { object, support } => {
            let (Some(a), Some(b)) = (trace.owner(object), trace.owner(support)) else { return missing(support) };
            Check { value: serde_json::json!(touching(a, b)), pass: touching(a, b) }
        }
        Criterion::TouchesOnly { object, others } => {
            let Some(a) = trace.owner(object) else { return missing(object) };
            let allowed: Vec<u16> = others.iter().filter_map(|n| trace.owner(n)).collect();
            let touched: Vec<String> = s
                .contacts
                .iter()
                .filter(|p| p[0] == a || p[1] == a)
                .map(|p| if p[0] == a { p[1] } else { p[0] })
                .map(|i| trace.owners[i as usize].clone())
                .collect();
            let ok = !touched.is_empty()
                && s.contacts
                    .iter()
                    .filter(|p| p[0] == a || p[1] == a)
                    .all(|p| allowed.contains(if p[0] == a { &p[1] } else { &p[0] }));
            Check { value: serde_json::json!(touched), pass: ok }
        }
        Criterion::Joint { fixture, min, max } => {
            let Some(k) = trace.joints.iter().position(|j| j == fixture) else { return missing(fixture) };
            let v = s.joints[k];
            let ok = min.is_none_or(|m| v >= m) && max.is_none_or(|m| v <= m);
            Check { value: serde_json::json!(round(v)), pass: ok }
        }
        Criterion::Upright { object, tolerance_deg } => {
            let Some(i) = trace.object(object) else { return missing(object) };
            let o = s.objects[i];
            let z = math::rotate(xyzw([o[3], o[4], o[5], o[6]]), [0.0, 0.0, 1.0]);
            let tilt = z[2].clamp(-1.0, 1.0).acos().to_degrees();
            Check { value: serde_json::json!({"tilt_deg": round(tilt)}), pass: tilt <= *tolerance_deg }
        }
        Criterion::Released { objects, min_distance_m, window_s, require_open } => {
            let Some(robot) = trace.owner("robot") else { return missing("robot") };
            // What the robot must not touch: the named objects, or with none named every object
            // and fixture (the table and the floor do not count).
            let mut held = Vec::new();
            for o in objects {
                let Some(a) = trace.owner(o) else { return missing(o) };
                held.push(a);
            }
            if objects.is_empty() {
                let ground = |n: &str| matches!(n, "table" | "robot" | "floor");
                held.extend((0..trace.owners.len()).filter(|&k| !ground(&trace.owners[k])).map(|k| k as u16));
            }
            let t_end = s.t_s;
            let mut last_touch: Option<(f64, u16)> = None;
            for x in trace.samples.iter().filter(|x| x.t_s >= t_end - window_s) {
                for c in &x.contacts {
                    let other = if c[0] == robot {
                        c[1]
                    } else if c[1] == robot {
                        c[0]
                    } else {
                        continue;
                    };
                    if held.contains(&other) {
                        last_touch = Some((x.t_s, other));
                    }
                }
            }
            let mut nearest = f64::INFINITY;
            for o in objects {
                let Some(i) = trace.object(o) else { return missing(o) };
                let p = s.objects[i];
                let d =
                    ((p[0] - s.tcp_m[0]).powi(2) + (p[1] - s.tcp_m[1]).powi(2) + (p[2] - s.tcp_m[2]).powi(2)).sqrt();
                nearest = nearest.min(d);
            }
            let open = s.finger_m > 0.5 * trace.finger_max_m;
            let mut value = serde_json::json!({
                "robot_contact": last_touch.map(|(t, k)| serde_json::json!({
                    "with": trace.owners[k as usize], "s_before_end": round(t_end - t)
                })),
                "gripper_open": open,
            });
            if !objects.is_empty() {
                value["tcp_distance_m"] = serde_json::json!(round(nearest));
            }
            let long_enough = trace.samples.first().is_some_and(|f| t_end - f.t_s >= window_s - 0.011);
            Check {
                value,
                pass: long_enough && last_touch.is_none() && nearest >= *min_distance_m && (open || !require_open),
            }
        }
        Criterion::Stable { objects, fixtures, duration_s, max_speed_m_s, max_joint_deg_s } => {
            let t_end = s.t_s;
            let window: Vec<&Sample> = trace.samples.iter().filter(|x| x.t_s >= t_end - duration_s).collect();
            let (mut fastest, mut fastest_joint, mut joints_ok) = (0.0f64, 0.0f64, true);
            for o in objects {
                let Some(i) = trace.object(o) else { return missing(o) };
                for w in window.windows(2) {
                    let (a, b) = (w[0].objects[i], w[1].objects[i]);
                    let dt = (w[1].t_s - w[0].t_s).max(1e-9);
                    let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
                    fastest = fastest.max(d / dt);
                }
            }
            for f in fixtures {
                let Some(k) = trace.joints.iter().position(|j| j == f) else { return missing(f) };
                let hinge = scene
                    .fixtures
                    .iter()
                    .find(|x| &x.name == f)
                    .and_then(|x| x.joint.as_ref())
                    .is_some_and(|j| j.kind == crate::scene::JointKind::Hinge);
                for w in window.windows(2) {
                    let speed = (w[1].joints[k] - w[0].joints[k]).abs() / (w[1].t_s - w[0].t_s).max(1e-9);
                    fastest_joint = fastest_joint.max(speed);
                    joints_ok &= speed <= if hinge { *max_joint_deg_s } else { *max_speed_m_s };
                }
            }
            let long_enough = window.first().is_some_and(|f| t_end - f.t_s >= duration_s - 0.011);
            Check {
                value: serde_json::json!({"max_speed_m_s": round(fastest), "max_joint_speed": round(fastest_joint)}),
                pass: long_enough && fastest <= *max_speed_m_s && joints_ok,
            }
        }
        Criterion::Apart { a, b } => {
            let (Some(x), Some(y)) = (trace.owner(a), trace.owner(b)) else { return missing(&format!("{a} or {b}")) };
            let t = touching(x, y);
            Check { value: serde_json::json!({"touching": t}), pass: !t }
        }
        Criterion::Past { object, axis, above, below } => {
            let Some(i) = trace.object(object) else { return missing(object) };
            let v = s.objects[i][*axis];
            let ok = above.is_none_or(|a| v >= a) && below.is_none_or(|b| v <= b);
            Check { value: serde_json::json!(round(v)), pass: ok }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene_with(rules: &str) -> Scene {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        // Tests run in parallel: one folder per call.
        static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("r2g-trace-unit-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let text = format!(
            "name = \"t\"\ncameras = []\n[robot]\nurdf = \"{}\"\ninitial_joints_rad = [0.0, -0.78, 0.0, -2.35, 0.0, 1.57, 0.78]\n[[objects]]\nname = \"box\"\nshape = \"box\"\nsize_m = [0.02, 0.02, 0.02]\nposition_m = [0.5, 0.0, 0.02]\n[task]\nsuccess = [{rules}]\n",
            root.join("robots/panda/panda.urdf").display()
        );
        std::fs::write(dir.join("scene.toml"), text).expect("write");
        let s = Scene::load(&dir.join("scene.toml")).unwrap_or_else(|e| panic!("{e}"));
        let _ = std::fs::remove_dir_all(&dir);
        s
    }

    fn trace(zs: &[f64], penetration: &[f64]) -> Trace {
        Trace {
            gym: "t".into(),
            owners: vec!["box".into(), "table".into(), "robot".into(), "floor".into()],
            objects: vec!["box".into()],
            finger_max_m: 0.04,
            samples: zs
                .iter()
                .zip(penetration)
                .enumerate()
                .map(|(i, (&z, &p))| Sample {
                    t_s: i as f64 * 0.01,
                    objects: vec![[0.5, 0.0, z, 1.0, 0.0, 0.0, 0.0]],
                    joints: vec![],
                    tcp_m: [0.3, 0.0, 0.5],
                    finger_m: 0.04,
                    arm_rad: Vec::new(),
                    contacts: vec![],
                    penetration_m: p,
                    penetration_pair: [0, 2],
                })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn rules_with_the_same_label_are_all_reported() {
        let scene = scene_with(
            "{ kind = \"past\", object = \"box\", axis = 2, above = 0.1 }, { kind = \"past\", object = \"box\", axis = 2, below = 0.5 }",
        );
        let e = evaluate(&scene, &trace(&[0.02; 100], &[0.0; 100]));
        assert!(!e.checks["past:box:z"].pass);
        assert!(e.checks["past:box:z#2"].pass);
        assert!(!e.success);
    }

    #[test]
    fn penetration_fails_only_when_it_persists() {
        let scene = scene_with("{ kind = \"past\", object = \"box\", axis = 2, above = 0.0 }");
        let mut pen = vec![0.0; 100];
        pen[10..15].fill(0.005); // 40 ms over the limit: allowed
        assert!(evaluate(&scene, &trace(&[0.02; 100], &pen)).success);
        pen[40..60].fill(0.005); // 190 ms over the limit: not allowed
        let e = evaluate(&scene, &trace(&[0.02; 100], &pen));
        assert!(!e.success && !e.checks["no_persistent_penetration"].pass, "{:?}", e.checks);
    }

    #[test]
    fn stable_looks_at_the_final_window_only() {
        let scene = scene_with("{ kind = \"stable\", objects = [\"box\"], duration_s = 0.3 }");
        let mut z: Vec<f64> = (0..100).map(|i| 0.02 + 0.001 * i as f64).collect(); // moving 0.1 m/s
        assert!(!evaluate(&scene, &trace(&z, &[0.0; 100])).success);
        z[60..].fill(0.2); // at rest for the last 0.4 s
        assert!(evaluate(&scene, &trace(&z, &[0.0; 100])).success);
        // A trace shorter than the window cannot prove stability.
        assert!(!evaluate(&scene, &trace(&[0.2; 10], &[0.0; 10])).success);
    }

    #[test]
    fn released_is_judged_by_contact_and_distance_not_finger_opening() {
        let scene = scene_with("{ kind = \"released\", objects = [\"box\"], min_distance_m = 0.1 }");
        // Hand 0.2 m from the box, fingers mostly closed (g = 0.4 leaves 30 % open), no contact.
        let mut t = trace(&[0.02; 100], &[0.0; 100]);
        t.samples.iter_mut().for_each(|s| s.finger_m = 0.3 * 0.04);
        let e = evaluate(&scene, &t);
        assert!(e.checks["released:box"].pass, "{:?}", e.checks);
        // The old proxy, asked for explicitly, still fails it.
        let strict =
            scene_with("{ kind = \"released\", objects = [\"box\"], min_distance_m = 0.1, require_open = true }");
        assert!(!evaluate(&strict, &t).checks["released:box"].pass);
        // A finger touching the box 0.2 s before the end: not released, whatever the opening.
        let mut touching = trace(&[0.02; 100], &[0.0; 100]);
        touching.samples[80].contacts = vec![[0, 2]];
        let e = evaluate(&scene, &touching);
        let c = &e.checks["released:box"];
        assert!(!c.pass && c.value["robot_contact"]["with"] == "box", "{:?}", c);
        // Contact before the final window no longer counts.
        touching.samples[80].contacts.clear();
        touching.samples[20].contacts = vec![[0, 2]];
        assert!(evaluate(&scene, &touching).checks["released:box"].pass);
        // Too close to the box: not released.
        let mut close = trace(&[0.02; 100], &[0.0; 100]);
        close.samples.iter_mut().for_each(|s| s.tcp_m = [0.5, 0.0, 0.08]);
        assert!(!evaluate(&scene, &close).checks["released:box"].pass);
        // With no object named, touching anything but the table and the floor counts.
        let any = scene_with("{ kind = \"released\", objects = [] }");
        let mut on_table = trace(&[0.02; 100], &[0.0; 100]);
        on_table.samples[99].contacts = vec![[1, 2]];
        assert!(evaluate(&any, &on_table).checks["released:gripper"].pass);
        on_table.samples[99].contacts = vec![[0, 2]];
        assert!(!evaluate(&any, &on_table).checks["released:gripper"].pass);
    }
}
