//! The reference the controller follows each tick: a chunk plan samples it, the limiter tracks
//! it. Its own module so that the dependency runs one way: `chunk` → `limiter` → `reference`.

use crate::N;

/// A reference sample: where the arm should be, how fast it should move, and the gripper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reference {
    pub q_rad: [f64; N],
    pub dq_rad_s: [f64; N],
    pub gripper: f64,
    /// Per joint, where the current one-directional stretch of the reference ends: the next
    /// waypoint at which it turns back, or the last one. The limiter never passes it.
    pub goal_q_rad: [f64; N],
    /// Waypoints whose segment has ended.
    pub reached: usize,
    pub finished: bool,
}
