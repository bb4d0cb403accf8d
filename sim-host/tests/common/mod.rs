//! What the scene tests share: the robot and table every test scene starts from, and a fresh
//! temporary folder per test.

use std::path::{Path, PathBuf};

/// The `[robot]` (shipped Panda, absolute URDF path, ready pose) and `[table]` tables.
pub fn robot_and_table() -> String {
    let urdf = Path::new(env!("CARGO_MANIFEST_DIR")).join("../robots/panda/panda.urdf").canonicalize().expect("urdf");
    format!(
        "[robot]\nurdf = \"{}\"\ninitial_joints_rad = [0.0, -0.7853982, 0.0, -2.3561945, 0.0, 1.5707963, 0.7853982]\n\
         [table]\ntop_center_m = [0.45, 0.0, 0.0]\nsize_m = [1.3, 1.2]\n",
        urdf.display()
    )
}

/// An empty folder of this test process, named after `tag`.
pub fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("r2g-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}
