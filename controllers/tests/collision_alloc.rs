//! `CollisionModel::check` and `clearance` must not allocate: counted with a global allocator.
//! Kept in its own test binary so no other test allocates while this one counts.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use controllers::collision::{CollisionModel, StaticScene, Workspace};
use controllers::{Profile, RobotModel};
use nalgebra::Isometry3;

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn check_does_not_allocate() {
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../robots/panda/panda.urdf")).expect("URDF");
    let robot = RobotModel::from_urdf_str(&xml, "hand_tcp", Profile::Panda).expect("model");
    let col = CollisionModel::from_urdf_str(&xml, &robot).expect("collision model");
    let mut scene = StaticScene::new();
    scene.add_box("table", Isometry3::translation(0.5, 0.0, 0.2), [0.3, 0.5, 0.02]).expect("table");
    scene.add_half_space("floor", [0.0; 3], [0.0, 0.0, 1.0]).expect("floor");
    let ws = Workspace::new([-1.0; 3], [1.0; 3]).expect("box").with_bodies();
    let free = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];
    let folded = [-0.27, -0.17, 0.42, -2.86, -0.15, 1.10, 1.18];
    let mut nan = free;
    nan[0] = f64::NAN;

    let before = ALLOCATIONS.load(Ordering::SeqCst);
    let mut results = [false; 4];
    for _ in 0..100 {
        results[0] = col.check(&free, &scene, &ws, 0.01).is_ok();
        results[1] = col.check(&folded, &scene, &ws, 0.01).is_ok();
        results[2] = col.check(&nan, &scene, &ws, 0.01).is_ok();
        results[3] = col.clearance(&folded, &scene).is_ok();
    }
    let after = ALLOCATIONS.load(Ordering::SeqCst);
    assert_eq!(results, [true, false, false, true]);
    assert_eq!(after - before, 0, "check allocated");
}
