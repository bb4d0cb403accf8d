//! `r2g bench ik`: full-pose IK on reachable Panda TCP poses. Beside the solver, in the same
//! run: plain FK (the floor of any iterative solver), a naive undamped Jacobian pseudo-inverse
//! solver, and Pinocchio's damped least squares in Python when `pinocchio` is importable.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context};
use controllers::ik::SplitMix64;
use controllers::kinematics::{from_arrays, to_arrays};
use controllers::{FrameId, IkConfig, IkSolver, Kinematics, Profile, RobotModel, N};
use nalgebra::{Cholesky, Isometry3, SMatrix, SVector, Vector3};
use serde_json::{json, Value};

/// Seed of the random targets: the same 10,000 poses on every run.
const TARGET_SEED: u64 = 0x1C_2024;
/// The Panda's usual ready pose.
pub const HOME: [f64; N] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];
const TOL: f64 = 1e-5;
/// The Pinocchio baseline, written to a temporary file and run with the venv's Python.
const PINOCCHIO_SCRIPT: &str = include_str!("../ik_pinocchio.py");

struct Target {
    pose: Isometry3<f64>,
    seed: [f64; N],
}

/// Figures of one solver over the targets.
struct Figures {
    solved: usize,
    times_us: Vec<f64>,
    iterations: Vec<u32>,
}

impl Figures {
    fn json(&self) -> Value {
        let n = self.times_us.len();
        let mut t = self.times_us.clone();
        t.sort_by(f64::total_cmp);
        let mean_it = if self.iterations.is_empty() {
            Value::Null
        } else {
            json!(self.iterations.iter().map(|&i| i as f64).sum::<f64>() / self.iterations.len() as f64)
        };
        json!({
            "targets": n,
            "solved": self.solved,
            "success_rate": self.solved as f64 / n.max(1) as f64,
            "median_us": percentile(&t, 0.5),
            "p99_us": percentile(&t, 0.99),
            "max_us": t.last().copied().unwrap_or(f64::NAN),
            "mean_iterations": mean_it,
        })
    }
}

/// The `p` quantile of sorted values (nearest rank).
fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (p * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

fn panda() -> anyhow::Result<(RobotModel, PathBuf)> {
    let path = runtime::launch::robots_dir().join("panda").join("panda.urdf");
    let xml = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    Ok((RobotModel::from_urdf_str(&xml, "hand_tcp", Profile::Panda)?, path))
}

fn random_targets(robot: &RobotModel, solver: &IkSolver, count: usize) -> Vec<Target> {
    let (lo, hi) = solver.bounds();
    let mut rng = SplitMix64::new(TARGET_SEED);
    (0..count)
        .map(|_| {
            let q = rng.config(lo, hi);
            let seed = rng.config(lo, hi);
            Target { pose: robot.kin.fk(&q, robot.kin.tcp), seed }
        })
        .collect()
}

fn read_targets(path: &Path) -> anyhow::Result<Vec<Target>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let v: Value = serde_json::from_str(line).with_context(|| format!("{}:{}: not JSON", path.display(), i + 1))?;
        let get = |key: &str, len: usize| -> anyhow::Result<Option<Vec<f64>>> {
            let Some(a) = v.get(key) else { return Ok(None) };
            let a: Vec<f64> = a.as_array().map(|a| a.iter().filter_map(Value::as_f64).collect()).unwrap_or_default();
            if a.len() != len {
                bail!("{}:{}: \"{key}\" must be {len} numbers", path.display(), i + 1);
            }
            Ok(Some(a))
        };
        let (Some(p), Some(q)) = (get("position", 3)?, get("quaternion", 4)?) else {
            bail!("{}:{}: needs \"position\" and \"quaternion\"", path.display(), i + 1);
        };
        if q.iter().map(|x| x * x).sum::<f64>() < 1e-18 {
            bail!("{}:{}: \"quaternion\" has zero length", path.display(), i + 1);
        }
        let seed = match get("seed", N)? {
            Some(s) => std::array::from_fn(|j| s[j]),
            None => HOME,
        };
        out.push(Target { pose: from_arrays([p[0], p[1], p[2]], [q[0], q[1], q[2], q[3]]), seed });
    }
    if out.is_empty() {
        bail!("{} holds no targets", path.display());
    }
    Ok(out)
}

/// Position and rotation error of `q` against `target`, measured with FK.
fn check(kin: &Kinematics, frame: FrameId, q: &[f64; N], target: &Isometry3<f64>) -> bool {
    let pose = kin.fk(q, frame);
    (pose.translation.vector - target.translation.vector).norm() <= TOL
        && pose.rotation.angle_to(&target.rotation) <= TOL
}

fn run_solver(robot: &RobotModel, solver: &IkSolver, targets: &[Target], seed: Option<[f64; N]>) -> Figures {
    // Warm caches and branch predictors on a few targets before timing.
    for t in targets.iter().take(50) {
        let _ = solver.solve(&t.pose, &seed.unwrap_or(t.seed));
    }
    let mut f = Figures { solved: 0, times_us: Vec::with_capacity(targets.len()), iterations: Vec::new() };
    for t in targets {
        let s0 = seed.unwrap_or(t.seed);
        let t0 = Instant::now();
        let r = solver.solve(&t.pose, &s0);
        f.times_us.push(t0.elapsed().as_secs_f64() * 1e6);
        if let Ok(s) = r {
            f.iterations.push(s.iterations);
            if s.ok && check(&robot.kin, robot.kin.tcp, &s.q, &t.pose) {
                f.solved += 1;
            }
        }
    }
    f
}

/// The textbook solver: undamped pseudo-inverse steps `Jᵀ(JJᵀ)⁻¹e`, clamped into the limits,
/// at most 100 steps, no restarts. What the damping, step control and restarts buy.
fn naive_solve(kin: &Kinematics, lo: &[f64; N], hi: &[f64; N], target: &Isometry3<f64>, seed: [f64; N]) -> bool {
    let mut q = seed;
    for _ in 0..100 {
        let (pose, jac) = kin.jacobian(&q, kin.tcp);
        let dp: Vector3<f64> = target.translation.vector - pose.translation.vector;
        let dr = (target.rotation * pose.rotation.inverse()).scaled_axis();
        if dp.norm() <= TOL && dr.norm() <= TOL {
            return true;
        }
        let e = SVector::<f64, 6>::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z);
        let a: SMatrix<f64, 6, 6> = jac * jac.transpose();
        let Some(chol) = Cholesky::new(a) else { return false };
        let dq = jac.transpose() * chol.solve(&e);
        for j in 0..N {
            q[j] = (q[j] + dq[j]).clamp(lo[j], hi[j]);
        }
        if q.iter().any(|v| !v.is_finite()) {
            return false;
        }
    }
    false
}

fn run_naive(robot: &RobotModel, solver: &IkSolver, targets: &[Target]) -> Figures {
    let (lo, hi) = solver.bounds();
    let mut f = Figures { solved: 0, times_us: Vec::with_capacity(targets.len()), iterations: Vec::new() };
    for t in targets {
        let t0 = Instant::now();
        let ok = naive_solve(&robot.kin, lo, hi, &t.pose, t.seed);
        f.times_us.push(t0.elapsed().as_secs_f64() * 1e6);
        f.solved += usize::from(ok);
    }
    f
}

/// Mean time of one FK of the TCP, over all target seeds (batched: one call is too short for
/// the clock).
fn fk_us(robot: &RobotModel, targets: &[Target]) -> f64 {
    let mut sink = 0.0;
    let reps = 20;
    let t0 = Instant::now();
    for _ in 0..reps {
        for t in targets {
            sink += robot.kin.fk(std::hint::black_box(&t.seed), robot.kin.tcp).translation.vector.x;
        }
    }
    let us = t0.elapsed().as_secs_f64() * 1e6 / (reps * targets.len()) as f64;
    std::hint::black_box(sink);
    us
}

/// The Python that has Pinocchio: the checkout's `.venv`, else `python3`. Err says why none.
fn pinocchio_python() -> Result<(PathBuf, String), String> {
    let venv = runtime::launch::robots_dir().join("..").join(".venv").join("bin").join("python");
    let mut tried = Vec::new();
    for py in [venv, PathBuf::from("python3")] {
        let out = Command::new(&py).args(["-c", "import pinocchio; print(pinocchio.__version__)"]).output();
        match out {
            Ok(o) if o.status.success() => return Ok((py, String::from_utf8_lossy(&o.stdout).trim().to_string())),
            Ok(_) => tried.push(format!("{}: no module pinocchio", py.display())),
            Err(e) => tried.push(format!("{}: {e}", py.display())),
        }
    }
    Err(tried.join("; "))
}

/// Runs the same targets and seeds through Pinocchio; `None` with the reason when it cannot.
fn run_pinocchio(urdf: &Path, targets: &[Target]) -> Result<(Figures, String), String> {
    let (py, version) = pinocchio_python()?;
    let dir = std::env::temp_dir().join(format!("r2g-bench-ik-{}", std::process::id()));
    let write = || -> std::io::Result<(PathBuf, PathBuf)> {
        std::fs::create_dir_all(&dir)?;
        let script = dir.join("ik_pinocchio.py");
        std::fs::write(&script, PINOCCHIO_SCRIPT)?;
        let file = dir.join("targets.jsonl");
        let mut w = std::io::BufWriter::new(std::fs::File::create(&file)?);
        for t in targets {
            let (p, q) = to_arrays(&t.pose);
            writeln!(w, "{}", json!({ "position": p, "quaternion": q, "seed": t.seed }))?;
        }
        w.flush()?;
        Ok((script, file))
    };
    let result = (|| {
        let (script, file) = write().map_err(|e| format!("writing targets: {e}"))?;
        eprintln!("bench ik: Pinocchio {version} on {} targets (in Python)...", targets.len());
        let out = Command::new(&py)
            .arg(&script)
            .args(["--urdf", &urdf.display().to_string(), "--tcp", "hand_tcp", "--targets"])
            .arg(&file)
            .output()
            .map_err(|e| format!("running {}: {e}", py.display()))?;
        if !out.status.success() {
            return Err(format!("the Pinocchio script failed: {}", String::from_utf8_lossy(&out.stderr).trim()));
        }
        let text = String::from_utf8_lossy(&out.stdout);
        let v: Value = serde_json::from_str(text.lines().last().unwrap_or_default())
            .map_err(|e| format!("the Pinocchio script's last line is not JSON: {e}"))?;
        let times_us: Vec<f64> =
            v["times_us"].as_array().map(|a| a.iter().filter_map(Value::as_f64).collect()).unwrap_or_default();
        let solved = v["solved"].as_u64().unwrap_or(0) as usize;
        if times_us.len() != targets.len() {
            return Err(format!("the Pinocchio script timed {} of {} targets", times_us.len(), targets.len()));
        }
        Ok((Figures { solved, times_us, iterations: Vec::new() }, version))
    })();
    let _ = std::fs::remove_dir_all(&dir);
    result
}

pub fn run(targets_file: Option<&Path>, count: usize) -> anyhow::Result<Value> {
    let (robot, urdf) = panda()?;
    let solver = IkSolver::new(&robot, IkConfig::default())?;
    let generated = targets_file.is_none();
    let targets = match targets_file {
        Some(p) => read_targets(p)?,
        None => {
            if count == 0 {
                bail!("--count must be at least 1");
            }
            random_targets(&robot, &solver, count)
        }
    };
    let n = targets.len();
    let source =
        if generated { "random reachable Panda TCP poses, a random seed configuration each" } else { "from file" };
    eprintln!("bench ik: {n} targets ({source})...");

    let ours = run_solver(&robot, &solver, &targets, None);
    let home = generated.then(|| run_solver(&robot, &solver, &targets, Some(HOME)));
    let naive = run_naive(&robot, &solver, &targets);
    let fk = fk_us(&robot, &targets);
    let pin = run_pinocchio(&urdf, &targets);

    let mut rows = Vec::new();
    let row = |name: &str, f: &Figures| {
        let j = f.json();
        let num = |k: &str| j[k].as_f64().unwrap_or(f64::NAN);
        vec![
            name.to_string(),
            format!("{}", f.times_us.len()),
            format!("{:.2}", 100.0 * num("success_rate")),
            format!("{:.1}", num("median_us")),
            format!("{:.1}", num("p99_us")),
            format!("{:.1}", num("max_us")),
            j["mean_iterations"].as_f64().map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into()),
        ]
    };
    rows.push(row(if generated { "r2g IK, random seed" } else { "r2g IK, file seeds" }, &ours));
    if let Some(h) = &home {
        rows.push(row("r2g IK, home seed", h));
    }
    rows.push(row("naive pinv (no damping/restarts)", &naive));
    match &pin {
        Ok((f, v)) => rows.push(row(&format!("Pinocchio {v} DLS (Python)"), f)),
        Err(_) => rows.push(vec![
            "Pinocchio".into(),
            "-".into(),
            "not run".into(),
            "-".into(),
            "-".into(),
            "-".into(),
            "-".into(),
        ]),
    }
    rows.push(vec![
        "FK only (one call)".into(),
        format!("{n}"),
        "-".into(),
        format!("{fk:.3}"),
        "-".into(),
        "-".into(),
        "-".into(),
    ]);
    crate::print_table(&["solver", "targets", "success %", "median µs", "p99 µs", "max µs", "mean iters"], &rows);
    if let Err(why) = &pin {
        println!("Pinocchio: not run ({why})");
    }

    let mut out = ours.json();
    let o = out.as_object_mut().context("figures are an object")?;
    let med = |f: &Figures| f.json()["median_us"].as_f64().unwrap_or(f64::NAN);
    o.insert("bench".into(), json!("ik"));
    o.insert("tolerance_m".into(), json!(TOL));
    o.insert("tolerance_rad".into(), json!(TOL));
    o.insert("seed".into(), json!(if generated { "random per target" } else { "from file (home when absent)" }));
    o.insert("home_seed".into(), home.as_ref().map(Figures::json).unwrap_or(Value::Null));
    o.insert("fk_us".into(), json!(fk));
    o.insert("median_over_fk".into(), json!(med(&ours) / fk));
    o.insert("naive_pinv".into(), naive.json());
    match &pin {
        Ok((f, v)) => {
            let mut p = f.json();
            if let Some(po) = p.as_object_mut() {
                po.insert("version".into(), json!(v));
                po.insert("median_over_ours".into(), json!(med(f) / med(&ours)));
            }
            o.insert("pinocchio".into(), p);
        }
        Err(why) => {
            o.insert("pinocchio".into(), Value::Null);
            o.insert("pinocchio_note".into(), json!(format!("not run: {why}")));
        }
    }
    println!("{out}");
    Ok(out)
}
