//! The window's render worker without a window: `nimbus bench latency` (milliseconds
//! from a change to the first published image) and `nimbus bench memory` (resident
//! memory over a long accumulation).

use crate::scene::SceneFile;
use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct BenchMemoryArgs {
    /// How long to accumulate.
    #[arg(long, default_value_t = 3600.0)]
    pub seconds: f64,
    /// Seconds between memory samples.
    #[arg(long, default_value_t = 30.0)]
    pub interval: f64,
    /// Image width and height.
    #[arg(long, default_value_t = 256)]
    pub size: u32,
    /// Write memory.csv and memory.png here.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct BenchLatencyArgs {
    /// Repetitions per kind of change (the median is reported).
    #[arg(long, default_value_t = 9)]
    pub reps: u32,
    /// Milliseconds to wait before each timed change, so that the worker has finished
    /// what the previous change set going (0: the next change follows the previous
    /// first image at once, as when an artist keeps adjusting).
    #[arg(long, default_value_t = 0)]
    pub settle_ms: u64,
    /// The shipped model of the first look and of prediction: auto (the default, as
    /// the window's), cloud or global.
    #[arg(long, default_value = "auto", value_parser = crate::cli::common::predictor_arg)]
    pub predictor: String,
}

/// Resident set size of this process in MiB (Linux), or None where /proc is missing.
pub fn resident_mib() -> Option<f64> {
    super::render::resident_bytes().map(|b| b as f64 / 1048576.0)
}

/// Least-squares slope of y over x.
fn slope(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let sxx: f64 = x.iter().map(|a| (a - mx) * (a - mx)).sum();
    if sxx > 0.0 { sxy / sxx } else { 0.0 }
}

/// Memory over a long accumulation: the render worker renders the window's default
/// cloud in prediction mode with the path-traced comparison, while this thread plays
/// the UI (every 50 ms it tone-maps the latest pass of both films, as the viewport
/// and the compare view do). Reports resident memory at each interval and the
/// growth rate over the second half, where a leak would show and warm-up would not.
pub fn bench_memory(args: BenchMemoryArgs) -> Result<()> {
    use crate::gui::worker::WorkerHandle;
    use crate::output::ToneMap;
    if !(args.seconds > 0.0 && args.interval > 0.0) {
        bail!("--seconds and --interval must be positive");
    }
    let Some(start_mib) = resident_mib() else { bail!("cannot read /proc/self/status: resident memory unknown") };
    let worker = WorkerHandle::start(|| {});
    let mut scene = crate::gui::default_scene();
    scene.render.mode = "predict".into();
    (scene.camera.width, scene.camera.height) = (args.size, args.size);
    worker.render_with(&scene, false, false, true, crate::gui::worker::RenderTarget::Unlimited);
    println!(
        "# nimbus bench memory: {}x{} cumulus 96^3, prediction k {} with the path-traced comparison, {:.0} s, {} threads",
        args.size,
        args.size,
        scene.k,
        args.seconds,
        rayon::current_num_threads()
    );
    println!("| minutes | resident MiB | spp (prediction / reference) |");
    println!("|---|---|---|");
    let t0 = std::time::Instant::now();
    let (mut times, mut rss, mut rows) = (vec![], vec![], vec![]);
    let mut next = 0.0;
    let mut spp = (0, 0);
    loop {
        let elapsed = t0.elapsed().as_secs_f64();
        let latest = worker.mailbox.lock().unwrap().latest.clone();
        if let Some(p) = &latest {
            std::hint::black_box(ToneMap::Filmic.to_rgba8(&p.film.mean(engine::Buffer::Full), 0.0));
            if let Some(r) = &p.reference {
                std::hint::black_box(ToneMap::Filmic.to_rgba8(&r.mean(engine::Buffer::Full), 0.0));
                spp = (p.film.spp(), r.spp());
            }
        }
        if let Some((_, e)) = &worker.mailbox.lock().unwrap().error {
            if !e.contains("falls back") {
                bail!("the worker failed: {e}");
            }
        }
        drop(latest);
        if elapsed >= next || elapsed >= args.seconds {
            let mib = resident_mib().unwrap_or(f64::NAN);
            println!("| {:.1} | {:.1} | {} / {} |", elapsed / 60.0, mib, spp.0, spp.1);
            rows.push(format!("{elapsed:.1},{mib:.2},{},{}", spp.0, spp.1));
            times.push(elapsed);
            rss.push(mib);
            next += args.interval;
            if elapsed >= args.seconds {
                break;
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    drop(worker);
    let half = times.len() / 2;
    let per_hour = slope(&times[half..], &rss[half..]) * 3600.0;
    let max = rss.iter().copied().fold(f64::MIN, f64::max);
    println!(
        "\nresident memory: {start_mib:.1} MiB at start, {:.1} MiB after the first sample, {:.1} MiB at the end, max {max:.1} MiB; \
         growth over the second half {per_hour:+.2} MiB per hour; {} / {} spp",
        rss.get(1).copied().unwrap_or(rss[0]),
        rss[rss.len() - 1],
        spp.0,
        spp.1
    );
    if let Some(dir) = &args.out {
        crate::output::create_dir(dir)?;
        let csv = format!("seconds,resident_mib,spp_prediction,spp_reference\n{}\n", rows.join("\n"));
        crate::output::write_atomically(&dir.join("memory.csv"), |tmp| Ok(std::fs::write(tmp, &csv)?))?;
        let points: Vec<(f64, f64)> = times.iter().zip(&rss).map(|(t, m)| (t / 60.0, *m)).collect();
        let png = models::plot::line_plot_png(
            "resident memory during accumulation",
            "minutes",
            "MiB",
            &[models::plot::Series { label: "resident".into(), colour: models::plot::PALETTE[0], points }],
        );
        crate::output::write_atomically(&dir.join("memory.png"), |tmp| Ok(std::fs::write(tmp, &png)?))?;
        println!("wrote {}/memory.csv and memory.png", dir.display());
    }
    Ok(())
}

/// Median milliseconds from a change to the first published image, for the kinds of
/// change an artist makes, on the window's default scene (256x256, cumulus 96^3).
pub fn bench_latency(args: BenchLatencyArgs) -> Result<()> {
    use crate::gui::worker::WorkerHandle;
    let worker = WorkerHandle::start(|| {});
    let mut base = crate::gui::default_scene();
    base.render.predictor = args.predictor.clone();
    let first_image = |scene: &SceneFile, coarse: bool| -> Result<f64> {
        let t = std::time::Instant::now();
        let g = worker.render(scene, coarse);
        loop {
            {
                let mb = worker.mailbox.lock().unwrap();
                if mb.latest.as_ref().is_some_and(|p| p.generation == g) {
                    return Ok(t.elapsed().as_secs_f64() * 1e3);
                }
                if let Some((eg, e)) = &mb.error {
                    if *eg == g && !e.contains("falls back") {
                        bail!("{e}");
                    }
                }
            }
            if t.elapsed().as_secs() > 120 {
                bail!("no image after 120 s");
            }
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
    };
    let mut predict = base.clone();
    predict.render.mode = "predict".into();
    let changes: Vec<(&str, Box<dyn Fn(&SceneFile, u32) -> (SceneFile, bool)>)> = vec![
        (
            "camera orbit (no rebuild)",
            Box::new(|s, i| {
                let mut s = s.clone();
                s.camera.fov_y_deg = 30.0 + (i % 2) as f32;
                (s, false)
            }),
        ),
        (
            "density rho",
            Box::new(|s, i| {
                let mut s = s.clone();
                s.medium.rho = 40.0 + (i % 2) as f32;
                (s, false)
            }),
        ),
        (
            "cloud shape while dragging (coarse 48^3)",
            Box::new(|s, i| {
                let mut s = s.clone();
                s.seed = i as u64;
                s.grid.builtin = None;
                s.grid.preset = Some(["scene-a", "scene-b"][i as usize % 2].into());
                (s, true)
            }),
        ),
        (
            "cloud shape released (full 96^3)",
            Box::new(|s, i| {
                let mut s = s.clone();
                s.grid.builtin = None;
                s.grid.preset = Some(["scene-a", "scene-b"][i as usize % 2].into());
                (s, false)
            }),
        ),
    ];
    println!(
        "# nimbus bench latency: ms from a change to the first image (median of {}, {} ms settling before each), {} model, {} threads",
        args.reps,
        args.settle_ms,
        base.predictor_kind().name(),
        rayon::current_num_threads()
    );
    println!("| change | path tracing | prediction (k 2) |");
    println!("|---|---|---|");
    for (name, change) in &changes {
        let mut cols = vec![];
        for scene in [&base, &predict] {
            first_image(scene, false)?;
            let mut times: Vec<f64> = (0..args.reps.max(1))
                .map(|i| {
                    std::thread::sleep(std::time::Duration::from_millis(args.settle_ms));
                    first_image(&change(scene, i).0, change(scene, i).1)
                })
                .collect::<Result<_>>()?;
            times.sort_by(f64::total_cmp);
            cols.push(times[times.len() / 2]);
        }
        println!("| {name} | {:.0} | {:.0} |", cols[0], cols[1]);
    }
    Ok(())
}
