#![doc = include_str!("../README.md")]

pub mod chunk;
pub mod collision;
pub mod diffik;
pub mod error;
pub mod ik;
pub mod kinematics;
pub mod limiter;
pub mod math;
pub mod mesh;
pub mod monitor;
pub mod reference;
pub mod robot;
pub mod safety;

pub use chunk::{ChunkPlan, Waypoint};
pub use collision::{CollisionModel, StaticScene, Violation, Workspace};
pub use error::{Error, Rejection, StepQuantity};
pub use ik::{IkConfig, IkError, IkSolution, IkSolver};
pub use kinematics::{FrameId, Jacobian, Kinematics};
pub use limiter::{JointTracker, LimiterConfig};
pub use reference::Reference;
pub use robot::{CartesianLimits, JointLimits, Profile, RobotModel};

/// Arm joints of the supported robots.
pub const N: usize = 7;
