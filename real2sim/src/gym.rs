//! Gym folders: what a scene says about the task's roles and geometry, scene files rewritten for
//! a new folder (relative paths rebased), and whole folders written at once (into a hidden
//! sibling, then renamed), so a failure never leaves half a gym behind.

use std::path::{Component, Path, PathBuf};

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use sim_host::scene::{Criterion, ObjectSpec, PartSpec, Role, Scene, Shape};

use crate::{Error, Result};

/// World pose of a (w, x, y, z) quaternion and a position.
pub fn pose_wxyz(p: [f64; 3], q: [f64; 4]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(p[0], p[1], p[2]),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3])),
    )
}

/// Axis-aligned bounds of a part in its owner's frame (meshes: unknown, None).
pub fn part_bounds(p: &PartSpec) -> Option<([f64; 3], [f64; 3])> {
    let s = &p.size_m;
    let half = match p.shape {
        Shape::Box if s.len() >= 3 => [s[0], s[1], s[2]],
        Shape::Cylinder if s.len() >= 2 => [s[0], s[0], s[1]],
        Shape::Capsule if s.len() >= 2 => [s[0], s[0], s[1] + s[0]],
        Shape::Sphere if !s.is_empty() => [s[0]; 3],
        _ => return None,
    };
    let r = pose_wxyz(p.position_m, p.quat_wxyz);
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for corner in 0..8 {
        let c = Point3::new(
            if corner & 1 == 0 { -half[0] } else { half[0] },
            if corner & 2 == 0 { -half[1] } else { half[1] },
            if corner & 4 == 0 { -half[2] } else { half[2] },
        );
        let w = r * c;
        for k in 0..3 {
            lo[k] = lo[k].min(w[k]);
            hi[k] = hi[k].max(w[k]);
        }
    }
    Some((lo, hi))
}

/// Bounds of the colliding parts of a set of parts, in their owner's frame.
pub fn parts_bounds(parts: &[PartSpec]) -> Option<([f64; 3], [f64; 3])> {
    let mut out: Option<([f64; 3], [f64; 3])> = None;
    for p in parts.iter().filter(|p| p.role != Role::Visual) {
        if let Some((lo, hi)) = part_bounds(p) {
            out = Some(match out {
                None => (lo, hi),
                Some((a, b)) => (std::array::from_fn(|k| a[k].min(lo[k])), std::array::from_fn(|k| b[k].max(hi[k]))),
            });
        }
    }
    out
}

pub fn object_bounds(o: &ObjectSpec) -> Option<([f64; 3], [f64; 3])> {
    parts_bounds(&o.all_parts())
}

/// The start pose in the world of an object or fixture, by name.
pub fn entity_pose(scene: &Scene, name: &str) -> Option<Isometry3<f64>> {
    if let Some(o) = scene.objects.iter().find(|o| o.name == name) {
        return Some(pose_wxyz(o.position_m, o.quat_wxyz));
    }
    scene.fixtures.iter().find(|f| f.name == name).map(|f| pose_wxyz(f.position_m, f.quat_wxyz))
}

/// A point of an object or fixture in the world: the centre of its cavity when it has one, else
/// the centre of its colliding parts' bounds, else its origin.
pub fn entity_centre(scene: &Scene, name: &str) -> Option<[f64; 3]> {
    let pose = entity_pose(scene, name)?;
    let local = if let Some(o) = scene.objects.iter().find(|o| o.name == name) {
        match (o.cavity_min_m, o.cavity_max_m) {
            (Some(lo), Some(hi)) => Some(mid(lo, hi)),
            _ => object_bounds(o).map(|(lo, hi)| mid(lo, hi)),
        }
    } else {
        let f = scene.fixtures.iter().find(|f| f.name == name)?;
        match (f.cavity_min_m, f.cavity_max_m) {
            (Some(lo), Some(hi)) => Some(mid(lo, hi)),
            _ => parts_bounds(&f.parts).map(|(lo, hi)| mid(lo, hi)),
        }
    };
    let p = pose * Point3::from(local.unwrap_or([0.0; 3]));
    Some([p.x, p.y, p.z])
}

/// Lowest and highest point of an object's colliding parts below and above its origin, in the
/// world's vertical at its start orientation, m.
pub fn vertical_extent(o: &ObjectSpec) -> Option<(f64, f64)> {
    let (lo, hi) = object_bounds(o)?;
    let rot = pose_wxyz([0.0; 3], o.quat_wxyz).rotation;
    let z: Vec<f64> = (0..8)
        .map(|c| {
            let p = Point3::new(
                if c & 1 == 0 { lo[0] } else { hi[0] },
                if c & 2 == 0 { lo[1] } else { hi[1] },
                if c & 4 == 0 { lo[2] } else { hi[2] },
            );
            (rot * p).z
        })
        .collect();
    Some((z.iter().cloned().fold(f64::INFINITY, f64::min), z.iter().cloned().fold(f64::NEG_INFINITY, f64::max)))
}

/// Height of the highest point of an object's colliding parts at its start pose, m (world).
pub fn entity_top(scene: &Scene, name: &str) -> Option<f64> {
    let o = scene.objects.iter().find(|o| o.name == name)?;
    vertical_extent(o).map(|(_, hi)| o.position_m[2] + hi)
}

fn mid(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|k| 0.5 * (a[k] + b[k]))
}

/// The task's roles as its success rules name them: the object moved (the first free object a
/// rule is about) and where it goes (the support, container or the first thing it may touch).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Roles {
    pub object: Option<String>,
    pub target: Option<String>,
}

pub fn roles(scene: &Scene) -> Roles {
    let free = |n: &str| scene.objects.iter().any(|o| o.name == n && o.free);
    let mut r = Roles::default();
    for c in &scene.task.success {
        let (object, target) = match c {
            Criterion::On { object, support } => (object, Some(support.clone())),
            Criterion::Inside { object, container, .. } => (object, container.clone()),
            Criterion::TouchesOnly { object, others } => (object, others.first().cloned()),
            Criterion::Upright { object, .. } | Criterion::Past { object, .. } => (object, None),
            _ => continue,
        };
        if !free(object) {
            continue;
        }
        if r.object.is_none() {
            r.object = Some(object.clone());
        }
        if r.object.as_deref() == Some(object.as_str()) && r.target.is_none() {
            r.target = target.filter(|t| t != Scene::TABLE);
        }
    }
    r
}

/// `to` relative to the folder `from_dir` (both made absolute first).
pub fn relative_to(to: &Path, from_dir: &Path) -> PathBuf {
    let abs =
        |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| std::env::current_dir().unwrap_or_default().join(p));
    let (to, from) = (abs(to), abs(from_dir));
    let tc: Vec<Component> = to.components().collect();
    let fc: Vec<Component> = from.components().collect();
    let common = tc.iter().zip(&fc).take_while(|(a, b)| a == b).count();
    let mut out = PathBuf::new();
    for _ in common..fc.len() {
        out.push("..");
    }
    for c in &tc[common..] {
        out.push(c);
    }
    out
}

/// The scene file's TOML, its relative paths (robot URDF, meshes) rebased from the scene's
/// folder to `to_dir`, the demonstration pointed at `demo.csv` beside it.
pub fn rebased_scene(scene_path: &Path, to_dir: &Path) -> Result<toml::Table> {
    let text = std::fs::read_to_string(scene_path).map_err(Error::io(scene_path))?;
    let mut t: toml::Table = toml::from_str(&text)
        .map_err(|e| Error::Episode(anyhow::anyhow!("scene {}: {}", scene_path.display(), e.message())))?;
    let from = scene_path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let rebase = |v: &mut toml::Value| {
        if let Some(s) = v.as_str() {
            let p = Path::new(s);
            if p.is_relative() {
                *v = toml::Value::String(relative_to(&from.join(p), to_dir).display().to_string());
            }
        }
    };
    if let Some(u) = t.get_mut("robot").and_then(|r| r.get_mut("urdf")) {
        rebase(u);
    }
    let rebase_parts = |parts: Option<&mut toml::Value>| {
        for p in parts.and_then(|p| p.as_array_mut()).into_iter().flatten() {
            if let Some(m) = p.get_mut("mesh") {
                rebase(m);
            }
        }
    };
    for key in ["objects", "fixtures"] {
        for item in t.get_mut(key).and_then(|v| v.as_array_mut()).into_iter().flatten() {
            if let Some(m) = item.get_mut("mesh") {
                rebase(m);
            }
            rebase_parts(item.get_mut("parts"));
            if let Some(j) = item.get_mut("joint") {
                rebase_parts(j.get_mut("parts"));
            }
        }
    }
    if let Some(task) = t.get_mut("task").and_then(|v| v.as_table_mut()) {
        task.insert("demonstration".into(), toml::Value::String("demo.csv".into()));
    }
    Ok(t)
}

/// A folder built in a hidden sibling (`.<name>.partial-<pid>`) and renamed into place by
/// [`Staging::commit`]; dropped uncommitted, it is removed. Relative paths resolve the same from
/// the sibling as from the final folder, so episodes can run inside it before the commit.
pub struct Staging {
    pub dir: PathBuf,
    out: PathBuf,
    committed: bool,
}

impl Staging {
    /// Refuses an existing non-empty `out`.
    pub fn new(out: &Path) -> Result<Self> {
        if out.exists() && std::fs::read_dir(out).map(|mut d| d.next().is_some()).unwrap_or(true) {
            return Err(Error::Output {
                path: out.into(),
                why: "exists and is not empty; choose another --out".into(),
            });
        }
        let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        std::fs::create_dir_all(parent).map_err(Error::io(parent))?;
        let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "gym".into());
        let dir = parent.join(format!(".{name}.partial-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).map_err(Error::io(&dir))?;
        Ok(Self { dir, out: out.into(), committed: false })
    }

    pub fn write(&self, file: &str, bytes: &[u8]) -> Result<PathBuf> {
        let p = self.dir.join(file);
        std::fs::write(&p, bytes).map_err(Error::io(&p))?;
        Ok(p)
    }

    pub fn commit(mut self) -> Result<PathBuf> {
        if self.out.exists() {
            std::fs::remove_dir(&self.out).map_err(Error::io(&self.out))?;
        }
        std::fs::rename(&self.dir, &self.out).map_err(Error::io(&self.out))?;
        self.committed = true;
        Ok(self.out.clone())
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// Writes a whole folder at once (see [`Staging`]).
pub fn write_folder(out: &Path, files: &[(&str, Vec<u8>)]) -> Result<()> {
    let s = Staging::new(out)?;
    for (file, bytes) in files {
        s.write(file, bytes)?;
    }
    s.commit().map(|_| ())
}

/// Unit vector along z of a rotation (the tool axis of a TCP pose).
pub fn z_axis(r: &UnitQuaternion<f64>) -> Vector3<f64> {
    r * Vector3::z()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_climb_out_and_down() {
        let base = std::env::temp_dir().join(format!("r2s-rel-{}", std::process::id()));
        std::fs::create_dir_all(base.join("a/b")).expect("dir");
        std::fs::create_dir_all(base.join("c")).expect("dir");
        assert_eq!(relative_to(&base.join("c/x.urdf"), &base.join("a/b")), PathBuf::from("../../c/x.urdf"));
        let _ = std::fs::remove_dir_all(&base);
    }

    #[test]
    fn a_folder_is_written_whole_or_not_at_all() {
        let base = std::env::temp_dir().join(format!("r2s-folder-{}", std::process::id()));
        let out = base.join("gym");
        write_folder(&out, &[("a.txt", b"1".to_vec()), ("b.txt", b"2".to_vec())]).expect("write");
        assert_eq!(std::fs::read_to_string(out.join("b.txt")).expect("b"), "2");
        let e = write_folder(&out, &[("a.txt", b"3".to_vec())]).expect_err("exists");
        assert!(e.to_string().contains("not empty"), "{e}");
        // A file that cannot be written (a folder in the way) leaves no output and no temporary.
        let out2 = base.join("gym2");
        assert!(write_folder(&out2, &[("sub/a.txt", b"1".to_vec())]).is_err());
        assert!(!out2.exists());
        assert_eq!(std::fs::read_dir(&base).expect("list").count(), 1);
        let _ = std::fs::remove_dir_all(&base);
    }
}
