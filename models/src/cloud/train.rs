//! Training the cloud-aware model: standardized stencil features, the target
//! ln(1 + 4 pi L_ms) for the output's scale, and a relative L2 loss in linear space
//! ([`Loss::RelativeL2`]), so that the noisy, unbiased path-traced targets (a few paths
//! per point, or one) train an unbiased model. The test split holds out whole clouds;
//! the report gives the relative bias on them (sum of predictions over sum of
//! targets, the quantity an image's bias follows), overall and per cloud, and the same
//! on a held-out data set of clouds no training set draws. With teachers
//! ([`CloudTrainData::distill_from`]) the network is fitted to the mean of several
//! trained networks' predictions instead of the paths (distillation).

use super::datagen::CloudDataset;
use super::features::{DerivedInputs, N_FEATURES, feature_names};
use super::model::{CloudModel, CloudSidecar, MODEL_FORMAT, MODEL_FORMAT_VERSION, TARGET_TRANSFORM};
use crate::nn::dense::Activation;
use crate::nn::fit::{
    EpochRecord, FitData, FitSchedule, Fitted, Loss, RunIdentity, TrainError, TrainObserver, TrainPaths, fit,
    save_tensors, shuffle, write_text,
};
use crate::nn::mlp::Mlp;
use crate::nn::optim::Optimizer;
use crate::nn::refit::{RefitReport, cholesky_solve, refit_output_layer};
use engine::Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

fn two() -> f32 {
    2.0
}

const FOUR_PI: f32 = 4.0 * std::f32::consts::PI;

/// Which stored target to train on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetColumn {
    /// The mean of the point's paths.
    Mean,
    /// The first path alone (a cheap, unbiased, noisy target).
    OnePath,
}

impl TargetColumn {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "mean" => Some(TargetColumn::Mean),
            "one-path" => Some(TargetColumn::OnePath),
            _ => None,
        }
    }

    fn column(self) -> usize {
        match self {
            TargetColumn::Mean => 0,
            TargetColumn::OnePath => 3,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CloudTrainConfig {
    /// Network, epochs, batch, optimizer, learning rate and its decay, seed.
    #[serde(flatten)]
    pub schedule: FitSchedule,
    /// Fraction of the clouds held out as the test split.
    pub test_fraction: f64,
    pub target: TargetColumn,
    /// eps of the relative loss, in units of (4 pi L_ms)^2.
    pub eps: f32,
    /// Use at most this many training points (0: all), the first ones of each data
    /// set in order: the data-set-size study trains on growing prefixes.
    pub max_points: usize,
    /// The relative loss's power ([`Loss::RelativeL2`]): 2 relative errors alike, 1
    /// absolute errors over v.
    #[serde(default = "two")]
    pub loss_power: f32,
    /// Gauss-Newton iterations of the output layer refitted on the whole training
    /// split after the stochastic fit (0: none; [`crate::nn::refit`]).
    #[serde(default)]
    pub refit_output: usize,
    /// Which derived features ([`super::features::derive_inputs`]) the network reads
    /// beside the stored ones.
    #[serde(default)]
    pub derived: DerivedInputs,
    /// Weighs each row's loss by 1 / (its target's relative noise variance as the
    /// noise model predicts it from the row's features, plus this floor), the weights'
    /// mean over the training rows 1 ([`noise_weights`]); None: every row alike.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_weights: Option<f32>,
}

impl Default for CloudTrainConfig {
    fn default() -> Self {
        CloudTrainConfig {
            schedule: FitSchedule {
                hidden: vec![128, 128, 128],
                activation: Activation::Relu,
                epochs: 20,
                batch: 512,
                optimizer: Optimizer::Adam,
                lr: 2e-3,
                lr_decay: 0.85,
                seed: 1,
                average_last: 0,
            },
            test_fraction: 0.1,
            target: TargetColumn::Mean,
            eps: 2.5e-3,
            max_points: 0,
            refit_output: 0,
            loss_power: 2.0,
            derived: DerivedInputs::Coupling,
            noise_weights: None,
        }
    }
}

impl CloudTrainConfig {
    pub fn validate(&self) -> Result<(), TrainError> {
        self.schedule.validate(self.test_fraction)?;
        if !(self.loss_power.is_finite() && (0.5..=2.0).contains(&self.loss_power)) {
            return Err(TrainError::Setting { flag: "--loss-power", why: "must lie in 0.5 ..= 2".into() });
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return Err(TrainError::Setting { flag: "--eps", why: "must be a positive number".into() });
        }
        if let Some(floor) = self.noise_weights {
            if !(floor.is_finite() && floor > 0.0) {
                return Err(TrainError::Setting {
                    flag: "--noise-weights",
                    why: format!("the floor must be a positive relative variance, got {floor}"),
                });
            }
        }
        Ok(())
    }
}

/// Rows of one or more cloud data sets.
#[derive(Clone)]
pub struct CloudTrainData {
    pub features: Vec<f32>,
    /// The five stored targets per row.
    pub targets: Vec<f32>,
    /// Which cloud each row comes from: (data set index, chunk).
    pub clouds: Vec<(u32, u64)>,
    pub sources: Vec<String>,
    /// Set by [`CloudTrainData::distill_from`].
    pub distilled: Option<Distilled>,
    /// Set by [`CloudTrainData::start_from`].
    pub init: Option<WarmStart>,
}

/// A trained model to start from (fine-tuning): its weights and its standardization.
#[derive(Clone, Debug)]
pub struct WarmStart {
    pub model: CloudModel,
    /// Its fingerprint (part of the run's identity).
    pub fingerprint: String,
}

/// Distillation's training targets and where they come from.
#[derive(Clone, Debug)]
pub struct Distilled {
    /// 4 pi times the teachers' mean prediction per row, the training target in place
    /// of the path-traced mean.
    pub targets: Vec<f32>,
    /// The teachers' fingerprints (part of the run's identity).
    pub teachers: Vec<String>,
}

impl CloudTrainData {
    /// The rows of the data sets in `dirs`, in order, read into buffers of their
    /// total size (no data set is held twice while loading).
    pub fn load(dirs: &[PathBuf]) -> Result<CloudTrainData, TrainError> {
        if dirs.is_empty() {
            return Err(TrainError::Data("no data set given".into()));
        }
        let data = |e: crate::dataset::manifest::DatagenError| TrainError::Data(e.to_string());
        let mut manifests = vec![];
        for d in dirs {
            let manifest = CloudDataset::manifest_of(d).map_err(data)?;
            if manifest.settings.held_out {
                return Err(TrainError::Data(format!(
                    "{} is a held-out data set: it tests the model and is never trained on (pass it as --held-out)",
                    d.display()
                )));
            }
            manifests.push(manifest);
        }
        let mut rows = 0usize;
        for (d, m) in dirs.iter().zip(&manifests) {
            rows += CloudDataset::rows_of(d, m).map_err(data)?;
        }
        let mut out = CloudTrainData {
            // The stored rows are spread in place to rows of N_FEATURES as they load.
            features: Vec::with_capacity(rows * N_FEATURES),
            targets: Vec::with_capacity(rows * 5),
            clouds: Vec::with_capacity(rows),
            sources: vec![],
            distilled: None,
            init: None,
        };
        for (k, (d, manifest)) in dirs.iter().zip(&manifests).enumerate() {
            CloudDataset::read_rows(d, manifest, &mut out.features, &mut out.targets).map_err(data)?;
            out.clouds.extend((0..manifest.counts.points).map(|i| (k as u32, manifest.settings.cloud_of(i))));
            out.sources.push(d.display().to_string());
        }
        Ok(out)
    }

    pub fn len(&self) -> usize {
        self.clouds.len()
    }

    /// Fine-tuning: the fit starts from `model`'s weights and keeps its feature and
    /// target standardization (the weights mean nothing under other statistics), so
    /// its network and inputs must be the run's. `fingerprint` names it in the run's
    /// identity, so a resume from another model is refused.
    pub fn start_from(&mut self, model: CloudModel, fingerprint: String) {
        self.init = Some(WarmStart { model, fingerprint });
    }

    pub fn is_empty(&self) -> bool {
        self.clouds.is_empty()
    }

    fn row(&self, i: usize) -> &[f32] {
        &self.features[i * N_FEATURES..(i + 1) * N_FEATURES]
    }

    /// Distillation: the training targets become the mean of `teachers`' predictions
    /// at every row's features (noise-free, where a path-traced mean of a few paths has
    /// a relative standard deviation near 1 at strongly forward-scattering views).
    /// Networks trained on the same data disagree configuration by configuration; their
    /// mean is closer to the truth than any of them, and a network fitted to it inherits
    /// that at its own cost per prediction. The test split and the held-out report keep
    /// the path-traced targets. `fingerprints` name the teachers in the run's identity,
    /// so a resume with other teachers is refused.
    pub fn distill_from(&mut self, teachers: &[&CloudModel], fingerprints: Vec<String>) -> Result<(), TrainError> {
        use rayon::prelude::*;
        if teachers.is_empty() {
            return Err(TrainError::Setting { flag: "--teacher", why: "names no model".into() });
        }
        const ROWS: usize = 4096;
        let mut y = vec![0.0f32; self.len()];
        y.par_chunks_mut(ROWS).enumerate().for_each(|(c, out)| {
            let mut scratch: Vec<_> = teachers.iter().map(|t| t.mlp.scratch()).collect();
            for (j, v) in out.iter_mut().enumerate() {
                let row = self.row(c * ROWS + j);
                let sum: f64 = teachers.iter().zip(&mut scratch).map(|(t, s)| t.predict_features(row, s) as f64).sum();
                *v = FOUR_PI * (sum / teachers.len() as f64) as f32;
            }
        });
        self.distilled = Some(Distilled { targets: y, teachers: fingerprints });
        Ok(())
    }
}

/// Relative bias of predictions against targets over a set of rows, overall and per
/// cloud.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct BiasReport {
    pub points: usize,
    pub clouds: usize,
    /// sum(prediction) / sum(target) - 1 over all rows.
    pub bias: f64,
    /// Its standard error from the targets' own standard errors.
    pub bias_std_error: f64,
    /// |bias| per cloud: median and 90th percentile.
    pub cloud_abs_bias_median: f64,
    pub cloud_abs_bias_p90: f64,
    /// Point by point: sqrt(mean((prediction - target)^2 - se^2)) / mean(target), the
    /// error an image of these points would show pixel by pixel (its RMSE floor, in
    /// the form of `relative_rmse_less`), with the targets' own noise removed; errors
    /// of opposite sign at different points, which cancel in `bias`, add up here.
    #[serde(default)]
    pub point_rmse: f64,
}

/// The relative bias of `model` on `rows` of `features`/`targets` (5 columns, the
/// stored mean as the reference) grouped by `clouds`.
pub fn bias_report(
    model: &CloudModel,
    features: &[f32],
    targets: &[f32],
    clouds: &[(u32, u64)],
    rows: &[usize],
) -> BiasReport {
    ensemble_bias_report(&[model], features, targets, clouds, rows)
}

/// [`bias_report`] of the mean of `models`' predictions (an ensemble, the target a
/// student of them is distilled to; one model: its own report).
pub fn ensemble_bias_report(
    models: &[&CloudModel],
    features: &[f32],
    targets: &[f32],
    clouds: &[(u32, u64)],
    rows: &[usize],
) -> BiasReport {
    assert!(!models.is_empty(), "an ensemble of at least one model");
    let mut scratch: Vec<_> = models.iter().map(|m| m.mlp.scratch()).collect();
    let mut per: std::collections::BTreeMap<(u32, u64), (f64, f64)> = Default::default();
    let (mut sp, mut st, mut var, mut sq) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for &i in rows {
        let row = &features[i * N_FEATURES..(i + 1) * N_FEATURES];
        let sum: f64 = models.iter().zip(&mut scratch).map(|(m, s)| m.predict_features(row, s) as f64).sum();
        let p = sum / models.len() as f64;
        let (t, se) = (targets[i * 5] as f64, targets[i * 5 + 1] as f64);
        sp += p;
        st += t;
        var += se * se;
        sq += (p - t) * (p - t) - se * se;
        let e = per.entry(clouds[i]).or_default();
        e.0 += p;
        e.1 += t;
    }
    let mut abs: Vec<f64> = per.values().filter(|(_, t)| *t > 0.0).map(|(p, t)| (p / t - 1.0).abs()).collect();
    abs.sort_by(f64::total_cmp);
    let q = |p: f64| abs.get(((abs.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(f64::NAN);
    BiasReport {
        points: rows.len(),
        clouds: per.len(),
        bias: if st > 0.0 { sp / st - 1.0 } else { f64::NAN },
        // (sp / st) has relative standard error sqrt(var) / st from the targets.
        bias_std_error: if st > 0.0 { (sp / st) * var.sqrt() / st } else { f64::NAN },
        cloud_abs_bias_median: q(0.5),
        cloud_abs_bias_p90: q(0.9),
        point_rmse: if st > 0.0 {
            (sq.max(0.0) / rows.len() as f64).sqrt() / (st / rows.len() as f64)
        } else {
            f64::NAN
        },
    }
}

/// Rows the noise model is fitted on, at most: every k-th training row with a noise
/// estimate. Its 1 + inputs coefficients are fixed by far fewer.
const NOISE_MODEL_ROWS: usize = 65_536;

/// Rows per partial sum of the noise model's normal equations: the partial sums are
/// formed in parallel and added in their order, so the fit is the same bits on any
/// number of threads.
const NOISE_MODEL_CHUNK: usize = 4096;

/// The ridge of the noise model, per fitted row, on standardized inputs.
const NOISE_MODEL_RIDGE: f64 = 1e-3;

/// How the rows' loss weights were made ([`noise_weights`]).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct NoiseWeightReport {
    /// The floor added to every row's predicted relative noise variance.
    pub floor: f32,
    /// Rows the noise model was fitted on.
    pub fit_rows: usize,
    /// The share of ln(noise variance)'s spread over those rows the model explains.
    pub r_squared: f64,
    /// The weights' 10th, 50th and 90th percentiles over the training rows (mean 1).
    pub weight_quantiles: [f32; 3],
    /// The factor by which the weights shrink the variance of a weighted mean of the
    /// training rows' targets against the plain mean, from their measured noise:
    /// mean(s^2) (sum w)^2 / (n sum w^2 s^2), s^2 the noise plus the floor: what a fit
    /// that pooled every row would gain. The network's fit pools rows of similar
    /// features, whose weights are alike, and gains less.
    pub pooled_gain: f64,
}

/// Loss weights from the targets' noise. Path-traced targets differ in noise by
/// orders of magnitude (the relative standard deviation of a 256-path mean at the
/// data's corner spreads from 0.13 to 0.83 between its 5th and 95th percentiles), and
/// rows of equal weight let the noisiest dominate what the network pools. Each row's
/// own noise estimate is not a fair weight: a path far in the tail raises the row's
/// mean and its standard error together, so weighting by it would pull the fit low.
/// The weights come instead from a noise model: ln of the relative noise variance
/// (`noise`, NaN where a row has none), fitted by ridge regression on the
/// standardized inputs (`x_train`, rows of `n_in`) over up to [`NOISE_MODEL_ROWS`]
/// rows, its prediction corrected for the log's mean (the mean of exp of the
/// residuals). A row's weight is 1 / (predicted variance + `floor`), a function of
/// its features alone, so the fit's minimizer at every input stays E[y | x]; the
/// floor stands for the model's own error, which no number of paths removes, and
/// bounds the largest weight. Weights are scaled to mean 1 over the training rows;
/// the test rows (`x_test`) get the same function. Returns the training and test
/// weights and the report.
pub fn noise_weights(
    x_train: &[f32],
    x_test: &[f32],
    n_in: usize,
    noise: &[f64],
    floor: f32,
) -> Result<(Vec<f32>, Vec<f32>, NoiseWeightReport), TrainError> {
    use rayon::prelude::*;
    let n = noise.len();
    debug_assert_eq!(x_train.len(), n * n_in);
    let with_noise: Vec<usize> = (0..n).filter(|&i| noise[i] > 0.0 && noise[i].is_finite()).collect();
    let step = with_noise.len().div_ceil(NOISE_MODEL_ROWS).max(1);
    let fit_rows: Vec<usize> = with_noise.iter().step_by(step).copied().collect();
    let d = n_in + 1;
    if fit_rows.len() < 4 * d {
        return Err(TrainError::Data(format!(
            "--noise-weights: {} rows with a noise estimate (paths per point above 1) for a noise model of {d} \
             coefficients; use more points",
            fit_rows.len()
        )));
    }
    let z = |i: usize, k: usize| if k < n_in { x_train[i * n_in + k] as f64 } else { 1.0 };
    // Normal equations, upper triangle, in chunk partial sums added in order.
    let partials: Vec<(Vec<f64>, Vec<f64>)> = fit_rows
        .par_chunks(NOISE_MODEL_CHUNK)
        .map(|rows| {
            let (mut a, mut b) = (vec![0.0f64; d * d], vec![0.0f64; d]);
            let mut zi = vec![0.0f64; d];
            for &i in rows {
                zi.iter_mut().enumerate().for_each(|(k, v)| *v = z(i, k));
                let y = noise[i].ln();
                for r in 0..d {
                    let zr = zi[r];
                    b[r] += zr * y;
                    for (acc, zc) in a[r * d + r..(r + 1) * d].iter_mut().zip(&zi[r..]) {
                        *acc += zr * zc;
                    }
                }
            }
            (a, b)
        })
        .collect();
    let (mut a, mut b) = (vec![0.0f64; d * d], vec![0.0f64; d]);
    for (pa, pb) in &partials {
        a.iter_mut().zip(pa).for_each(|(x, y)| *x += y);
        b.iter_mut().zip(pb).for_each(|(x, y)| *x += y);
    }
    let lambda = NOISE_MODEL_RIDGE * fit_rows.len() as f64;
    for r in 0..d {
        // The intercept is not shrunk.
        if r < n_in {
            a[r * d + r] += lambda;
        }
        for c in 0..r {
            a[r * d + c] = a[c * d + r];
        }
    }
    let beta = cholesky_solve(&a, &b)
        .ok_or_else(|| TrainError::Data("--noise-weights: the noise model's normal equations are singular".into()))?;
    let predict = |x: &[f32], i: usize| -> f64 {
        x[i * n_in..(i + 1) * n_in].iter().zip(&beta).map(|(v, c)| *v as f64 * c).sum::<f64>() + beta[n_in]
    };
    // The log's mean correction and the fit's R^2 over the fitted rows.
    let (mut resid_exp, mut ss_res, mut ys, mut yss) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for &i in &fit_rows {
        let y = noise[i].ln();
        let r = y - predict(x_train, i);
        resid_exp += r.exp();
        ss_res += r * r;
        ys += y;
        yss += y * y;
    }
    let m = fit_rows.len() as f64;
    let correction = resid_exp / m;
    let ss_tot = yss - ys * ys / m;
    let r_squared = if ss_tot > 0.0 { 1.0 - ss_res / ss_tot } else { 0.0 };
    let weight = |x: &[f32], i: usize| -> f64 {
        // A predicted variance is at most e^60: the weight stays finite and positive.
        let v = correction * predict(x, i).min(60.0).exp();
        1.0 / (v + floor as f64)
    };
    let raw_train: Vec<f64> = (0..n).into_par_iter().map(|i| weight(x_train, i)).collect();
    let scale = n as f64 / raw_train.iter().sum::<f64>();
    let w_train: Vec<f32> = raw_train.iter().map(|w| (w * scale) as f32).collect();
    let n_test = x_test.len() / n_in;
    let w_test: Vec<f32> = (0..n_test).into_par_iter().map(|i| (weight(x_test, i) * scale) as f32).collect();
    let mut sorted = w_train.clone();
    sorted.sort_by(f32::total_cmp);
    let q = |p: f64| sorted[((sorted.len() - 1) as f64 * p).round() as usize];
    let (mut s2, mut sw, mut sw2s2) = (0.0f64, 0.0f64, 0.0f64);
    for &i in &with_noise {
        let v = noise[i] + floor as f64;
        let w = w_train[i] as f64;
        s2 += v;
        sw += w;
        sw2s2 += w * w * v;
    }
    let k = with_noise.len() as f64;
    let report = NoiseWeightReport {
        floor,
        fit_rows: fit_rows.len(),
        r_squared,
        weight_quantiles: [q(0.1), q(0.5), q(0.9)],
        pooled_gain: (s2 / k) * sw * sw / (k * sw2s2),
    };
    Ok((w_train, w_test, report))
}

/// The final report.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CloudReport {
    pub train_points: usize,
    pub test: BiasReport,
    pub held_out: Option<BiasReport>,
    pub test_loss: f64,
    /// The output layer's refit, if made.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refit: Option<RefitReport>,
    /// The noise model behind the rows' weights, if weighted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_weights: Option<NoiseWeightReport>,
    pub samples_per_second: f64,
    pub seconds: f64,
    pub history: Vec<EpochRecord>,
}

/// Trains on `data` (the test split by cloud), reports on the test clouds and on
/// `held_out` (a data set made with `--held-out`), writes OUT.safetensors, OUT.json,
/// the loss history and the checkpoint; returns the loaded model and the report.
/// `data` is consumed: its feature buffer becomes the standardized training matrix.
#[allow(clippy::too_many_arguments)]
pub fn train(
    mut data: CloudTrainData,
    held_out: Option<&CloudDataset>,
    cfg: &CloudTrainConfig,
    out: &Path,
    resume: bool,
    command: &str,
    code_version: &str,
    observer: &dyn TrainObserver,
) -> Result<(CloudModel, CloudReport), TrainError> {
    cfg.validate()?;
    // The network reads the first n_in values of each row.
    let n_in = cfg.derived.inputs();
    if let Some(start) = &data.init {
        let (m, s) = (&start.model.sidecar, &cfg.schedule);
        if start.model.inputs() != n_in || m.hidden != s.hidden || m.activation != s.activation {
            return Err(TrainError::Setting {
                flag: "--init",
                why: format!(
                    "the model reads {} inputs through {:?} ({:?}); this run's network reads {n_in} through {:?} ({:?})",
                    start.model.inputs(),
                    m.hidden,
                    m.activation,
                    s.hidden,
                    s.activation
                ),
            });
        }
    }
    let started = std::time::Instant::now();
    let col = cfg.target.column();
    // Rows with a finite, non-negative target and finite features.
    let usable = |i: usize| {
        let t = data.targets[i * 5 + col];
        t.is_finite() && t >= 0.0 && data.row(i).iter().all(|v| v.is_finite())
    };
    // Clouds split by a seeded shuffle.
    let mut ids: Vec<(u32, u64)> = data.clouds.clone();
    ids.dedup();
    let mut rng = Rng::new(cfg.schedule.seed, 0x73706c6974, 1); // "split"
    shuffle(&mut ids, &mut rng);
    let n_test = ((ids.len() as f64 * cfg.test_fraction).round() as usize).clamp(1, ids.len().saturating_sub(1).max(1));
    let test_ids: std::collections::HashSet<(u32, u64)> = ids[..n_test].iter().copied().collect();
    let (mut train_rows, mut test_rows) = (vec![], vec![]);
    for i in 0..data.len() {
        if !usable(i) {
            continue;
        }
        if test_ids.contains(&data.clouds[i]) { test_rows.push(i) } else { train_rows.push(i) }
    }
    if cfg.max_points > 0 {
        train_rows.truncate(cfg.max_points);
    }
    if train_rows.is_empty() || test_rows.is_empty() {
        return Err(TrainError::Data(format!(
            "{} training and {} test rows: use more clouds",
            train_rows.len(),
            test_rows.len()
        )));
    }
    // The value a training row is fitted to, 4 pi L_ms: the path-traced target, or
    // the teachers' mean when distilling.
    let train_target = |i: usize| match &data.distilled {
        Some(d) => d.targets[i],
        None => FOUR_PI * data.targets[i * 5 + col],
    };
    let (feature_mean, feature_std, target_mean, target_std) = match &data.init {
        // Fine-tuning keeps the starting model's statistics (checked above).
        Some(start) => {
            let m = &start.model.sidecar;
            (m.feature_mean.clone(), m.feature_std.clone(), m.target_mean, m.target_std)
        }
        // Statistics of the training split (f64 accumulation).
        None => {
            let (mut mean, mut sq) = (vec![0.0f64; n_in], vec![0.0f64; n_in]);
            let (mut ym, mut ysq) = (0.0f64, 0.0f64);
            for &i in &train_rows {
                for (k, v) in data.row(i)[..n_in].iter().enumerate() {
                    mean[k] += *v as f64;
                    sq[k] += (*v as f64).powi(2);
                }
                let y = train_target(i).ln_1p() as f64;
                ym += y;
                ysq += y * y;
            }
            let n = train_rows.len() as f64;
            let std_of = |s: f64, q: f64| {
                let sd = (q / n - (s / n).powi(2)).max(0.0).sqrt();
                if sd < 1e-6 { 1.0 } else { sd }
            };
            (
                mean.iter().map(|m| (m / n) as f32).collect(),
                mean.iter().zip(&sq).map(|(m, q)| std_of(*m, *q) as f32).collect(),
                (ym / n) as f32,
                std_of(ym, ysq) as f32,
            )
        }
    };
    let standardize_row = |row: &mut [f32]| {
        for (k, v) in row[..n_in].iter_mut().enumerate() {
            *v = (*v - feature_mean[k]) / feature_std[k];
        }
    };
    // The test split, raw (whole rows, for the bias report) and standardized (the
    // network's n_in), copied out; then the training rows' first n_in values are
    // standardized in place, moved to the front and the rest dropped, so the features
    // are held once (a 6 M-point set is 10.8 GB).
    let f = N_FEATURES;
    let test_raw: Vec<f32> = test_rows.iter().flat_map(|&i| data.row(i).iter().copied()).collect();
    let mut x_test: Vec<f32> = test_raw.chunks_exact(f).flat_map(|r| r[..n_in].iter().copied()).collect();
    x_test.chunks_exact_mut(n_in).for_each(standardize_row);
    let test_targets: Vec<f32> =
        test_rows.iter().flat_map(|&i| data.targets[i * 5..i * 5 + 5].iter().copied()).collect();
    let test_clouds: Vec<(u32, u64)> = test_rows.iter().map(|&i| data.clouds[i]).collect();
    // The loss compares 4 pi L_ms (the linear value the output stands for).
    let y_test: Vec<f32> = test_rows.iter().map(|&i| FOUR_PI * data.targets[i * 5 + col]).collect();
    let y_train: Vec<f32> = train_rows.iter().map(|&i| train_target(i)).collect();
    // The relative noise variance of each training row's target (NaN where its paths
    // do not give one): the mean's, or one path's for the one-path column.
    let noise_of = |i: usize| {
        let t = &data.targets[i * 5..i * 5 + 5];
        let (mean, se, n) = (t[0] as f64, t[1] as f64, t[2] as f64);
        let rv = (se / mean).powi(2) * if cfg.target == TargetColumn::OnePath { n } else { 1.0 };
        if mean > 0.0 && se > 0.0 && n > 1.0 && rv.is_finite() { rv } else { f64::NAN }
    };
    let noise_train: Vec<f64> = match cfg.noise_weights {
        Some(_) if data.distilled.is_some() => {
            return Err(TrainError::Setting {
                flag: "--noise-weights",
                why: "a distilled run's targets are the teachers' predictions, which carry no path noise".into(),
            });
        }
        Some(_) => train_rows.iter().map(|&i| noise_of(i)).collect(),
        None => vec![],
    };
    let mut x_train = std::mem::take(&mut data.features);
    for (j, &i) in train_rows.iter().enumerate() {
        // Rows ascend and j n_in <= i f, so no row is overwritten before it has moved.
        x_train.copy_within(i * f..i * f + n_in, j * n_in);
        standardize_row(&mut x_train[j * n_in..(j + 1) * n_in]);
    }
    x_train.truncate(train_rows.len() * n_in);
    x_train.shrink_to_fit();
    let (weights, noise_report) = match cfg.noise_weights {
        Some(floor) => {
            let (w_train, w_test, report) = noise_weights(&x_train, &x_test, n_in, &noise_train, floor)?;
            (Some((w_train, w_test)), Some(report))
        }
        None => (None, None),
    };
    let fit_data = FitData {
        n_f: n_in,
        x_train,
        y_train,
        x_test,
        y_test,
        loss: Loss::RelativeL2 { mean: target_mean, std: target_std, eps: cfg.eps, power: cfg.loss_power },
        init: data.init.as_ref().map(|s| s.model.mlp.layers_out_in()),
        weights,
    };
    let paths = TrainPaths::new(out);
    // The refit follows the stochastic fit deterministically, so a checkpoint stands
    // for any refit: a finished run resumed with another --refit-output refits only.
    let fit_cfg = CloudTrainConfig { refit_output: 0, ..cfg.clone() };
    let teachers: &[String] = data.distilled.as_ref().map_or(&[], |d| &d.teachers);
    let sources: Vec<String> = data
        .sources
        .iter()
        .cloned()
        .chain(teachers.iter().map(|t| format!("teacher {t}")))
        .chain(data.init.iter().map(|s| format!("init {}", s.fingerprint)))
        .collect();
    let identity = RunIdentity { config: &fit_cfg, sources: &sources, points: data.len() };
    let Fitted { mut net, history, samples_per_second } =
        fit(&fit_data, &cfg.schedule, &paths, resume, identity, observer)?;
    let refit = if cfg.refit_output > 0 {
        let (x, y) = (&fit_data.x_train, &fit_data.y_train);
        let w = fit_data.weights.as_ref().map(|(w, _)| &w[..]);
        Some(refit_output_layer(&mut net, x, y, w, n_in, fit_data.loss, cfg.refit_output)?)
    } else {
        None
    };
    let mut sidecar = CloudSidecar {
        format: MODEL_FORMAT.into(),
        format_version: MODEL_FORMAT_VERSION,
        feature_names: feature_names()[..n_in].to_vec(),
        feature_mean,
        feature_std,
        target: TARGET_TRANSFORM.into(),
        target_mean,
        target_std,
        hidden: cfg.schedule.hidden.clone(),
        activation: cfg.schedule.activation,
        training: serde_json::Value::Null,
    };
    let mlp: Mlp = net.to_mlp()?;
    let model = CloudModel::new(sidecar.clone(), mlp);
    // The test split is judged on the stored means (the precise reference) whatever
    // the training column.
    let test = bias_report(&model, &test_raw, &test_targets, &test_clouds, &(0..test_rows.len()).collect::<Vec<_>>());
    let held_out = held_out.map(|h| {
        let clouds: Vec<(u32, u64)> = (0..h.len()).map(|i| (0, h.cloud_of(i))).collect();
        let rows: Vec<usize> = (0..h.len()).filter(|&i| h.targets[i * 5].is_finite()).collect();
        bias_report(&model, &h.features, &h.targets, &clouds, &rows)
    });
    let report = CloudReport {
        train_points: train_rows.len(),
        test,
        held_out,
        test_loss: history.last().map(|h| h.final_test_mse()).unwrap_or(f64::NAN),
        refit,
        noise_weights: noise_report,
        samples_per_second,
        seconds: started.elapsed().as_secs_f64(),
        history: history.clone(),
    };
    sidecar.training = serde_json::json!({
        "command": command,
        "code_version": code_version,
        "data": data.sources,
        "teachers": teachers,
        "init": data.init.as_ref().map(|s| s.fingerprint.clone()),
        "points": data.len(),
        "config": cfg,
        "report": report,
    });
    save_tensors(&net.named(), &paths.weights)?;
    write_text(&paths.sidecar, &serde_json::to_string_pretty(&sidecar).expect("serializes"))?;
    let model = CloudModel::load(&paths.weights).map_err(|e| TrainError::Data(e.to_string()))?;
    Ok((model, report))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows whose relative noise variance is a known function of their features,
    /// measured with mean-one log-normal scatter (as a row's own estimate from its
    /// paths scatters): the weights follow the inverse of the true variance (slope -1
    /// in logs, where the floor is negligible), average 1 over the training rows,
    /// give a test row what the same features give in training, ignore rows without
    /// a noise estimate in the fit, and are the same bits on 1 and 3 threads.
    #[test]
    fn noise_weights_follow_the_true_noise() {
        let (n, n_in) = (20_000usize, 3usize);
        let mut rng = Rng::new(21, 0, 0);
        let normal = |rng: &mut Rng| {
            let (u1, u2) = (rng.uniform_f64().max(1e-300), rng.uniform_f64());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let x: Vec<f32> = (0..n * n_in).map(|_| normal(&mut rng) as f32).collect();
        let truth: Vec<f64> =
            x.chunks_exact(n_in).map(|r| (1.2 * r[0] as f64 - 0.6 * r[1] as f64 + 0.2f64.ln()).exp()).collect();
        let s = 0.7;
        let mut noise: Vec<f64> = truth.iter().map(|v| v * (s * normal(&mut rng) - 0.5 * s * s).exp()).collect();
        // Rows without an estimate (one path, or a zero mean) are left out of the fit.
        for i in (0..n).step_by(10) {
            noise[i] = f64::NAN;
        }
        let x_test = x[5 * n_in..6 * n_in].to_vec();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| noise_weights(&x, &x_test, n_in, &noise, 1e-6).unwrap())
        };
        let (w, w_test, report) = run(1);
        assert_eq!(run(3).0, w, "the weights depend on the thread count");
        let mean = w.iter().map(|v| *v as f64).sum::<f64>() / n as f64;
        assert!((mean - 1.0).abs() < 1e-5, "mean weight {mean}");
        assert_eq!(w_test[0], w[5], "a test row's weight is not the training row's of the same features");
        assert_eq!(report.fit_rows, n - n / 10);
        // ln w against ln(true variance): a line of slope -1.
        let (lx, ly): (Vec<f64>, Vec<f64>) = truth.iter().zip(&w).map(|(t, w)| (t.ln(), (*w as f64).ln())).unzip();
        let (mx, my) = (lx.iter().sum::<f64>() / n as f64, ly.iter().sum::<f64>() / n as f64);
        let sxy: f64 = lx.iter().zip(&ly).map(|(a, b)| (a - mx) * (b - my)).sum();
        let sxx: f64 = lx.iter().map(|a| (a - mx).powi(2)).sum();
        let slope = sxy / sxx;
        assert!((slope + 1.0).abs() < 0.03, "slope {slope}");
        // The scatter is 0.7 in logs against a spread of 1.34: R^2 about 0.79.
        assert!(report.r_squared > 0.7 && report.r_squared < 0.9, "{report:?}");
        assert!(report.pooled_gain > 1.5, "{report:?}");
        // A floor bounds every weight at 1 / floor before scaling.
        let (wf, _, _) = noise_weights(&x, &x_test, n_in, &noise, 0.5).unwrap();
        let spread = wf.iter().fold(0.0f32, |m, v| m.max(*v)) / wf.iter().fold(f32::MAX, |m, v| m.min(*v));
        let unfloored = w.iter().fold(0.0f32, |m, v| m.max(*v)) / w.iter().fold(f32::MAX, |m, v| m.min(*v));
        assert!(spread < unfloored / 10.0, "floor 0.5: spread {spread}, without {unfloored}");
        // Too few rows with an estimate for the model: refused, naming the flag.
        let few = vec![f64::NAN; n];
        let err = noise_weights(&x, &x_test, n_in, &few, 0.003).unwrap_err().to_string();
        assert!(err.contains("--noise-weights"), "{err}");
    }

    /// A floor that is not a positive number is refused, naming the flag.
    #[test]
    fn a_bad_noise_floor_is_refused() {
        for floor in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let cfg = CloudTrainConfig { noise_weights: Some(floor), ..Default::default() };
            let err = cfg.validate().unwrap_err().to_string();
            assert!(err.contains("--noise-weights"), "{floor}: {err}");
        }
        assert!(CloudTrainConfig { noise_weights: Some(0.003), ..Default::default() }.validate().is_ok());
    }
}
