//! `nimbus render`: a scene file to a multi-layer EXR (full, direct, low, high,
//! variance) and optionally a PNG, with the scene's settings overridden by flags;
//! one JSON line of figures at the end.

use super::common::{BdptPredictionArgs, RunArgs, init_threads, progress_bar, stop_on_ctrl_c};
use crate::output::{self, ToneMap};
use crate::progressive::render_spp;
use crate::scene::SceneFile;
use anyhow::{Context, Result, bail};
use clap::Args;
use engine::integrator::preview::MultipleScattering;
use engine::{Buffer, RenderControl};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene file (TOML).
    pub scene: PathBuf,
    /// Samples per pixel (default 64; with --time-limit, as many as fit).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Render for at most this many seconds (counted from the first pass), then
    /// write what is done, as Ctrl-C does.
    #[arg(long, value_name = "SECONDS")]
    pub time_limit: Option<f64>,
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
    #[command(flatten)]
    pub run: RunArgs,
    /// Prediction mode at bounce K: vertices 1 .. K-1 path traced, the learned model
    /// predicts the rest at vertex K (overrides the scene's render.mode and k). With
    /// --integrator bdpt: K segments on each subpath, orders 1 .. 2K by BDPT and the
    /// point-to-point model between the subpaths' ends (buffers split at 2K + 1).
    #[arg(long, value_name = "K")]
    pub predict: Option<u32>,
    /// Full light transport, no prediction (overrides a scene's render.mode = "predict").
    #[arg(long, conflicts_with = "predict")]
    pub reference: bool,
    /// The instant preview: ray marching with single scattering from a precomputed
    /// sun transmittance and the higher orders learned (the model of --predictor on a
    /// lattice, the default) or from the octave approximation.
    #[arg(long, value_name = "learned|octaves", num_args = 0..=1, default_missing_value = "learned",
          conflicts_with_all = ["predict", "reference"])]
    pub preview: Option<String>,
    /// Prediction probability p in (0, 1] (Russian roulette on the prediction).
    #[arg(long)]
    pub p: Option<f32>,
    /// Choose p by minimizing TTUV from 8 pilot passes (see `progressive::auto_p`).
    #[arg(long)]
    pub auto_p: bool,
    /// The model of prediction at bounce K and of the learned preview (.safetensors +
    /// .json sidecar, global or cloud-aware); default: the shipped one of --predictor.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// The shipped model without --model: auto (the default: the cloud-aware model
    /// under a sun alone, the thesis's global model under a sky or a soft sun), cloud
    /// or global. Overrides the scene's render.predictor.
    #[arg(long, value_parser = super::common::predictor_arg)]
    pub predictor: Option<String>,
    /// Light transport: path (default) or bdpt (volumetric bidirectional path
    /// tracing with MIS); overrides the scene's render.integrator.
    #[arg(long, value_name = "path|bdpt")]
    pub integrator: Option<String>,
    /// The point-to-point model for --integrator bdpt --predict K (.safetensors +
    /// .json); default: the shipped single-cloud model.
    #[arg(long)]
    pub p2p_model: Option<PathBuf>,
    #[command(flatten)]
    pub bdpt: BdptPredictionArgs,
}

/// An error unless `path` ends in `.ext` (any case), saying what the flag takes.
fn check_extension(flag: &str, path: &Path, ext: &str, what: &str) -> Result<()> {
    if !path.extension().is_some_and(|e| e.eq_ignore_ascii_case(ext)) {
        bail!("{flag} {}: expected a .{ext} name ({what})", path.display());
    }
    Ok(())
}

pub(crate) fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s.split_once('x').with_context(|| format!("--size {s}: expected WIDTHxHEIGHT, e.g. 512x512"))?;
    Ok((w.trim().parse().context("--size width")?, h.trim().parse().context("--size height")?))
}

/// `nimbus render`: renders a scene file to EXR (and PNG), prints a JSON summary.
pub fn render(args: RenderArgs) -> Result<()> {
    let threads = init_threads(args.run.threads)?;
    let tone = ToneMap::from_name(&args.tonemap)
        .with_context(|| format!("--tonemap {}: choose filmic or clamp", args.tonemap))?;
    if args.spp == Some(0) {
        bail!("--spp must be at least 1");
    }
    if let Some(t) = args.time_limit {
        if !(t > 0.0 && t.is_finite()) {
            bail!("--time-limit must be a positive number of seconds, got {t}");
        }
    }
    let spp = args.spp.unwrap_or(if args.time_limit.is_some() { u32::MAX } else { 64 });
    if !args.exposure.is_finite() {
        bail!("--exposure must be a finite number of stops, got {}", args.exposure);
    }
    check_extension("--out", &args.out, "exr", "an OpenEXR file; the PNG goes to --png")?;
    if let Some(png) = &args.png {
        check_extension("--png", png, "png", "a PNG file")?;
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
    if let Some(which) = &args.preview {
        file.render.mode = "preview".into();
        file.render.preview = which.clone();
    }
    if let Some(p) = args.p {
        file.render.p = p;
    }
    if let Some(i) = &args.integrator {
        file.render.integrator = i.clone();
    }
    if let Some(r) = args.bdpt.r {
        file.render.r = r;
    }
    if let Some(m) = args.bdpt.candidates {
        file.render.candidates = m;
    }
    if let Some(n) = args.bdpt.extension_samples {
        file.render.extension_samples = n;
    }
    if let Some(m) = &args.model {
        // Relative to where nimbus runs, like every other path on the command line.
        file.render.model = Some(std::path::absolute(m)?.display().to_string());
    }
    if let Some(p) = &args.predictor {
        file.render.predictor = p.clone();
    }
    if let Some(m) = &args.p2p_model {
        file.render.p2p_model = Some(std::path::absolute(m)?.display().to_string());
    }
    file.validate()?;
    // A model named on the command line must load: the scene file's own falls back.
    if args.model.is_some() {
        file.load_model().context("--model")?;
    }
    if args.p2p_model.is_some() {
        file.load_p2p_model().map_err(anyhow::Error::msg).context("--p2p-model")?;
    }
    let scene = Arc::new(file.build_scene(None)?);
    if let Some(w) = crate::scene::density_warning(scene.medium.grid()) {
        eprintln!("warning: {w}");
    }
    let setup = file.integrator(&scene, models::global::depth_field::DEFAULT_MAX_NODES)?;
    if let Some(w) = &setup.warning {
        eprintln!("warning: {w}");
    }
    let mut integrator = setup.integrator;
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    if args.auto_p && integrator.predictor().is_some() {
        let a = crate::progressive::auto_p(scene.clone(), &integrator, 8, &control)?;
        eprintln!(
            "automatic p = {:.3} (V1 {:.3e}, B {:.3e}, c0 {:.3} s, c1 {:.3} s per pass)",
            a.p, a.v1, a.b, a.c0, a.c1
        );
        let settings = engine::RenderSettings { mode: engine::Mode::Predict { p: a.p }, ..*integrator.settings() };
        integrator = integrator.with_settings(settings)?;
    }
    let mode = match integrator.settings().mode {
        _ if let Some(preview) = integrator.preview_state() => match preview.multiple() {
            MultipleScattering::Lattice(l) => format!("preview (learned, lattice {})", l.nodes()),
            MultipleScattering::Octaves { octaves, a, b, c } => {
                format!("preview (octaves {octaves}, a {a}, b {b}, c {c})")
            }
            MultipleScattering::None => "preview (single scattering)".to_string(),
        },
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
    let bar = match args.time_limit {
        // Counting passes against no fixed total: a spinner with the pass count.
        Some(_) if args.spp.is_none() => {
            let bar = progress_bar(0, "spp", args.run.quiet);
            bar.set_length(0);
            bar
        }
        _ => progress_bar(spp as u64, "spp", args.run.quiet),
    };
    if let Some(limit) = args.time_limit {
        let c = control.clone();
        std::thread::Builder::new().name("nimbus-time-limit".into()).spawn(move || {
            std::thread::sleep(std::time::Duration::from_secs_f64(limit));
            c.request_stop();
        })?;
    }
    // (Kept to state its memory after the render: a lazy lattice grows as it is read.)
    let preview = integrator.preview_state().cloned();
    let outcome = render_spp(scene.clone(), integrator, spp, &control, |done| bar.set_position(done as u64))?;
    let preview_mib = preview.map(|p| p.memory_bytes() as f64 / 1048576.0);
    bar.finish_and_clear();
    let film = &outcome.film;
    if film.spp() == 0 {
        bail!("stopped before the first pass finished: nothing written");
    }
    write_outputs(film, &args.out, args.png.as_deref(), tone, args.exposure)?;
    if film.rejected_samples() > 0 {
        eprintln!("warning: {} non-finite samples were dropped", film.rejected_samples());
    }
    // The noise is measured from the per-pixel variance, unknown below two samples
    // per pixel: null then, as is the efficiency, rather than a noise of 0.
    let noise = (film.spp() >= 2).then(|| film.relative_noise(Buffer::Full)).filter(|n| n.is_finite() && *n > 0.0);
    let summary = serde_json::json!({
        "spp": film.spp(),
        "seconds": outcome.render_secs,
        "samples_per_second": outcome.samples_per_sec(),
        "width": film.width(),
        "height": film.height(),
        "threads": threads,
        "stopped_early": outcome.stopped,
        "mean_full": film.average(Buffer::Full),
        "relative_noise": noise,
        // Inverse of (relative variance x seconds): higher is better, comparable
        // between integrators on the same scene and machine.
        "efficiency": noise.map(|n| 1.0 / (n * n * outcome.render_secs).max(1e-300)),
        "mode": mode,
        // What the preview keeps after the render (the sun's transmittance, the learned
        // lattice's bricks read so far and the model's fields it holds), in MiB.
        "preview_fields_mib": preview_mib,
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
