//! Fixed-size latency histograms, allocated before the loop starts so recording costs a few
//! integer operations and never allocates.

/// Histogram of durations with 100 ns bins up to 10 ms and one overflow bin.
pub struct Histogram {
    bins: Box<[u32]>,
    count: u64,
    max_ns: u64,
    sum_ns: u64,
}

const BIN_NS: u64 = 100;
const BINS: usize = 100_000;

impl Default for Histogram {
    fn default() -> Self {
        Self::new()
    }
}

impl Histogram {
    pub fn new() -> Self {
        Self { bins: vec![0u32; BINS + 1].into_boxed_slice(), count: 0, max_ns: 0, sum_ns: 0 }
    }

    #[inline]
    pub fn record(&mut self, ns: u64) {
        let i = ((ns / BIN_NS) as usize).min(BINS);
        self.bins[i] = self.bins[i].saturating_add(1);
        self.count += 1;
        self.sum_ns += ns;
        self.max_ns = self.max_ns.max(ns);
    }

    /// Adds every sample of `other`.
    pub fn merge(&mut self, other: &Histogram) {
        for (a, b) in self.bins.iter_mut().zip(other.bins.iter()) {
            *a = a.saturating_add(*b);
        }
        self.count += other.count;
        self.sum_ns += other.sum_ns;
        self.max_ns = self.max_ns.max(other.max_ns);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn max_us(&self) -> f64 {
        self.max_ns as f64 / 1000.0
    }

    pub fn mean_us(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum_ns as f64 / self.count as f64 / 1000.0
        }
    }

    /// The p-quantile (0..1) in microseconds, at bin resolution (upper edge of the bin).
    pub fn quantile_us(&self, p: f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let target = ((p * self.count as f64).ceil() as u64).max(1);
        let mut acc = 0u64;
        for (i, &n) in self.bins.iter().enumerate() {
            acc += n as u64;
            if acc >= target {
                if i == BINS {
                    return self.max_us();
                }
                return (((i as u64 + 1) * BIN_NS).min(self.max_ns.max(1))) as f64 / 1000.0;
            }
        }
        self.max_us()
    }

    pub fn summary(&self) -> serde_json::Value {
        serde_json::json!({
            "count": self.count,
            "mean_us": self.mean_us(),
            "p50_us": self.quantile_us(0.50),
            "p99_us": self.quantile_us(0.99),
            "p999_us": self.quantile_us(0.999),
            "max_us": self.max_us(),
            "cdf": self.cdf(),
        })
    }

    /// The distribution as `[latency µs, fraction at or below]` points, dense in the tail
    /// (every percent, then 99.x and 99.9x), for plots.
    pub fn cdf(&self) -> Vec<[f64; 2]> {
        let mut ps: Vec<f64> = (1..=99).map(|k| k as f64 / 100.0).collect();
        ps.extend((1..=9).map(|k| 0.99 + k as f64 / 1000.0));
        ps.extend((1..=9).map(|k| 0.999 + k as f64 / 10_000.0));
        ps.push(1.0);
        ps.into_iter().map(|p| [self.quantile_us(p), p]).collect()
    }
}

/// What every tick records.
#[derive(Default)]
pub struct TickStats {
    pub wake: Histogram,
    pub compute: Histogram,
    /// Tick-to-command latency: from each deadline (paced: the state's publication) until its
    /// command was out. A deadline skipped by an overrun counts until the next command.
    pub command: Histogram,
    /// Chunks: from taking the request to its `accepted` or `rejected` reply (on the tick, or
    /// through the planner thread).
    pub accept: Histogram,
    /// The planner thread's checks, one sample per chunk (wall mode, acceptance off the tick).
    pub planning: Histogram,
    /// Where chunks were checked: "planner" (a thread of its own) or "tick".
    pub acceptance: &'static str,
    /// The deadline of the last command (for [`Self::command_sent`]).
    last_command_deadline: u64,
    pub overruns: u64,
    pub ticks: u64,
    /// Failed sends/receives on agent-facing ports (counted, never fatal).
    pub agent_port_errors: u64,
    /// The same on the robot side's ports (a robot side that died or restarted).
    pub robot_port_errors: u64,
    /// Times the robot side fell silent past the state timeout.
    pub robot_losses: u64,
    /// Commands outside the position, velocity or acceleration limits (each checked against
    /// the one before; 0 is the only right answer).
    pub limit_violations: u64,
}

impl TickStats {
    /// Records the tick-to-command latency of a command sent at `sent` for the tick due at
    /// `deadline`, and of every earlier deadline since the last command (`period` apart; an
    /// overrun skipped them, so they waited for this one). `period` 0: this deadline only.
    /// Allocation-free.
    #[inline]
    pub fn command_sent(&mut self, deadline: u64, period: u64, sent: u64) {
        if period > 0 && self.last_command_deadline > 0 && deadline > self.last_command_deadline {
            let skipped = ((deadline - self.last_command_deadline) / period).saturating_sub(1).min(10_000);
            for k in 1..=skipped {
                self.command.record(sent.saturating_sub(self.last_command_deadline + k * period));
            }
        }
        self.command.record(sent.saturating_sub(deadline));
        self.last_command_deadline = deadline;
    }

    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "ticks": self.ticks,
            "overruns": self.overruns,
            "agent_port_errors": self.agent_port_errors,
            "robot_port_errors": self.robot_port_errors,
            "robot_losses": self.robot_losses,
            "limit_violations": self.limit_violations,
            "tick_allocations": crate::alloc_count::tick_allocations(),
            "tick_pool_allocations": crate::alloc_count::tick_pool_allocations(),
            "tick_frees": crate::alloc_count::tick_frees(),
            "wake": self.wake.summary(),
            "compute": self.compute.summary(),
            "command": self.command.summary(),
            "accept": self.accept.summary(),
            "planning": self.planning.summary(),
            "acceptance": self.acceptance,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_of_a_known_distribution() {
        let mut h = Histogram::new();
        for i in 1..=1000u64 {
            h.record(i * 1000);
        }
        assert!((h.quantile_us(0.5) - 500.1).abs() < 0.2, "{}", h.quantile_us(0.5));
        assert!((h.quantile_us(0.99) - 990.1).abs() < 0.2);
        assert_eq!(h.max_us(), 1000.0);
        let cdf = h.cdf();
        assert!(cdf.windows(2).all(|w| w[0][0] <= w[1][0] && w[0][1] < w[1][1]), "monotone");
        assert_eq!(cdf.last().map(|p| p[0]), Some(1000.0));
        h.record(u64::MAX / 2);
        assert_eq!(h.count(), 1001);
    }

    #[test]
    fn a_skipped_deadline_waits_for_the_next_command() {
        let mut s = TickStats::default();
        s.command_sent(1_000_000, 1_000_000, 1_020_000);
        // The tick of 2 ms overran: the next command goes out for 3 ms, at 3.02 ms.
        s.command_sent(3_000_000, 1_000_000, 3_020_000);
        assert_eq!(s.command.count(), 3);
        assert_eq!(s.command.max_us(), 1020.0);
        assert!((s.command.quantile_us(0.5) - 20.0).abs() < 0.2);
    }
}
