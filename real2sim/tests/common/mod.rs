//! Helpers shared by the integration tests.

use std::path::{Path, PathBuf};

/// The checkout this crate is in.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("checkout").to_path_buf()
}

/// A fresh folder under the build's temporary folder (`target/tmp`, inside the checkout, so
/// relative paths to the checkout's robots resolve only when they are right), unique to this
/// process.
pub fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("r2s-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("tmp");
    d
}
