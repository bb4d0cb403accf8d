#![doc = include_str!("../README.md")]

pub mod bop;
pub mod env_service;
pub mod mjcf;
pub mod placement;
pub mod render;
pub mod scene;
pub mod sim;
pub mod trace;

pub use scene::Scene;
pub use sim::{Sim, SimError};
