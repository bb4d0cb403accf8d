//! The services a gymnasium environment uses beside `robo` (`r2g-sim --env`, `r2g up --env`):
//! the evaluator's verdict on the episode so far, judged here on the native trace, and the
//! augmentation seed of the next episode. Only the environment opens them; the agent side
//! (`robo`, the sandbox) never does, and an instance started without `--env` has none.

use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use ipc_schema::{EnvAnswer, EnvQuery, EnvQueryKind, Qos, Services, ENV_ANSWER_LEN};

use crate::trace::{evaluate, Evaluation, Trace};
use crate::Sim;

type S = ipc::Service;

/// Queries from many environments (a vector of them may share an instance), answers to all.
const QUERIES: Qos = Qos { history: 0, buffer: 16, max_publishers: 8, max_subscribers: 1, borrowed: 2 };
const ANSWERS: Qos = Qos { history: 0, buffer: 16, max_publishers: 1, max_subscribers: 8, borrowed: 2 };

pub struct EnvService {
    queries: Subscriber<S, EnvQuery, ()>,
    answers: Publisher<S, EnvAnswer, ()>,
    wake: Notifier<S>,
}

/// The sizes both ends open the services with.
pub fn qos() -> (Qos, Qos) {
    (QUERIES, ANSWERS)
}

impl EnvService {
    pub fn open(node: &Node<S>, services: &Services) -> anyhow::Result<Self> {
        let queries = ipc_schema::open_or_create_pubsub::<EnvQuery>(node, &services.env_query(), QUERIES)?
            .subscriber_builder()
            .create()?;
        let answers = ipc_schema::open_or_create_pubsub::<EnvAnswer>(node, &services.env_answer(), ANSWERS)?
            .publisher_builder()
            .create()?;
        let wake = ipc_schema::open_or_create_event(node, &services.env_wake())?.notifier_builder().create()?;
        Ok(Self { queries, answers, wake })
    }

    /// Answers every waiting query: a seed is kept for the next reset, a verdict is judged on
    /// `trace` (the episode so far). Returns whether anything was answered.
    pub fn serve(&self, sim: &mut Sim, trace: &Trace, reset_id: u64) -> anyhow::Result<bool> {
        let mut answered = false;
        while let Some(q) = self.queries.receive()? {
            let mut a = EnvAnswer {
                id: q.id,
                reset_id,
                sim_time_s: sim.time_s(),
                success: 0,
                len: 0,
                json: [0; ENV_ANSWER_LEN],
            };
            match q.kind {
                k if k == EnvQueryKind::Seed as u32 => sim.seed = q.seed,
                k if k == EnvQueryKind::Evaluate as u32 => {
                    let e = evaluate(&sim.scene, trace);
                    a.success = u32::from(e.success);
                    let json = verdict_json(&e)?;
                    a.json[..json.len()].copy_from_slice(&json);
                    a.len = json.len() as u32;
                }
                _ => {
                    let json = format!("{{\"error\": \"unknown query kind {}\"}}", q.kind);
                    a.json[..json.len()].copy_from_slice(json.as_bytes());
                    a.len = json.len() as u32;
                }
            }
            self.answers.send_copy(a)?;
            answered = true;
        }
        if answered {
            self.wake.notify()?;
        }
        Ok(answered)
    }
}

/// The verdict as JSON of at most [`ENV_ANSWER_LEN`] bytes, never half a document: the whole
/// evaluation, else its checks without their values (`{"checks": {name: {"pass": ..}}}`, the
/// shape the environment reads either way), else the success alone; `cut` says what was left out.
pub fn verdict_json(e: &Evaluation) -> serde_json::Result<Vec<u8>> {
    let json = serde_json::to_vec(e)?;
    if json.len() <= ENV_ANSWER_LEN {
        return Ok(json);
    }
    let checks: serde_json::Map<String, serde_json::Value> =
        e.checks.iter().map(|(k, c)| (k.clone(), serde_json::json!({"pass": c.pass}))).collect();
    let json = serde_json::to_vec(&serde_json::json!({
        "gym": e.gym, "success": e.success, "checks": checks, "cut": "the checks' values did not fit"
    }))?;
    if json.len() <= ENV_ANSWER_LEN {
        return Ok(json);
    }
    let json = serde_json::to_vec(&serde_json::json!({
        "gym": e.gym, "success": e.success, "checks": {}, "cut": "the checks did not fit"
    }))?;
    if json.len() <= ENV_ANSWER_LEN {
        return Ok(json);
    }
    serde_json::to_vec(&serde_json::json!({"success": e.success, "checks": {}, "cut": "the verdict did not fit"}))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trace::Check;

    fn evaluation(checks: usize, value_bytes: usize) -> Evaluation {
        Evaluation {
            gym: "g".into(),
            success: true,
            checks: (0..checks)
                .map(|i| (format!("check_{i:04}"), Check { value: "v".repeat(value_bytes).into(), pass: i % 2 == 0 }))
                .collect(),
            trace_sha256: String::new(),
            criteria_sha256: String::new(),
            samples: 1,
            sim_time_s: 0.0,
        }
    }

    fn read(json: &[u8]) -> serde_json::Value {
        assert!(json.len() <= ENV_ANSWER_LEN, "{} bytes", json.len());
        serde_json::from_slice(json).expect("a whole document")
    }

    #[test]
    fn an_oversized_verdict_keeps_the_checks_pass_in_the_shape_the_environment_reads() {
        let small = read(&verdict_json(&evaluation(3, 10)).expect("json"));
        assert_eq!(small["checks"]["check_0000"]["value"], "vvvvvvvvvv");
        let cut = read(&verdict_json(&evaluation(20, 400)).expect("json"));
        assert_eq!(cut["checks"].as_object().map(|c| c.len()), Some(20));
        assert_eq!(cut["checks"]["check_0000"]["pass"], true);
        assert_eq!(cut["checks"]["check_0001"]["pass"], false);
        assert!(cut["cut"].is_string());
        let bare = read(&verdict_json(&evaluation(400, 1)).expect("json"));
        assert_eq!((bare["success"].as_bool(), bare["checks"].as_object().map(|c| c.len())), (Some(true), Some(0)));
    }
}
