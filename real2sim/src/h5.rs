//! HDF5 files through h5py: `py/r2g_h5read.py` (run with the checkout's `.venv` Python) prints
//! the datasets asked for as JSON, and this module checks every shape and value an importer
//! relies on, naming the file, the field and the frame of the first fault.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use serde::Deserialize;

use crate::{Error, Result};

#[derive(Debug, Deserialize)]
pub struct Dataset {
    pub shape: Vec<usize>,
    /// Row-major values; None where the file holds NaN or an infinity.
    #[serde(default)]
    pub data: Vec<Option<f64>>,
    #[serde(default)]
    pub text: Vec<serde_json::Value>,
    #[serde(default)]
    pub unsupported: Option<String>,
}

#[derive(Debug, Deserialize)]
struct Dump {
    datasets: BTreeMap<String, Dataset>,
    attrs: BTreeMap<String, serde_json::Value>,
}

/// The datasets of one file that an importer asked for.
#[derive(Debug)]
pub struct H5 {
    /// The file as the user named it (for messages).
    pub file: String,
    pub datasets: BTreeMap<String, Dataset>,
    pub attrs: BTreeMap<String, serde_json::Value>,
}

/// The interpreter that runs the reader: `$R2G_PYTHON`, else the checkout's `.venv/bin/python`.
fn python() -> PathBuf {
    std::env::var_os("R2G_PYTHON").map(PathBuf::from).unwrap_or_else(|| checkout().join(".venv/bin/python"))
}

fn checkout() -> PathBuf {
    runtime::launch::gyms_dir().parent().map(Path::to_path_buf).unwrap_or_default()
}

impl H5 {
    /// Reads the datasets under `prefixes` (every dataset when empty) and the root attributes.
    pub fn read(path: &Path, prefixes: &[&str]) -> Result<Self> {
        let file = path.display().to_string();
        if !path.is_file() {
            return Err(Error::Reader { file, why: "no such file".into() });
        }
        let script = checkout().join("real2sim/py/r2g_h5read.py");
        let py = python();
        let out = Command::new(&py).arg(&script).arg(path).args(prefixes).output().map_err(|e| Error::Reader {
            file: file.clone(),
            why: format!("cannot run {} {} ({e}); build the venv first: make robo", py.display(), script.display()),
        })?;
        if !out.status.success() {
            let why = String::from_utf8_lossy(&out.stderr).trim().lines().last().unwrap_or("").to_string();
            return Err(Error::Reader { file, why });
        }
        let dump: Dump = serde_json::from_slice(&out.stdout)
            .map_err(|e| Error::Reader { file: file.clone(), why: format!("reader output: {e}") })?;
        Ok(Self { file, datasets: dump.datasets, attrs: dump.attrs })
    }

    /// Names of the datasets directly or deeper under `prefix`.
    pub fn names_under(&self, prefix: &str) -> Vec<String> {
        self.datasets.keys().filter(|k| k.starts_with(prefix)).cloned().collect()
    }

    pub fn has(&self, field: &str) -> bool {
        self.datasets.contains_key(field)
    }

    fn get(&self, field: &str) -> Result<&Dataset> {
        self.datasets.get(field).ok_or_else(|| {
            let parent = field.rsplit_once('/').map(|(p, _)| p).unwrap_or("");
            let near: Vec<&str> =
                self.datasets.keys().filter(|k| k.starts_with(parent)).map(String::as_str).take(8).collect();
            let why = if near.is_empty() {
                format!("missing (nothing else under '{parent}/' either)")
            } else {
                format!("missing (found beside it: {})", near.join(", "))
            };
            Error::input(&self.file, field, None, why)
        })
    }

    /// A numeric dataset of shape `[frames, inner...]` as one row of `inner` values per frame,
    /// every value finite. `frames`: the count required, when known.
    pub fn rows(&self, field: &str, inner: &[usize], frames: Option<usize>) -> Result<Vec<Vec<f64>>> {
        let d = self.get(field)?;
        let bad = |frame: Option<usize>, why: String| Error::input(&self.file, field, frame, why);
        if let Some(t) = &d.unsupported {
            return Err(bad(None, format!("holds {t}, expected numbers")));
        }
        if !d.text.is_empty() {
            return Err(bad(None, "holds text, expected numbers".into()));
        }
        let shape_ok = d.shape.len() == inner.len() + 1 && d.shape[1..] == *inner;
        let expected = match frames {
            Some(n) => format!("[{n}{}]", inner.iter().map(|v| format!(", {v}")).collect::<String>()),
            None => format!("[N{}]", inner.iter().map(|v| format!(", {v}")).collect::<String>()),
        };
        if !shape_ok || frames.is_some_and(|n| d.shape[0] != n) {
            return Err(bad(None, format!("shape {:?}, expected {expected}", d.shape)));
        }
        let width: usize = inner.iter().product();
        let mut rows = Vec::with_capacity(d.shape[0]);
        for (i, chunk) in d.data.chunks(width.max(1)).enumerate() {
            let mut row = Vec::with_capacity(width);
            for (k, v) in chunk.iter().enumerate() {
                match v {
                    Some(x) => row.push(*x),
                    None => return Err(bad(Some(i), format!("value {k} is NaN or infinite"))),
                }
            }
            rows.push(row);
        }
        Ok(rows)
    }

    /// As [`H5::rows`], but a non-finite value is kept as NaN for the caller to judge (frames an
    /// importer may drop, such as low-confidence hand frames).
    pub fn rows_lenient(&self, field: &str, inner: &[usize], frames: Option<usize>) -> Result<Vec<Vec<f64>>> {
        let d = self.get(field)?;
        let width: usize = inner.iter().product();
        if d.shape.len() != inner.len() + 1 || d.shape[1..] != *inner || frames.is_some_and(|n| d.shape[0] != n) {
            return Err(Error::input(
                &self.file,
                field,
                None,
                format!("shape {:?}, expected [{}{}]", d.shape, frames.map(|n| n.to_string()).unwrap_or("N".into()), {
                    inner.iter().map(|v| format!(", {v}")).collect::<String>()
                }),
            ));
        }
        Ok(d.data.chunks(width.max(1)).map(|c| c.iter().map(|v| v.unwrap_or(f64::NAN)).collect()).collect())
    }

    /// A 1-D numeric dataset.
    pub fn column(&self, field: &str, frames: Option<usize>) -> Result<Vec<f64>> {
        Ok(self.rows(field, &[], frames)?.into_iter().map(|r| r[0]).collect())
    }

    /// A root attribute as text, if present.
    pub fn attr_text(&self, name: &str) -> Option<String> {
        match self.attrs.get(name)? {
            serde_json::Value::String(s) => Some(s.clone()),
            serde_json::Value::Null => None,
            other => Some(other.to_string()),
        }
    }
}
