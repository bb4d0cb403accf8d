#![doc = include_str!("../README.md")]

pub mod chunk;
pub mod error;
pub mod limiter;
pub mod math;
pub mod robot;

pub use chunk::{ChunkPlan, Waypoint};
pub use error::{Error, Rejection};
pub use limiter::{JointTracker, LimiterConfig};
pub use robot::{JointLimits, RobotModel};

/// Arm joints of the supported robots.
pub const N: usize = 7;
