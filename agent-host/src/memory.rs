//! Append-only memory records (robot-skill/memory/README.md): earlier records copied into a
//! program's scratch folder before it runs, new ones appended to the memory folder after it.

use std::io::Write as _;
use std::path::Path;

/// Most memory records one episode (or one `r2g exec`) may add, and the largest one, bytes.
pub const MAX_RECORDS: usize = 50;
pub const MAX_RECORD_BYTES: u64 = 64 * 1024;

/// Gives a fresh scratch folder `memory/` with copies of every earlier record in `memory_dir`
/// (none if it does not exist), so a stage program reads them where the documents say.
/// Whatever an earlier program left at `scratch/memory` (a reused scratch folder of `r2g exec`)
/// is removed first, following no links, so a planted link cannot redirect the copies.
pub fn seed(scratch: &Path, memory_dir: &Path) -> anyhow::Result<()> {
    if !memory_dir.is_dir() {
        return Ok(());
    }
    let dst = scratch.join("memory");
    match std::fs::symlink_metadata(&dst) {
        Ok(m) if m.is_dir() => std::fs::remove_dir_all(&dst)?,
        Ok(_) => std::fs::remove_file(&dst)?,
        Err(_) => {}
    }
    std::fs::create_dir(&dst)?;
    mirror(memory_dir, &dst)
}

/// Copies every record of `memory_dir` that `dst` (an existing folder the host owns) lacks:
/// records only (`<timestamp>-<uuid>.json` or `.md`), not the folder's README or anything else;
/// a name `dst` holds already is left as it is (records never change).
pub fn mirror(memory_dir: &Path, dst: &Path) -> anyhow::Result<()> {
    let Ok(rd) = std::fs::read_dir(memory_dir) else { return Ok(()) };
    let records = rd
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_file()) && is_record_name(&e.file_name().to_string_lossy()));
    for e in records {
        let Ok(body) = std::fs::read(e.path()) else { continue };
        // A record already there (or a name taken by something else) stays as it is.
        let _ = write_new(&dst.join(e.file_name()), &body);
    }
    Ok(())
}

/// Writes a new file whole or not at all, never replacing one: the bytes go to a temporary
/// name beside it, which is then hard-linked to `path` (the link fails if `path` exists, even as
/// a dangling link) and removed. A reader never sees a half-written record.
fn write_new(path: &Path, body: &[u8]) -> std::io::Result<()> {
    use std::os::unix::fs::OpenOptionsExt as _;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.{}.partial", std::process::id()));
    let mut out = std::fs::OpenOptions::new().write(true).create_new(true).custom_flags(libc::O_NOFOLLOW).open(&tmp)?;
    let written = out.write_all(body).and_then(|_| out.sync_data()).and_then(|_| std::fs::hard_link(&tmp, path));
    let _ = std::fs::remove_file(&tmp);
    written
}

/// A record's file name as robot-skill/memory/README.md gives it: `<UTC timestamp>-<uuid4>`
/// with `.json` or `.md`, so it starts with a digit (the folder's README is no record).
pub fn is_record_name(name: &str) -> bool {
    name.len() < 120
        && name.starts_with(|c: char| c.is_ascii_digit())
        && name.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        && (name.ends_with(".json") || name.ends_with(".md"))
}

/// Copies new memory records the worker wrote under `scratch/memory/` to the memory folder,
/// never overwriting one that exists (records are append-only). Runs while no worker is alive;
/// follows no links and reads only regular files of a bounded size.
pub fn collect(scratch: &Path, memory_dir: &Path, taken: &mut usize) -> Vec<String> {
    use std::io::Read as _;
    use std::os::unix::fs::OpenOptionsExt as _;
    let mut added = Vec::new();
    let dir = scratch.join("memory");
    if !std::fs::symlink_metadata(&dir).is_ok_and(|m| m.is_dir()) {
        return added;
    }
    let Ok(rd) = std::fs::read_dir(&dir) else { return added };
    for e in rd.flatten() {
        if *taken >= MAX_RECORDS {
            break;
        }
        let name = e.file_name().to_string_lossy().into_owned();
        let dst = memory_dir.join(&name);
        if !is_record_name(&name) || dst.exists() {
            continue;
        }
        let Ok(mut f) =
            std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK).open(e.path())
        else {
            continue;
        };
        if !f.metadata().is_ok_and(|m| m.is_file() && m.len() <= MAX_RECORD_BYTES) {
            continue;
        }
        let mut body = Vec::new();
        if (&mut f).take(MAX_RECORD_BYTES).read_to_end(&mut body).is_err() {
            continue;
        }
        let written = std::fs::create_dir_all(memory_dir).and_then(|_| write_new(&dst, &body));
        if written.is_ok() {
            *taken += 1;
            added.push(name);
        }
    }
    added
}
