//! A demonstration played natively (a `lockstep::Episode`, in process), remembering when each
//! row was reached in simulated time. The runtime stretches segments so no joint exceeds half
//! its velocity limit and waits for the arm to come to rest after each chunk, so native time
//! runs behind row time (`row / demonstration_hz`); events are compared on the native clock.

use std::path::Path;

use controllers::{ChunkPlan, LimiterConfig};
use ipc_schema::{ControlType, Status, MAX_CHUNK};
use lockstep::Episode;

use crate::Result;

pub struct Native {
    pub episode: Episode,
    /// Simulated time at which each row's segment ends (the row is reached).
    pub row_times_s: Vec<f64>,
    /// Chunks that did not execute: (first row, reason).
    pub failures: Vec<(usize, String)>,
}

/// End of each segment of a plan, s from its start: the earliest time its sample has passed it.
fn segment_ends(plan: &ChunkPlan) -> Vec<f64> {
    let total = plan.duration_s();
    (0..plan.len())
        .map(|w| {
            let (mut lo, mut hi) = (0.0, total);
            for _ in 0..40 {
                let mid = 0.5 * (lo + hi);
                if plan.sample(mid).reached > w || plan.sample(mid).finished {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            hi
        })
        .collect()
}

/// Plays `rows` at `hz` from the scene's start (augmented by `seed`), then lets physics run on
/// for `settle_s`.
pub fn play(scene_path: &Path, seed: u64, rows: &[[f64; 8]], hz: f64, settle_s: f64) -> Result<Native> {
    let mut ep = Episode::new(scene_path, seed)?;
    let mut row_times_s = Vec::with_capacity(rows.len());
    let mut failures = Vec::new();
    for (k, chunk) in rows.chunks(MAX_CHUNK).enumerate() {
        let start_s = ep.sim.time_s();
        let start_q = ep.sim.measure(0, 0, 0).q_rad;
        match ChunkPlan::joint(chunk, hz, start_q, &ep.sim.robot, &LimiterConfig::default(), None) {
            Ok(plan) => row_times_s.extend(segment_ends(&plan).into_iter().map(|t| start_s + t)),
            Err(_) => row_times_s.extend(std::iter::repeat_n(start_s, chunk.len())),
        }
        let r = ep.run_chunk(ControlType::Joint, chunk, hz);
        if r.status != Status::Executed as u32 {
            failures.push((k * MAX_CHUNK, r.reason_str().to_string()));
        }
    }
    ep.hold(settle_s);
    Ok(Native { episode: ep, row_times_s, failures })
}

impl Native {
    /// Native time of a (fractional) row.
    pub fn time_of_row(&self, row: f64) -> f64 {
        let t = &self.row_times_s;
        if t.is_empty() {
            return 0.0;
        }
        let r = row.clamp(0.0, (t.len() - 1) as f64);
        let (a, w) = (r.floor() as usize, r.fract());
        let b = (a + 1).min(t.len() - 1);
        t[a] + w * (t[b] - t[a])
    }

    /// The row being worked on at native time `t_s` (the first not yet reached).
    pub fn row_at(&self, t_s: f64) -> usize {
        self.row_times_s.partition_point(|x| *x < t_s).min(self.row_times_s.len().saturating_sub(1))
    }
}
