//! `nimbus eval`: the thesis's evaluation of the global model (section 5.5, appendix B),
//! with the figures of merit of docs/conventions.md.
//!
//! For every scene (A, B, C), lighting configuration (toplit, backlit, frontlit) and
//! density scale rho (20/40/80 for A and B, 80/160/320 for C) it renders
//! - the full-transport reference by path tracing (`--spp-ref`, seed 0), cached on disk;
//! - for every k, the image with prediction at bounce k (`--spp`, seed 100 + k), which
//!   also holds the path-traced low orders 1 .. k-1 in its low buffer;
//!
//! and reports bias (16x box downscale, mean |reference - prediction| over non-empty
//! pixels), relative bias, TTUV (mean variance of the pixel estimate over non-empty
//! pixels times render seconds), speedup (TTUV of the reference / TTUV of the
//! prediction) and time to preview (seconds until the running image is within 5 %
//! relative RMSE of the reference; path tracing gets its own run with another seed).
//!
//! Departure from the thesis (docs/conventions.md): the reference high-order
//! image of the sheets is reference full minus the prediction run's low buffer (the
//! same path-traced estimator of orders 1 .. k-1) instead of a separate low-order
//! render per k; bias and speedup use full images only, exactly as the thesis did.
//!
//! Every finished render is cached (`OUT/cache`), so a stopped study resumes where it
//! stopped, and `--scenes`, `--configs`, `--rho` and `--k` pick a subset.

use super::common::{Csv, TileSheet, image_npy, opt_cell, read_image_npy, read_json, render_tracked, write_json};
use super::preview::PreviewJob;
use crate::cli::common::{RunArgs, init_threads, progress_bar, stop_on_ctrl_c};
use crate::metrics::{
    Image, bias_in, error_colours, lit_mean, masked_mean, projected_preview, reference_noise, relative_rmse_less, ttuv,
};
use crate::output::{ToneMap, write_bytes_atomically};
use crate::scene::SceneFile;
use anyhow::{Context, Result, bail};
use clap::Args;
use engine::{Buffer, DensityGrid, Integrator, RenderControl};
use models::prediction::{PredictionModel, PredictorKind};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

#[derive(Args, Debug, Clone)]
pub struct EvalArgs {
    /// Scenes: A (nearly convex), B (concave, multi-lobe), C (heterogeneous).
    #[arg(long, value_delimiter = ',', default_value = "A,B,C")]
    pub scenes: Vec<String>,
    /// Lighting configurations.
    #[arg(long, value_delimiter = ',', default_value = "toplit,backlit,frontlit")]
    pub configs: Vec<String>,
    /// Density scales (default: 20,40,80 for A and B, 80,160,320 for C).
    #[arg(long, value_delimiter = ',')]
    pub rho: Vec<f32>,
    /// Bounces at which the model predicts.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8")]
    pub k: Vec<u32>,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 512)]
    pub size: u32,
    /// Samples per pixel of the full-transport reference (thesis: 4096).
    #[arg(long, default_value_t = 4096)]
    pub spp_ref: u32,
    /// Samples per pixel of the predictions (thesis: 2048).
    #[arg(long, default_value_t = 2048)]
    pub spp: u32,
    /// Prediction probability p (thesis: 0.25).
    #[arg(long, default_value_t = 0.25)]
    pub p: f32,
    /// Choose p per configuration and k by minimizing TTUV from pilot passes
    /// (`progressive::auto_p`) instead of `--p`.
    #[arg(long)]
    pub auto_p: bool,
    /// Density grid resolution of the clouds.
    #[arg(long, default_value_t = 128)]
    pub res: u32,
    /// Depth-field nodes per axis of the model's features.
    #[arg(long, default_value_t = models::global::depth_field::DEFAULT_MAX_NODES)]
    pub field_nodes: u32,
    /// A model of prediction at bounce k, cloud-aware or global (default: the shipped
    /// one of --predictor).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// The shipped model used without --model: auto (the default: the cloud-aware
    /// model, or the global one with --sky, whose light the cloud-aware model does not
    /// answer), cloud or global.
    #[arg(long, default_value = "auto", value_parser = crate::cli::common::predictor_arg)]
    pub predictor: String,
    /// Also measure path tracing's time to preview (a second path-traced run per
    /// configuration, another seed, until 5 % relative RMSE against the reference, its
    /// own noise subtracted, or --preview-spp samples), and report every prediction's
    /// RMSE floor and projected time to preview.
    #[arg(long)]
    pub preview: bool,
    /// Sample cap of path tracing's preview run (default: 4 x spp-ref).
    #[arg(long)]
    pub preview_spp: Option<u32>,
    /// Passes of each instant preview with --preview (the learned one, the octave
    /// approximation with its defaults and fitted to the reference).
    #[arg(long, default_value_t = 32)]
    pub preview_passes: u32,
    /// Times each instant preview that reaches 5 % this many times, each run stopped
    /// at 5 % and set up anew: a new sun field, and for the cloud-aware model a new
    /// binding with its density pyramid built again (the global model's binding is
    /// built once per configuration and its seconds counted in every run); the cell
    /// reports the median and the range (the first pass's time varies from run to run
    /// on a shared machine).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub preview_repeats: u32,
    /// Nodes per axis, at most, of the learned preview's lattice of multiple
    /// scattering, and at most two per voxel (default: the scene files', or the
    /// default lattice: 96 per axis, finer over optically thick clouds).
    #[arg(long, value_parser = clap::value_parser!(u32).range(2..=256))]
    pub preview_nodes: Option<u32>,
    /// Nodes per axis, at most, of the lattice of the model's answers toward the
    /// camera that prediction at k = 1 reads; 0 evaluates the model at every
    /// predicted vertex, as at other k (default: the scene files',
    /// render.prediction_lattice).
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=256))]
    pub prediction_lattice: Option<u32>,
    /// Where prediction at k = 1 places its vertex: guided (default), weighted or
    /// free-flight (render.first_vertex).
    #[arg(long, value_parser = crate::scene::FirstVertexChoice::NAMES)]
    pub first_vertex: Option<String>,
    /// Light every scene by the evaluation sky as well as the sun ([`EVAL_SKY`]: a
    /// clear-day gradient over a ground of albedo 0.3), for the bias of prediction
    /// under sun + sky against the same scenes under the sun alone.
    #[arg(long)]
    pub sky: bool,
    /// Output directory (tables, plots, sheets, and the render cache).
    #[arg(long, default_value = "out/eval")]
    pub out: PathBuf,
    #[command(flatten)]
    pub run: RunArgs,
}

/// The evaluation scenes: label, modeler preset, default density scales.
pub const SCENES: [(&str, &str, [f32; 3]); 3] = [
    ("A", "scene-a", [20.0, 40.0, 80.0]),
    ("B", "scene-b", [20.0, 40.0, 80.0]),
    ("C", "scene-c", [80.0, 160.0, 320.0]),
];

/// Thesis table B.2 / 5.2, scene A: speedup at k = 1 and k = 2 (config, rho, [k1, k2]).
pub const THESIS_SCENE_A_SPEEDUP: [(&str, f32, [f64; 2]); 9] = [
    ("toplit", 20.0, [9.2, 6.7]),
    ("toplit", 40.0, [16.5, 12.6]),
    ("toplit", 80.0, [25.4, 20.6]),
    ("backlit", 20.0, [6.0, 4.0]),
    ("backlit", 40.0, [14.1, 9.7]),
    ("backlit", 80.0, [25.7, 20.7]),
    ("frontlit", 20.0, [9.8, 8.1]),
    ("frontlit", 40.0, [13.9, 11.8]),
    ("frontlit", 80.0, [18.5, 16.0]),
];

/// Thesis table B.1, scene A: absolute bias at k = 1, 2, 4, 8.
pub const THESIS_SCENE_A_BIAS: [(&str, f32, [f64; 4]); 9] = [
    ("toplit", 20.0, [0.0213, 0.0157, 0.0077, 0.0027]),
    ("toplit", 40.0, [0.0290, 0.0244, 0.0161, 0.0071]),
    ("toplit", 80.0, [0.0318, 0.0271, 0.0208, 0.0126]),
    ("backlit", 20.0, [0.0324, 0.0156, 0.0081, 0.0037]),
    ("backlit", 40.0, [0.0363, 0.0164, 0.0113, 0.0066]),
    ("backlit", 80.0, [0.0421, 0.0210, 0.0133, 0.0091]),
    ("frontlit", 20.0, [0.0156, 0.0117, 0.0069, 0.0026]),
    ("frontlit", 40.0, [0.0234, 0.0195, 0.0143, 0.0078]),
    ("frontlit", 80.0, [0.0279, 0.0243, 0.0206, 0.0162]),
];

pub use super::common::CellResult;

#[derive(Clone, Debug, Serialize, Deserialize)]
struct ReferenceMeta {
    spp: u32,
    seconds: f64,
    ttuv: f64,
    preview_secs: Option<f64>,
    /// The path-traced preview run's (seconds, relative RMSE) curve; empty until
    /// that run is made (it may not have reached 5 %).
    #[serde(default)]
    preview_curve: Vec<(f64, f64)>,
}

/// The render cache's name for a model: a fingerprint of its bytes (weights and
/// sidecar), so a model retrained into the same file, or a new shipped one, never
/// reuses old renders, and a file with the shipped bytes shares the shipped one's.
fn model_id(args: &EvalArgs) -> Result<String> {
    Ok(match &args.model {
        Some(path) => format!("{:016x}", models::fingerprint::model_file_fingerprint(path)?),
        None => format!("{:016x}", models::prediction::shipped_fingerprint(predictor_kind(args)?)),
    })
}

fn predictor_kind(args: &EvalArgs) -> Result<PredictorKind> {
    PredictorKind::parse(&args.predictor)
        .with_context(|| format!("--predictor {:?}: choose {}", args.predictor, PredictorKind::NAMES))?;
    // Every scene of the study has the same lights: the sharp sun, and the sky with --sky.
    let mut scene = eval_scene("scene-a", "toplit", 40.0, 2, 8, args.sky)?;
    scene.render.predictor = args.predictor.clone();
    Ok(scene.predictor_kind())
}

/// The cache name of one prediction cell: everything its numbers depend on.
fn cell_key(key: &str, k: u32, args: &EvalArgs, model_id: &str) -> String {
    let p = if args.auto_p { "auto".to_string() } else { args.p.to_string() };
    // At k = 1: the lattice of the model's answers (none at 0) and the first vertex.
    let first = if k == 1 {
        let lattice = match args.prediction_lattice.unwrap_or(crate::scene::DEFAULT_PREDICTION_LATTICE) {
            0 => String::new(),
            n => format!("_lat{n}"),
        };
        use crate::scene::FirstVertexChoice as V;
        let vertex = match args.first_vertex.as_deref().and_then(V::parse).unwrap_or(V::Guided) {
            V::FreeFlight => "",
            V::Weighted => "_wfv",
            V::Guided => "_gfv",
        };
        format!("{lattice}{vertex}")
    } else {
        String::new()
    };
    format!("{key}_k{k}_p{p}_spp{}_ref{}_nodes{}{first}_{model_id}", args.spp, args.spp_ref, args.field_nodes)
}

/// The sky of `nimbus eval --sky`: zenith and horizon radiance of a clear day (blue
/// overhead, paler toward the horizon) for a sun of irradiance 1, whose upper
/// hemisphere delivers about a third of the sun's irradiance to a level surface, and a
/// ground of albedo 0.3 lit by both.
pub const EVAL_SKY: &str = "[sky]\nradiance = [0.05, 0.09, 0.18]\nhorizon = [0.16, 0.18, 0.21]\nground_albedo = 0.3\n";

/// The scene file of one evaluation configuration (with [`EVAL_SKY`] if `sky`).
pub fn eval_scene(preset: &str, config: &str, rho: f32, size: u32, res: u32, sky: bool) -> Result<SceneFile> {
    let text = format!(
        "[grid]\npreset = \"{preset}\"\nresolution = {res}\n[medium]\nrho = {rho}\nalbedo = 1.0\nphase = \"hg\"\ng = 0.85\n\
         [camera]\npreset = \"{config}\"\nwidth = {size}\nheight = {size}\n{}",
        if sky { EVAL_SKY } else { "" }
    );
    let s = SceneFile::from_toml_str(&text, "evaluation scene")?;
    s.validate()?;
    Ok(s)
}

/// The pixels the cloud covers: some light scattered in the cloud reaches them (full
/// minus the order-0 image > 0). Without a sky, the non-empty pixels; with one, the
/// sky around the cloud is left out of every figure.
fn cloud_pixels(full: &[[f32; 3]], direct: &[[f32; 3]]) -> Vec<bool> {
    full.iter().zip(direct).map(|(f, d)| (0..3).map(|c| f[c] - d[c]).sum::<f32>() > 0.0).collect()
}

/// Runs the study (or the selected part of it); returns every cell's result.
pub fn eval(args: &EvalArgs) -> Result<Vec<CellResult>> {
    let threads = init_threads(args.run.threads)?;
    for c in &args.configs {
        if crate::scene::CameraPreset::from_name(c).is_none() {
            bail!("--configs {c}: choose from toplit, backlit, frontlit");
        }
    }
    let mut scenes = vec![];
    for s in &args.scenes {
        let found = SCENES.iter().find(|(l, _, _)| l.eq_ignore_ascii_case(s));
        scenes.push(*found.with_context(|| format!("--scenes {s}: choose from A, B, C"))?);
    }
    if args.k.is_empty() || args.k.iter().any(|k| !(1..=64).contains(k)) {
        bail!("--k {:?}: every k must lie in 1 ..= 64", args.k);
    }
    if !(args.p > 0.0 && args.p <= 1.0) {
        bail!("--p {}: must lie in (0, 1]", args.p);
    }
    if args.spp < 2 || args.spp_ref < 2 || args.size == 0 {
        bail!("--spp and --spp-ref must be at least 2 (variances need two samples), --size at least 1");
    }
    let kind = predictor_kind(args)?;
    let model = PredictionModel::load_or_shipped(args.model.as_deref(), kind)?;
    let model_id = model_id(args).context("--model")?;
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    let cache = args.out.join("cache");
    crate::output::create_dir(&cache)?;
    let groups: Vec<(&str, &str, String, f32)> = scenes
        .iter()
        .flat_map(|(label, preset, rhos)| {
            let rhos: Vec<f32> = if args.rho.is_empty() { rhos.to_vec() } else { args.rho.clone() };
            args.configs
                .iter()
                .flat_map(move |c| rhos.clone().into_iter().map(move |r| (*label, *preset, c.clone(), r)))
        })
        .collect();
    if !args.run.quiet {
        eprintln!(
            "nimbus eval: {} configurations x k {:?}, {}x{}, reference {} spp, predictions {} spp, p {}, {threads} threads, model {}",
            groups.len(),
            args.k,
            args.size,
            args.size,
            args.spp_ref,
            args.spp,
            args.p,
            args.model.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| format!("shipped {}", kind.name()))
        );
    }
    let renders_per_group = args.spp_ref as u64 + args.spp as u64 * args.k.len() as u64;
    let bar = progress_bar(groups.len() as u64 * renders_per_group, "passes", args.run.quiet);
    let mut results = vec![];
    let mut previews = vec![];
    let mut grids: Vec<(String, Arc<DensityGrid>)> = vec![];
    for (gi, (label, preset, config, rho)) in groups.iter().enumerate() {
        let base = (gi as u64) * renders_per_group;
        bar.set_position(base);
        bar.set_message(format!("scene {label} {config} rho {rho}"));
        let mut file = eval_scene(preset, config, *rho, args.size, args.res, args.sky)?;
        if let Some(n) = args.preview_nodes {
            file.render.preview_nodes = Some(n);
        }
        if let Some(n) = args.prediction_lattice {
            file.render.prediction_lattice = n;
        }
        if let Some(v) = &args.first_vertex {
            file.render.first_vertex = v.clone();
        }
        let grid = match grids.iter().find(|(p, _)| p == preset) {
            Some((_, g)) => g.clone(),
            None => {
                let g = Arc::new(file.build_grid()?);
                grids.push((preset.to_string(), g.clone()));
                g
            }
        };
        let scene = Arc::new(file.build_scene(Some(grid))?);
        let key =
            format!("{label}_{config}_rho{rho}_{}px_res{}{}", args.size, args.res, if args.sky { "_sky" } else { "" });
        // The reference, from the cache or rendered now.
        let ref_npy = cache.join(format!("{key}_ref{}.npy", args.spp_ref));
        let ref_json = ref_npy.with_extension("json");
        // Full transport by path tracing with the given seed.
        let path_traced = |seed: u64| -> Result<Integrator> {
            let mut f = file.clone();
            (f.seed, f.k) = (seed, 1);
            Ok(f.integrator_with(None)?)
        };
        // The reference's full image (mean, variance) and its order-0 image (the sky
        // seen through the cloud), from the cache or rendered now.
        let cached = match (read_json::<ReferenceMeta>(&ref_json), ref_npy.exists()) {
            (Some(meta), true) => read_image_npy(&ref_npy, args.size, args.size, 3).ok().map(|layers| {
                let mut it = layers.into_iter();
                let (mean, var, direct) = (it.next().unwrap(), it.next().unwrap(), it.next().unwrap());
                (Image { w: args.size, h: args.size, mean, var }, direct, meta)
            }),
            _ => None,
        };
        let (reference, ref_direct, mut meta) = match cached {
            Some(c) => c,
            None => {
                let t = render_tracked(scene.clone(), path_traced(0)?, args.spp_ref, &control, None, false, |d| {
                    bar.set_position(base + d as u64)
                })?;
                let img = Image::from_film(&t.film, Buffer::Full);
                let direct = t.film.mean(Buffer::Direct);
                let mask = cloud_pixels(&img.mean, &direct);
                let meta = ReferenceMeta {
                    spp: args.spp_ref,
                    seconds: t.seconds,
                    ttuv: ttuv(&img.var, &mask, t.seconds),
                    preview_secs: None,
                    preview_curve: vec![],
                };
                write_bytes_atomically(
                    &ref_npy,
                    &image_npy(&[img.mean.clone(), img.var.clone(), direct.clone()], args.size, args.size),
                )?;
                write_json(&ref_json, &meta)?;
                (img, direct, meta)
            }
        };
        let mask = cloud_pixels(&reference.mean, &ref_direct);
        let ref_mean = masked_mean(&reference.mean, &mask);
        let ref_noise = reference_noise(&reference, &mask);
        if args.preview && meta.preview_curve.is_empty() {
            // The reference's own noise is subtracted (`relative_rmse`), so path tracing
            // may need more samples than the reference has.
            let t = render_tracked(
                scene.clone(),
                path_traced(7)?,
                args.preview_spp.unwrap_or(args.spp_ref.saturating_mul(4)).max(1),
                &control,
                Some((&reference, &mask)),
                true,
                |_| {},
            )?;
            (meta.preview_secs, meta.preview_curve) = (t.preview_secs, t.curve);
            write_json(&ref_json, &meta)?;
        }
        // The model bound to this cloud and sun, built once for every k and the
        // preview, with the seconds it took.
        let bound = std::cell::OnceCell::new();
        let bind = || -> super::preview::Bound {
            bound
                .get_or_init(|| {
                    let t = Instant::now();
                    let b = model
                        .bind_scene(&scene, args.field_nodes, engine::Cancel::NEVER)
                        .expect("evaluation scenes have a sun");
                    (b, t.elapsed().as_secs_f64())
                })
                .clone()
        };
        // The preview's binding: a cloud-aware model reads the preview's sun field
        // (as `nimbus render --preview learned` does); the global model's is the one
        // above. Its seconds are those of a new cloud: the density pyramid is built
        // again, not found from an earlier configuration of the same cloud.
        let bind_preview = |field: &Arc<engine::field::SunTransmittance>| -> super::preview::Bound {
            match &model {
                PredictionModel::Cloud(_) => {
                    models::cloud::features::forget_pyramids();
                    let t = Instant::now();
                    let b = model
                        .bind_scene_with_sun(&scene, field, args.field_nodes, engine::Cancel::NEVER)
                        .expect("evaluation scenes have a sun");
                    (b, t.elapsed().as_secs_f64())
                }
                PredictionModel::Global(_) => bind(),
            }
        };
        let mut group_cells = vec![];
        for (ki, &k) in args.k.iter().enumerate() {
            let kbase = base + args.spp_ref as u64 + ki as u64 * args.spp as u64;
            bar.set_position(kbase);
            let cell_key = cell_key(&key, k, args, &model_id);
            let cell_json = cache.join(format!("{cell_key}.json"));
            let cell_npy = cache.join(format!("{cell_key}.npy"));
            if let (Some(cell), true) = (read_json::<CellResult>(&cell_json), cell_npy.exists()) {
                group_cells.push(cell);
                continue;
            }
            let (pred, secs_field) = bind();
            let mut f = file.clone();
            f.seed = 100 + k as u64;
            f.k = k;
            f.render.mode = "predict".into();
            f.render.p = args.p;
            let t_pilot = Instant::now();
            // Prediction mode's integrator, built anew for the pilots and for the
            // render (as for a new cloud): at k = 1 its lattice is filled, and its
            // guide's field built, within the render's seconds.
            let integrate = |f: &SceneFile| {
                f.prediction_integrator(&scene, pred.clone(), &mut Default::default(), engine::Cancel::NEVER)
            };
            if args.auto_p {
                f.render.p = crate::progressive::auto_p(scene.clone(), &integrate(&f)?, 8, &control)?.p;
            }
            let secs_pilot = if args.auto_p { t_pilot.elapsed().as_secs_f64() } else { 0.0 };
            let t_setup = Instant::now();
            let integrator = integrate(&f)?;
            let secs_setup = t_setup.elapsed().as_secs_f64();
            let t =
                render_tracked(scene.clone(), integrator, args.spp, &control, Some((&reference, &mask)), false, |d| {
                    bar.set_position(kbase + d as u64)
                })?;
            let full = Image::from_film(&t.film, Buffer::Full);
            let (b, rb, floor) = bias_in(&reference, &full, &mask);
            let ttuv_pred = ttuv(&full.var, &mask, t.seconds + secs_setup);
            let rmse_floor = relative_rmse_less(&full.mean, &reference, &mask, Some(&full.var));
            let cell = CellResult {
                scene: label.to_string(),
                config: config.clone(),
                rho: *rho,
                k,
                p: f.render.p,
                spp_ref: args.spp_ref,
                spp: args.spp,
                size: args.size,
                bias: b,
                rel_bias: rb,
                rel_noise_floor: floor,
                ttuv_ref: meta.ttuv,
                ttuv_pred,
                speedup: if ttuv_pred > 0.0 { meta.ttuv / ttuv_pred } else { f64::INFINITY },
                secs_ref: meta.seconds,
                secs_pred: t.seconds + secs_setup,
                secs_field,
                secs_pilot,
                preview_secs_pred: t.preview_secs,
                preview_secs_ref: meta.preview_secs,
                rmse_floor: Some(rmse_floor),
                preview_projected_pred: projected_preview(ttuv_pred, ref_mean, rmse_floor),
                preview_projected_ref: None,
                ref_noise: None,
                curve: t.curve.clone(),
            };
            let layers = [full.mean, t.film.mean(Buffer::Low), t.film.mean(Buffer::High)];
            write_bytes_atomically(&cell_npy, &image_npy(&layers, args.size, args.size))?;
            write_json(&cell_json, &cell)?;
            group_cells.push(cell);
        }
        // Fill in what a cached cell could not know (a later --preview run, or a
        // reference rendered again: speedups compare timings of the same run).
        for c in &mut group_cells {
            (c.ttuv_ref, c.secs_ref) = (meta.ttuv, meta.seconds);
            c.speedup = if c.ttuv_pred > 0.0 { meta.ttuv / c.ttuv_pred } else { f64::INFINITY };
            c.preview_secs_ref = meta.preview_secs;
            c.preview_projected_ref = projected_preview(meta.ttuv, ref_mean, 0.0);
            c.ref_noise = Some(ref_noise);
        }
        write_sheet(&args.out.join(format!("sheet_{key}.png")), &reference, &cache, &key, args, &model_id)?;
        if args.preview {
            let job = PreviewJob {
                file: &file,
                scene: &scene,
                reference: &reference,
                mask: &mask,
                bound: &bind_preview,
                field_nodes: args.field_nodes,
                spp: args.preview_passes.max(2),
                repeats: args.preview_repeats.max(1),
                control: &control,
                cache: &cache,
                // The floor, the first pass's error and the time to 5 % are measured
                // against the reference, so its samples are part of the key.
                key: &format!("{key}_ref{}_{model_id}", args.spp_ref),
                labels: (label, config, *rho),
            };
            let cells = job.run()?;
            super::preview::write_group(&args.out, &key, &job, &cells, &meta.preview_curve, &group_cells)?;
            previews.extend(cells.into_iter().map(|(c, _)| c));
        }
        results.extend(group_cells);
    }
    bar.finish_and_clear();
    write_reports(&args.out, &results, args)?;
    if args.preview {
        super::preview::write_reports(&args.out, &results, &previews, args.run.quiet)?;
    }
    Ok(results)
}

/// One PNG per configuration, one row per k: reference full, prediction full,
/// low orders (1 .. k-1), reference high orders (reference - low), predicted high
/// orders, and |predicted - reference high| in false colour (scale: black 0, yellow
/// = the mean reference high order over lit pixels, as in the window), like the
/// thesis's figure 5.9.
fn write_sheet(path: &Path, reference: &Image, cache: &Path, key: &str, args: &EvalArgs, model_id: &str) -> Result<()> {
    let (w, h) = (reference.w, reference.h);
    let mut sheet = TileSheet::new(w, h, 6, args.k.len() as u32);
    let tone = ToneMap::Filmic;
    for (row, &k) in args.k.iter().enumerate() {
        let cell_npy = cache.join(format!("{}.npy", cell_key(key, k, args, model_id)));
        let Ok(layers) = read_image_npy(&cell_npy, w, h, 3) else { continue };
        let (full, low, high) = (&layers[0], &layers[1], &layers[2]);
        let ref_high: Vec<[f32; 3]> =
            reference.mean.iter().zip(low).map(|(r, l)| std::array::from_fn(|c| (r[c] - l[c]).max(0.0))).collect();
        // The error's colour scale, as in the window: yellow at the mean reference high.
        let scale = lit_mean(&ref_high).max(1e-12);
        let toned = |img: &[[f32; 3]]| tone.to_rgb8(img, 0.0);
        let error = error_colours(high, &ref_high, scale);
        let tiles = [toned(&reference.mean), toned(full), toned(low), toned(&ref_high), toned(high), error];
        for (col, tile) in tiles.iter().enumerate() {
            sheet.put(col as u32, row as u32, tile);
        }
    }
    sheet.save(path)
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map(|s| format!("{s:.1}")).unwrap_or_else(|| "-".into())
}

/// results.csv, results.md (tables like the thesis's B.1-B.6) and the bias and speedup
/// plots against k (figure 5.8), one pair per scene.
fn write_reports(out: &Path, results: &[CellResult], args: &EvalArgs) -> Result<()> {
    let csv = Csv::<CellResult>::new()
        .col("scene", |c| c.scene.clone())
        .col("config", |c| c.config.clone())
        .col("rho", |c| c.rho.to_string())
        .col("k", |c| c.k.to_string())
        .col("p", |c| c.p.to_string())
        .col("size", |c| c.size.to_string())
        .col("spp_ref", |c| c.spp_ref.to_string())
        .col("spp", |c| c.spp.to_string())
        .col("bias", |c| format!("{:.6e}", c.bias))
        .col("rel_bias", |c| format!("{:.6}", c.rel_bias))
        .col("rel_noise_floor", |c| format!("{:.6}", c.rel_noise_floor))
        .col("ttuv_ref", |c| format!("{:.6e}", c.ttuv_ref))
        .col("ttuv_pred", |c| format!("{:.6e}", c.ttuv_pred))
        .col("speedup", |c| format!("{:.3}", c.speedup))
        .col("secs_ref", |c| format!("{:.2}", c.secs_ref))
        .col("secs_pred", |c| format!("{:.2}", c.secs_pred))
        .col("secs_field", |c| format!("{:.2}", c.secs_field))
        .col("secs_pilot", |c| format!("{:.2}", c.secs_pilot))
        .col("preview_secs_ref", |c| opt_cell(c.preview_secs_ref))
        .col("preview_secs_pred", |c| opt_cell(c.preview_secs_pred))
        .col("rmse_floor", |c| opt_cell(c.rmse_floor))
        .col("preview_projected_ref", |c| opt_cell(c.preview_projected_ref))
        .col("preview_projected_pred", |c| opt_cell(c.preview_projected_pred))
        .col("ref_noise", |c| opt_cell(c.ref_noise))
        .render(results);
    write_bytes_atomically(&out.join("results.csv"), csv.as_bytes())?;
    let mut md = format!(
        "# nimbus eval\n\n{}x{} pixels, reference {} spp, predictions {} spp, p = {}, grids {}^3, albedo 1, HG g = 0.85.\n\
         Cells: relative bias (noise floor) / speedup in TTUV. Bias as in docs/conventions.md (16x box downscale).\n",
        args.size,
        args.size,
        args.spp_ref,
        args.spp,
        if args.auto_p { "automatic (per cell, see results.csv)".to_string() } else { args.p.to_string() },
        args.res
    );
    let mut scenes: Vec<&str> = results.iter().map(|c| c.scene.as_str()).collect();
    scenes.dedup();
    for s in &scenes {
        let mut ks: Vec<u32> = results.iter().filter(|c| c.scene == *s).map(|c| c.k).collect();
        ks.sort();
        ks.dedup();
        md += &format!(
            "\n## Scene {s}\n\n| config | rho | TTUV reference | {} |\n|---|---|---|{}\n",
            ks.iter().map(|k| format!("k = {k}")).collect::<Vec<_>>().join(" | "),
            "---|".repeat(ks.len())
        );
        let mut rows: Vec<(&str, f32)> =
            results.iter().filter(|c| c.scene == *s).map(|c| (c.config.as_str(), c.rho)).collect();
        rows.dedup();
        for (config, rho) in &rows {
            let cells: Vec<&CellResult> =
                results.iter().filter(|c| c.scene == *s && c.config == *config && c.rho == *rho).collect();
            let ttuv_ref = cells.first().map(|c| c.ttuv_ref).unwrap_or(0.0);
            let cols: Vec<String> = ks
                .iter()
                .map(|k| match cells.iter().find(|c| c.k == *k) {
                    Some(c) => {
                        format!("{:.2} % ({:.2} %) / {:.1}x", 100.0 * c.rel_bias, 100.0 * c.rel_noise_floor, c.speedup)
                    }
                    None => "-".into(),
                })
                .collect();
            md += &format!("| {config} | {rho} | {ttuv_ref:.3e} | {} |\n", cols.join(" | "));
        }
        if *s == "A" {
            md += "\nScene A beside the thesis (table B.2 speedup, B.1 absolute bias; our bias is in the units of a unit-radiance sun, like the thesis's):\n\n\
                   | config | rho | speedup k=1 (thesis) | speedup k=2 (thesis) | bias k=1 (thesis) |\n|---|---|---|---|---|\n";
            for (config, rho, sp) in THESIS_SCENE_A_SPEEDUP {
                let get =
                    |k: u32| results.iter().find(|c| c.scene == "A" && c.config == config && c.rho == rho && c.k == k);
                let bias_t =
                    THESIS_SCENE_A_BIAS.iter().find(|b| b.0 == config && b.1 == rho).map(|b| b.2[0]).unwrap_or(0.0);
                if get(1).is_none() && get(2).is_none() {
                    continue;
                }
                md += &format!(
                    "| {config} | {rho} | {} ({:.1}x) | {} ({:.1}x) | {} ({bias_t}) |\n",
                    get(1).map(|c| format!("{:.1}x", c.speedup)).unwrap_or("-".into()),
                    sp[0],
                    get(2).map(|c| format!("{:.1}x", c.speedup)).unwrap_or("-".into()),
                    sp[1],
                    get(1).map(|c| format!("{:.4}", c.bias)).unwrap_or("-".into()),
                );
            }
        }
        let previews: Vec<&CellResult> = results
            .iter()
            .filter(|c| {
                c.scene == *s && (args.preview || c.preview_secs_ref.is_some() || c.preview_secs_pred.is_some())
            })
            .collect();
        if !previews.is_empty() {
            md += "\nTime to preview (5 % relative RMSE against the converged image, the reference's own noise \
                   subtracted), seconds measured (projected from TTUV); the prediction's RMSE floor is its bias part, \
                   at or above 5 % it never previews:\n\n\
                   | config | rho | k | reference noise | path tracing | prediction | prediction floor | ratio |\n|---|---|---|---|---|---|---|---|\n";
            for c in previews {
                let secs = |m: Option<f64>, p: Option<f64>| format!("{} ({})", fmt_opt(m), fmt_opt(p));
                let ratio = match (
                    c.preview_secs_ref.or(c.preview_projected_ref),
                    c.preview_secs_pred.or(c.preview_projected_pred),
                ) {
                    (Some(a), Some(b)) if b > 0.0 => format!("{:.1}x", a / b),
                    _ => "-".into(),
                };
                md += &format!(
                    "| {} | {} | {} | {} | {} | {} | {} | {ratio} |\n",
                    c.config,
                    c.rho,
                    c.k,
                    c.ref_noise.map(|v| format!("{:.1} %", 100.0 * v)).unwrap_or("-".into()),
                    secs(c.preview_secs_ref, c.preview_projected_ref),
                    secs(c.preview_secs_pred, c.preview_projected_pred),
                    c.rmse_floor.map(|v| format!("{:.1} %", 100.0 * v)).unwrap_or("-".into()),
                );
            }
        }
        // Plots against k, one series per (config, rho).
        let mut bias_series = vec![];
        let mut speed_series = vec![];
        for (i, (config, rho)) in rows.iter().enumerate() {
            let cells: Vec<&CellResult> =
                results.iter().filter(|c| c.scene == *s && c.config == *config && c.rho == *rho).collect();
            let colour = models::plot::PALETTE[i % models::plot::PALETTE.len()];
            let label = format!("{config} {rho}");
            bias_series.push(models::plot::Series {
                label: label.clone(),
                colour,
                points: cells.iter().map(|c| (c.k as f64, c.rel_bias)).collect(),
            });
            speed_series.push(models::plot::Series {
                label,
                colour,
                points: cells.iter().map(|c| (c.k as f64, c.speedup)).collect(),
            });
        }
        let title = format!("scene {s}");
        write_bytes_atomically(
            &out.join(format!("bias_{s}.png")),
            &models::plot::line_plot_png(&title, "k", "relative bias", &bias_series),
        )?;
        write_bytes_atomically(
            &out.join(format!("speedup_{s}.png")),
            &models::plot::line_plot_png(&title, "k", "speedup", &speed_series),
        )?;
    }
    write_bytes_atomically(&out.join("results.md"), md.as_bytes())?;
    if !args.run.quiet {
        println!("{md}");
        eprintln!("wrote results.md, results.csv, plots and sheets to {}", out.display());
    }
    Ok(())
}
