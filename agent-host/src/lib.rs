#![doc = include_str!("../README.md")]

pub mod cassette;
pub mod episode;
pub mod llm;
pub mod memory;
pub mod prompt;
pub mod sandbox;
pub mod session;
pub mod tokens;
pub mod viewer;
pub mod worker;

/// A binary next to the running one (test binaries live one level deeper, in deps/).
pub fn sibling(name: &str) -> anyhow::Result<std::path::PathBuf> {
    let exe = std::env::current_exe()?;
    let dir = exe.parent().ok_or_else(|| anyhow::anyhow!("executable has no folder"))?;
    for d in [dir, dir.parent().unwrap_or(dir)] {
        let p = d.join(name);
        if p.is_file() {
            return Ok(p);
        }
    }
    anyhow::bail!("{name} not found next to {} (run `make build`)", exe.display())
}
