#![doc = include_str!("../README.md")]

pub mod augment;
pub mod blender;
pub mod compare;
pub mod droid;
pub mod egodex;
pub mod events;
pub mod gym;
pub mod h5;
pub mod import;
pub mod judge;
pub mod record;
pub mod replay;
pub mod resample;
pub mod retarget;
pub mod sheet;
pub mod validate;

pub use record::Record;

use std::path::PathBuf;

/// What went wrong, with the file, the field and the frame where the input is at fault.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The source file is wrong: a missing field, a wrong shape, a NaN, time running backwards,
    /// a hand never seen, a pose the robot cannot reach.
    #[error("{file}: {field}{}: {why}", frame.map(|f| format!(": frame {f}")).unwrap_or_default())]
    Input { file: String, field: String, frame: Option<usize>, why: String },
    /// The HDF5 reader could not read the file at all.
    #[error("{file}: cannot read it as HDF5: {why}")]
    Reader { file: String, why: String },
    #[error("{path}: {why}")]
    Output { path: PathBuf, why: String },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// Scenes, episodes and the robot model (the lower crates' errors, with their context).
    #[error(transparent)]
    Episode(#[from] anyhow::Error),
}

impl Error {
    pub(crate) fn input(file: &str, field: &str, frame: Option<usize>, why: impl Into<String>) -> Self {
        Error::Input { file: file.into(), field: field.into(), frame, why: why.into() }
    }

    pub(crate) fn io(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> Self + '_ {
        move |source| Error::Io { path: path.to_path_buf(), source }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

/// SHA-256 of bytes, lower-case hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}
