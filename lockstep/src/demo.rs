//! Demonstrations on disk: CSV rows of q1..q7 (rad) and the gripper (−1 open … +1 closed) at the
//! scene's `task.demonstration_hz`.

use std::path::Path;

use anyhow::{bail, Context};
use ipc_schema::WAYPOINT_LEN;

/// Reads a demonstration: CSV rows of q1..q7 (rad) and the gripper (−1 open … +1 closed); a
/// first line that is not numbers is a header.
pub fn read_demo(path: &Path) -> anyhow::Result<Vec<[f64; WAYPOINT_LEN]>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading demonstration {}", path.display()))?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        let parsed: Result<Vec<f64>, _> = cells.iter().map(|c| c.parse::<f64>()).collect();
        match parsed {
            Err(_) if rows.is_empty() && i == 0 => continue,
            Err(_) => bail!("{}: line {}: not a row of numbers", path.display(), i + 1),
            Ok(v) if v.len() != WAYPOINT_LEN || !v.iter().all(|x| x.is_finite()) => {
                bail!(
                    "{}: line {}: expected {WAYPOINT_LEN} finite numbers (q1..q7, gripper), got {}",
                    path.display(),
                    i + 1,
                    v.len()
                )
            }
            Ok(v) => {
                let mut row = [0.0; WAYPOINT_LEN];
                row.copy_from_slice(&v);
                rows.push(row);
            }
        }
    }
    if rows.is_empty() {
        bail!("{}: the demonstration has no rows", path.display());
    }
    Ok(rows)
}

/// Writes a demonstration in the format [`read_demo`] reads.
pub fn write_demo(path: &Path, rows: &[[f64; WAYPOINT_LEN]]) -> anyhow::Result<()> {
    let mut out = String::from("q1,q2,q3,q4,q5,q6,q7,gripper\n");
    for r in rows {
        out.push_str(&r.iter().map(|v| format!("{v:.6}")).collect::<Vec<_>>().join(","));
        out.push('\n');
    }
    write_atomic(path, out.as_bytes())
}

/// Writes `bytes` to a sibling temporary file, then renames it over `path`: a reader never sees
/// a half-written file, and a failure leaves any earlier file as it was.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let name = path.file_name().with_context(|| format!("{} is not a file path", path.display()))?;
    let tmp = path.with_file_name(format!(".{}.tmp{}", name.to_string_lossy(), std::process::id()));
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| {
        let _ = std::fs::remove_file(&tmp);
        format!("renaming {} to {}", tmp.display(), path.display())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_written_demonstration_reads_back_and_bad_rows_name_their_line() {
        let dir = std::env::temp_dir().join(format!("r2g-demo-unit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("demo.csv");
        let rows = vec![[0.1, -0.2, 0.3, -2.0, 0.0, 1.5, 0.7, -1.0], [0.2, -0.2, 0.3, -2.1, 0.0, 1.6, 0.7, 1.0]];
        write_demo(&path, &rows).expect("write");
        assert_eq!(read_demo(&path).expect("read"), rows);
        // No temporary file is left beside it.
        assert_eq!(std::fs::read_dir(&dir).expect("list").count(), 1);
        std::fs::write(&path, "q1,q2,q3,q4,q5,q6,q7,gripper\n0,0,0,0,0,0,0,0\n0,0,0,NaN,0,0,0,0\n").expect("write");
        let e = read_demo(&path).expect_err("NaN").to_string();
        assert!(e.contains("line 3") && e.contains("8 finite numbers"), "{e}");
        std::fs::write(&path, "0,0,0\n").expect("write");
        assert!(read_demo(&path).expect_err("short").to_string().contains("got 3"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
