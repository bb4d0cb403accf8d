//! The skill library on disk: `<dir>/<skill id>/v0001.json`, `v0002.json`, ... — a revision
//! writes a new file, nothing is ever rewritten — and `<dir>/events.jsonl`, an append-only log
//! of what changed, what was dropped and why, and which skills episodes were given.
//!
//! A version is written under a temporary name, synced, then linked to its final name, which
//! fails if that name exists (two writers never overwrite each other), so the library is never
//! left half-written.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use serde_json::{json, Value};

use crate::format::{Skill, Status};

pub struct Library {
    pub dir: PathBuf,
    /// Every version of every skill, oldest first.
    pub versions: BTreeMap<String, Vec<Skill>>,
}

fn version_name(v: u32) -> String {
    format!("v{v:04}.json")
}

impl Library {
    /// Reads every version under `dir` (a missing folder is an empty library). A file that is
    /// not a valid skill, or whose id/version disagree with its path, is an error naming it.
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        let mut versions: BTreeMap<String, Vec<Skill>> = BTreeMap::new();
        let Ok(rd) = std::fs::read_dir(dir) else {
            return Ok(Self { dir: dir.to_path_buf(), versions });
        };
        let mut folders: Vec<_> = rd.flatten().filter(|e| e.file_type().is_ok_and(|t| t.is_dir())).collect();
        folders.sort_by_key(|e| e.file_name());
        for f in folders {
            let id = f.file_name().to_string_lossy().into_owned();
            let mut files: Vec<_> = std::fs::read_dir(f.path())?
                .flatten()
                .map(|e| e.path())
                .filter(|p| {
                    p.extension().is_some_and(|x| x == "json")
                        && p.file_name().is_some_and(|n| n.to_string_lossy().starts_with('v'))
                })
                .collect();
            files.sort();
            let mut list = Vec::new();
            for p in files {
                let text = std::fs::read_to_string(&p).with_context(|| format!("reading {}", p.display()))?;
                let s = Skill::parse(&text).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
                let expect = version_name(s.version);
                if s.id != id || p.file_name().is_none_or(|n| n.to_string_lossy() != expect) {
                    bail!("{}: holds skill {} v{} (its path says otherwise)", p.display(), s.id, s.version);
                }
                list.push(s);
            }
            for (i, s) in list.iter().enumerate() {
                if s.version as usize != i + 1 {
                    bail!("{}: versions of {id} are not 1..{} without gaps", f.path().display(), list.len());
                }
            }
            if !list.is_empty() {
                versions.insert(id, list);
            }
        }
        Ok(Self { dir: dir.to_path_buf(), versions })
    }

    /// The newest version of each skill.
    pub fn latest(&self) -> impl Iterator<Item = &Skill> {
        self.versions.values().filter_map(|v| v.last())
    }

    pub fn get(&self, id: &str) -> Option<&Skill> {
        self.versions.get(id).and_then(|v| v.last())
    }

    /// Writes `skill` as the next version of its id (its `version` must be that number) and
    /// keeps it in memory; never replaces an existing file.
    pub fn write(&mut self, skill: Skill) -> anyhow::Result<()> {
        skill.validate()?;
        let next = self.versions.get(&skill.id).map_or(1, |v| v.len() as u32 + 1);
        if skill.version != next {
            bail!("skill {}: writing v{} but the next version is v{next}", skill.id, skill.version);
        }
        let folder = self.dir.join(&skill.id);
        std::fs::create_dir_all(&folder).with_context(|| format!("creating {}", folder.display()))?;
        let final_path = folder.join(version_name(skill.version));
        let tmp = folder.join(format!(".{}.{}.partial", version_name(skill.version), std::process::id()));
        {
            let mut f = std::fs::File::create(&tmp).with_context(|| format!("writing {}", tmp.display()))?;
            f.write_all(&serde_json::to_vec_pretty(&skill)?)?;
            f.write_all(b"\n")?;
            f.sync_all()?;
        }
        // link(2) fails when the name exists: an existing version is never overwritten.
        let linked = std::fs::hard_link(&tmp, &final_path);
        let _ = std::fs::remove_file(&tmp);
        linked.with_context(|| format!("{} already exists or cannot be written", final_path.display()))?;
        self.versions.entry(skill.id.clone()).or_default().push(skill);
        Ok(())
    }

    /// Appends one event line (synced) to `events.jsonl`.
    pub fn log(&self, event: &str, detail: Value) -> anyhow::Result<()> {
        std::fs::create_dir_all(&self.dir)?;
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(self.dir.join("events.jsonl"))?;
        let line = json!({"event": event, "at_unix_s": unix_now(), "detail": detail});
        writeln!(f, "{line}")?;
        f.sync_data()?;
        Ok(())
    }

    /// The events logged so far (unreadable lines skipped).
    pub fn events(&self) -> Vec<Value> {
        std::fs::read_to_string(self.dir.join("events.jsonl"))
            .map(|t| t.lines().filter_map(|l| serde_json::from_str(l).ok()).collect())
            .unwrap_or_default()
    }

    /// Skills that are not retired, newest versions.
    pub fn active(&self) -> impl Iterator<Item = &Skill> {
        self.latest().filter(|s| s.status != Status::Retired)
    }
}

pub fn unix_now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}
