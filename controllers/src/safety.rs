//! What the runtime checks besides joint limits: self-collision, known static geometry and a
//! workspace box, for chunk waypoints and the path between them at acceptance, and for every
//! command (and the configuration its braking would end in) in the tick.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use crate::collision::{BuildError, CollisionModel, StaticScene, Violation, Workspace};
use crate::robot::RobotModel;
use crate::N;

/// Joint-space spacing at which the path between two waypoints is checked, rad.
pub const PATH_STEP_RAD: f64 = 0.02;
/// Most configurations checked along one chunk's path: long chunks get a coarser spacing, so
/// that accepting one costs at most about a millisecond.
pub const MAX_PATH_CHECKS: usize = 512;

#[derive(Debug, Clone)]
pub struct SafetyChecks {
    pub collision: CollisionModel,
    pub scene: StaticScene,
    pub workspace: Workspace,
    /// Clearance required between bodies, and between a body and an obstacle, m.
    pub margin_m: f64,
}

/// A table top (world frame) as the scene describes it.
#[derive(Debug, Clone, Copy)]
pub struct Table {
    pub top_center_m: [f64; 3],
    pub size_m: [f64; 2],
}

impl SafetyChecks {
    /// The checks for a robot standing at `base_position_m` (yaw `base_yaw_rad`) in a world
    /// with an optional table; the workspace defaults to the table's footprint up to 1 m above
    /// it, or to a box around the arm's reach without a table. `urdf_path`, the file `urdf` was
    /// read from, locates its meshes ([`CollisionModel::from_urdf_file`]).
    #[allow(clippy::too_many_arguments)]
    pub fn for_scene(
        urdf: &str,
        urdf_path: Option<&std::path::Path>,
        robot: &RobotModel,
        base_position_m: [f64; 3],
        base_yaw_rad: f64,
        table: Option<Table>,
        workspace: Option<([f64; 3], [f64; 3])>,
        margin_m: f64,
    ) -> Result<Self, BuildError> {
        let collision = match urdf_path {
            Some(path) => CollisionModel::from_urdf_file(urdf, path, robot)?,
            None => CollisionModel::from_urdf_str(urdf, robot)?,
        };
        let world_from_base = Isometry3::from_parts(
            Translation3::new(base_position_m[0], base_position_m[1], base_position_m[2]),
            UnitQuaternion::from_euler_angles(0.0, 0.0, base_yaw_rad),
        );
        let base_from_world = world_from_base.inverse();
        let mut scene = StaticScene::new();
        let mut ws = workspace;
        if let Some(t) = table {
            // A 5 cm slab whose top face is the table top.
            let [x, y, z] = t.top_center_m;
            let centre = base_from_world * Isometry3::translation(x, y, z - 0.025);
            scene.add_box("table", centre, [t.size_m[0] / 2.0, t.size_m[1] / 2.0, 0.025])?;
            if ws.is_none() {
                // The footprint's corners in the base frame bound the box (yaw may turn it).
                let mut lo = [f64::INFINITY; 3];
                let mut hi = [f64::NEG_INFINITY; 3];
                for (sx, sy, sz) in [(-1.0, -1.0, 0.0), (1.0, -1.0, 0.0), (-1.0, 1.0, 0.0), (1.0, 1.0, 1.0)] {
                    for corner in [
                        [x + sx * t.size_m[0] / 2.0, y + sy * t.size_m[1] / 2.0, z + sz],
                        [x - sx * t.size_m[0] / 2.0, y - sy * t.size_m[1] / 2.0, z + 1.0 - sz],
                    ] {
                        let p = base_from_world * nalgebra::Point3::from(corner);
                        for k in 0..3 {
                            lo[k] = lo[k].min(p[k]);
                            hi[k] = hi[k].max(p[k]);
                        }
                    }
                }
                ws = Some((lo, hi));
            }
        }
        let (lo, hi) = ws.unwrap_or(([-1.0, -1.0, -0.5], [1.0, 1.0, 1.5]));
        Ok(Self { collision, scene, workspace: Workspace::new(lo, hi)?, margin_m })
    }

    #[inline]
    pub fn check(&self, q: &[f64; N]) -> Result<(), Violation<'_>> {
        self.collision.check(q, &self.scene, &self.workspace, self.margin_m)
    }

    /// Checks the straight joint-space path from `a` to `b` (both ends included) at
    /// `spacing_rad` of the largest joint's travel (never finer than [`PATH_STEP_RAD`]).
    pub fn check_path(&self, a: &[f64; N], b: &[f64; N], spacing_rad: f64) -> Result<(), Violation<'_>> {
        let span = (0..N).map(|j| (b[j] - a[j]).abs()).fold(0.0, f64::max);
        let steps = ((span / spacing_rad.max(PATH_STEP_RAD)).ceil() as usize).clamp(1, MAX_PATH_CHECKS);
        for k in 0..=steps {
            let s = k as f64 / steps as f64;
            let q: [f64; N] = std::array::from_fn(|j| a[j] + s * (b[j] - a[j]));
            self.check(&q)?;
        }
        Ok(())
    }
}
