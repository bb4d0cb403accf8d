//! What a round did, read from a native trace (synthetic traces written here): a free fall, a
//! topple onto the table, a grasp, resting on another object, a gripper shut on nothing.

use std::path::PathBuf;

use sim_host::trace::{Sample, Trace};
use sim_host::Scene;
use skills::record::effects;

const BLOCK: u16 = 0;
const PLATE: u16 = 1;
const TABLE: u16 = 2;
const ROBOT: u16 = 3;

fn scene() -> Scene {
    Scene::load(&PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../gyms/pick_block_plate/scene.toml")).expect("scene")
}

/// (t, block pose [x, y, z, qw, qx, qy, qz], finger opening, contacts)
type Synthetic<'a> = (f64, [f64; 7], f64, &'a [[u16; 2]]);

fn trace(samples: &[Synthetic]) -> Trace {
    Trace {
        gym: "pick_block_plate".into(),
        owners: ["block", "plate", "table", "robot", "floor"].map(String::from).to_vec(),
        objects: vec!["block".into(), "plate".into()],
        finger_max_m: 0.04,
        samples: samples
            .iter()
            .map(|(t, b, f, c)| Sample {
                t_s: *t,
                objects: vec![*b, [0.5, 0.15, 0.006, 1.0, 0.0, 0.0, 0.0]],
                joints: vec![],
                tcp_m: [0.4, 0.0, 0.3],
                finger_m: *f,
                arm_rad: Vec::new(),
                contacts: c.to_vec(),
                penetration_m: 0.0,
                penetration_pair: [0, 0],
            })
            .collect(),
        ..Default::default()
    }
}

const UP: [f64; 4] = [1.0, 0.0, 0.0, 0.0];

fn at(x: f64, y: f64, z: f64, q: [f64; 4]) -> [f64; 7] {
    [x, y, z, q[0], q[1], q[2], q[3]]
}

#[test]
fn a_free_fall_a_topple_a_grasp_a_placement_and_an_empty_grasp_are_told_apart() {
    let s = scene();
    // Carried at 20 cm, let go, falls to the table.
    let fell = trace(&[
        (0.0, at(0.5, 0.0, 0.2, UP), 0.02, &[[BLOCK, ROBOT]]),
        (0.1, at(0.5, 0.0, 0.2, UP), 0.04, &[]),
        (0.2, at(0.5, 0.0, 0.02, UP), 0.04, &[[BLOCK, TABLE]]),
    ]);
    let e = effects(&s, &fell, 0.0, 0.2).expect("effects");
    assert_eq!(e.fell.len(), 1, "{e:?}");
    assert!(e.fell[0].1 > 0.17);
    // Lowered with the hand, then released just above the table: no fall.
    let placed = trace(&[
        (0.0, at(0.5, 0.0, 0.2, UP), 0.02, &[[BLOCK, ROBOT]]),
        (0.1, at(0.5, 0.0, 0.025, UP), 0.02, &[[BLOCK, ROBOT]]),
        (0.2, at(0.5, 0.15, 0.032, UP), 0.04, &[[BLOCK, PLATE]]),
    ]);
    let e = effects(&s, &placed, 0.0, 0.2).expect("effects");
    assert!(e.fell.is_empty(), "{e:?}");
    assert_eq!(e.rests_on, vec![("block".to_string(), "plate".to_string())]);
    // Knocked over: lying on its side on the table.
    let side = [std::f64::consts::FRAC_1_SQRT_2, std::f64::consts::FRAC_1_SQRT_2, 0.0, 0.0];
    let toppled = trace(&[
        (0.0, at(0.5, 0.0, 0.02, UP), 0.04, &[[BLOCK, TABLE]]),
        (0.2, at(0.52, 0.0, 0.02, side), 0.04, &[[BLOCK, TABLE]]),
    ]);
    assert_eq!(effects(&s, &toppled, 0.0, 0.2).expect("effects").toppled.len(), 1);
    // Grasped and lifted.
    let grasped = trace(&[
        (0.0, at(0.5, 0.0, 0.02, UP), 0.04, &[[BLOCK, TABLE]]),
        (0.2, at(0.5, 0.0, 0.08, UP), 0.019, &[[BLOCK, ROBOT]]),
    ]);
    let e = effects(&s, &grasped, 0.0, 0.2).expect("effects");
    assert_eq!(e.grasped, vec!["block".to_string()]);
    assert_eq!(e.rose.len(), 1);
    assert!(!e.closed_on_nothing);
    // Closed beside the block: shut on nothing.
    let missed = trace(&[
        (0.0, at(0.5, 0.0, 0.02, UP), 0.04, &[[BLOCK, TABLE]]),
        (0.2, at(0.5, 0.0, 0.02, UP), 0.0, &[[BLOCK, TABLE]]),
    ]);
    let e = effects(&s, &missed, 0.0, 0.2).expect("effects");
    assert!(e.closed_on_nothing && e.grasped.is_empty(), "{e:?}");
    // A window outside the trace, or backwards, says nothing rather than panicking.
    assert!(effects(&s, &missed, 0.2, 0.0).is_none());
}
