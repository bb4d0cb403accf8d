//! Selection: which skills an episode's prompt gets. Deterministic and offline:
//! 1. filter — status (validated; candidates only when asked), the same fingerprint (kinematics,
//!    gripper, profile) and backend, and every object class the skill needs among those
//!    perception finds in the episode's first observation;
//! 2. rank — BM25 relevance of the instruction to the skill's name, summary, keywords, task kind
//!    and stage names, times a conservative success estimate (the Wilson lower bound of its
//!    natively judged runs); ties by id;
//! 3. take the best few whose rendered text fits a token budget. Each rule is shown in its
//!    anchor's frame, said to be so, and with the base-frame pose it binds to in the episode's
//!    first observation (a model must not read anchor-relative yaws as base-frame angles).
//!
//! The choice, with every score and every reason for leaving one out, is logged in the episode
//! record (skills.json, shown by the viewer) and in the library's events.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use agent_host::episode::{ChosenSkills, SkillSource};
use serde::Serialize;
use serde_json::{json, Value};

use crate::format::{wilson_lower, Backend, Fingerprint, Skill, Status, Step};
use crate::library::Library;

#[derive(Debug, Clone)]
pub struct SelectOpts {
    pub max_skills: usize,
    /// Estimated tokens (4 characters each) the skills section may take.
    pub token_budget: usize,
    pub include_candidates: bool,
}

impl Default for SelectOpts {
    fn default() -> Self {
        Self { max_skills: 3, token_budget: 2000, include_candidates: false }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Scored {
    pub id: String,
    pub version: u32,
    pub relevance: f64,
    pub success_lower_bound: f64,
    pub score: f64,
    pub tokens: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct Selection {
    pub instruction: String,
    pub perceived_classes: Vec<String>,
    pub chosen: Vec<String>,
    pub ranked: Vec<Scored>,
    /// (skill id, why it was left out).
    pub excluded: Vec<(String, String)>,
    #[serde(skip)]
    pub prompt: String,
}

fn tokens(text: &str) -> Vec<String> {
    text.split(|c: char| !c.is_alphanumeric()).filter(|w| w.len() > 1).map(str::to_lowercase).collect()
}

fn document(s: &Skill) -> Vec<String> {
    let mut d = tokens(&s.name);
    d.extend(tokens(&s.summary));
    d.extend(s.applicability.keywords.iter().flat_map(|k| tokens(k)));
    d.extend(tokens(&s.applicability.task_kind.replace('_', " ")));
    d.extend(s.procedure.iter().flat_map(|st| tokens(&st.name.replace('_', " "))));
    d.extend(s.objects.values().flat_map(|o| tokens(&o.prompt)));
    d
}

/// BM25 (k1 = 1.2, b = 0.75) of `query` against each document.
fn bm25(query: &[String], docs: &[Vec<String>]) -> Vec<f64> {
    let n = docs.len() as f64;
    let avg = docs.iter().map(Vec::len).sum::<usize>() as f64 / n.max(1.0);
    let mut q: Vec<&String> = query.iter().collect();
    q.sort();
    q.dedup();
    docs.iter()
        .map(|d| {
            q.iter()
                .map(|t| {
                    let df = docs.iter().filter(|x| x.contains(t)).count() as f64;
                    let tf = d.iter().filter(|x| x == t).count() as f64;
                    if tf == 0.0 {
                        return 0.0;
                    }
                    let idf = ((n - df + 0.5) / (df + 0.5) + 1.0).ln();
                    idf * tf * 2.2 / (tf + 1.2 * (0.25 + 0.75 * d.len() as f64 / avg.max(1.0)))
                })
                .sum()
        })
        .collect()
}

/// The skills section text for one skill.
pub fn render(s: &Skill) -> String {
    render_bound(s, &Value::Null)
}

/// A pose as the prompt shows it: 3 decimals.
fn pose_text(v: &Value) -> String {
    let nums: Vec<String> =
        v.as_array().into_iter().flatten().filter_map(Value::as_f64).map(|x| format!("{x:.3}")).collect();
    format!("[{}]", nums.join(", "))
}

/// The skills section text for one skill; `bound` (rule id → the pose it binds to in the
/// episode's first observation, or {"error": why}) adds that pose beside each rule.
pub fn render_bound(s: &Skill, bound: &Value) -> String {
    let (k, n) = s.record();
    let mut t = format!(
        "### skill {} v{} ({:?}; {k} of {n} natively judged runs succeeded)\n{}\nFile: skills/{}.json (in your scratch folder)\nObjects: {}\nProcedure:\n",
        s.id,
        s.version,
        s.status,
        s.summary,
        s.id,
        s.objects.iter().map(|(r, o)| format!("{r} = \"{}\" ({})", o.prompt, o.class)).collect::<Vec<_>>().join(", ")
    );
    let rules: BTreeMap<&str, _> = s.rules.iter().map(|r| (r.id.as_str(), r)).collect();
    for (i, st) in s.procedure.iter().enumerate() {
        let steps: Vec<String> = st
            .steps
            .iter()
            .map(|step| match step {
                Step::Move { rule } => match rules.get(rule.as_str()) {
                    Some(r) => {
                        let snake = |v: &dyn std::fmt::Debug| {
                            let d = format!("{v:?}");
                            d.chars().enumerate().fold(String::new(), |mut o, (i, c)| {
                                if c.is_uppercase() && i > 0 {
                                    o.push('_');
                                }
                                o.push(c.to_ascii_lowercase());
                                o
                            })
                        };
                        let second = r.second_anchor.as_ref().map_or(String::new(), |s2| {
                            let along: Vec<String> = s2
                                .along
                                .iter()
                                .map(|(a, v)| format!("{} {v:+.3} from {} of {}", snake(a), snake(&s2.feature), s2.object))
                                .collect();
                            format!(" but along {}", along.join(", "))
                        });
                        let now = match &bound[rule.as_str()] {
                            Value::Array(_) => format!(" → now {}", pose_text(&bound[rule.as_str()])),
                            Value::Object(e) => {
                                format!(" → not bound now: {}", e.get("error").and_then(Value::as_str).unwrap_or("?"))
                            }
                            _ => String::new(),
                        };
                        format!(
                            "move {rule} ({} [{:.3}, {:.3}, {:.3}] m, yaw {:.2} rad in the {} frame of {}{second}, gripper {:+.1}{now})",
                            snake(&r.actor),
                            r.offset_m[0],
                            r.offset_m[1],
                            r.offset_m[2],
                            r.yaw_rad,
                            snake(&r.anchor.feature),
                            r.anchor.object,
                            r.gripper
                        )
                    }
                    None => format!("move {rule}"),
                },
                Step::Gripper { gripper, settle_s } => format!("gripper {gripper:?} ({settle_s} s)"),
                Step::Hold { hold_s } => format!("hold {hold_s} s"),
            })
            .collect();
        let checks: Vec<String> = st
            .checks
            .iter()
            .map(|c| {
                format!("{:?}", c.kind).to_lowercase()
                    + &c.object.as_ref().map(|o| format!(" {o}")).unwrap_or_default()
                    + &c.support.as_ref().map(|o| format!(" on {o}")).unwrap_or_default()
            })
            .collect();
        let what = st
            .description
            .as_deref()
            .map(|d| {
                // A cut text says so: the skill file holds it whole.
                let (text, cut) = crate::extract::whole_sentences(d, STAGE_TEXT_CHARS);
                format!(" ({}{})", text.trim_end_matches([';', ',']), if cut { " …" } else { "" })
            })
            .unwrap_or_default();
        t.push_str(&format!(
            "{}. {}{what}: {}{}\n",
            i + 1,
            st.name,
            steps.join("; "),
            if checks.is_empty() { String::new() } else { format!(" — then check: {}", checks.join(", ")) }
        ));
    }
    for r in &s.recovery {
        t.push_str(&format!("Recovery: when {}, {}\n", r.when, r.action));
    }
    t
}

/// How much of a stage's description the prompt shows (whole sentences), characters.
const STAGE_TEXT_CHARS: usize = 200;

pub const HOW_TO_USE: &str = "These skills were learned in earlier episodes. Their motions are relative to objects \
(robot-skill/skills/README.md): every offset and yaw of a rule is in its anchor's frame, NOT the robot's base frame — \
origin at the named feature of the object as seen when the stage begins, z up (the support surface's normal), x along \
the object's long side (for a round object, or a side that looks the same turned, the direction facing the TCP when the \
stage begins; for in_hand, the TCP's own frame when the stage begins, laid level), y = z × x; yaw is the hand's turn \
about that z from that x (3.14 means facing back along the object's x, not a base-frame angle). \"→ now [...]\" gives the base-frame TCP pose [x, y, z, ax, ay, az] a rule binds to in the first \
observation of this episode, with the TCP where it is now as the reference: a later stage's rules bind to where their \
objects are when that stage begins, so bind them again then rather than copying these numbers. A stage's text that \
ends in \"…\" continues in the skill's file (its `description`). Run a whole skill: \
`import json, robo_skills; robo_skills.run_skill(json.load(open(\"skills/<id>.json\")))` (one JSON line per event, \
then `SKILL RESULT {...}`); or one rule: `r = robo_skills.SkillRunner(skill); scene, state = r.observe(); \
pose = r.target(\"<rule id>\", scene, state)`. Verify effects yourself as always.";

/// Whether a skill's context (after a split) fits this episode; the reason when it does not.
/// Keys: `object_classes` (comma-separated classes that must all be seen), `instruction`
/// (words that must all be in the instruction), each with a `not_` form (must not all hold:
/// the part a split gave to another skill). Any other key cannot be checked: not selected.
pub fn context_mismatch(
    context: &std::collections::BTreeMap<String, String>,
    instruction: &str,
    classes: &[String],
) -> Option<String> {
    let words = tokens(instruction);
    for (key, value) in context {
        let (negated, k) = match key.strip_prefix("not_") {
            Some(k) => (true, k),
            None => (false, key.as_str()),
        };
        let items: Vec<String> = value.split(',').map(|v| v.trim().to_lowercase()).filter(|v| !v.is_empty()).collect();
        let holds = match k {
            "object_classes" => items.iter().all(|c| classes.iter().any(|x| x == c)),
            "instruction" => items.iter().all(|w| words.contains(w)),
            other => return Some(format!("its context names '{other}', which selection cannot check")),
        };
        if holds == negated {
            return Some(format!("its context {key} = {value} does not fit this episode"));
        }
    }
    None
}

/// Steps 1-3.
pub fn select(
    lib: &Library,
    instruction: &str,
    classes: &[String],
    fp: &Fingerprint,
    backend: Backend,
    o: &SelectOpts,
) -> Selection {
    select_bound(lib, instruction, classes, fp, backend, o, &Value::Null)
}

/// Steps 1-3, each skill's rules shown with the poses they bind to now (`bound`: skill id →
/// rule id → pose or {"error": why}, from `skill_tools.py offer`), counted in its tokens.
pub fn select_bound(
    lib: &Library,
    instruction: &str,
    classes: &[String],
    fp: &Fingerprint,
    backend: Backend,
    o: &SelectOpts,
    bound: &Value,
) -> Selection {
    let mut excluded = Vec::new();
    let mut pool: Vec<&Skill> = Vec::new();
    for s in lib.latest() {
        let why = if s.status == Status::Retired {
            Some("retired".to_string())
        } else if s.status == Status::Candidate && !o.include_candidates {
            Some("a candidate (not validated)".to_string())
        } else if &s.applicability.fingerprint != fp {
            Some("learned with another arm, gripper or profile (fingerprint differs)".to_string())
        } else if s.applicability.backend != backend {
            Some(format!("learned on {:?}", s.applicability.backend))
        } else if let Some(missing) = s.applicability.object_classes.iter().find(|c| !classes.contains(c)) {
            Some(format!("needs a {missing}, which perception does not see"))
        } else {
            context_mismatch(&s.applicability.context, instruction, classes)
        };
        match why {
            Some(w) => excluded.push((s.id.clone(), w)),
            None => pool.push(s),
        }
    }
    let query = tokens(instruction);
    let docs: Vec<Vec<String>> = pool.iter().map(|s| document(s)).collect();
    let rel = bm25(&query, &docs);
    let mut ranked: Vec<(Scored, &Skill)> = pool
        .iter()
        .zip(rel)
        .map(|(s, r)| {
            let (k, n) = s.record();
            // A candidate (no judged run yet) counts as a small success estimate when allowed.
            let lb = if n == 0 {
                if o.include_candidates {
                    0.05
                } else {
                    0.0
                }
            } else {
                wilson_lower(k, n).max(0.01)
            };
            let text = render_bound(s, &bound[s.id.as_str()]);
            (
                Scored {
                    id: s.id.clone(),
                    version: s.version,
                    relevance: r,
                    success_lower_bound: lb,
                    score: r * lb,
                    tokens: text.len() / 4,
                },
                *s,
            )
        })
        .collect();
    ranked.sort_by(|a, b| b.0.score.total_cmp(&a.0.score).then(a.0.id.cmp(&b.0.id)));
    let mut chosen = Vec::new();
    let mut prompt = String::new();
    let mut used = HOW_TO_USE.len() / 4;
    for (sc, s) in &ranked {
        if chosen.len() >= o.max_skills {
            break;
        }
        if sc.score <= 0.0 {
            excluded.push((sc.id.clone(), "not relevant to the instruction".into()));
            continue;
        }
        if used + sc.tokens > o.token_budget {
            excluded.push((sc.id.clone(), format!("over the token budget of {}", o.token_budget)));
            continue;
        }
        used += sc.tokens;
        chosen.push(sc.id.clone());
        prompt.push_str(&render_bound(s, &bound[s.id.as_str()]));
        prompt.push('\n');
    }
    if !chosen.is_empty() {
        prompt = format!("{HOW_TO_USE}\n\n{prompt}");
    }
    Selection {
        instruction: instruction.to_string(),
        perceived_classes: classes.to_vec(),
        chosen,
        ranked: ranked.into_iter().map(|(s, _)| s).collect(),
        excluded,
        prompt,
    }
}

/// A library offered to episodes ([`SkillSource`]): reads the library when an episode starts,
/// perceives its first observation, selects, and logs the choice.
pub struct LibrarySource {
    pub root: PathBuf,
    pub dir: PathBuf,
    pub fingerprint: Fingerprint,
    pub opts: SelectOpts,
}

impl SkillSource for LibrarySource {
    fn choose(&self, task: &str, first_obs: &Path, state: &Value) -> anyhow::Result<ChosenSkills> {
        let lib = Library::open(&self.dir)?;
        // Perceive once, and bind every rule of the skills that could be chosen to what is seen.
        let candidates: Vec<&Skill> = lib
            .latest()
            .filter(|s| s.status != Status::Retired && s.applicability.fingerprint == self.fingerprint)
            .collect();
        let seen = crate::tools::call(&self.root, "offer", &json!({"obs": first_obs, "skills": candidates}))?;
        let mut classes: Vec<String> = seen["objects"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or_default()
            .iter()
            .filter_map(|o| o["shape"].as_str().map(str::to_string))
            .collect();
        classes.sort();
        classes.dedup();
        let backend = if state["backend"] == "simulation" { Backend::Sim } else { Backend::Real };
        let sel = select_bound(&lib, task, &classes, &self.fingerprint, backend, &self.opts, &seen["bound"]);
        lib.log("selected", json!({"instruction": task, "chosen": sel.chosen, "ranked": sel.ranked}))?;
        let files = sel
            .chosen
            .iter()
            .filter_map(|id| lib.get(id))
            .map(|s| Ok((format!("skills/{}.json", s.id), serde_json::to_vec_pretty(s)?)))
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(ChosenSkills { prompt: sel.prompt.clone(), log: serde_json::to_value(&sel)?, files })
    }
}
