#![doc = include_str!("../README.md")]

pub mod mjcf;
pub mod render;
pub mod scene;
pub mod sim;

pub use scene::Scene;
pub use sim::{Sim, SimError};
