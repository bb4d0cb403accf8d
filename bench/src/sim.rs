//! `r2g bench sim`: how fast physics runs in lockstep with the 1 kHz controller, per gym, beside
//! MuJoCo stepping the same scene alone in the same run; and how long a frame takes to render
//! (RGB alone, and RGB plus depth) with the headless EGL renderer.

use std::time::Instant;

use ipc_schema::{ControlType, JointCommand, MAX_CHUNK};
use serde_json::{json, Map, Value};
use sim_host::render::Cameras;

use lockstep::{read_demo, Episode};

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

pub fn run(only: &[String], frames: usize) -> anyhow::Result<Value> {
    let gyms: Vec<String> = if only.is_empty() { runtime::launch::gym_names() } else { only.to_vec() };
    let mut per_gym = Map::new();
    println!("{:<18} {:>8} {:>14} {:>16} {:>8}", "gym", "sim s", "lockstep RTF", "physics-only RTF", "ratio");
    for gym in &gyms {
        let scene = runtime::launch::resolve_scene(gym)?;
        // Controller + physics + trace, replaying the demonstration.
        let mut ep = Episode::new(&scene, 0)?;
        let rows = match &ep.sim.scene.task.demonstration {
            Some(p) => read_demo(p)?,
            None => Vec::new(),
        };
        let hz = ep.sim.scene.task.demonstration_hz;
        let t0 = Instant::now();
        for chunk in rows.chunks(MAX_CHUNK) {
            ep.run_chunk(ControlType::Joint, chunk, hz);
        }
        ep.hold(1.0);
        let wall = t0.elapsed().as_secs_f64();
        let sim_s = ep.ticks as f64 * ep.sim.scene.timestep_s;
        let lockstep = sim_s / wall;
        // MuJoCo alone: the same number of steps holding the start pose.
        let mut ep2 = Episode::new(&scene, 0)?;
        let q = ep2.sim.scene.robot.initial_joints_rad;
        let cmd = JointCommand { q_rad: q, finger_m: ep2.sim.robot.finger_max_m, ..Default::default() };
        let t0 = Instant::now();
        for _ in 0..ep.ticks {
            ep2.sim.step(&cmd);
        }
        let physics = sim_s / t0.elapsed().as_secs_f64();
        println!("{gym:<18} {sim_s:>8.1} {lockstep:>13.1}x {physics:>15.1}x {:>8.2}", lockstep / physics);
        per_gym.insert(
            gym.clone(),
            json!({"sim_s": sim_s, "lockstep_rtf": lockstep, "physics_only_rtf": physics, "ticks": ep.ticks}),
        );
    }
    // Rendering: every camera of the first gym, RGB alone and RGB-D.
    let scene = runtime::launch::resolve_scene(gyms.first().map(String::as_str).unwrap_or("pick_block_plate"))?;
    let ep = Episode::new(&scene, 0)?;
    let mut render = Map::new();
    if let Some(first) = ep.sim.scene.cameras.first() {
        let (w, h) = (first.width, first.height);
        for (mode, depth) in [("rgb", false), ("rgbd", true)] {
            let mut cams = Cameras::new(ep.sim.model.clone(), w, h, depth)?;
            cams.set_state(ep.sim.qpos(), 0.0);
            let mut times = Vec::new();
            for i in 0..frames + 2 {
                for &(_, cam) in &ep.sim.layout.cameras {
                    let t0 = Instant::now();
                    cams.render(cam)?;
                    if i >= 2 {
                        times.push(t0.elapsed().as_secs_f64() * 1e3);
                    }
                }
            }
            let p50 = median(&mut times);
            println!("render {mode:<5} {w}x{h}: {p50:.2} ms per frame (median of {})", times.len());
            render.insert(format!("{mode}_frame_p50_ms"), json!(p50));
        }
        render.insert("width".into(), json!(w));
        render.insert("height".into(), json!(h));
    }
    let out = json!({"gyms": per_gym, "render": render});
    println!("{out}");
    Ok(out)
}
