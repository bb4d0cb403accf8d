#![doc = include_str!("../README.md")]

pub mod author;
pub mod demo;
pub mod episode;

pub use author::{author_demo, AuthoredDemo};
pub use demo::{read_demo, write_demo};
pub use episode::{replay, Episode, Replay};
