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
use crate::nn::refit::{RefitReport, refit_output_layer};
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
    let mut x_train = std::mem::take(&mut data.features);
    for (j, &i) in train_rows.iter().enumerate() {
        // Rows ascend and j n_in <= i f, so no row is overwritten before it has moved.
        x_train.copy_within(i * f..i * f + n_in, j * n_in);
        standardize_row(&mut x_train[j * n_in..(j + 1) * n_in]);
    }
    x_train.truncate(train_rows.len() * n_in);
    x_train.shrink_to_fit();
    let fit_data = FitData {
        n_f: n_in,
        x_train,
        y_train,
        x_test,
        y_test,
        loss: Loss::RelativeL2 { mean: target_mean, std: target_std, eps: cfg.eps, power: cfg.loss_power },
        init: data.init.as_ref().map(|s| s.model.mlp.layers_out_in()),
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
        Some(refit_output_layer(&mut net, x, y, n_in, fit_data.loss, cfg.refit_output)?)
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
