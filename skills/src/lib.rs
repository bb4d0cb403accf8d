#![doc = include_str!("../README.md")]

pub mod admit;
pub mod extract;
pub mod fingerprint;
pub mod format;
pub mod learn;
pub mod library;
pub mod merge;
pub mod record;
pub mod run;
pub mod select;
pub mod tools;

pub use format::Skill;
pub use library::Library;
