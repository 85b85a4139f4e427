//! `nimbus eval p2p`: the point-to-point model's evaluation (thesis 6.5).
//!
//! One cloud (scene A of the modeler, the cloud the shipped model was trained on) at
//! rho = 25, albedo 0.99, isotropic, backlit and frontlit, k = 1 .. 4 segments per
//! subpath. Per configuration and k:
//! - the high-order reference: BDPT without prediction, buffers split at 2k + 1
//!   (`--spp-ref` samples; thesis: 16k), whose high buffer is also the baseline of
//!   the speedup, as in the thesis's table 6.3;
//! - BDPT with prediction (`--spp`; thesis: 4k), one per model: the shipped or
//!   `--model` single-cloud model, and `--multi-model` if given;
//! - per configuration, full transport by unidirectional path tracing (`--spp-ref`),
//!   the honest comparison the thesis also made.
//!
//! Figures of merit: the thesis's bias (mean absolute error of the high-order image
//! over all pixels, linear), docs/conventions.md's bias and relative bias (16x box
//! downscale, lit blocks) with its noise floor, TTUV of the high buffer (mean
//! variance of the pixel estimate over lit pixels times render seconds) and the
//! speedup against BDPT's high buffer, and the TTUV of the full image against path
//! tracing's. Renders are cached under OUT/cache (a rerun resumes), Ctrl-C stops.
//! Writes OUT/p2p.md, OUT/p2p.csv and one image sheet per configuration
//! (figures 6.8-6.9: reference high orders, prediction, error).

use super::common::{Csv, TileSheet, image_npy, read_image_npy, read_json, render_tracked, write_json};
use crate::cli::common::{BdptPredictionArgs, RunArgs, init_threads, progress_bar, stop_on_ctrl_c};
use crate::metrics::{Image, bias, error_colours, lit_mean, nonempty, ttuv};
use crate::output::{ToneMap, write_bytes_atomically};
use crate::scene::{PredictorCache, SceneFile};
use anyhow::{Context, Result, bail};
use clap::Args;
use engine::{Buffer, Integrator, RenderControl, Scene};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Args, Debug, Clone)]
pub struct EvalP2pArgs {
    /// Lighting configurations.
    #[arg(long, value_delimiter = ',', default_value = "backlit,frontlit")]
    pub configs: Vec<String>,
    /// Segments per subpath.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3,4")]
    pub k: Vec<u32>,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 128)]
    pub size: u32,
    /// Samples per pixel of the BDPT references and of path tracing (thesis: 16384).
    #[arg(long, default_value_t = 1024)]
    pub spp_ref: u32,
    /// Samples per pixel of the predictions (thesis: 4096).
    #[arg(long, default_value_t = 256)]
    pub spp: u32,
    /// Prediction probability p.
    #[arg(long, default_value_t = 1.0)]
    pub p: f32,
    /// r, candidates and samples per close pair, for the predictions and the
    /// estimated baseline alike.
    #[command(flatten)]
    pub bdpt: BdptPredictionArgs,
    /// The cloud (a modeler preset).
    #[arg(long, default_value = "scene-a")]
    pub cloud: String,
    /// Density grid resolution.
    #[arg(long, default_value_t = 128)]
    pub res: u32,
    /// The single-cloud model (default: the shipped one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// A model trained on twelve clouds with the evaluated one among them, as the
    /// thesis's multi model was (docs/point-to-point.md: scene-a and set-01 .. set-11), evaluated
    /// beside the single one.
    #[arg(long)]
    pub multi_model: Option<PathBuf>,
    /// More models to evaluate beside them, NAME=PATH (e.g. mlp=out/mlp.safetensors);
    /// repeatable.
    #[arg(long = "also", value_name = "NAME=PATH")]
    pub also: Vec<String>,
    /// Output directory (tables, sheets and the render cache).
    #[arg(long, default_value = "out/eval-p2p")]
    pub out: PathBuf,
    #[command(flatten)]
    pub run: RunArgs,
}

/// Thesis table 6.2: bias of the single and multi models (backlit k = 1..4, frontlit
/// k = 1..4).
pub const THESIS_BIAS: [(&str, [f64; 4], [f64; 4]); 2] = [
    ("single", [0.0021, 0.0010, 0.0007, 0.0007], [0.0080, 0.0045, 0.0031, 0.0021]),
    ("multi", [0.0112, 0.0076, 0.0061, 0.0052], [0.0279, 0.0159, 0.0109, 0.0084]),
];

/// Thesis table 6.3: speedup against BDPT's high orders (backlit, frontlit).
pub const THESIS_SPEEDUP: [(&str, [f64; 4], [f64; 4]); 2] =
    [("single", [7.9, 8.9, 10.4, 11.3], [6.0, 7.4, 8.3, 9.3]), ("multi", [6.8, 8.3, 9.7, 10.5], [5.1, 6.6, 7.6, 8.6])];

/// Thesis table 6.3: TTUV of full path tracing and of the single model's prediction
/// at k = 1 (backlit, frontlit): the prediction was 69x and 91x slower.
pub const THESIS_PT_VS_PRED: [(&str, f64, f64); 2] = [("backlit", 10.3, 706.0), ("frontlit", 78.3, 7099.8)];

/// One cached render: its timing and the images it yields.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct RenderMeta {
    seconds: f64,
    spp: u32,
}

/// The figures of one (config, model, k) cell.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct P2pCell {
    pub config: String,
    pub model: String,
    pub k: u32,
    /// The thesis's bias: mean |reference - prediction| of the high orders, all pixels.
    pub mae: f64,
    /// docs/conventions.md bias, relative bias and relative noise floor.
    pub bias: f64,
    pub rel_bias: f64,
    pub rel_noise_floor: f64,
    pub ttuv_bdpt_high: f64,
    /// TTUV of the high orders with the transport between the subpaths' ends
    /// estimated instead of predicted: the thesis's baseline for table 6.3.
    pub ttuv_estimated_high: f64,
    /// TTUV estimated / TTUV predicted: the thesis's speedup.
    pub speedup_thesis: f64,
    /// Relative bias of the estimated baseline (unbiased: its noise floor only).
    pub rel_bias_estimated: f64,
    pub ttuv_pred_high: f64,
    /// TTUV of full BDPT's high orders / TTUV predicted.
    pub speedup: f64,
    pub ttuv_pt_full: f64,
    pub ttuv_pred_full: f64,
    /// TTUV of path tracing's full image / TTUV of the prediction's full image
    /// (above 1: prediction wins).
    pub vs_path_tracing: f64,
    pub secs_ref: f64,
    pub secs_pred: f64,
    /// Seconds of the estimated baseline's render (the same spp as the prediction's).
    #[serde(default)]
    pub secs_estimated: f64,
    /// Per-sample variance of the estimated baseline over that of the prediction
    /// (high orders, same spp): the speedup a prediction costing what one
    /// point-to-point sample costs would reach. speedup_thesis = variance_ratio x
    /// secs_estimated / secs_pred.
    #[serde(default)]
    pub variance_ratio: f64,
    /// Seconds of the same subpaths with a free (zero-cost) predictor.
    #[serde(default)]
    pub secs_free: f64,
    /// The speedup against the baseline a free network would reach:
    /// variance_ratio x secs_estimated / secs_free.
    #[serde(default)]
    pub free_ceiling: f64,
}

/// A predictor that answers 0 at no cost. Its render traces the same subpaths as the
/// prediction and the estimated baseline, so its time is what a free network would
/// take: the ceiling of the speedup against the baseline is the variance ratio times
/// seconds estimated / seconds free. (Its image is not used: 0 - T_1 is no estimate.)
struct FreeTransport;

impl engine::TransportPredictor for FreeTransport {
    fn predict(&self, _: &engine::Medium, _: &engine::P2pQuery, _: &mut engine::Rng) -> f32 {
        0.0
    }

    fn predict_batch(&self, _: &engine::Medium, _: &[engine::P2pQuery], _: &mut [engine::Rng], out: &mut [f32]) {
        out.fill(0.0);
    }

    fn name(&self) -> &str {
        "free transport (timing only)"
    }
}

fn scene_file(args: &EvalP2pArgs, config: &str) -> Result<SceneFile> {
    let text = format!(
        "seed = 1\n[grid]\npreset = \"{}\"\nresolution = {}\n[medium]\nrho = 25.0\nalbedo = 0.99\nphase = \"isotropic\"\n\
         [camera]\npreset = \"{config}\"\nwidth = {s}\nheight = {s}\n[render]\nintegrator = \"bdpt\"\np = {}\nr = {}\ncandidates = {}\nextension_samples = {}\n",
        args.cloud,
        args.res,
        args.p,
        args.bdpt.r(),
        args.bdpt.candidates(),
        args.bdpt.extension_samples(),
        s = args.size
    );
    let s = SceneFile::from_toml_str(&text, "point-to-point evaluation scene")?;
    s.validate()?;
    Ok(s)
}

/// The render cache's name for a model: a fingerprint of its bytes (weights and
/// sidecar), so a model retrained into the same file, or a new shipped one, never
/// reuses old renders, and a file with the shipped bytes shares the shipped one's.
fn model_id(p: Option<&Path>) -> Result<String> {
    Ok(match p {
        Some(p) => format!("{:016x}", models::fingerprint::model_file_fingerprint(p)?),
        None => format!("{:016x}", models::p2p::model::shipped_fingerprint()),
    })
}

/// Renders (or reads from the cache) the buffers `bufs` of one render.
#[allow(clippy::too_many_arguments)]
fn cached(
    cache: &Path,
    key: &str,
    scene: &Arc<Scene>,
    make: &mut dyn FnMut() -> Result<Integrator>,
    spp: u32,
    bufs: &[Buffer],
    control: &RenderControl,
    on_pass: &dyn Fn(u32),
) -> Result<(Vec<Image>, RenderMeta)> {
    let (npy, json) = (cache.join(format!("{key}.npy")), cache.join(format!("{key}.json")));
    let (w, h) = (scene.camera.width(), scene.camera.height());
    if let Some(meta) = read_json::<RenderMeta>(&json) {
        if let Ok(layers) = read_image_npy(&npy, w, h, 2 * bufs.len()) {
            on_pass(spp);
            let imgs = layers.chunks_exact(2).map(|l| Image { w, h, mean: l[0].clone(), var: l[1].clone() }).collect();
            return Ok((imgs, meta));
        }
    }
    let t = render_tracked(scene.clone(), make()?, spp, control, None, false, on_pass)?;
    let imgs: Vec<Image> = bufs.iter().map(|b| Image::from_film(&t.film, *b)).collect();
    let layers: Vec<Vec<[f32; 3]>> = imgs.iter().flat_map(|i| [i.mean.clone(), i.var.clone()]).collect();
    write_bytes_atomically(&npy, &image_npy(&layers, w, h))?;
    let meta = RenderMeta { seconds: t.seconds, spp };
    write_json(&json, &meta)?;
    Ok((imgs, meta))
}

/// The integrator a scene file asks for; a model's fallback warning is an error here.
fn from_file(file: &SceneFile, scene: &Scene, predictors: &mut PredictorCache) -> Result<Integrator> {
    let setup = file.integrator_cached(
        scene,
        models::global::depth_field::DEFAULT_MAX_NODES,
        predictors,
        engine::Cancel::NEVER,
    )?;
    if let Some(w) = setup.warning {
        bail!("{w}");
    }
    Ok(setup.integrator)
}

pub fn eval_p2p(args: &EvalP2pArgs) -> Result<Vec<P2pCell>> {
    let threads = init_threads(args.run.threads)?;
    for c in &args.configs {
        if !matches!(c.as_str(), "backlit" | "frontlit" | "toplit") {
            bail!("--configs {c}: choose from backlit, frontlit, toplit");
        }
    }
    if args.k.is_empty() || args.k.iter().any(|k| !(1..=16).contains(k)) {
        bail!("--k {:?}: every k must lie in 1 ..= 16", args.k);
    }
    if args.spp < 2 || args.spp_ref < 2 || args.size == 0 {
        bail!("--spp and --spp-ref must be at least 2 (variances need two samples), --size at least 1");
    }
    if modeler::preset(&args.cloud).is_none() {
        bail!("--cloud {}: not a modeler preset ({})", args.cloud, modeler::PRESET_NAMES.join(", "));
    }
    let mut named: Vec<(String, Option<PathBuf>)> = vec![("single".into(), args.model.clone())];
    if let Some(m) = &args.multi_model {
        named.push(("multi".into(), Some(m.clone())));
    }
    for a in &args.also {
        let (name, path) = a.split_once('=').with_context(|| format!("--also {a}: expected NAME=PATH"))?;
        named.push((name.to_string(), Some(PathBuf::from(path))));
    }
    // Fail early, naming the file, if a model does not load; then name its renders.
    let mut models: Vec<(String, Option<PathBuf>, String)> = vec![];
    for (name, path) in named {
        match &path {
            Some(p) => {
                models::p2p::model::P2pModel::load(p).map_err(|e| anyhow::anyhow!("{name} model: {e}"))?;
            }
            None => {
                models::p2p::model::P2pModel::shipped().map_err(|e| anyhow::anyhow!("shipped model: {e}"))?;
            }
        }
        let id = model_id(path.as_deref()).with_context(|| format!("{name} model"))?;
        models.push((name, path, id));
    }
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    let cache = args.out.join("cache");
    crate::output::create_dir(&cache)?;
    let per_config =
        args.spp_ref as u64 * (1 + args.k.len() as u64) + args.spp as u64 * (args.k.len() * (2 + models.len())) as u64;
    let bar = progress_bar(per_config * args.configs.len() as u64, "spp", args.run.quiet);
    eprintln!(
        "point-to-point evaluation: {} at {}x{}, configs {:?}, k {:?}, {} spp references, {} spp predictions, {} threads",
        args.cloud, args.size, args.size, args.configs, args.k, args.spp_ref, args.spp, threads
    );
    let mut cells = vec![];
    let mut done = 0u64;
    let sheets = args.out.join("sheets");
    crate::output::create_dir(&sheets)?;
    for config in &args.configs {
        let base = scene_file(args, config)?;
        let scene = Arc::new(base.build_scene(None)?);
        let tag = format!("{}_{config}_{}_{}", args.cloud, args.size, args.res);
        // Prediction renders are named by their light subpath candidates (picked from
        // the pass's shared pool) and their samples per close pair.
        let m = format!("_pool{}_x{}", args.bdpt.candidates(), args.bdpt.extension_samples());
        let mut caches: Vec<PredictorCache> = models.iter().map(|_| PredictorCache::default()).collect();
        let mut none = PredictorCache::default();
        let step = |n: u32, start: u64| bar.set_position(start + n as u64);
        // Full transport by path tracing.
        let mut pt = base.clone();
        pt.render.integrator = "path".into();
        pt.render.mode = "reference".into();
        let start = done;
        let (pt_img, pt_meta) = cached(
            &cache,
            &format!("{tag}_pt_full_spp{}", args.spp_ref),
            &scene,
            &mut || from_file(&pt, &scene, &mut none),
            args.spp_ref,
            &[Buffer::Full],
            &control,
            &|n| step(n, start),
        )?;
        done += args.spp_ref as u64;
        let ttuv_pt = ttuv(&pt_img[0].var, &nonempty(&pt_img[0].mean), pt_meta.seconds);
        let mut rows = vec![];
        for &k in &args.k {
            let mut reference = base.clone();
            reference.render.mode = "reference".into();
            reference.k = 2 * k + 1;
            let start = done;
            let (ref_img, ref_meta) = cached(
                &cache,
                &format!("{tag}_bdpt_k{k}_spp{}", args.spp_ref),
                &scene,
                &mut || from_file(&reference, &scene, &mut none),
                args.spp_ref,
                &[Buffer::High],
                &control,
                &|n| step(n, start),
            )?;
            done += args.spp_ref as u64;
            let ref_high = &ref_img[0];
            let mask = nonempty(&ref_high.mean);
            let ttuv_ref = ttuv(&ref_high.var, &mask, ref_meta.seconds);
            // The thesis's baseline: the same subpaths, the transport between their
            // ends estimated (one sample of the point-to-point estimator).
            let mut pred = base.clone();
            pred.render.mode = "predict".into();
            pred.k = k;
            // The same subpaths with another transport between their ends, not a model.
            let mut with_transport =
                |name: &str, transport: Arc<dyn engine::TransportPredictor>| -> Result<(Vec<Image>, RenderMeta)> {
                    let start = done;
                    let out = cached(
                        &cache,
                        &format!("{tag}_{name}_k{k}_p{}_r{}{m}_spp{}", args.p, args.bdpt.r(), args.spp),
                        &scene,
                        &mut || {
                            Ok(Integrator::bdpt_prediction(
                                pred.settings(),
                                Default::default(),
                                transport.clone(),
                                args.bdpt.r(),
                            )?
                            .with_light_candidates(args.bdpt.candidates())?
                            .with_extension_samples(args.bdpt.extension_samples())?)
                        },
                        args.spp,
                        &[Buffer::High],
                        &control,
                        &|n| step(n, start),
                    )?;
                    done += args.spp as u64;
                    Ok(out)
                };
            let (base_img, base_meta) =
                with_transport("estimated", Arc::new(engine::integrator::p2p::EstimatedTransport::default()))?;
            let ttuv_base = ttuv(&base_img[0].var, &mask, base_meta.seconds);
            let (_, free_meta) = with_transport("free", Arc::new(FreeTransport))?;
            let mut row = vec![];
            for (mi, (name, path, id)) in models.iter().enumerate() {
                pred.render.p2p_model =
                    path.as_ref().map(|p| std::path::absolute(p).unwrap_or(p.clone()).display().to_string());
                let start = done;
                let (imgs, meta) = cached(
                    &cache,
                    // "_q16": features from the pyramid's 16-bit samples; renders
                    // timed with the earlier 32-bit ones are not reused.
                    &format!("{tag}_pred_{id}_k{k}_p{}_r{}{m}_q16_spp{}", args.p, args.bdpt.r(), args.spp),
                    &scene,
                    &mut || from_file(&pred, &scene, &mut caches[mi]),
                    args.spp,
                    &[Buffer::High, Buffer::Full],
                    &control,
                    &|n| step(n, start),
                )?;
                done += args.spp as u64;
                let (high, full) = (&imgs[0], &imgs[1]);
                let mae = high
                    .mean
                    .iter()
                    .zip(&ref_high.mean)
                    .map(|(a, b)| (0..3).map(|c| (a[c] as f64 - b[c] as f64).abs()).sum::<f64>() / 3.0);
                let mae = mae.sum::<f64>() / high.mean.len().max(1) as f64;
                let (b, rb, floor) = bias(ref_high, high);
                let ttuv_pred = ttuv(&high.var, &mask, meta.seconds);
                let ttuv_pred_full = ttuv(&full.var, &nonempty(&pt_img[0].mean), meta.seconds);
                // Per-sample variance, estimated over predicted (same spp).
                let variance_ratio = if ttuv_pred > 0.0 {
                    (ttuv_base / base_meta.seconds.max(1e-9)) / (ttuv_pred / meta.seconds.max(1e-9))
                } else {
                    f64::INFINITY
                };
                let cell = P2pCell {
                    config: config.clone(),
                    model: name.clone(),
                    k,
                    mae,
                    bias: b,
                    rel_bias: rb,
                    rel_noise_floor: floor,
                    ttuv_bdpt_high: ttuv_ref,
                    ttuv_estimated_high: ttuv_base,
                    speedup_thesis: if ttuv_pred > 0.0 { ttuv_base / ttuv_pred } else { f64::INFINITY },
                    rel_bias_estimated: bias(ref_high, &base_img[0]).1,
                    ttuv_pred_high: ttuv_pred,
                    speedup: if ttuv_pred > 0.0 { ttuv_ref / ttuv_pred } else { f64::INFINITY },
                    ttuv_pt_full: ttuv_pt,
                    ttuv_pred_full,
                    vs_path_tracing: if ttuv_pred_full > 0.0 { ttuv_pt / ttuv_pred_full } else { f64::INFINITY },
                    secs_ref: ref_meta.seconds,
                    secs_pred: meta.seconds,
                    secs_estimated: base_meta.seconds,
                    variance_ratio,
                    secs_free: free_meta.seconds,
                    free_ceiling: variance_ratio * base_meta.seconds / free_meta.seconds.max(1e-9),
                };
                if !args.run.quiet {
                    bar.println(format!(
                        "{config} {name} k {k}: bias {:.2e} (relative {:.1} %, floor {:.1} %), speedup {:.2}x (thesis's baseline), {:.2}x vs BDPT high, {:.3}x vs path tracing",
                        cell.mae,
                        100.0 * rb,
                        100.0 * floor,
                        cell.speedup_thesis,
                        cell.speedup,
                        cell.vs_path_tracing
                    ));
                }
                row.push(high.mean.clone());
                cells.push(cell);
            }
            rows.push((ref_high.mean.clone(), row));
        }
        write_sheet(&sheets.join(format!("{config}.png")), args.size, &rows)?;
    }
    bar.finish_and_clear();
    write_reports(&args.out, &cells, args)?;
    eprintln!("wrote {}", args.out.join("p2p.md").display());
    Ok(cells)
}

/// One row per k: the reference high orders, then per model its prediction and the
/// error |prediction - reference| in false colour (yellow = the row's mean lit
/// reference value). Exposure per row puts the reference's lit mean at mid-grey.
fn write_sheet(path: &Path, size: u32, rows: &[(Vec<[f32; 3]>, Vec<Vec<[f32; 3]>>)]) -> Result<()> {
    let cols = rows.first().map_or(1, |r| 1 + 2 * r.1.len()) as u32;
    let mut sheet = TileSheet::new(size, size, cols, rows.len() as u32);
    let tone = ToneMap::Filmic;
    for (r, (reference, preds)) in rows.iter().enumerate() {
        let scale = lit_mean(reference).max(1e-12);
        let exposure = (0.18 / scale as f32).log2();
        let mut tiles = vec![tone.to_rgb8(reference, exposure)];
        for pred in preds {
            tiles.push(tone.to_rgb8(pred, exposure));
            tiles.push(error_colours(pred, reference, scale));
        }
        for (c, tile) in tiles.iter().enumerate() {
            sheet.put(c as u32, r as u32, tile);
        }
    }
    sheet.save(path)
}

fn write_reports(out: &Path, cells: &[P2pCell], args: &EvalP2pArgs) -> Result<()> {
    let csv = Csv::<P2pCell>::new()
        .col("config", |c| c.config.clone())
        .col("model", |c| c.model.clone())
        .col("k", |c| c.k.to_string())
        .col("mae", |c| format!("{:.6e}", c.mae))
        .col("bias", |c| format!("{:.6e}", c.bias))
        .col("rel_bias", |c| format!("{:.5}", c.rel_bias))
        .col("rel_noise_floor", |c| format!("{:.5}", c.rel_noise_floor))
        .col("rel_bias_estimated", |c| format!("{:.5}", c.rel_bias_estimated))
        .col("ttuv_bdpt_high", |c| format!("{:.6e}", c.ttuv_bdpt_high))
        .col("ttuv_estimated_high", |c| format!("{:.6e}", c.ttuv_estimated_high))
        .col("ttuv_pred_high", |c| format!("{:.6e}", c.ttuv_pred_high))
        .col("speedup_thesis", |c| format!("{:.4}", c.speedup_thesis))
        .col("speedup", |c| format!("{:.4}", c.speedup))
        .col("ttuv_pt_full", |c| format!("{:.6e}", c.ttuv_pt_full))
        .col("ttuv_pred_full", |c| format!("{:.6e}", c.ttuv_pred_full))
        .col("vs_path_tracing", |c| format!("{:.5}", c.vs_path_tracing))
        .col("secs_ref", |c| format!("{:.2}", c.secs_ref))
        .col("secs_pred", |c| format!("{:.2}", c.secs_pred))
        .col("secs_estimated", |c| format!("{:.2}", c.secs_estimated))
        .col("variance_ratio", |c| format!("{:.4}", c.variance_ratio))
        .col("secs_free", |c| format!("{:.2}", c.secs_free))
        .col("free_ceiling", |c| format!("{:.4}", c.free_ceiling))
        .render(cells);
    write_bytes_atomically(&out.join("p2p.csv"), csv.as_bytes())?;
    let thesis = |table: &[(&str, [f64; 4], [f64; 4])], model: &str, config: &str, k: u32| -> String {
        let Some(row) = table.iter().find(|r| r.0 == model) else { return "-".into() };
        let v = match config {
            "backlit" => row.1,
            "frontlit" => row.2,
            _ => return "-".into(),
        };
        v.get(k as usize - 1).map_or("-".into(), |x| format!("{x}"))
    };
    let mut md = format!(
        "# Point-to-point model: evaluation (thesis 6.5)\n\n{} at {}x{}, rho 25, albedo 0.99, isotropic; BDPT references \
         {} spp (split at 2k + 1), predictions and the estimated baseline {} spp, p {}, r {}, {} light subpath \
         candidate(s) per camera end vertex, {} point-to-point sample(s) per pair closer than r.\n\n",
        args.cloud,
        args.size,
        args.size,
        args.spp_ref,
        args.spp,
        args.p,
        args.bdpt.r(),
        args.bdpt.candidates(),
        args.bdpt.extension_samples()
    );
    md += "## Bias of the high orders (table 6.2)\n\nMAE: the thesis's measure (mean absolute error of the high-order \
           image, all pixels, linear; it includes noise, and its scale depends on the scene's brightness). Relative bias: \
           docs/conventions.md (16x box downscale, lit blocks) with its noise floor; \"estimated\": the same for the unbiased \
           baseline, a check of the reference.\n\n\
           | config | model | k | MAE | thesis | relative bias | noise floor | estimated |\n|---|---|---|---|---|---|---|---|\n";
    for c in cells {
        md += &format!(
            "| {} | {} | {} | {:.2e} | {} | {:.1} % | {:.1} % | {:.1} % |\n",
            c.config,
            c.model,
            c.k,
            c.mae,
            thesis(&THESIS_BIAS, &c.model, &c.config, c.k),
            100.0 * c.rel_bias,
            100.0 * c.rel_noise_floor,
            100.0 * c.rel_bias_estimated
        );
    }
    md += "\n## TTUV and speedup (table 6.3)\n\nTTUV of the high orders. Speedup as the thesis measured it: TTUV with the \
           transport between the subpaths' ends estimated (one point-to-point sample) / TTUV predicted. Against full BDPT: \
           TTUV of BDPT's high orders (all strategies, MIS) / TTUV predicted. Against path tracing: TTUV of path-traced full \
           transport / TTUV of the prediction's full image. Below 1 the other method wins. The speedup splits into two \
           factors: the variance ratio (estimated / predicted, per sample: what the speedup would be if a prediction \
           cost what one point-to-point sample costs) times the time ratio (seconds estimated / predicted, same spp). \
           Free-network ceiling: the variance ratio times seconds estimated / seconds of the same subpaths with a \
           zero-cost predictor: the speedup a free network with the same variance would reach.\n\n\
           | config | model | k | TTUV estimated | TTUV predicted | speedup | = variance ratio | x time ratio | free-network ceiling | thesis | TTUV BDPT high | vs BDPT | vs path tracing |\n\
           |---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
    for c in cells {
        md += &format!(
            "| {} | {} | {} | {:.3e} | {:.3e} | {:.2}x | {:.2} | {:.2} | {:.2}x | {}x | {:.3e} | {:.3}x | {:.3}x |\n",
            c.config,
            c.model,
            c.k,
            c.ttuv_estimated_high,
            c.ttuv_pred_high,
            c.speedup_thesis,
            c.variance_ratio,
            c.secs_estimated / c.secs_pred.max(1e-9),
            c.free_ceiling,
            thesis(&THESIS_SPEEDUP, &c.model, &c.config, c.k),
            c.ttuv_bdpt_high,
            c.speedup,
            c.vs_path_tracing
        );
    }
    md += "\nThesis, against path tracing at k = 1 (single model): ";
    md +=
        &THESIS_PT_VS_PRED.iter().map(|(c, pt, pred)| format!("{c} {:.3}x", pt / pred)).collect::<Vec<_>>().join(", ");
    md += ".\n";
    write_bytes_atomically(&out.join("p2p.md"), md.as_bytes())?;
    Ok(())
}
