//! `nimbus eval`: the thesis's evaluation of the global model (section 5.5, appendix B),
//! with the figures of merit of CONVENTIONS.md.
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
//! Departure from the thesis, stated here and in the README: the reference high-order
//! image of the sheets is reference full minus the prediction run's low buffer (the
//! same path-traced estimator of orders 1 .. k-1) instead of a separate low-order
//! render per k; bias and speedup use full images only, exactly as the thesis did.
//!
//! Every finished render is cached (`OUT/cache`), so a stopped study resumes where it
//! stopped, and `--scenes`, `--configs`, `--rho` and `--k` pick a subset.

use crate::cli::{init_threads, progress_bar, stop_on_ctrl_c};
use crate::output::{ToneMap, write_bytes_atomically};
use crate::scene::SceneFile;
use anyhow::{Context, Result, bail};
use clap::Args;
use engine::{Buffer, DensityGrid, Film, Integrator, PassOutcome, RenderControl, Renderer, Scene};
use models::global::BoundGlobalModel;
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
    #[arg(long, default_value_t = models::depth_field::DEFAULT_MAX_NODES)]
    pub field_nodes: u32,
    /// The global model (default: the shipped one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Also measure path tracing's time to preview (a second path-traced run per
    /// configuration, another seed, until 5 % relative RMSE against the reference, its
    /// own noise subtracted, or --preview-spp samples), and report every prediction's
    /// RMSE floor and projected time to preview.
    #[arg(long)]
    pub preview: bool,
    /// Sample cap of path tracing's preview run (default: 4 x spp-ref).
    #[arg(long)]
    pub preview_spp: Option<u32>,
    /// Output directory (tables, plots, sheets, and the render cache).
    #[arg(long, default_value = "out/eval")]
    pub out: PathBuf,
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long)]
    pub quiet: bool,
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

/// Relative RMSE that counts as a preview (CONVENTIONS.md).
pub const PREVIEW_RMSE: f64 = 0.05;

/// The figures of merit of one (scene, config, rho, k) cell.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CellResult {
    pub scene: String,
    pub config: String,
    pub rho: f32,
    pub k: u32,
    pub p: f32,
    pub spp_ref: u32,
    pub spp: u32,
    pub size: u32,
    /// Absolute bias (CONVENTIONS.md).
    pub bias: f64,
    /// bias / mean reference over the same pixels.
    pub rel_bias: f64,
    /// The bias that noise alone would show (both images' variances, after the
    /// downscale), relative: bias values near it are not resolved.
    pub rel_noise_floor: f64,
    pub ttuv_ref: f64,
    pub ttuv_pred: f64,
    pub speedup: f64,
    pub secs_ref: f64,
    pub secs_pred: f64,
    /// Seconds to build the model's depth field for this cloud and sun (once per
    /// configuration; not part of TTUV).
    pub secs_field: f64,
    /// Seconds of the automatic-p pilot passes (0 without --auto-p; not part of TTUV).
    pub secs_pilot: f64,
    pub preview_secs_pred: Option<f64>,
    pub preview_secs_ref: Option<f64>,
    /// The prediction's relative RMSE once its noise is gone (its bias part; see
    /// [`relative_rmse_less`]): at or above [`PREVIEW_RMSE`] it never previews.
    #[serde(default)]
    pub rmse_floor: Option<f64>,
    /// Seconds to preview projected from TTUV and the floor (variance falls as 1/t):
    /// TTUV / (mean^2 (0.05^2 - floor^2)); None when the floor is at or above 5 %.
    #[serde(default)]
    pub preview_projected_pred: Option<f64>,
    /// The same projection for path tracing (floor 0: it is unbiased), a check on the
    /// measured `preview_secs_ref`.
    #[serde(default)]
    pub preview_projected_ref: Option<f64>,
    /// The reference's own relative noise ([`reference_noise`]).
    #[serde(default)]
    pub ref_noise: Option<f64>,
}

/// Seconds until the relative RMSE reaches [`PREVIEW_RMSE`] for an estimator whose
/// variance of the mean is `ttuv / t` (mean over the lit pixels) and whose bias part
/// is `floor` (relative), for an image of mean `mean`; None if the floor is too high.
pub fn projected_preview(ttuv: f64, mean: f64, floor: f64) -> Option<f64> {
    let room = PREVIEW_RMSE * PREVIEW_RMSE - floor * floor;
    (room > 0.0 && mean > 0.0).then(|| ttuv / (mean * mean * room))
}

#[derive(Clone, Debug, Serialize, Deserialize)]
struct ReferenceMeta {
    spp: u32,
    seconds: f64,
    ttuv: f64,
    preview_secs: Option<f64>,
    /// Whether the path-traced preview run was made (it may not have reached 5 %).
    #[serde(default)]
    preview_tried: bool,
}

/// An image with the per-pixel variance of its estimate.
pub struct Image {
    pub w: u32,
    pub h: u32,
    pub mean: Vec<[f32; 3]>,
    pub var: Vec<[f32; 3]>,
}

impl Image {
    pub fn from_film(film: &Film, b: Buffer) -> Self {
        Image { w: film.width(), h: film.height(), mean: film.mean(b), var: film.variance_of_mean(b) }
    }
}

fn avg3(v: &[f32; 3]) -> f64 {
    (v[0] as f64 + v[1] as f64 + v[2] as f64) / 3.0
}

/// Pixels whose reference value is > 0.
pub fn nonempty(reference: &[[f32; 3]]) -> Vec<bool> {
    reference.iter().map(|p| avg3(p) > 0.0).collect()
}

/// Mean of the pixels whose value (averaged over channels) is > 0.
pub fn lit_mean(img: &[[f32; 3]]) -> f64 {
    let (s, n) = img.iter().map(avg3).filter(|v| *v > 0.0).fold((0.0f64, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 { 0.0 } else { s / n as f64 }
}

/// TTUV: mean over `mask` of the variance of the pixel estimate, times seconds.
pub fn ttuv(var: &[[f32; 3]], mask: &[bool], seconds: f64) -> f64 {
    let (mut s, mut n) = (0.0f64, 0usize);
    for (v, m) in var.iter().zip(mask) {
        if *m {
            s += avg3(v);
            n += 1;
        }
    }
    if n == 0 { 0.0 } else { s / n as f64 * seconds }
}

/// Box-filters an image down by `f` per axis (partial blocks at the edges averaged over
/// the pixels they hold); per-channel means, and the variance of each block mean.
fn downscale(img: &Image, f: u32) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let (bw, bh) = (img.w.div_ceil(f), img.h.div_ceil(f));
    let mut mean = vec![[0.0f64; 3]; (bw * bh) as usize];
    let mut var = vec![[0.0f64; 3]; (bw * bh) as usize];
    let mut count = vec![0u32; (bw * bh) as usize];
    for y in 0..img.h {
        for x in 0..img.w {
            let i = (y * img.w + x) as usize;
            let b = ((y / f) * bw + x / f) as usize;
            for c in 0..3 {
                mean[b][c] += img.mean[i][c] as f64;
                var[b][c] += img.var[i][c] as f64;
            }
            count[b] += 1;
        }
    }
    for b in 0..mean.len() {
        let n = count[b] as f64;
        for c in 0..3 {
            mean[b][c] /= n;
            var[b][c] /= n * n;
        }
    }
    (mean, var)
}

/// (bias, relative bias, relative noise floor) of `pred` against `reference`
/// (CONVENTIONS.md): 16x box downscale, mean over blocks with a reference value > 0
/// of |reference - prediction| averaged over channels; relative = divided by the mean
/// reference over those blocks. The noise floor is E|N(0, s)| = s sqrt(2 / pi) with
/// s^2 the two block means' variances, averaged the same way.
pub fn bias(reference: &Image, pred: &Image) -> (f64, f64, f64) {
    let (rm, rv) = downscale(reference, 16);
    let (pm, pv) = downscale(pred, 16);
    let (mut err, mut refsum, mut floor, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
    for b in 0..rm.len() {
        let r = (rm[b][0] + rm[b][1] + rm[b][2]) / 3.0;
        if r <= 0.0 {
            continue;
        }
        n += 1;
        refsum += r;
        for c in 0..3 {
            err += (rm[b][c] - pm[b][c]).abs() / 3.0;
            floor += (rv[b][c] + pv[b][c]).sqrt() * (2.0 / std::f64::consts::PI).sqrt() / 3.0;
        }
    }
    if n == 0 || refsum <= 0.0 {
        return (0.0, 0.0, 0.0);
    }
    let (err, mean, floor) = (err / n as f64, refsum / n as f64, floor / n as f64);
    (err, err / mean, floor / mean)
}

/// Relative RMSE of `img` against the converged image, measured with a reference that
/// is itself noisy: sqrt(mean over `mask` of (img - ref)^2 - var(ref)) divided by the
/// mean reference value. For an image independent of the reference,
/// E[(img - ref)^2] = E[(img - truth)^2] + var(ref), so subtracting the reference's
/// own variance of the mean (unbiased per pixel) leaves an unbiased estimate of the
/// squared error against the truth: a reference about as converged as the preview
/// itself is enough, where comparing against its mean alone needs one far below 5 %.
/// Clamped at 0 (the estimate can dip below zero when both are nearly exact).
pub fn relative_rmse(img: &[[f32; 3]], reference: &Image, mask: &[bool]) -> f64 {
    relative_rmse_less(img, reference, mask, None)
}

/// [`relative_rmse`] with, optionally, the image's own variance of the mean also
/// subtracted: what is left is the error no amount of samples removes, the bias part
/// of the RMSE (the floor a biased estimator converges to).
pub fn relative_rmse_less(img: &[[f32; 3]], reference: &Image, mask: &[bool], img_var: Option<&[[f32; 3]]>) -> f64 {
    let (mut se, mut r, mut n) = (0.0f64, 0.0f64, 0usize);
    for (i, m) in mask.iter().enumerate() {
        if *m {
            let (a, b, v) = (&img[i], &reference.mean[i], &reference.var[i]);
            for c in 0..3 {
                let d = a[c] as f64 - b[c] as f64;
                let own = img_var.map_or(0.0, |iv| iv[i][c] as f64);
                se += (d * d - v[c] as f64 - own) / 3.0;
            }
            r += avg3(b);
            n += 1;
        }
    }
    // No lit pixel: no preview can be judged.
    if n == 0 || r <= 0.0 { f64::INFINITY } else { (se / n as f64).max(0.0).sqrt() / (r / n as f64) }
}

/// The reference's own relative noise: sqrt(mean over `mask` of its variance of the
/// mean) / its mean; the RMSE a comparison against its mean alone could not go below.
pub fn reference_noise(reference: &Image, mask: &[bool]) -> f64 {
    let mean = lit_mean(&reference.mean);
    if mean > 0.0 { ttuv(&reference.var, mask, 1.0).sqrt() / mean } else { f64::INFINITY }
}

/// What a tracked render returns.
pub(crate) struct Tracked {
    pub film: Film,
    /// Seconds spent rendering passes (the RMSE checks are not counted).
    pub seconds: f64,
    /// Render seconds until the image first came within 5 % relative RMSE.
    preview_secs: Option<f64>,
}

/// Renders up to `spp` passes; with a reference, checks the relative RMSE after every
/// pass and, if `stop_at_preview`, stops once it is within [`PREVIEW_RMSE`].
pub(crate) fn render_tracked(
    scene: Arc<Scene>,
    integrator: Integrator,
    spp: u32,
    control: &RenderControl,
    reference: Option<(&Image, &[bool])>,
    stop_at_preview: bool,
    mut on_pass: impl FnMut(u32),
) -> Result<Tracked> {
    let mut r = Renderer::new(scene, integrator)?;
    let generation = control.generation();
    let (mut seconds, mut preview_secs) = (0.0f64, None);
    for done in 1..=spp {
        let t = Instant::now();
        if r.render_pass(control, generation) == PassOutcome::Cancelled {
            bail!("stopped; finished renders are cached and a rerun resumes from them");
        }
        seconds += t.elapsed().as_secs_f64();
        on_pass(done);
        if let (Some((reference, mask)), None) = (reference, preview_secs) {
            let film = r.film_handle();
            let img = film.read().unwrap_or_else(|e| e.into_inner()).mean(Buffer::Full);
            if relative_rmse(&img, reference, mask) <= PREVIEW_RMSE {
                preview_secs = Some(seconds);
                if stop_at_preview {
                    break;
                }
            }
        }
    }
    Ok(Tracked { film: r.snapshot(), seconds, preview_secs })
}

pub(crate) fn image_npy(img: &[Vec<[f32; 3]>], w: u32, h: u32) -> Vec<u8> {
    let mut flat = Vec::with_capacity(img.len() * (w * h * 3) as usize);
    for i in 0..(w * h) as usize {
        for layer in img {
            flat.extend_from_slice(&layer[i]);
        }
    }
    models::npy::npy_bytes_f32(&[h as usize, w as usize, 3 * img.len()], &flat)
}

/// Reads an (h, w, 3 n) image stack back as n layers.
pub(crate) fn read_image_npy(path: &Path, w: u32, h: u32, n: usize) -> Result<Vec<Vec<[f32; 3]>>> {
    let (shape, data) = models::npy::read_f32(path)?;
    if shape != [h as usize, w as usize, 3 * n] {
        bail!("{}: shape {shape:?}, expected [{h}, {w}, {}]", path.display(), 3 * n);
    }
    let mut layers = vec![Vec::with_capacity((w * h) as usize); n];
    for px in data.chunks_exact(3 * n) {
        for (l, layer) in layers.iter_mut().enumerate() {
            layer.push([px[3 * l], px[3 * l + 1], px[3 * l + 2]]);
        }
    }
    Ok(layers)
}

/// The render cache's name for a model: a fingerprint of its bytes (weights and
/// sidecar), so a model retrained into the same file, or a new shipped one, never
/// reuses old renders, and a file with the shipped bytes shares the shipped one's.
fn model_id(args: &EvalArgs) -> Result<String> {
    Ok(match &args.model {
        Some(path) => format!("{:016x}", models::model_file_fingerprint(path)?),
        None => format!("{:016x}", models::global::shipped_fingerprint()),
    })
}

/// The cache name of one prediction cell: everything its numbers depend on.
fn cell_key(key: &str, k: u32, args: &EvalArgs, model_id: &str) -> String {
    let p = if args.auto_p { "auto".to_string() } else { args.p.to_string() };
    format!("{key}_k{k}_p{p}_spp{}_ref{}_nodes{}_{model_id}", args.spp, args.spp_ref, args.field_nodes)
}

pub(crate) fn write_json(path: &Path, v: &impl Serialize) -> Result<()> {
    Ok(write_bytes_atomically(path, serde_json::to_string_pretty(v)?.as_bytes())?)
}

pub(crate) fn read_json<T: for<'a> Deserialize<'a>>(path: &Path) -> Option<T> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// The scene file of one evaluation configuration.
pub fn eval_scene(preset: &str, config: &str, rho: f32, size: u32, res: u32) -> Result<SceneFile> {
    let text = format!(
        "[grid]\npreset = \"{preset}\"\nresolution = {res}\n[medium]\nrho = {rho}\nalbedo = 1.0\nphase = \"hg\"\ng = 0.85\n\
         [camera]\npreset = \"{config}\"\nwidth = {size}\nheight = {size}\n"
    );
    let s = SceneFile::from_toml_str(&text, "evaluation scene")?;
    s.validate()?;
    Ok(s)
}

/// Runs the study (or the selected part of it); returns every cell's result.
pub fn eval(args: &EvalArgs) -> Result<Vec<CellResult>> {
    let threads = init_threads(args.threads)?;
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
    let model = match &args.model {
        Some(p) => Arc::new(models::global::GlobalModel::load(p)?),
        None => models::global::GlobalModel::shipped()?,
    };
    let model_id = model_id(args).context("--model")?;
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    let cache = args.out.join("cache");
    std::fs::create_dir_all(&cache).with_context(|| format!("cannot create {}", cache.display()))?;
    let groups: Vec<(&str, &str, String, f32)> = scenes
        .iter()
        .flat_map(|(label, preset, rhos)| {
            let rhos: Vec<f32> = if args.rho.is_empty() { rhos.to_vec() } else { args.rho.clone() };
            args.configs
                .iter()
                .flat_map(move |c| rhos.clone().into_iter().map(move |r| (*label, *preset, c.clone(), r)))
        })
        .collect();
    if !args.quiet {
        eprintln!(
            "nimbus eval: {} configurations x k {:?}, {}x{}, reference {} spp, predictions {} spp, p {}, {threads} threads, model {}",
            groups.len(),
            args.k,
            args.size,
            args.size,
            args.spp_ref,
            args.spp,
            args.p,
            args.model.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "shipped".into())
        );
    }
    let renders_per_group = args.spp_ref as u64 + args.spp as u64 * args.k.len() as u64;
    let bar = progress_bar(groups.len() as u64 * renders_per_group, "passes", args.quiet);
    let mut results = vec![];
    let mut grids: Vec<(String, Arc<DensityGrid>)> = vec![];
    for (gi, (label, preset, config, rho)) in groups.iter().enumerate() {
        let base = (gi as u64) * renders_per_group;
        bar.set_position(base);
        bar.set_message(format!("scene {label} {config} rho {rho}"));
        let file = eval_scene(preset, config, *rho, args.size, args.res)?;
        let grid = match grids.iter().find(|(p, _)| p == preset) {
            Some((_, g)) => g.clone(),
            None => {
                let g = Arc::new(file.build_grid()?);
                grids.push((preset.to_string(), g.clone()));
                g
            }
        };
        let scene = Arc::new(file.build_scene(Some(grid))?);
        let key = format!("{label}_{config}_rho{rho}_{}px_res{}", args.size, args.res);
        // The reference, from the cache or rendered now.
        let ref_npy = cache.join(format!("{key}_ref{}.npy", args.spp_ref));
        let ref_json = ref_npy.with_extension("json");
        // Full transport by path tracing with the given seed.
        let path_traced = |seed: u64| -> Result<Integrator> {
            let mut f = file.clone();
            (f.seed, f.k) = (seed, 1);
            Ok(f.integrator_with(None)?)
        };
        let (reference, mut meta) = match (read_json::<ReferenceMeta>(&ref_json), ref_npy.exists()) {
            (Some(meta), true) => {
                let layers = read_image_npy(&ref_npy, args.size, args.size, 2)?;
                let mut it = layers.into_iter();
                let (mean, var) = (it.next().unwrap(), it.next().unwrap());
                (Image { w: args.size, h: args.size, mean, var }, meta)
            }
            _ => {
                let t = render_tracked(scene.clone(), path_traced(0)?, args.spp_ref, &control, None, false, |d| {
                    bar.set_position(base + d as u64)
                })?;
                let img = Image::from_film(&t.film, Buffer::Full);
                let mask = nonempty(&img.mean);
                let meta = ReferenceMeta {
                    spp: args.spp_ref,
                    seconds: t.seconds,
                    ttuv: ttuv(&img.var, &mask, t.seconds),
                    preview_secs: None,
                    preview_tried: false,
                };
                write_bytes_atomically(
                    &ref_npy,
                    &image_npy(&[img.mean.clone(), img.var.clone()], args.size, args.size),
                )?;
                write_json(&ref_json, &meta)?;
                (img, meta)
            }
        };
        let mask = nonempty(&reference.mean);
        let ref_mean = lit_mean(&reference.mean);
        let ref_noise = reference_noise(&reference, &mask);
        if args.preview && !meta.preview_tried {
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
            (meta.preview_secs, meta.preview_tried) = (t.preview_secs, true);
            write_json(&ref_json, &meta)?;
        }
        // The model bound to this cloud and sun, built once for every k.
        let mut bound: Option<(Arc<BoundGlobalModel>, f64)> = None;
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
            let (pred, secs_field) = match &bound {
                Some(b) => b.clone(),
                None => {
                    let t = Instant::now();
                    let sun = scene.sun.as_ref().expect("evaluation scenes have a sun");
                    let b = Arc::new(BoundGlobalModel::new(model.clone(), &scene.medium, sun, args.field_nodes));
                    let built = (b, t.elapsed().as_secs_f64());
                    bound = Some(built.clone());
                    built
                }
            };
            let mut f = file.clone();
            f.seed = 100 + k as u64;
            f.k = k;
            f.render.mode = "predict".into();
            f.render.p = args.p;
            let t_pilot = Instant::now();
            if args.auto_p {
                f.render.p = crate::progressive::auto_p(scene.clone(), f.settings(), pred.clone(), 8, &control)?.p;
            }
            let secs_pilot = if args.auto_p { t_pilot.elapsed().as_secs_f64() } else { 0.0 };
            let integrator = f.integrator_with(Some(pred))?;
            let t =
                render_tracked(scene.clone(), integrator, args.spp, &control, Some((&reference, &mask)), false, |d| {
                    bar.set_position(kbase + d as u64)
                })?;
            let full = Image::from_film(&t.film, Buffer::Full);
            let (b, rb, floor) = bias(&reference, &full);
            let ttuv_pred = ttuv(&full.var, &mask, t.seconds);
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
                secs_pred: t.seconds,
                secs_field,
                secs_pilot,
                preview_secs_pred: t.preview_secs,
                preview_secs_ref: meta.preview_secs,
                rmse_floor: Some(rmse_floor),
                preview_projected_pred: projected_preview(ttuv_pred, ref_mean, rmse_floor),
                preview_projected_ref: None,
                ref_noise: None,
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
        results.extend(group_cells);
    }
    bar.finish_and_clear();
    write_reports(&args.out, &results, args)?;
    Ok(results)
}

/// False colour for t in [0, 1]: black, purple, orange, yellow (an inferno-like ramp).
pub fn false_colour(t: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] =
        [[0.0, 0.0, 0.02], [0.34, 0.06, 0.43], [0.73, 0.21, 0.33], [0.98, 0.55, 0.04], [0.99, 1.0, 0.64]];
    let x = t.clamp(0.0, 1.0) * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f32;
    std::array::from_fn(|c| ((STOPS[i][c] * (1.0 - f) + STOPS[i + 1][c] * f) * 255.0 + 0.5) as u8)
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
        let toned = |img: &Vec<[f32; 3]>| img.iter().map(|p| p.map(|v| tone.apply(v, 0.0))).collect::<Vec<[u8; 3]>>();
        let error: Vec<[u8; 3]> = high
            .iter()
            .zip(&ref_high)
            .map(|(a, b)| false_colour((avg3(&std::array::from_fn(|c| (a[c] - b[c]).abs())) / scale) as f32))
            .collect();
        let tiles = [toned(&reference.mean), toned(full), toned(low), toned(&ref_high), toned(high), error];
        for (col, tile) in tiles.iter().enumerate() {
            sheet.put(col as u32, row as u32, tile);
        }
    }
    sheet.save(path)
}

/// A grid of equally sized image tiles on a dark ground, 4 px apart.
pub(crate) struct TileSheet {
    image: image::RgbImage,
    w: u32,
    h: u32,
}

impl TileSheet {
    const GAP: u32 = 4;

    pub(crate) fn new(w: u32, h: u32, cols: u32, rows: u32) -> Self {
        let (sw, sh) = (cols * (w + Self::GAP) - Self::GAP, rows * (h + Self::GAP));
        TileSheet { image: image::RgbImage::from_pixel(sw.max(1), sh.max(1), image::Rgb([40, 40, 40])), w, h }
    }

    /// Puts a w x h tile (row-major pixels) at column `col`, row `row`.
    pub(crate) fn put(&mut self, col: u32, row: u32, tile: &[[u8; 3]]) {
        let (ox, oy) = (col * (self.w + Self::GAP), row * (self.h + Self::GAP));
        for y in 0..self.h {
            for x in 0..self.w {
                self.image.put_pixel(ox + x, oy + y, image::Rgb(tile[(y * self.w + x) as usize]));
            }
        }
    }

    /// Writes the sheet as a PNG, atomically.
    pub(crate) fn save(&self, path: &Path) -> Result<()> {
        let mut bytes = std::io::Cursor::new(Vec::new());
        self.image.write_to(&mut bytes, image::ImageFormat::Png)?;
        write_bytes_atomically(path, &bytes.into_inner())?;
        Ok(())
    }
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map(|s| format!("{s:.1}")).unwrap_or_else(|| "-".into())
}

/// results.csv, results.md (tables like the thesis's B.1-B.6) and the bias and speedup
/// plots against k (figure 5.8), one pair per scene.
fn write_reports(out: &Path, results: &[CellResult], args: &EvalArgs) -> Result<()> {
    let mut csv = String::from(
        "scene,config,rho,k,p,size,spp_ref,spp,bias,rel_bias,rel_noise_floor,ttuv_ref,ttuv_pred,speedup,secs_ref,secs_pred,secs_field,secs_pilot,preview_secs_ref,preview_secs_pred,rmse_floor,preview_projected_ref,preview_projected_pred,ref_noise\n",
    );
    for c in results {
        csv += &format!(
            "{},{},{},{},{},{},{},{},{:.6e},{:.6},{:.6},{:.6e},{:.6e},{:.3},{:.2},{:.2},{:.2},{:.2},{},{},{},{},{},{}\n",
            c.scene,
            c.config,
            c.rho,
            c.k,
            c.p,
            c.size,
            c.spp_ref,
            c.spp,
            c.bias,
            c.rel_bias,
            c.rel_noise_floor,
            c.ttuv_ref,
            c.ttuv_pred,
            c.speedup,
            c.secs_ref,
            c.secs_pred,
            c.secs_field,
            c.secs_pilot,
            c.preview_secs_ref.map(|v| v.to_string()).unwrap_or_default(),
            c.preview_secs_pred.map(|v| v.to_string()).unwrap_or_default(),
            c.rmse_floor.map(|v| v.to_string()).unwrap_or_default(),
            c.preview_projected_ref.map(|v| v.to_string()).unwrap_or_default(),
            c.preview_projected_pred.map(|v| v.to_string()).unwrap_or_default(),
            c.ref_noise.map(|v| v.to_string()).unwrap_or_default()
        );
    }
    write_bytes_atomically(&out.join("results.csv"), csv.as_bytes())?;
    let mut md = format!(
        "# nimbus eval\n\n{}x{} pixels, reference {} spp, predictions {} spp, p = {}, grids {}^3, albedo 1, HG g = 0.85.\n\
         Cells: relative bias (noise floor) / speedup in TTUV. Bias as in CONVENTIONS.md (16x box downscale).\n",
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
    if !args.quiet {
        println!("{md}");
        eprintln!("wrote results.md, results.csv, plots and sheets to {}", out.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::Rng;

    /// A pixel estimate from `m` samples of value * Exp(1) (a skewed, heavy-ish tailed
    /// estimator like a path tracer's): (mean, unbiased variance of the mean), as the
    /// film computes them.
    fn estimate(value: f64, m: u32, rng: &mut Rng) -> (f32, f32) {
        let xs: Vec<f64> = (0..m).map(|_| -value * (1.0 - rng.uniform() as f64).max(1e-12).ln()).collect();
        let mean = xs.iter().sum::<f64>() / m as f64;
        let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (m - 1) as f64;
        (mean as f32, (var / m as f64) as f32)
    }

    /// Mean and standard error of per-pixel terms.
    fn mean_se(t: &[f64]) -> (f64, f64) {
        let n = t.len() as f64;
        let m = t.iter().sum::<f64>() / n;
        (m, (t.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0) / n).sqrt())
    }

    /// A noisy reference of `m_ref` samples per pixel, and an image of `m_img` samples
    /// of truth + a known relative bias up to `amp`, on 20,000 pixels.
    fn setup(seed: u64, m_ref: u32, m_img: u32, amp: f64) -> (Vec<f64>, Vec<f64>, Image, Image) {
        let n = 20_000;
        let mut rng = Rng::new(seed, 0, 0);
        let truth: Vec<f64> = (0..n).map(|_| 0.2 + 0.8 * rng.uniform() as f64).collect();
        let bias: Vec<f64> = truth.iter().enumerate().map(|(i, t)| amp * t * (i as f64 * 0.01).sin()).collect();
        let mk = |vals: Vec<(f32, f32)>| Image {
            w: n as u32,
            h: 1,
            mean: vals.iter().map(|v| [v.0; 3]).collect(),
            var: vals.iter().map(|v| [v.1; 3]).collect(),
        };
        let reference = mk(truth.iter().map(|t| estimate(*t, m_ref, &mut rng)).collect());
        let img = mk(truth.iter().zip(&bias).map(|(t, b)| estimate(t + b, m_img, &mut rng)).collect());
        (truth, bias, reference, img)
    }

    /// Checks that `rel` (a relative RMSE over all pixels) squared, in absolute units,
    /// matches `exact` within 4 standard errors of the per-pixel `terms`, the
    /// differences whose mean is zero; returns (the squared estimate, its standard error).
    fn agrees(rel: f64, reference: &Image, terms: impl Fn(usize) -> f64, exact: f64, what: &str) -> (f64, f64) {
        let est = (rel * lit_mean(&reference.mean)).powi(2);
        let (_, se) = mean_se(&(0..reference.mean.len()).map(terms).collect::<Vec<_>>());
        assert!((est - exact).abs() <= 4.0 * se, "{what}: estimate {est}, exact {exact}, se {se}");
        (est, se)
    }

    /// The noise-corrected squared error against a noisy reference agrees with the
    /// squared error against the truth within 4 standard errors of the difference (the
    /// per-pixel terms -2 (img - t)(ref - t) + (ref - t)^2 - var(ref), mean zero); the
    /// uncorrected one is off by far more: the reference's variance.
    #[test]
    fn noise_corrected_rmse_matches_the_rmse_against_the_truth() {
        for seed in 0..3 {
            let (truth, _, reference, img) = setup(seed, 16, 64, 0.03);
            let n = truth.len() as f64;
            let px = |i: usize| (img.mean[i][0] as f64, reference.mean[i][0] as f64, reference.var[i][0] as f64);
            let exact = truth.iter().zip(&img.mean).map(|(t, a)| (a[0] as f64 - t).powi(2)).sum::<f64>() / n;
            let rel = relative_rmse(&img.mean, &reference, &vec![true; truth.len()]);
            let term = |i: usize| {
                let (a, r, v) = px(i);
                (a - r).powi(2) - v - (a - truth[i]).powi(2)
            };
            let (est, se) = agrees(rel, &reference, term, exact, &format!("seed {seed}"));
            let naive = est + reference.var.iter().map(|v| v[0] as f64).sum::<f64>() / n;
            assert!(naive - exact > 20.0 * se, "seed {seed}: the reference noise should show: {naive} vs {exact}");
        }
    }

    /// With the image's own variance also subtracted, what remains is the squared bias:
    /// within 4 standard errors of its exact mean.
    #[test]
    fn rmse_floor_is_the_bias_part() {
        for seed in 10..13 {
            let (truth, bias, reference, img) = setup(seed, 256, 256, 0.1);
            let exact = bias.iter().map(|b| b * b).sum::<f64>() / bias.len() as f64;
            let rel = relative_rmse_less(&img.mean, &reference, &vec![true; truth.len()], Some(&img.var));
            let term = |i: usize| {
                let (a, r) = (img.mean[i][0] as f64, reference.mean[i][0] as f64);
                (a - r).powi(2) - reference.var[i][0] as f64 - img.var[i][0] as f64 - bias[i].powi(2)
            };
            let (_, se) = agrees(rel, &reference, term, exact, &format!("seed {seed}, floor"));
            assert!(exact > 8.0 * se, "the test's bias must be resolvable: {exact} vs se {se}");
        }
    }

    /// Projection: an unbiased estimator reaching 5 % needs TTUV / (0.05 mean)^2
    /// seconds; a floor of 3 % leaves 0.05^2 - 0.03^2 of room; 5 % leaves none.
    #[test]
    fn projected_preview_follows_the_variance() {
        let t0 = projected_preview(0.01, 0.2, 0.0).unwrap();
        assert!((t0 - 0.01 / (0.01 * 0.01)).abs() < 1e-9 * t0);
        let t3 = projected_preview(0.01, 0.2, 0.03).unwrap();
        assert!((t3 / t0 - 0.0025 / 0.0016).abs() < 1e-9);
        assert!(projected_preview(0.01, 0.2, 0.05).is_none());
    }
}
