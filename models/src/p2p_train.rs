//! Training the point-to-point model (`nimbus train p2p`) and loading it.
//!
//! Inputs: every feature through ln(1 + x) (densities and phi_D span decades), then
//! standardized with the training split's means and deviations. Target: ln of the
//! local-frame transport D^2 T (lengths divided by the emitter-sensor distance D,
//! which makes T scale-free), standardized. The split is by data point, not by row:
//! the rotations of one point share its target and must not straddle train and test.
//! Written like the global model: OUT.safetensors, OUT.json (architecture, feature
//! set, transforms, metrics), OUT.loss.csv and OUT.loss.png, and a checkpoint after
//! every epoch (OUT.checkpoint/) from which `--resume` goes on.

use crate::density_features::{DensityPyramid, LocalFrame, P2pFeatures};
use crate::p2p_datagen::P2pManifest;
use crate::p2p_net::{P2pArch, P2pBatchScratch, P2pEvaluator, P2pNetwork, P2pScratch};
use crate::train::OptState;
use candle_core::Device;
use engine::Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub const MODEL_FORMAT: &str = "nimbus-p2p-model";

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum ArchDesc {
    Residual { width: usize, layers: usize },
    Mlp { hidden: Vec<usize> },
}

impl From<&P2pArch> for ArchDesc {
    fn from(a: &P2pArch) -> Self {
        match a {
            P2pArch::Residual { width, layers } => ArchDesc::Residual { width: *width, layers: *layers },
            P2pArch::Mlp { hidden } => ArchDesc::Mlp { hidden: hidden.clone() },
        }
    }
}

impl ArchDesc {
    pub fn describe(&self) -> String {
        match self {
            ArchDesc::Residual { width, layers } => format!("residual, {width} units x {layers} layers per block"),
            ArchDesc::Mlp { hidden } => format!("MLP {hidden:?}"),
        }
    }

    pub fn arch(&self) -> P2pArch {
        match self {
            ArchDesc::Residual { width, layers } => P2pArch::Residual { width: *width, layers: *layers },
            ArchDesc::Mlp { hidden } => P2pArch::Mlp { hidden: hidden.clone() },
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct P2pSidecar {
    pub format: String,
    pub arch: ArchDesc,
    pub features: P2pFeatures,
    pub feature_mean: Vec<f32>,
    pub feature_std: Vec<f32>,
    pub target_mean: f32,
    pub target_std: f32,
    /// Medium the data came from (the model is trained for one albedo and g).
    pub albedo: f32,
    pub g: f32,
    pub data: Vec<String>,
    pub epochs: usize,
    /// Learning-rate factor per epoch (1: constant, what models before it had).
    #[serde(default = "constant_lr")]
    pub lr_decay: f64,
    pub test_mse: f64,
    /// Median and 90th percentile of |predicted T / true T - 1| on the test points.
    pub test_rel_error_median: f64,
    pub test_rel_error_p90: f64,
}

#[derive(Clone, Debug)]
pub struct P2pTrainConfig {
    pub arch: P2pArch,
    pub epochs: usize,
    pub batch: usize,
    /// Learning rate of the first epoch.
    pub lr: f64,
    /// Learning-rate factor per epoch: epoch e (from 0) trains at lr x lr_decay^e.
    pub lr_decay: f64,
    pub seed: u64,
    pub test_fraction: f64,
}

impl Default for P2pTrainConfig {
    fn default() -> Self {
        P2pTrainConfig {
            arch: P2pArch::default(),
            epochs: 20,
            batch: 250,
            lr: 1e-3,
            lr_decay: 1.0,
            seed: 1,
            test_fraction: 0.2,
        }
    }
}

impl P2pTrainConfig {
    /// Checks the settings, naming the `nimbus train p2p` flag of a bad one (the
    /// schedule checks are the global trainer's, [`crate::train::check_schedule`]).
    pub fn validate(&self) -> Result<(), String> {
        crate::train::check_schedule(self.epochs, self.batch, self.lr, self.lr_decay, self.test_fraction)
            .map_err(|(flag, why)| format!("{flag} {why}"))
    }
}

fn constant_lr() -> f64 {
    1.0
}

fn err(e: impl std::fmt::Display) -> String {
    e.to_string()
}

/// A trained model ready to predict.
pub struct P2pModel {
    pub sidecar: P2pSidecar,
    eval: P2pEvaluator,
}

/// Where the shipped point-to-point model lives in the repository; it is compiled
/// into the binary, so BDPT's prediction mode works without any file.
pub const SHIPPED_PATH: &str = "assets/models/p2p.safetensors";
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../assets/models/p2p.safetensors");
const SHIPPED_SIDECAR: &str = include_str!("../../assets/models/p2p.json");

/// [`crate::fingerprint`] of the shipped point-to-point model's weights and sidecar.
pub fn shipped_fingerprint() -> u64 {
    crate::fingerprint(&[SHIPPED_WEIGHTS, SHIPPED_SIDECAR.as_bytes()])
}

impl P2pModel {
    /// Loads OUT.safetensors with its OUT.json sidecar, naming the file on any problem.
    pub fn load(weights: &Path) -> Result<Self, String> {
        let side = weights.with_extension("json");
        let text = std::fs::read_to_string(&side).map_err(|e| format!("{}: {e}", side.display()))?;
        let bytes = std::fs::read(weights).map_err(|e| format!("{}: {e}", weights.display()))?;
        Self::from_bytes(&bytes, &text, weights)
    }

    /// The shipped single-cloud model (`assets/models/p2p.*`), loaded once.
    pub fn shipped() -> Result<std::sync::Arc<P2pModel>, String> {
        static SHIPPED: std::sync::OnceLock<Result<std::sync::Arc<P2pModel>, String>> = std::sync::OnceLock::new();
        SHIPPED
            .get_or_init(|| {
                Self::from_bytes(SHIPPED_WEIGHTS, SHIPPED_SIDECAR, Path::new(SHIPPED_PATH)).map(std::sync::Arc::new)
            })
            .clone()
    }

    /// A model from its weights' bytes and its sidecar's text; `weights` names it in
    /// messages.
    pub fn from_bytes(bytes: &[u8], text: &str, weights: &Path) -> Result<Self, String> {
        let side = weights.with_extension("json");
        let sidecar: P2pSidecar = serde_json::from_str(text)
            .map_err(|e| format!("{}: not a point-to-point model sidecar: {e}", side.display()))?;
        if sidecar.format != MODEL_FORMAT {
            return Err(format!("{}: format {:?} is not {MODEL_FORMAT}", side.display(), sidecar.format));
        }
        let n = sidecar.features.len();
        if sidecar.feature_mean.len() != n || sidecar.feature_std.len() != n {
            return Err(format!(
                "{}: transforms for {} features, the feature set has {n}",
                side.display(),
                sidecar.feature_mean.len()
            ));
        }
        let named = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)
            .map_err(|e| format!("{}: {e}", weights.display()))?;
        let net = P2pNetwork::new(&sidecar.features, sidecar.arch.arch(), 0, &Device::Cpu).map_err(err)?;
        net.load_named(&named).map_err(|e| format!("{}: {e}", weights.display()))?;
        Ok(P2pModel { eval: net.evaluator().map_err(err)?, sidecar })
    }

    /// Predicted T (world units) between the ends of `frame`, from raw features.
    pub fn predict_features(
        &self,
        raw: &[f32],
        frame_scale: f32,
        input: &mut Vec<f32>,
        scratch: &mut P2pScratch,
    ) -> f32 {
        input.resize(raw.len(), 0.0);
        self.standardize(raw, input);
        self.finish(self.eval.forward(input, scratch), frame_scale)
    }

    /// The network's input from raw features: ln(1 + x), standardized.
    fn standardize(&self, raw: &[f32], input: &mut [f32]) {
        let s = &self.sidecar;
        crate::fastmath::standardize(raw, &s.feature_mean, &s.feature_std, input);
    }

    /// T in world units from the network's output for a pair `frame_scale` apart.
    fn finish(&self, y: f32, frame_scale: f32) -> f32 {
        let s = &self.sidecar;
        (y * s.target_std + s.target_mean).exp() / (frame_scale * frame_scale)
    }

    /// Features and prediction for an emitter-sensor pair.
    pub fn predict(&self, pyramid: &DensityPyramid, rho: f32, frame: &LocalFrame) -> f32 {
        let mut raw = vec![0.0; self.sidecar.features.len()];
        self.sidecar.features.write(pyramid, rho, self.sidecar.albedo, frame, &mut raw);
        self.predict_features(&raw, frame.scale, &mut Vec::new(), &mut P2pScratch::default())
    }
}

thread_local! {
    /// Per render thread: raw features, network input and the network's scratch.
    static SCRATCH: std::cell::RefCell<(Vec<f32>, Vec<f32>, P2pScratch)> =
        std::cell::RefCell::new((Vec::new(), Vec::new(), P2pScratch::default()));
    /// Per render thread, for batches: network inputs, frame scales, batch scratch
    /// (grown to the largest batch seen, then reused).
    static BATCH_SCRATCH: std::cell::RefCell<(Vec<f32>, Vec<f32>, Vec<f32>, P2pBatchScratch)> =
        std::cell::RefCell::new(Default::default());
}

/// A point-to-point model bound to one cloud: its density pyramid is built once
/// here (about 0.7 s and 56 MiB for a 128^3 grid), after which a prediction is the
/// feature lookups and one network evaluation, without allocation (per-thread
/// scratch). Plugs into BDPT's prediction mode as an [`engine::TransportPredictor`].
pub struct BoundP2pModel {
    model: std::sync::Arc<P2pModel>,
    pyramid: DensityPyramid,
    rho: f32,
    name: String,
}

impl BoundP2pModel {
    pub fn new(model: std::sync::Arc<P2pModel>, medium: &engine::Medium) -> Self {
        let grid = medium.grid();
        let pyramid =
            crate::density_features::pyramid_for(grid, &model.sidecar.features, grid.bounds().extent().length());
        let name = format!("point-to-point model ({})", model.sidecar.arch.describe());
        BoundP2pModel { model, pyramid, rho: medium.rho(), name }
    }

    /// Why this model may not fit `medium` (it is trained for one albedo and an
    /// isotropic phase function), if it may not.
    pub fn mismatch(&self, medium: &engine::Medium) -> Option<String> {
        let s = &self.model.sidecar;
        let g = match medium.phase() {
            engine::PhaseFunction::HenyeyGreenstein { g } => g,
            engine::PhaseFunction::Isotropic => 0.0,
            _ => f32::NAN,
        };
        let off = (medium.albedo() - s.albedo).abs() > 1e-3 || !((g - s.g).abs() <= 1e-3);
        off.then(|| {
            format!(
                "the point-to-point model was trained for albedo {} and g {}; this medium has albedo {} and {:?}: \
                 its predictions are extrapolations",
                s.albedo,
                s.g,
                medium.albedo(),
                medium.phase()
            )
        })
    }

    pub fn model(&self) -> &P2pModel {
        &self.model
    }
}

impl engine::TransportPredictor for BoundP2pModel {
    fn predict(&self, _medium: &engine::Medium, q: &engine::p2p::P2pQuery, rng: &mut Rng) -> f32 {
        // A random rotation about the emitter-sensor axis, as in training.
        let Some(frame) = LocalFrame::new(q.emitter, q.sensor, std::f32::consts::TAU * rng.uniform()) else {
            return 0.0;
        };
        SCRATCH.with_borrow_mut(|(raw, input, scratch)| {
            let s = &self.model.sidecar;
            raw.resize(s.features.len(), 0.0);
            s.features.write(&self.pyramid, self.rho, s.albedo, &frame, raw);
            self.model.predict_features(raw, frame.scale, input, scratch)
        })
    }

    /// Features for every query, then the network over all rows at once (four rows
    /// per weight pass), which costs a fraction of single passes.
    fn predict_batch(
        &self,
        _medium: &engine::Medium,
        queries: &[engine::p2p::P2pQuery],
        rngs: &mut [Rng],
        out: &mut [f32],
    ) {
        assert!(queries.len() == rngs.len() && queries.len() == out.len(), "one stream and one output per query");
        BATCH_SCRATCH.with_borrow_mut(|(raw, input, scales, bs)| {
            let s = &self.model.sidecar;
            let n = s.features.len();
            raw.resize(n, 0.0);
            input.resize(queries.len() * n, 0.0);
            scales.clear();
            for ((q, rng), row) in queries.iter().zip(rngs.iter_mut()).zip(input.chunks_exact_mut(n)) {
                // The same draw as `predict`: a random rotation about the axis.
                match LocalFrame::new(q.emitter, q.sensor, std::f32::consts::TAU * rng.uniform()) {
                    Some(frame) => {
                        s.features.write(&self.pyramid, self.rho, s.albedo, &frame, raw);
                        self.model.standardize(raw, row);
                        scales.push(frame.scale);
                    }
                    None => {
                        row.fill(0.0);
                        scales.push(f32::NAN);
                    }
                }
            }
            self.model.eval.forward_batch(&input[..queries.len() * n], out, bs);
            for (o, &scale) in out.iter_mut().zip(scales.iter()) {
                *o = if scale.is_nan() { 0.0 } else { self.model.finish(*o, scale) };
            }
        })
    }

    fn name(&self) -> &str {
        &self.name
    }
}

fn with_ext(out: &Path, ext: &str) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(ext);
    PathBuf::from(s)
}

/// What a checkpoint must match to be resumed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct CheckpointKey {
    arch: ArchDesc,
    batch: usize,
    lr: f64,
    #[serde(default = "constant_lr")]
    lr_decay: f64,
    seed: u64,
    test_fraction: f64,
    data: Vec<String>,
    rows: usize,
}

#[derive(Serialize, Deserialize)]
struct Checkpoint {
    key: CheckpointKey,
    step: u64,
    /// (epoch, train mse, test mse) per finished epoch.
    history: Vec<(f64, f64, f64)>,
}

/// Trains on complete data sets in `dirs` and writes the model to `out` (.safetensors,
/// .json, .loss.csv, .loss.png). Returns the sidecar.
pub fn train(
    dirs: &[PathBuf],
    cfg: &P2pTrainConfig,
    out: &Path,
    resume: bool,
    cancel: &std::sync::atomic::AtomicBool,
    progress: &dyn Fn(usize, f64),
) -> Result<P2pSidecar, String> {
    cfg.validate()?;
    let mut x = vec![];
    let mut y = vec![];
    let mut group = vec![]; // data point id of each row
    let mut medium: Option<(f32, f32, P2pFeatures)> = None;
    for (di, d) in dirs.iter().enumerate() {
        let m = P2pManifest::load(d).map_err(err)?;
        if !m.complete {
            return Err(format!("{}: the data set is not complete; finish or merge it first", d.display()));
        }
        let s = &m.settings;
        let this = (s.albedo, s.g, s.features);
        if medium.is_some_and(|m| m != this) {
            return Err(format!("{}: another albedo, g or feature set than the first data set", d.display()));
        }
        medium = Some(this);
        let (fs, f) = crate::npy::read_f32(&d.join("features.npy")).map_err(err)?;
        let (ts, t) = crate::npy::read_f32(&d.join("targets.npy")).map_err(err)?;
        let n_f = s.features.len();
        if fs.len() != 2 || fs[1] != n_f || ts != [fs[0], 5] {
            return Err(format!("{}: features {fs:?} / targets {ts:?} do not match the manifest", d.display()));
        }
        for (r, (fr, tr)) in f.chunks_exact(n_f).zip(t.chunks_exact(5)).enumerate() {
            if !(tr[4] > 0.0 && tr[4].is_finite()) || fr.iter().any(|v| !v.is_finite()) {
                continue;
            }
            x.extend(fr.iter().map(|v| crate::fastmath::ln_1p(*v)));
            y.push(tr[4].ln());
            group.push((di as u64) << 40 | (r / s.rotations as usize) as u64);
        }
    }
    let (albedo, g, features) = medium.ok_or("no data sets given")?;
    let n_f = features.len();
    let n = y.len();
    if n < 10 {
        return Err(format!("only {n} usable rows"));
    }
    // Split by data point.
    let is_test = |gid: u64| Rng::new(cfg.seed, gid, 0x7465_7374).uniform_f64() < cfg.test_fraction;
    let (train_rows, test_rows): (Vec<usize>, Vec<usize>) = (0..n).partition(|&r| !is_test(group[r]));
    if train_rows.is_empty() || test_rows.is_empty() {
        return Err("the split left no training or no test rows; use more data".into());
    }
    let mut mean = vec![0.0f64; n_f];
    let mut var = vec![0.0f64; n_f];
    for &r in &train_rows {
        for j in 0..n_f {
            mean[j] += x[r * n_f + j] as f64;
        }
    }
    mean.iter_mut().for_each(|m| *m /= train_rows.len() as f64);
    for &r in &train_rows {
        for j in 0..n_f {
            var[j] += (x[r * n_f + j] as f64 - mean[j]).powi(2);
        }
    }
    let std: Vec<f32> = var.iter().map(|v| ((v / train_rows.len() as f64).sqrt() as f32).max(1e-6)).collect();
    let mean: Vec<f32> = mean.iter().map(|m| *m as f32).collect();
    let ym = train_rows.iter().map(|&r| y[r] as f64).sum::<f64>() / train_rows.len() as f64;
    let ys = (train_rows.iter().map(|&r| (y[r] as f64 - ym).powi(2)).sum::<f64>() / train_rows.len() as f64)
        .sqrt()
        .max(1e-6);
    let rows = |set: &[usize]| -> (Vec<f32>, Vec<f32>) {
        let mut xs = Vec::with_capacity(set.len() * n_f);
        for &r in set {
            xs.extend((0..n_f).map(|j| (x[r * n_f + j] - mean[j]) / std[j]));
        }
        (xs, set.iter().map(|&r| ((y[r] as f64 - ym) / ys) as f32).collect())
    };
    let (xtr, ytr) = rows(&train_rows);
    let (xte, yte) = rows(&test_rows);
    let net = P2pNetwork::new(&features, cfg.arch.clone(), cfg.seed, &Device::Cpu).map_err(err)?;
    let vars = net.vars();
    let mut opt = OptState::new(&vars).map_err(err)?;
    let mut history: Vec<(f64, f64, f64)> = vec![];
    let eval_mse = |net: &P2pNetwork| -> Result<f64, String> {
        let e = net.evaluator().map_err(err)?;
        let mut out = vec![0.0; yte.len()];
        e.forward_batch(&xte, &mut out, &mut Default::default());
        Ok(out.iter().zip(&yte).map(|(a, b)| ((a - b) as f64).powi(2)).sum::<f64>() / yte.len() as f64)
    };
    // Checkpoint: OUT.checkpoint/state.json (what was trained so far, on what) and
    // state.safetensors (parameters and Adam moments), written after every epoch.
    let ckpt = with_ext(out, ".checkpoint");
    let key = CheckpointKey {
        arch: (&cfg.arch).into(),
        batch: cfg.batch,
        lr: cfg.lr,
        lr_decay: cfg.lr_decay,
        seed: cfg.seed,
        test_fraction: cfg.test_fraction,
        data: dirs.iter().map(|d| d.display().to_string()).collect(),
        rows: n,
    };
    if resume && ckpt.join("state.json").exists() {
        let path = ckpt.join("state.json");
        let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        let st: Checkpoint = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        if st.key != key {
            return Err(format!(
                "{}: the checkpoint was made with other settings or data; train without --resume to start over",
                path.display()
            ));
        }
        let t = candle_core::safetensors::load(ckpt.join("state.safetensors"), &Device::Cpu)
            .map_err(|e| format!("{}: {e}", ckpt.display()))?;
        for (k, var) in vars.iter().enumerate() {
            let get = |name: String| t.get(&name).cloned().ok_or_else(|| format!("{}: {name} missing", ckpt.display()));
            var.set(&get(format!("param.{k}"))?).map_err(err)?;
            opt.m[k] = get(format!("m.{k}"))?;
            opt.v[k] = get(format!("v.{k}"))?;
        }
        opt.step = st.step;
        history = st.history;
    }
    for epoch in history.len()..cfg.epochs {
        if cancel.load(std::sync::atomic::Ordering::Relaxed) {
            return Err(format!(
                "cancelled after epoch {epoch} of {}; the checkpoint is kept, rerun with --resume to go on",
                cfg.epochs
            ));
        }
        let lr = cfg.lr * cfg.lr_decay.powi(epoch as i32);
        let train_mse =
            net.fit_epoch(&xtr, &ytr, cfg.batch, lr, cfg.seed.wrapping_add(epoch as u64), &mut opt).map_err(err)?;
        let test = eval_mse(&net)?;
        history.push((epoch as f64 + 1.0, train_mse, test));
        let mut tensors = std::collections::HashMap::new();
        for (k, var) in vars.iter().enumerate() {
            tensors.insert(format!("param.{k}"), var.as_tensor().clone());
            tensors.insert(format!("m.{k}"), opt.m[k].clone());
            tensors.insert(format!("v.{k}"), opt.v[k].clone());
        }
        let state = ckpt.join("state.safetensors");
        crate::npy::write_atomically(&state, |tmp| {
            candle_core::safetensors::save(&tensors, tmp).map_err(|e| std::io::Error::other(e.to_string()))
        })
        .map_err(|e| format!("{}: {e}", state.display()))?;
        let st = Checkpoint { key: key.clone(), step: opt.step, history: history.clone() };
        crate::npy::write_bytes_atomically(&ckpt.join("state.json"), serde_json::to_string(&st).unwrap().as_bytes())
            .map_err(err)?;
        progress(epoch + 1, test);
    }
    let mut csv = String::from("epoch,train_mse,test_mse\n");
    for h in &history {
        csv.push_str(&format!("{},{},{}\n", h.0, h.1, h.2));
    }
    // Relative error of T on the test rows.
    let e = net.evaluator().map_err(err)?;
    let mut pred = vec![0.0; yte.len()];
    e.forward_batch(&xte, &mut pred, &mut Default::default());
    let mut rel: Vec<f64> = pred.iter().zip(&yte).map(|(p, t)| ((((p - t) as f64) * ys).exp() - 1.0).abs()).collect();
    rel.sort_by(f64::total_cmp);
    let sidecar = P2pSidecar {
        format: MODEL_FORMAT.into(),
        arch: (&cfg.arch).into(),
        features,
        feature_mean: mean,
        feature_std: std,
        target_mean: ym as f32,
        target_std: ys as f32,
        albedo,
        g,
        data: dirs.iter().map(|d| d.display().to_string()).collect(),
        epochs: cfg.epochs,
        lr_decay: cfg.lr_decay,
        test_mse: history.last().map(|h| h.2).unwrap_or(f64::NAN),
        test_rel_error_median: rel[rel.len() / 2],
        test_rel_error_p90: rel[(rel.len() * 9 / 10).min(rel.len() - 1)],
    };
    let with = |ext: &str| with_ext(out, ext);
    let weights = with(".safetensors");
    crate::npy::write_atomically(&weights, |tmp| {
        candle_core::safetensors::save(&net.named(), tmp).map_err(|e| std::io::Error::other(e.to_string()))
    })
    .map_err(|e| format!("{}: {e}", weights.display()))?;
    let text = serde_json::to_string_pretty(&sidecar).expect("sidecar serializes");
    crate::npy::write_bytes_atomically(&with(".json"), text.as_bytes()).map_err(err)?;
    crate::npy::write_bytes_atomically(&with(".loss.csv"), csv.as_bytes()).map_err(err)?;
    let series = |label: &str, colour, k: usize| crate::plot::Series {
        label: label.into(),
        colour,
        points: history.iter().map(|h| (h.0, if k == 1 { h.1 } else { h.2 })).collect(),
    };
    let png = crate::plot::line_plot_png(
        "point-to-point model: loss (standardized ln T)",
        "epoch",
        "mse",
        &[series("train", crate::plot::PALETTE[0], 1), series("test", crate::plot::PALETTE[1], 2)],
    );
    crate::npy::write_bytes_atomically(&with(".loss.png"), &png).map_err(err)?;
    Ok(sidecar)
}
