//! `r2g bench all`: every benchmark in turn with a progress bar, then `bench-report/` with a
//! Markdown summary, each benchmark's JSON (distributions included) and PNG plots: latency CDFs
//! per payload across transports, and the tick wake latency of the runtime against the bare
//! loop as a CDF and a histogram.

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use anyhow::{anyhow, Context};
use plotters::prelude::*;
use serde_json::{json, Value};

type Bench<'a> = (&'static str, Box<dyn Fn() -> anyhow::Result<Value> + 'a>);

fn progress(done: usize, total: usize, what: &str, started: Instant) {
    let width = 30;
    let filled = width * done / total.max(1);
    let bar: String = "#".repeat(filled) + &"-".repeat(width - filled);
    let s = started.elapsed().as_secs();
    eprintln!("bench all [{bar}] {done}/{total} {what} ({}m{:02}s)", s / 60, s % 60);
    let _ = std::io::stderr().flush();
}

/// One gym in quick runs, every gym otherwise.
fn quick_gym(quick: bool) -> Vec<String> {
    if quick {
        vec!["pick_block_plate".to_string()]
    } else {
        Vec::new()
    }
}

/// Runs everything; `quick` shrinks every run (frames only for IPC, one gym) to check the
/// pipeline end to end in under a minute.
pub fn run(jitter_s: f64, out: &Path, quick: bool) -> anyhow::Result<Value> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let (ipc_only, n, gyms) =
        if quick { (Some(":frame"), 10, vec!["pick_block_plate".to_string()]) } else { (None, 1, vec![]) };
    let benches: Vec<Bench> = vec![
        ("ipc", Box::new(move || crate::ipc::run(ipc_only))),
        ("robo", Box::new(move || crate::robo::run("pick_block_plate", if quick { 200 } else { 2000 }))),
        ("agent", Box::new(move || crate::agent::run(if quick { 1 } else { 3 }))),
        ("perception", Box::new(move || crate::perception::run(&quick_gym(quick), !quick))),
        ("jitter", Box::new(move || crate::tick::run("pick_block_plate", jitter_s, true))),
        ("tick", Box::new(move || crate::tick::run("pick_block_plate", (jitter_s / 6.0).max(3.0), false))),
        ("tick_compute", Box::new(move || crate::control::tick_compute(200_000 / n))),
        ("ik", Box::new(move || crate::ik::run(None, 10_000 / n as usize))),
        ("limiter_fuzz", Box::new(move || crate::control::limiter_fuzz(200_000 / n, 1))),
        ("sim", Box::new(move || crate::sim::run(&gyms, if quick { 3 } else { 20 }))),
    ];
    let started = Instant::now();
    let mut results = serde_json::Map::new();
    for (i, (name, f)) in benches.iter().enumerate() {
        progress(i, benches.len(), name, started);
        let t0 = Instant::now();
        let v = match f() {
            Ok(v) => v,
            Err(e) => json!({"error": format!("{e:#}")}),
        };
        let path = out.join(format!("{name}.json"));
        std::fs::write(&path, serde_json::to_vec_pretty(&v)?).with_context(|| format!("writing {}", path.display()))?;
        let mut v = v;
        if let Some(o) = v.as_object_mut() {
            o.remove("cdf");
            o.insert("seconds".into(), json!(t0.elapsed().as_secs_f64()));
        }
        results.insert((*name).into(), v);
    }
    progress(benches.len(), benches.len(), "plots and summary", started);
    let mut plots = Vec::new();
    let mut plot_errors = Vec::new();
    let ipc = std::fs::read_to_string(out.join("ipc.json")).ok().and_then(|t| serde_json::from_str::<Value>(&t).ok());
    if let Some(cdf) = ipc.as_ref().and_then(|v| v.get("cdf")).and_then(Value::as_object) {
        for payload in ["state", "command", "frame", "rgbd", "frame_burst"] {
            let series: Vec<(String, Vec<[f64; 2]>)> = cdf
                .iter()
                .filter(|(k, _)| k.ends_with(&format!(".{payload}")))
                .map(|(k, v)| (k.split('.').next().unwrap_or(k).to_string(), points(v)))
                .collect();
            if series.is_empty() {
                continue;
            }
            let file = format!("ipc_{payload}_cdf.png");
            match cdf_plot(&out.join(&file), &format!("publish → receive latency: {payload}"), &series) {
                Ok(()) => plots.push(file),
                Err(e) => plot_errors.push(format!("{file}: {e:#}")),
            }
        }
    }
    let jitter =
        std::fs::read_to_string(out.join("jitter.json")).ok().and_then(|t| serde_json::from_str::<Value>(&t).ok());
    if let Some(cdf) = jitter.as_ref().and_then(|v| v.get("cdf")) {
        let series =
            vec![("runtime".to_string(), points(&cdf["runtime"])), ("bare loop".to_string(), points(&cdf["baseline"]))];
        for (file, r) in [
            ("jitter_wake_cdf.png", cdf_plot(&out.join("jitter_wake_cdf.png"), "1 kHz tick wake latency", &series)),
            (
                "jitter_wake_hist.png",
                hist_plot(&out.join("jitter_wake_hist.png"), "1 kHz tick wake latency (histogram)", &series),
            ),
        ] {
            match r {
                Ok(()) => plots.push(file.to_string()),
                Err(e) => plot_errors.push(format!("{file}: {e:#}")),
            }
        }
    }
    let summary = summary_md(&results, &plots, &plot_errors, started.elapsed().as_secs_f64());
    std::fs::write(out.join("summary.md"), &summary)?;
    println!("{summary}");
    let headline = headline(&results);
    std::fs::write(
        out.join("figures.json"),
        serde_json::to_vec_pretty(&json!({"headline": headline, "benches": results}))?,
    )?;
    eprintln!("bench all: report in {}", out.display());
    println!("{headline}");
    Ok(headline)
}

fn points(v: &Value) -> Vec<[f64; 2]> {
    v.as_array()
        .map(|a| {
            a.iter()
                .filter_map(|p| Some([p.get(0)?.as_f64()?, p.get(1)?.as_f64()?]))
                .filter(|p| p[0].is_finite())
                .collect()
        })
        .unwrap_or_default()
}

fn num(v: &Value, ptr: &str) -> f64 {
    v.pointer(ptr).and_then(Value::as_f64).unwrap_or(f64::NAN)
}

/// The figures the issue asks for, with the ratios.
fn headline(r: &serde_json::Map<String, Value>) -> Value {
    let ipc = r.get("ipc").cloned().unwrap_or(Value::Null);
    let jit = r.get("jitter").cloned().unwrap_or(Value::Null);
    json!({
        "bench": "all",
        "iceoryx2.state_p50_us": num(&ipc, "/iceoryx2/state_p50_us"),
        "iceoryx2.frame_p50_us": num(&ipc, "/iceoryx2/frame_p50_us"),
        "uds.frame_p50_us": num(&ipc, "/uds/frame_p50_us"),
        "tcp.frame_p50_us": num(&ipc, "/tcp/frame_p50_us"),
        "zmq.frame_p50_us": num(&ipc, "/zmq/frame_p50_us"),
        "iceoryx2.frame_throughput_per_s": num(&ipc, "/iceoryx2/frame_burst_msgs_per_s"),
        "uds.frame_throughput_per_s": num(&ipc, "/uds/frame_burst_msgs_per_s"),
        "uds_over_iceoryx2_frame_p50": num(&ipc, "/uds/frame_p50_us") / num(&ipc, "/iceoryx2/frame_p50_us"),
        "runtime.p999_us": num(&jit, "/runtime/p999_us"),
        "baseline.p999_us": num(&jit, "/baseline/p999_us"),
        "runtime.overruns": jit.pointer("/runtime/overruns").cloned().unwrap_or(Value::Null),
        "jitter_p999_ratio": num(&jit, "/runtime/p999_us") / num(&jit, "/baseline/p999_us"),
    })
}

fn summary_md(r: &serde_json::Map<String, Value>, plots: &[String], errors: &[String], total_s: f64) -> String {
    let mut s = String::from("# Latency report\n\n");
    s.push_str(&format!(
        "Every figure below was measured on this machine in one `r2g bench all` run ({:.0} s). Absolute times on a shared machine drift; the ratios against the baselines measured in the same run are what carry over.\n\n",
        total_s
    ));
    if let Some(ipc) = r.get("ipc") {
        s.push_str("## IPC: publish → receive, one process per core (µs)\n\n| transport | payload | p50 | p99 | p99.9 | max | msgs/s | received |\n|---|---|---|---|---|---|---|---|\n");
        for t in ["iceoryx2", "uds", "tcp", "zmq"] {
            for p in ["state", "command", "frame", "rgbd", "frame_burst"] {
                let g = |k: &str| num(ipc, &format!("/{t}/{p}_{k}"));
                if g("p50_us").is_nan() {
                    continue;
                }
                s.push_str(&format!(
                    "| {t} | {p} | {:.2} | {:.1} | {:.1} | {:.1} | {:.0} | {} |\n",
                    g("p50_us"),
                    g("p99_us"),
                    g("p999_us"),
                    g("max_us"),
                    g("msgs_per_s"),
                    ipc[t][format!("{p}_received")]
                ));
            }
        }
        s.push_str(&format!(
            "\nAt 640×480 RGB the Unix-socket copy takes {:.0}× as long as iceoryx2 (p50); ZeroMQ {:.0}×. `frame_burst` sends frames back to back: its msgs/s is the throughput, its latency includes queueing, and iceoryx2 (which never blocks the publisher here) may drop the oldest frames a slow reader has not taken: see received.\n\n",
            num(ipc, "/uds/frame_p50_us") / num(ipc, "/iceoryx2/frame_p50_us"),
            num(ipc, "/zmq/frame_p50_us") / num(ipc, "/iceoryx2/frame_p50_us"),
        ));
    }
    if let Some(j) = r.get("jitter") {
        s.push_str("## 1 kHz tick under load (wake latency, µs)\n\nThe runtime in wall mode with sim-host rendering both cameras and a Python agent polling get_state and posting chunks, beside a bare clock_nanosleep loop.\n\n| loop | ticks | p50 | p99 | p99.9 | max | overruns | compute p99 |\n|---|---|---|---|---|---|---|---|\n");
        for k in ["runtime", "baseline"] {
            s.push_str(&format!(
                "| {k} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {} | {:.1} |\n",
                j[k]["ticks"],
                num(j, &format!("/{k}/p50_us")),
                num(j, &format!("/{k}/p99_us")),
                num(j, &format!("/{k}/p999_us")),
                num(j, &format!("/{k}/max_us")),
                j[k]["overruns"],
                num(j, &format!("/{k}/compute_p99_us")),
            ));
        }
        s.push_str(&format!(
            "\np99.9 wake latency, runtime over bare loop: {:.2}. Agent load: {}.\n\n",
            num(j, "/runtime/p999_us") / num(j, "/baseline/p999_us"),
            j["agent_load"]
        ));
    }
    s.push_str("## Other benchmarks\n\n");
    for (name, v) in r {
        if name == "ipc" || name == "jitter" {
            continue;
        }
        let mut short = v.clone();
        if let Some(o) = short.as_object_mut() {
            o.retain(|_, x| !x.is_array());
        }
        s.push_str(&format!("- **{name}**: `{short}`\n"));
    }
    if !plots.is_empty() {
        s.push_str("\n## Plots\n\n");
        for p in plots {
            s.push_str(&format!("![{p}]({p})\n\n"));
        }
    }
    for e in errors {
        s.push_str(&format!("- plot not drawn: {e}\n"));
    }
    s
}

/// Registers a font for the plots' text (plotters draws text with ab_glyph).
fn font() -> anyhow::Result<()> {
    static DONE: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    DONE.get_or_init(|| {
        let candidates = [
            "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
            "/usr/share/fonts/TTF/DejaVuSans.ttf",
            "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
        ];
        let bytes = candidates
            .iter()
            .find_map(|p| std::fs::read(p).ok())
            .ok_or_else(|| "no TrueType font found (install fonts-dejavu-core: make deps)".to_string())?;
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).map_err(|_| "font does not load".into())
    })
    .clone()
    .map_err(|e| anyhow!(e))
}

const W: u32 = 960;
const H: u32 = 600;

fn save_png(path: &Path, rgb: &[u8]) -> anyhow::Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), W, H);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header()?.write_image_data(rgb)?;
    Ok(())
}

fn x_range(series: &[(String, Vec<[f64; 2]>)]) -> (f64, f64) {
    let xs = series.iter().flat_map(|s| s.1.iter().map(|p| p[0])).filter(|x| *x > 0.0);
    let (lo, hi) = xs.fold((f64::INFINITY, 0.0f64), |(lo, hi), x| (lo.min(x), hi.max(x)));
    if lo.is_finite() && hi > lo {
        (lo * 0.8, hi * 1.25)
    } else {
        (0.1, 10.0)
    }
}

/// Draws line series on a log-x chart with a legend and writes it as PNG.
fn line_plot(
    path: &Path,
    title: &str,
    (x_desc, y_desc): (&str, &str),
    y_max: f64,
    legend_at: SeriesLabelPosition,
    lines: &[(String, Vec<(f64, f64)>)],
    (lo, hi): (f64, f64),
) -> anyhow::Result<()> {
    font()?;
    let mut buf = vec![0u8; (W * H * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (W, H)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 24))
            .margin(20)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d((lo..hi).log_scale(), 0.0..y_max)
            .map_err(|e| anyhow!("{e}"))?;
        chart.configure_mesh().x_desc(x_desc).y_desc(y_desc).draw().map_err(|e| anyhow!("{e}"))?;
        for (i, (name, pts)) in lines.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(pts.iter().map(|&(x, y)| (x.max(lo), y)), color.stroke_width(2)))
                .map_err(|e| anyhow!("{e}"))?
                .label(name.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], color.stroke_width(3)));
        }
        chart
            .configure_series_labels()
            .position(legend_at)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 18))
            .draw()
            .map_err(|e| anyhow!("{e}"))?;
        root.present().map_err(|e| anyhow!("{e}"))?;
    }
    save_png(path, &buf)
}

fn cdf_plot(path: &Path, title: &str, series: &[(String, Vec<[f64; 2]>)]) -> anyhow::Result<()> {
    let lines: Vec<(String, Vec<(f64, f64)>)> =
        series.iter().map(|(n, p)| (n.clone(), p.iter().map(|q| (q[0], q[1])).collect())).collect();
    let labels = ("latency, µs (log scale)", "fraction at or below");
    line_plot(path, title, labels, 1.0, SeriesLabelPosition::LowerRight, &lines, x_range(series))
}

/// A histogram on log-spaced bins, its mass read off each distribution's CDF (percentile
/// resolution), drawn as outlined steps per series.
fn hist_plot(path: &Path, title: &str, series: &[(String, Vec<[f64; 2]>)]) -> anyhow::Result<()> {
    let (lo, hi) = x_range(series);
    let bins = 40usize;
    let edges: Vec<f64> = (0..=bins).map(|k| lo * (hi / lo).powf(k as f64 / bins as f64)).collect();
    let cdf_at = |pts: &[[f64; 2]], x: f64| pts.iter().filter(|p| p[0] <= x).map(|p| p[1]).fold(0.0, f64::max);
    let lines: Vec<(String, Vec<(f64, f64)>)> = series
        .iter()
        .map(|(name, pts)| {
            let mut steps = Vec::new();
            for e in edges.windows(2) {
                let m = cdf_at(pts, e[1]) - cdf_at(pts, e[0]);
                steps.push((e[0], m));
                steps.push((e[1], m));
            }
            (name.clone(), steps)
        })
        .collect();
    let top = lines.iter().flat_map(|l| l.1.iter().map(|p| p.1)).fold(0.0f64, f64::max).max(1e-3) * 1.1;
    let labels = ("wake latency, µs (log scale)", "fraction of ticks per bin");
    line_plot(path, title, labels, top, SeriesLabelPosition::UpperRight, &lines, (lo, hi))
}
