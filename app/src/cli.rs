//! The `nimbus` command line: headless versions of what the window does.

use crate::output::{self, ToneMap};
use crate::progressive::render_spp;
use crate::scene::SceneFile;
use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use engine::{Buffer, RenderControl};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Parser, Debug)]
#[command(name = "nimbus", version, about = "Author and render clouds: path traced low orders, learned high orders")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Option<Command>,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Render a scene file to a multi-layer EXR (and optionally a PNG).
    Render(RenderArgs),
    /// Build a procedural cloud and write it out (.vdb, .vol Mitsuba volume, or .raw + .json).
    Model(ModelArgs),
    /// Write a scene's cloud, sun and camera as a Mitsuba 3 scene (cloud.vol + scene.xml).
    Mitsuba(MitsubaArgs),
    /// Render every modeler preset into one contact-sheet PNG.
    Sheet(SheetArgs),
    /// Make training data for the learned models (resumable, shardable).
    Datagen {
        #[command(subcommand)]
        which: crate::datagen_cmd::DatagenCommand,
    },
    /// Train a learned model on generated data.
    Train {
        #[command(subcommand)]
        which: crate::train_cmd::TrainCommand,
    },
    /// The thesis's evaluation of the global model: bias, TTUV and speedup against path
    /// tracing per scene, lighting, density and k; tables, plots and image sheets.
    /// `nimbus eval p2p` evaluates the point-to-point model instead (thesis 6.5).
    #[command(args_conflicts_with_subcommands = true)]
    Eval {
        #[command(subcommand)]
        which: Option<EvalCommand>,
        #[command(flatten)]
        args: crate::eval_cmd::EvalArgs,
    },
    /// Benchmarks.
    Bench {
        #[command(subcommand)]
        which: BenchCommand,
    },
}

#[derive(Subcommand, Debug)]
pub enum EvalCommand {
    /// The point-to-point model in BDPT (thesis 6.5): bias, TTUV and speedup against
    /// BDPT's high orders and against path tracing, backlit and frontlit, k = 1 .. 4.
    P2p(crate::eval_p2p::EvalP2pArgs),
}

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene file (TOML).
    pub scene: PathBuf,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Override the scene's k (first order of the high-order buffer).
    #[arg(long)]
    pub k: Option<u32>,
    /// Override the scene's seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Override the resolution: WIDTHxHEIGHT.
    #[arg(long)]
    pub size: Option<String>,
    /// Output EXR (layers full, direct, low, high, variance).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write a tone-mapped PNG of the full image.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Exposure in stops for the PNG.
    #[arg(long, default_value_t = 0.0)]
    pub exposure: f32,
    /// Tone curve for the PNG: filmic or clamp.
    #[arg(long, default_value = "filmic")]
    pub tonemap: String,
    /// Worker threads (default: all cores). The image does not depend on it.
    #[arg(long)]
    pub threads: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Prediction mode at bounce K: vertices 1 .. K-1 path traced, the learned model
    /// predicts the rest at vertex K (overrides the scene's render.mode and k). With
    /// --integrator bdpt: K segments on each subpath, orders 1 .. 2K by BDPT and the
    /// point-to-point model between the subpaths' ends (buffers split at 2K + 1).
    #[arg(long, value_name = "K")]
    pub predict: Option<u32>,
    /// Full light transport, no prediction (overrides a scene's render.mode = "predict").
    #[arg(long, conflicts_with = "predict")]
    pub reference: bool,
    /// Prediction probability p in (0, 1] (Russian roulette on the prediction).
    #[arg(long)]
    pub p: Option<f32>,
    /// Choose p by minimizing TTUV from 8 pilot passes (see `progressive::auto_p`).
    #[arg(long)]
    pub auto_p: bool,
    /// The global model (.safetensors + .json sidecar); default: the shipped model.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Light transport: path (default) or bdpt (volumetric bidirectional path
    /// tracing with MIS); overrides the scene's render.integrator.
    #[arg(long, value_name = "path|bdpt")]
    pub integrator: Option<String>,
    /// The point-to-point model for --integrator bdpt --predict K (.safetensors +
    /// .json); default: the shipped single-cloud model.
    #[arg(long)]
    pub p2p_model: Option<PathBuf>,
    /// Distance threshold r of BDPT prediction (default 0.04; the thesis's 0.08).
    #[arg(long)]
    pub r: Option<f32>,
    /// Light subpaths offered to each camera end vertex in BDPT prediction, one
    /// chosen by resampling (default 256, picked from the pass's pool; 1 is the thesis's pairing).
    #[arg(long)]
    pub candidates: Option<u32>,
    /// Point-to-point samples for each pair of end vertices closer than r in BDPT
    /// prediction (default 8).
    #[arg(long)]
    pub extension_samples: Option<u32>,
}

#[derive(Args, Debug)]
pub struct ModelArgs {
    /// A preset name (scene-a, scene-b, scene-c, set-01 .. set-12) or a TOML file of
    /// modeler parameters.
    pub source: String,
    /// Voxels per axis.
    #[arg(long, default_value_t = 128)]
    pub res: u32,
    /// Override the seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Output: NAME.vdb (OpenVDB), NAME.vol (Mitsuba grid volume) or NAME.raw (+ NAME.json).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args, Debug)]
pub struct MitsubaArgs {
    /// Scene file (TOML).
    pub scene: PathBuf,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Samples per pixel written into the XML.
    #[arg(long, default_value_t = 256)]
    pub spp: u32,
}

#[derive(Args, Debug)]
pub struct SheetArgs {
    #[arg(long)]
    pub out: PathBuf,
    /// Samples per pixel per cloud.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Edge of each tile in pixels.
    #[arg(long, default_value_t = 192)]
    pub tile: u32,
    /// Grid resolution of each cloud.
    #[arg(long, default_value_t = 96)]
    pub res: u32,
    /// Density scale.
    #[arg(long, default_value_t = 20.0)]
    pub rho: f32,
}

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Samples per second on the fixed benchmark scene (128^3 multi-lobe cloud,
    /// rho 40, albedo 1, g 0.85, toplit, 256x256, full transport).
    Render(BenchRenderArgs),
    /// Time to rebuild clouds from presets (128^3 and 256^3).
    Model(BenchModelArgs),
    /// Seconds per ground-truth data point, the thesis's table 5.1, one thread.
    Datagen(crate::datagen_cmd::BenchDatagenArgs),
    /// Microseconds per point-to-point prediction (features, deep residual network).
    PredictP2p(crate::train_cmd::BenchPredictP2pArgs),
    /// Seconds per point-to-point data point, the thesis's table 6.1, one thread.
    DatagenP2p(crate::datagen_cmd::BenchDatagenP2pArgs),
    /// Nanoseconds per prediction of the global model, network alone and with features.
    Predict(crate::train_cmd::BenchPredictArgs),
    /// The window's responsiveness without a window: milliseconds from a parameter
    /// change to the first image the render worker publishes.
    #[cfg(feature = "gui")]
    Latency(BenchLatencyArgs),
    /// Resident memory over a long accumulation in the window's render worker
    /// (prediction with the path-traced comparison, the heaviest mode), sampled at
    /// intervals, with the images tone-mapped each frame as the viewport does.
    #[cfg(feature = "gui")]
    Memory(BenchMemoryArgs),
}

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
}

#[derive(Args, Debug)]
pub struct BenchModelArgs {
    /// Repetitions per measurement (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub reps: u32,
    #[arg(long)]
    pub threads: Option<usize>,
}

#[derive(Args, Debug)]
pub struct BenchRenderArgs {
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    #[arg(long)]
    pub threads: Option<usize>,
    /// Majorant cell edge (voxels) of the measured configuration.
    #[arg(long, default_value_t = engine::medium::MajorantGrid::DEFAULT_CELL_VOXELS)]
    pub majorant_cells: u32,
    /// Also measure these majorant cell edges, as ratios against the first.
    #[arg(long, value_delimiter = ',')]
    pub compare_cells: Vec<u32>,
    /// Grid resolution of the benchmark cloud (128 is the reference setting; 256 and
    /// 512 check memory).
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
    /// Write the cloud (Mitsuba .vol), scene.json and nimbus_full.npy here for
    /// bench/mitsuba_compare.py.
    #[arg(long)]
    pub mitsuba_dir: Option<PathBuf>,
}

/// Runs the CLI; returns the process exit code.
pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        #[cfg(feature = "gui")]
        None => crate::gui::run(),
        #[cfg(not(feature = "gui"))]
        None => {
            use clap::CommandFactory;
            Cli::command().print_help()?;
            anyhow::bail!("this nimbus was built without the window (feature \"gui\"); use the subcommands")
        }
        Some(Command::Render(args)) => render(args),
        Some(Command::Model(args)) => crate::model_cmd::model(args),
        Some(Command::Sheet(args)) => crate::model_cmd::sheet(args),
        Some(Command::Mitsuba(args)) => {
            let file = SceneFile::load(&args.scene)?;
            let scene = file.build_scene(None)?;
            crate::mitsuba::export(&scene, args.spp, &args.out)?;
            println!("wrote {}/cloud.vol and {}/scene.xml", args.out.display(), args.out.display());
            Ok(())
        }
        Some(Command::Bench { which: BenchCommand::Model(args) }) => crate::model_cmd::bench_model(args),
        Some(Command::Bench { which: BenchCommand::Render(args) }) => bench_render(args),
        Some(Command::Bench { which: BenchCommand::Datagen(args) }) => crate::datagen_cmd::bench_datagen(args),
        Some(Command::Bench { which: BenchCommand::PredictP2p(args) }) => crate::train_cmd::bench_predict_p2p(args),
        Some(Command::Bench { which: BenchCommand::DatagenP2p(args) }) => crate::datagen_cmd::bench_datagen_p2p(args),
        Some(Command::Datagen { which }) => crate::datagen_cmd::datagen(which),
        Some(Command::Bench { which: BenchCommand::Predict(args) }) => crate::train_cmd::bench_predict(args),
        #[cfg(feature = "gui")]
        Some(Command::Bench { which: BenchCommand::Latency(args) }) => bench_latency(args),
        #[cfg(feature = "gui")]
        Some(Command::Bench { which: BenchCommand::Memory(args) }) => bench_memory(args),
        Some(Command::Train { which }) => crate::train_cmd::train(which),
        Some(Command::Eval { which: Some(EvalCommand::P2p(args)), .. }) => crate::eval_p2p::eval_p2p(&args).map(|_| ()),
        Some(Command::Eval { which: None, args }) => crate::eval_cmd::eval(&args).map(|_| ()),
    }
}

pub(crate) fn init_threads(threads: Option<usize>) -> Result<usize> {
    if let Some(n) = threads {
        if n == 0 {
            bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .thread_name(|i| format!("nimbus-render-{i}"))
            .build_global()
            .context("cannot start the render threads")?;
    }
    Ok(rayon::current_num_threads())
}

pub(crate) fn stop_on_ctrl_c(control: &Arc<RenderControl>) {
    let c = control.clone();
    // If a handler is already installed (tests), keep going without one.
    let _ = ctrlc::set_handler(move || {
        eprintln!("\nstopping after the current pass; the samples so far are kept");
        c.request_stop();
    });
}

/// The CLI's progress bar; `unit` names what is counted (spp, points, batches).
pub(crate) fn progress_bar(len: u64, unit: &str, quiet: bool) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(&format!(
            "{{spinner}} [{{elapsed_precise}}] {{bar:40}} {{pos}}/{{len}} {unit}  ETA {{eta}}  {{msg}}"
        ))
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar
}

fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s.split_once('x').with_context(|| format!("--size {s}: expected WIDTHxHEIGHT, e.g. 512x512"))?;
    Ok((w.trim().parse().context("--size width")?, h.trim().parse().context("--size height")?))
}

fn render(args: RenderArgs) -> Result<()> {
    let threads = init_threads(args.threads)?;
    let tone = ToneMap::from_name(&args.tonemap)
        .with_context(|| format!("--tonemap {}: choose filmic or clamp", args.tonemap))?;
    if args.spp == 0 {
        bail!("--spp must be at least 1");
    }
    let mut file = SceneFile::load(&args.scene)?;
    if let Some(k) = args.k {
        file.k = k;
    }
    if let Some(seed) = args.seed {
        file.seed = seed;
    }
    if let Some(size) = &args.size {
        (file.camera.width, file.camera.height) = parse_size(size)?;
    }
    file.validate()?;
    if let Some(k) = args.predict {
        file.k = k;
        file.render.mode = "predict".into();
    }
    if args.reference {
        file.render.mode = "reference".into();
    }
    if let Some(p) = args.p {
        file.render.p = p;
    }
    if let Some(i) = &args.integrator {
        file.render.integrator = i.clone();
    }
    if let Some(r) = args.r {
        file.render.r = r;
    }
    if let Some(m) = args.candidates {
        file.render.candidates = m;
    }
    if let Some(n) = args.extension_samples {
        file.render.extension_samples = n;
    }
    if let Some(m) = &args.model {
        // Relative to where nimbus runs, like every other path on the command line.
        file.render.model = Some(std::path::absolute(m)?.display().to_string());
    }
    if let Some(m) = &args.p2p_model {
        file.render.p2p_model = Some(std::path::absolute(m)?.display().to_string());
    }
    file.validate()?;
    let scene = Arc::new(file.build_scene(None)?);
    let setup = file.integrator(&scene, models::depth_field::DEFAULT_MAX_NODES)?;
    if let Some(w) = &setup.warning {
        eprintln!("warning: {w}");
    }
    let mut integrator = setup.integrator;
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    if let (true, Some(pred)) = (args.auto_p, integrator.predictor().cloned()) {
        let a = crate::progressive::auto_p(scene.clone(), *integrator.settings(), pred.clone(), 8, &control)?;
        eprintln!(
            "automatic p = {:.3} (V1 {:.3e}, B {:.3e}, c0 {:.3} s, c1 {:.3} s per pass)",
            a.p, a.v1, a.b, a.c0, a.c1
        );
        let settings = engine::RenderSettings { mode: engine::Mode::Predict { p: a.p }, ..*integrator.settings() };
        integrator = engine::Integrator::new(settings, Some(pred))?;
    }
    let mode = match integrator.settings().mode {
        engine::Mode::Reference if matches!(integrator.technique(), engine::Technique::Bdpt(_)) => {
            "reference (BDPT)".to_string()
        }
        engine::Mode::Reference => "reference".to_string(),
        engine::Mode::Predict { p } => match integrator.transport_prediction() {
            Some(pr) => format!(
                "predict (BDPT, k {} segments, orders {}+ by {}, r {}, p {p})",
                pr.segments,
                pr.first_predicted_order(),
                pr.predictor.name(),
                pr.r
            ),
            None => format!("predict (k {}, p {p})", integrator.settings().k),
        },
    };
    let bar = progress_bar(args.spp as u64, "spp", args.quiet);
    let outcome = render_spp(scene.clone(), integrator, args.spp, &control, |done| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    let film = &outcome.film;
    if film.spp() == 0 {
        bail!("stopped before the first pass finished: nothing written");
    }
    write_outputs(film, &args.out, args.png.as_deref(), tone, args.exposure)?;
    if film.rejected_samples() > 0 {
        eprintln!("warning: {} non-finite samples were dropped", film.rejected_samples());
    }
    let summary = serde_json::json!({
        "spp": film.spp(),
        "seconds": outcome.render_secs,
        "samples_per_second": outcome.samples_per_sec(),
        "width": film.width(),
        "height": film.height(),
        "threads": threads,
        "stopped_early": outcome.stopped,
        "mean_full": film.average(Buffer::Full),
        "relative_noise": film.relative_noise(Buffer::Full),
        // Inverse of (relative variance x seconds): higher is better, comparable
        // between integrators on the same scene and machine.
        "efficiency": 1.0 / (film.relative_noise(Buffer::Full).powi(2) * outcome.render_secs).max(1e-300),
        "mode": mode,
        "out": args.out,
    });
    println!("{summary}");
    Ok(())
}

/// EXR with every buffer, and the PNG if asked.
pub fn write_outputs(film: &engine::Film, exr: &Path, png: Option<&Path>, tone: ToneMap, exposure: f32) -> Result<()> {
    output::write_exr(exr, film.width(), film.height(), &output::film_layers(film))?;
    if let Some(png) = png {
        output::write_png(png, film.width(), film.height(), &film.mean(Buffer::Full), tone, exposure)?;
    }
    Ok(())
}

/// The fixed benchmark scene of `nimbus bench render`.
pub fn bench_scene_file() -> SceneFile {
    let mut s = SceneFile::from_toml_str("[grid]\nbuiltin = \"cumulus\"\nresolution = 128\n", "bench").expect("valid");
    s.medium.rho = 40.0;
    s.medium.albedo = 1.0;
    s.medium.g = 0.85;
    s.camera.preset = Some("toplit".into());
    s.camera.width = 256;
    s.camera.height = 256;
    s.seed = 1;
    s
}

fn bench_render(args: BenchRenderArgs) -> Result<()> {
    let threads = init_threads(args.threads)?;
    let mut file = bench_scene_file();
    file.grid.resolution = args.resolution;
    let grid = Arc::new(file.build_grid()?);
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    let mut cells = vec![args.majorant_cells];
    cells.extend(args.compare_cells.iter().copied().filter(|c| *c != args.majorant_cells));
    println!(
        "bench render: cumulus {}^3, rho 40, albedo 1, HG g 0.85, toplit, 256x256, {} spp, {threads} threads",
        args.resolution, args.spp
    );
    let mut base_rate = None;
    let mut results = Vec::new();
    let base = file.build_scene(Some(grid.clone()))?;
    for &c in &cells {
        let medium =
            engine::Medium::with_majorant_cells(grid.clone(), file.medium.rho, file.medium.albedo, file.phase(), c)?;
        let scene = Arc::new(engine::Scene { medium, ..base.clone() });
        let bar = progress_bar(args.spp as u64, "spp", false);
        let outcome =
            render_spp(scene.clone(), file.integrator_with(None)?, args.spp, &control, |d| bar.set_position(d as u64))?;
        bar.finish_and_clear();
        if outcome.stopped {
            bail!("stopped");
        }
        let rate = outcome.samples_per_sec();
        let ratio = rate / *base_rate.get_or_insert(rate);
        println!(
            "  majorant cells {c:>2} voxels: {:>8.3} Msamples/s  ({:.3}x)  {:.2} s",
            rate / 1e6,
            ratio,
            outcome.render_secs
        );
        results.push(serde_json::json!({"majorant_cells": c, "samples_per_second": rate, "seconds": outcome.render_secs, "ratio": ratio}));
        if let (Some(dir), true) = (&args.mitsuba_dir, c == args.majorant_cells) {
            write_mitsuba_bundle(dir, &scene, &outcome, threads)?;
        }
    }
    let peak = peak_resident_bytes();
    if let Some(p) = peak {
        println!(
            "  peak resident memory: {:.1} MiB (density grid {:.1} MiB)",
            p as f64 / 1048576.0,
            grid.memory_bytes() as f64 / 1048576.0
        );
    }
    println!(
        "{}",
        serde_json::json!({"bench": "render", "resolution": args.resolution, "spp": args.spp,
            "threads": threads, "peak_resident_bytes": peak, "results": results})
    );
    Ok(())
}

fn write_mitsuba_bundle(
    dir: &Path,
    scene: &engine::Scene,
    outcome: &crate::progressive::RenderOutcome,
    threads: usize,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    output::write_bytes_atomically(&dir.join("cloud.vol"), &output::mitsuba_vol_bytes(scene.medium.grid()))?;
    let film = &outcome.film;
    output::write_npy_image(&dir.join("nimbus_full.npy"), film.width(), film.height(), &film.mean(Buffer::Full))?;
    let cam = &scene.camera;
    let sun = scene.sun.expect("bench scene has a sun");
    let g = scene.medium.phase().mean_cosine();
    let json = serde_json::json!({
        "resolution": [cam.width(), cam.height()],
        "spp": film.spp(),
        "camera": {"origin": cam.position().to_array(), "target": cam.target().to_array(), "up": cam.up().to_array(), "fov_y_deg": cam.fov_y_deg()},
        "sun": {"direction": sun.direction().to_array(), "irradiance": sun.radiance().to_array()},
        "medium": {"rho": scene.medium.rho(), "albedo": scene.medium.albedo(), "g": g},
        "nimbus": {"spp": film.spp(), "seconds": outcome.render_secs, "samples_per_second": outcome.samples_per_sec(), "threads": threads, "image": "nimbus_full.npy"},
    });
    output::write_bytes_atomically(&dir.join("scene.json"), serde_json::to_string_pretty(&json)?.as_bytes())?;
    eprintln!("wrote cloud.vol, scene.json and nimbus_full.npy to {}", dir.display());
    Ok(())
}

/// Peak resident set size of this process (Linux: VmHWM), if known.
pub fn peak_resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Resident set size of this process in MiB (Linux), or None where /proc is missing.
pub fn resident_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
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
#[cfg(feature = "gui")]
fn bench_memory(args: BenchMemoryArgs) -> Result<()> {
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
    worker.render_compare(&scene, false, true);
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
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
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
#[cfg(feature = "gui")]
fn bench_latency(args: BenchLatencyArgs) -> Result<()> {
    use crate::gui::worker::WorkerHandle;
    let worker = WorkerHandle::start(|| {});
    let base = crate::gui::default_scene();
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
        "# nimbus bench latency: ms from a change to the first image (median of {}), {} threads",
        args.reps,
        rayon::current_num_threads()
    );
    println!("| change | path tracing | prediction (k 2) |");
    println!("|---|---|---|");
    for (name, change) in &changes {
        let mut cols = vec![];
        for scene in [&base, &predict] {
            first_image(scene, false)?;
            let mut times: Vec<f64> = (0..args.reps.max(1))
                .map(|i| first_image(&change(scene, i).0, change(scene, i).1))
                .collect::<Result<_>>()?;
            times.sort_by(f64::total_cmp);
            cols.push(times[times.len() / 2]);
        }
        println!("| {name} | {:.0} | {:.0} |", cols[0], cols[1]);
    }
    Ok(())
}
