//! Chunk acceptance off the tick thread (wall mode).
//!
//! Checking a chunk (IK along an ee_pose path, collisions and workspace at every sample) takes
//! up to about a millisecond for the heaviest or unreachable chunks: done inside the tick, it
//! would push the next command past its deadline. The tick keeps the cheap decisions that
//! depend on its state ([`Controller::admit`](crate::Controller::admit), [`Controller::commit`](crate::Controller::commit)); the chunk's own checks
//! ([`Acceptance::plan`]) run on the planner thread started here, before the loop thread
//! raises itself to SCHED_FIFO (so the planner keeps the normal scheduler).
//!
//! Handoff: [`SLOTS`] slots allocated once, each with a copy of the request's waypoints and a
//! boxed plan, passed around a ring by two counters. The tick fills slot `submitted % SLOTS`
//! and publishes it by incrementing `submitted` (release); the planner checks slots up to
//! `submitted` in order and publishes each by incrementing `done` (release); the tick takes
//! the finished slots up to `done` back in order and swaps their plan box with the running
//! one ([`Controller::commit`](crate::Controller::commit)). Each slot has exactly one owner at a time, decided by the two
//! counters: no lock, no allocation, no copy of a plan, and the tick never waits for the
//! planner. The planner sleeps in `park_timeout` when there is nothing to check; the loop
//! wakes it with [`Planner::wake`] after the tick (a futex wake, no allocation).
//!
//! Replies keep their order: a chunk's `accepted` (or `rejected` with the reason) goes out
//! when the tick commits it, before the tick that first samples its plan, so before anything
//! of it moves or finishes.

use std::cell::UnsafeCell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use controllers::{ChunkPlan, Rejection};
use ipc_schema::{Request, MAX_CHUNK, N_JOINTS, WAYPOINT_LEN};

use crate::controller::{Acceptance, Job};
use crate::stats::Histogram;

/// Chunks that may be in flight at once (all of one client: see [`Controller::admit`](crate::Controller::admit)).
pub const SLOTS: usize = 4;

/// One chunk on its way through the planner.
struct Slot {
    job: Job,
    actions: [[f64; WAYPOINT_LEN]; MAX_CHUNK],
    outcome: Result<(), Rejection>,
    /// The checked plan; after a commit, the plan it replaced (reused next time).
    plan: Box<ChunkPlan>,
    /// CLOCK_MONOTONIC when the tick took the request, ns.
    received_ns: u64,
}

struct Shared {
    slots: Box<[UnsafeCell<Slot>]>,
    /// Slots handed to the planner so far (written by the tick only).
    submitted: AtomicU64,
    /// Slots the planner has finished so far (written by the planner only).
    done: AtomicU64,
    stop: AtomicBool,
}

// SAFETY: a slot is touched only by its owner: the planner owns the slots in [done, submitted),
// the tick the finished ones in [head, done) and the free ones outside [head, submitted);
// ownership passes through the release stores and acquire loads of `submitted` and `done`.
unsafe impl Sync for Shared {}

/// The tick's side of the planner.
pub struct Planner {
    shared: Arc<Shared>,
    /// Next slot to take back (tick only).
    head: u64,
    /// Our own count of submitted slots (the atomic's only writer).
    submitted: u64,
    /// The client whose chunks are in flight (meaningful while any are).
    client: u64,
    wake_pending: bool,
    thread: Option<std::thread::JoinHandle<Histogram>>,
}

/// A finished chunk, handed to [`Planner::take_finished`]'s callback.
pub struct Finished<'a> {
    pub job: &'a Job,
    pub outcome: Result<(), Rejection>,
    /// Swap it in with [`Controller::commit`](crate::Controller::commit); it then holds the replaced plan.
    pub plan: &'a mut Box<ChunkPlan>,
    pub received_ns: u64,
}

impl Planner {
    /// Starts the planner thread: the normal scheduler, on every CPU but `tick_cpu` (the loop
    /// thread's) where there are others. Call before the loop thread goes real-time.
    pub fn spawn(acceptance: Acceptance, tick_cpu: Option<usize>) -> std::io::Result<Self> {
        let slots: Vec<UnsafeCell<Slot>> = (0..SLOTS)
            .map(|_| {
                UnsafeCell::new(Slot {
                    job: Job {
                        id: 0,
                        client: 0,
                        ct: ipc_schema::ControlType::Joint,
                        len: 0,
                        freq_hz: 0.0,
                        start_q: [0.0; N_JOINTS],
                    },
                    actions: [[0.0; WAYPOINT_LEN]; MAX_CHUNK],
                    outcome: Ok(()),
                    plan: Box::new(ChunkPlan::hold([0.0; N_JOINTS], -1.0)),
                    received_ns: 0,
                })
            })
            .collect();
        let shared = Arc::new(Shared {
            slots: slots.into_boxed_slice(),
            submitted: AtomicU64::new(0),
            done: AtomicU64::new(0),
            stop: AtomicBool::new(false),
        });
        let theirs = shared.clone();
        let thread = std::thread::Builder::new().name("r2g-planner".into()).spawn(move || {
            if let Some(cpu) = tick_cpu {
                keep_off(cpu);
            }
            plan_loop(&theirs, &acceptance)
        })?;
        Ok(Self { shared, head: 0, submitted: 0, client: 0, wake_pending: false, thread: Some(thread) })
    }

    /// The client whose chunks are being checked, if any.
    #[inline]
    pub fn in_flight(&self) -> Option<u64> {
        (self.submitted > self.head).then_some(self.client)
    }

    /// Hands a chunk admitted by [`Controller::admit`](crate::Controller::admit) to the planner: copies its waypoints
    /// into a free slot. Returns false (nothing taken) when every slot is in flight.
    /// Allocation-free.
    #[inline]
    pub fn submit(&mut self, job: &Job, req: &Request, received_ns: u64) -> bool {
        if self.submitted - self.head >= SLOTS as u64 {
            return false;
        }
        let cell = &self.shared.slots[(self.submitted % SLOTS as u64) as usize];
        // SAFETY: this slot is outside [head, submitted): neither the planner nor a finished
        // chunk of ours holds it (see `Shared`).
        let slot = unsafe { &mut *cell.get() };
        slot.job = *job;
        let n = job.len.min(MAX_CHUNK);
        slot.actions[..n].copy_from_slice(&req.actions[..n]);
        slot.received_ns = received_ns;
        slot.outcome = Ok(());
        self.submitted += 1;
        self.client = job.client;
        self.shared.submitted.store(self.submitted, Ordering::Release);
        self.wake_pending = true;
        true
    }

    /// Calls `f` for every chunk the planner has finished, oldest first, then frees its slot.
    /// Allocation-free.
    #[inline]
    pub fn take_finished(&mut self, mut f: impl FnMut(Finished<'_>)) {
        let done = self.shared.done.load(Ordering::Acquire);
        while self.head < done {
            let cell = &self.shared.slots[(self.head % SLOTS as u64) as usize];
            // SAFETY: head < done: the planner has published this slot and will not touch it
            // again until we submit into it anew.
            let slot = unsafe { &mut *cell.get() };
            let outcome = std::mem::replace(&mut slot.outcome, Ok(()));
            f(Finished { job: &slot.job, outcome, plan: &mut slot.plan, received_ns: slot.received_ns });
            self.head += 1;
        }
    }

    /// Whether the planner thread still runs (it ends only by a panic before [`Self::stop`]).
    /// Allocation-free.
    #[inline]
    pub fn alive(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Wakes the planner if chunks were submitted since the last call. Call after the tick.
    #[inline]
    pub fn wake(&mut self) {
        if std::mem::take(&mut self.wake_pending) {
            if let Some(t) = &self.thread {
                t.thread().unpark();
            }
        }
    }

    /// Stops the planner thread; returns how long its checks took (one sample per chunk).
    pub fn stop(mut self) -> Histogram {
        self.finish()
    }

    fn finish(&mut self) -> Histogram {
        self.shared.stop.store(true, Ordering::Release);
        match self.thread.take() {
            Some(t) => {
                t.thread().unpark();
                t.join().unwrap_or_default()
            }
            None => Histogram::new(),
        }
    }
}

impl Drop for Planner {
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.finish();
        }
    }
}

/// Takes the calling thread off `cpu`, if it may run anywhere else.
fn keep_off(cpu: usize) {
    // SAFETY: a zeroed cpu_set_t is a valid empty set; the calls get its true size.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0
            || cpu >= libc::CPU_SETSIZE as usize
            || !libc::CPU_ISSET(cpu, &set)
            || libc::CPU_COUNT(&set) < 2
        {
            return;
        }
        libc::CPU_CLR(cpu, &mut set);
        let _ = libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set);
    }
}

fn plan_loop(shared: &Shared, acceptance: &Acceptance) -> Histogram {
    let mut took = Histogram::new();
    loop {
        let done = shared.done.load(Ordering::Relaxed);
        if done < shared.submitted.load(Ordering::Acquire) {
            let cell = &shared.slots[(done % SLOTS as u64) as usize];
            // SAFETY: done < submitted: the tick has published this slot and leaves it alone
            // until we publish it back.
            let slot = unsafe { &mut *cell.get() };
            let t0 = crate::rt::now_ns();
            slot.outcome = match acceptance.plan(&slot.job, &slot.actions) {
                Ok(plan) => {
                    *slot.plan = plan;
                    Ok(())
                }
                Err(why) => Err(why),
            };
            took.record(crate::rt::now_ns() - t0);
            shared.done.store(done + 1, Ordering::Release);
            continue;
        }
        if shared.stop.load(Ordering::Acquire) {
            return took;
        }
        std::thread::park_timeout(Duration::from_millis(50));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::{Admission, Controller};
    use controllers::LimiterConfig;
    use ipc_schema::{ControlType, RequestKind, SimState, Status};

    const HOME: [f64; 7] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

    fn controller() -> Controller {
        let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../gyms/pick_block_plate/scene.toml");
        let (robot, safety) = crate::scene_robot(&scene).expect("scene");
        Controller::new(robot, LimiterConfig::default(), 0.001).with_safety(safety)
    }

    fn request(id: u64, q: [f64; 7]) -> Box<Request> {
        let mut r = Box::new(Request {
            id,
            client: 1,
            kind: RequestKind::Chunk as u32,
            control_type: ControlType::Joint as u32,
            len: 1,
            step_ticks: 0,
            freq_hz: 0.0,
            actions: [[0.0; WAYPOINT_LEN]; MAX_CHUNK],
        });
        r.actions[0][..7].copy_from_slice(&q);
        r.actions[0][7] = -1.0;
        r
    }

    /// Runs one request through admit → planner → commit, as the wall loop does.
    fn through(p: &mut Planner, ctl: &mut Controller, state: &SimState, req: &Request) -> Vec<(u64, u32)> {
        let mut replies = Vec::new();
        match ctl.admit(req, state, p.in_flight()) {
            Admission::Answer(r, _) => replies.extend(r.map(|r| (r.id, r.status))),
            Admission::Plan(job) => {
                assert!(p.submit(&job, req, 0));
                p.wake();
                let t0 = std::time::Instant::now();
                while p.in_flight().is_some() {
                    p.take_finished(|f| {
                        if let Some(r) = ctl.commit(f.job, f.outcome, Some(f.plan), state) {
                            replies.push((r.id, r.status));
                        }
                        if let Some(r) = ctl.take_accepted() {
                            replies.push((r.id, r.status));
                        }
                    });
                    assert!(t0.elapsed() < Duration::from_secs(10), "the planner never answered");
                    std::thread::yield_now();
                }
            }
        }
        replies
    }

    #[test]
    fn chunks_checked_on_the_planner_thread_decide_as_on_the_tick() {
        let mut ctl = controller();
        let mut p = Planner::spawn(ctl.acceptance(), None).expect("planner");
        let state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
        let mut near = HOME;
        near[0] = 0.2;
        let accepted = through(&mut p, &mut ctl, &state, &request(1, near));
        assert_eq!(accepted, vec![(1, Status::Accepted as u32)]);
        // Through the table: refused by the planner, with the reason, and nothing replaced.
        let down = [0.0, 1.7, 0.0, -0.2, 0.0, 1.571, 0.785];
        let refused = through(&mut p, &mut ctl, &state, &request(2, down));
        assert_eq!(refused, vec![(2, Status::Rejected as u32)]);
        assert_eq!(ctl.active_request(), 1);
        // The same client's next chunk replaces the running one: superseded, then accepted.
        let replaced = through(&mut p, &mut ctl, &state, &request(3, HOME));
        assert_eq!(replaced, vec![(1, Status::Failed as u32), (3, Status::Accepted as u32)]);
        let took = p.stop();
        assert_eq!(took.count(), 3);
    }

    #[test]
    fn in_flight_chunks_keep_their_order_and_others_wait() {
        let mut ctl = controller();
        let mut p = Planner::spawn(ctl.acceptance(), None).expect("planner");
        let state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
        let mut a = HOME;
        a[0] = 0.2;
        // Four chunks of one client in flight at once (the fifth finds no slot).
        for id in 1..=SLOTS as u64 {
            let Admission::Plan(job) = ctl.admit(&request(id, a), &state, p.in_flight()) else { panic!("admitted") };
            assert!(p.submit(&job, &request(id, a), 0));
        }
        let Admission::Plan(job) = ctl.admit(&request(9, a), &state, p.in_flight()) else { panic!("admitted") };
        assert!(!p.submit(&job, &request(9, a), 0));
        // Another client waits while they are checked, as it would behind a running chunk.
        let mut other = request(10, a);
        other.client = 2;
        let Admission::Answer(Some(r), _) = ctl.admit(&other, &state, p.in_flight()) else { panic!("refused") };
        assert_eq!(r.status, Status::Rejected as u32);
        assert!(r.reason_str().contains("another client"), "{}", r.reason_str());
        p.wake();
        let mut order = Vec::new();
        let t0 = std::time::Instant::now();
        while p.in_flight().is_some() {
            p.take_finished(|f| {
                if let Some(r) = ctl.commit(f.job, f.outcome, Some(f.plan), &state) {
                    order.push((r.id, r.status));
                }
                if let Some(r) = ctl.take_accepted() {
                    order.push((r.id, r.status));
                }
            });
            assert!(t0.elapsed() < Duration::from_secs(10));
            std::thread::yield_now();
        }
        let (acc, sup) = (Status::Accepted as u32, Status::Failed as u32);
        assert_eq!(order, vec![(1, acc), (1, sup), (2, acc), (2, sup), (3, acc), (3, sup), (4, acc)]);
    }

    #[test]
    fn the_state_is_checked_again_when_the_checks_come_back() {
        let mut ctl = controller();
        let state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
        let mut near = HOME;
        near[0] = 0.2;
        let Admission::Plan(job) = ctl.admit(&request(1, near), &state, None) else { panic!("admitted") };
        let outcome = ctl.plan_now(&job, &request(1, near));
        assert!(outcome.is_ok());
        // The robot side fell silent while the chunk was being checked: refused, nothing runs.
        ctl.robot_lost(150.0);
        let r = ctl.commit(&job, outcome, None, &state).expect("refused");
        assert_eq!((r.id, r.status), (1, Status::Rejected as u32));
        assert!(r.reason_str().contains("published no state"), "{}", r.reason_str());
        assert_eq!(ctl.active_request(), 0);
        assert!(ctl.take_accepted().is_none());
    }

    #[test]
    fn a_chunk_whose_start_has_moved_on_is_refused_at_commit() {
        let mut ctl = controller();
        let mut state = SimState { seq: 1, q_rad: HOME, finger_m: 0.04, finger_max_m: 0.04, ..SimState::default() };
        let mut far = HOME;
        far[0] = 0.3;
        assert!(ctl.request(&request(1, far), &state).0.is_none());
        // Admitted at home; then the running chunk moves the arm on before the checks return.
        let Admission::Plan(job) = ctl.admit(&request(2, HOME), &state, None) else { panic!("admitted") };
        let outcome = ctl.plan_now(&job, &request(2, HOME));
        for _ in 0..400 {
            let (cmd, _) = ctl.tick(&state);
            state.q_rad = cmd.q_rad;
            state.seq += 1;
        }
        let r = ctl.commit(&job, outcome, None, &state).expect("refused");
        assert_eq!((r.id, r.status), (2, Status::Rejected as u32));
        assert!(r.reason_str().contains("while this chunk was being checked"), "{}", r.reason_str());
        assert_eq!(ctl.active_request(), 1, "the running chunk goes on");
    }
}
