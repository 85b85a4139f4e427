//! Training the global model with candle (thesis section 5.2): the transformations of
//! eqs. 5.7-5.9 plus standardization, an MLP with Glorot-uniform initialization
//! (eq. 2.50), mean squared error, mini-batches, SGD with momentum or Adam, a
//! per-epoch learning-rate decay, a seeded shuffle and a seeded held-out test split;
//! per-epoch history, checkpoints every epoch and resume (the loop is
//! [`crate::nn::fit`]).

use super::datagen::Dataset;
use super::model::{
    FeatureLayout, GlobalModel, MODEL_FORMAT, MODEL_FORMAT_VERSION, Sidecar, Standardization, TargetKind,
    predicted_l_i, transform_target,
};
use crate::nn::dense::Activation;
pub use crate::nn::fit::{EpochRecord, Network, Quiet, TrainError, TrainObserver, TrainPaths};
use crate::nn::fit::{FitData, FitSchedule, Fitted, Loss, RunIdentity, fit, save_tensors, shuffle, write_text};
use crate::nn::optim::Optimizer;
use engine::Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    pub hidden: Vec<usize>,
    pub activation: Activation,
    pub epochs: usize,
    pub batch: usize,
    pub optimizer: Optimizer,
    /// Learning rate of the first epoch ...
    pub lr: f64,
    /// ... multiplied by this after every epoch.
    pub lr_decay: f64,
    pub test_fraction: f64,
    pub seed: u64,
    /// What the network learns: all of L_i (the thesis) or multiple scattering only.
    #[serde(default)]
    pub target: TargetKind,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            hidden: vec![200, 100],
            activation: Activation::Relu,
            epochs: 10,
            batch: 1000,
            optimizer: Optimizer::Adam,
            lr: 1e-3,
            lr_decay: 0.8,
            test_fraction: 0.2,
            seed: 1,
            target: TargetKind::Total,
        }
    }
}

impl TrainConfig {
    /// The network and schedule part.
    pub fn schedule(&self) -> FitSchedule {
        FitSchedule {
            hidden: self.hidden.clone(),
            activation: self.activation,
            epochs: self.epochs,
            batch: self.batch,
            optimizer: self.optimizer,
            lr: self.lr,
            lr_decay: self.lr_decay,
            seed: self.seed,
            average_last: 0,
        }
    }

    pub fn validate(&self) -> Result<(), TrainError> {
        self.schedule().validate(self.test_fraction)
    }
}

/// Training data: raw feature rows and L_i, from one or more data sets of one layout.
pub struct TrainData {
    pub layout: FeatureLayout,
    pub features: Vec<f32>,
    pub l_i: Vec<f32>,
    pub sources: Vec<String>,
}

impl TrainData {
    pub fn len(&self) -> usize {
        self.l_i.len()
    }

    pub fn is_empty(&self) -> bool {
        self.l_i.is_empty()
    }

    pub fn n_features(&self) -> usize {
        self.layout.names.len()
    }

    /// Loads data-set directories; refuses mismatched feature layouts.
    pub fn load(dirs: &[PathBuf]) -> Result<TrainData, TrainError> {
        let mut out: Option<TrainData> = None;
        for d in dirs {
            let ds = Dataset::load(d).map_err(|e| TrainError::Data(e.to_string()))?;
            let s = &ds.manifest.settings;
            let layout = FeatureLayout::current(s.directions, s.n_dirs);
            let l_i: Vec<f32> = ds.targets.chunks_exact(5).map(|r| r[0]).collect();
            match &mut out {
                None => {
                    out = Some(TrainData { layout, features: ds.features, l_i, sources: vec![d.display().to_string()] })
                }
                Some(t) => {
                    if t.layout != layout {
                        return Err(TrainError::Data(format!(
                            "{} has {} {} directions, {} has {} {}: data sets of different feature layouts cannot be mixed",
                            d.display(),
                            layout.n_dirs,
                            layout.direction_set.name(),
                            t.sources[0],
                            t.layout.n_dirs,
                            t.layout.direction_set.name()
                        )));
                    }
                    t.features.extend_from_slice(&ds.features);
                    t.l_i.extend_from_slice(&l_i);
                    t.sources.push(d.display().to_string());
                }
            }
        }
        out.ok_or_else(|| TrainError::Data("no data set given".into()))
    }
}

/// The final report.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Report {
    pub train_points: usize,
    pub test_points: usize,
    pub dropped_points: usize,
    /// Variance of the standardized target on the test set (1 up to sampling).
    pub test_target_variance: f64,
    pub test_mse: f64,
    /// |L_pred - L_i| / L_i on the test set.
    pub rel_error_median: f64,
    pub rel_error_p90: f64,
    pub samples_per_second: f64,
    pub seconds: f64,
    pub history: Vec<EpochRecord>,
}

struct Prepared {
    n_f: usize,
    /// Standardized rows.
    x_train: Vec<f32>,
    y_train: Vec<f32>,
    x_test: Vec<f32>,
    y_test: Vec<f32>,
    raw_test: Vec<f32>,
    l_test: Vec<f32>,
    stats: Standardization,
    dropped: usize,
}

fn prepare(data: &TrainData, cfg: &TrainConfig) -> Result<Prepared, TrainError> {
    let n_f = data.n_features();
    // Transformed targets; rows that are not finite are dropped (counted).
    let mut rows: Vec<usize> = vec![];
    let mut y_all = vec![0.0f32; data.len()];
    for i in 0..data.len() {
        let f = &data.features[i * n_f..(i + 1) * n_f];
        let y = transform_target(cfg.target, f, data.l_i[i]);
        if y.is_finite() && f.iter().all(|v| v.is_finite()) && data.l_i[i] >= 0.0 {
            y_all[i] = y;
            rows.push(i);
        }
    }
    let dropped = data.len() - rows.len();
    // Seeded split.
    let mut rng = Rng::new(cfg.seed, 0x73706c6974, 0); // "split"
    shuffle(&mut rows, &mut rng);
    let n_test = ((rows.len() as f64 * cfg.test_fraction).round() as usize).clamp(1, rows.len().saturating_sub(1));
    if rows.len() < 2 {
        return Err(TrainError::Data(format!("{} usable data points; at least 2 are needed", rows.len())));
    }
    let (test, train) = rows.split_at(n_test);
    // Statistics of the training split (f64 accumulation).
    let mut mean = vec![0.0f64; n_f];
    let mut sq = vec![0.0f64; n_f];
    let (mut ym, mut ysq) = (0.0f64, 0.0f64);
    for &i in train {
        for k in 0..n_f {
            let v = data.features[i * n_f + k] as f64;
            mean[k] += v;
            sq[k] += v * v;
        }
        ym += y_all[i] as f64;
        ysq += (y_all[i] as f64).powi(2);
    }
    let n = train.len() as f64;
    let std_of = |s: f64, q: f64| {
        let var = (q / n - (s / n).powi(2)).max(0.0);
        if var.sqrt() < 1e-6 { 1.0 } else { var.sqrt() }
    };
    let stats = Standardization {
        feature_mean: mean.iter().map(|m| (m / n) as f32).collect(),
        feature_std: mean.iter().zip(&sq).map(|(m, q)| std_of(*m, *q) as f32).collect(),
        target: cfg.target.transform().into(),
        target_mean: (ym / n) as f32,
        target_std: std_of(ym, ysq) as f32,
    };
    let standardize = |idx: &[usize]| {
        let mut x = Vec::with_capacity(idx.len() * n_f);
        let mut y = Vec::with_capacity(idx.len());
        for &i in idx {
            for k in 0..n_f {
                x.push((data.features[i * n_f + k] - stats.feature_mean[k]) / stats.feature_std[k]);
            }
            y.push((y_all[i] - stats.target_mean) / stats.target_std);
        }
        (x, y)
    };
    let (x_train, y_train) = standardize(train);
    let (x_test, y_test) = standardize(test);
    let raw_test = test.iter().flat_map(|&i| data.features[i * n_f..(i + 1) * n_f].iter().copied()).collect();
    let l_test = test.iter().map(|&i| data.l_i[i]).collect();
    Ok(Prepared { n_f, x_train, y_train, x_test, y_test, raw_test, l_test, stats, dropped })
}

/// Trains, writes the model files, returns the loaded model and the report.
pub fn train(
    data: &TrainData,
    cfg: &TrainConfig,
    out: &Path,
    resume: bool,
    command: &str,
    code_version: &str,
    observer: &dyn TrainObserver,
) -> Result<(GlobalModel, Report), TrainError> {
    cfg.validate()?;
    let started = std::time::Instant::now();
    let paths = TrainPaths::new(out);
    let mut prep = prepare(data, cfg)?;
    let n_f = prep.n_f;
    let fit_data = FitData {
        n_f,
        x_train: std::mem::take(&mut prep.x_train),
        y_train: std::mem::take(&mut prep.y_train),
        x_test: prep.x_test.clone(),
        y_test: prep.y_test.clone(),
        loss: Loss::Mse,
        init: None,
        weights: None,
    };
    let identity = RunIdentity { config: cfg, sources: &data.sources, points: data.len() };
    let Fitted { net, history, samples_per_second } =
        fit(&fit_data, &cfg.schedule(), &paths, resume, identity, observer)?;
    let n_train = fit_data.y_train.len();
    // Final evaluation with the fast evaluator (what the renderer will run).
    let mlp = net.to_mlp()?;
    let mut scratch = mlp.scratch();
    let mut rel: Vec<f64> = vec![];
    for (i, &l) in prep.l_test.iter().enumerate() {
        let raw = &prep.raw_test[i * n_f..(i + 1) * n_f];
        let y = mlp.forward(&prep.x_test[i * n_f..(i + 1) * n_f], &mut scratch);
        let pred = predicted_l_i(cfg.target, raw, y * prep.stats.target_std + prep.stats.target_mean);
        if l > 0.0 {
            rel.push(((pred - l) / l).abs() as f64);
        }
    }
    rel.sort_by(|a, b| a.total_cmp(b));
    let q = |p: f64| rel.get(((rel.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(f64::NAN);
    let var_y = {
        let m = prep.y_test.iter().map(|&v| v as f64).sum::<f64>() / prep.y_test.len() as f64;
        prep.y_test.iter().map(|&v| (v as f64 - m).powi(2)).sum::<f64>() / prep.y_test.len() as f64
    };
    let report = Report {
        train_points: n_train,
        test_points: prep.y_test.len(),
        dropped_points: prep.dropped,
        test_target_variance: var_y,
        test_mse: history.last().map(|h| h.test_mse).unwrap_or(f64::NAN),
        rel_error_median: q(0.5),
        rel_error_p90: q(0.9),
        samples_per_second,
        seconds: started.elapsed().as_secs_f64(),
        history: history.clone(),
    };
    let sidecar = Sidecar {
        format: MODEL_FORMAT.into(),
        format_version: MODEL_FORMAT_VERSION,
        features: data.layout.clone(),
        standardization: prep.stats.clone(),
        hidden: cfg.hidden.clone(),
        activation: cfg.activation,
        training: serde_json::json!({
            "command": command,
            "code_version": code_version,
            "data": data.sources,
            "points": data.len(),
            "config": cfg,
            "report": {
                "train_points": report.train_points,
                "test_points": report.test_points,
                "dropped_points": report.dropped_points,
                "test_mse_standardized": report.test_mse,
                "test_target_variance": report.test_target_variance,
                "rel_error_median": report.rel_error_median,
                "rel_error_p90": report.rel_error_p90,
                "samples_per_second": report.samples_per_second,
                "seconds": report.seconds,
            },
            "history": history,
        }),
    };
    save_tensors(&net.named(), &paths.weights)?;
    write_text(&paths.sidecar, &serde_json::to_string_pretty(&sidecar).expect("serializes"))?;
    let model = GlobalModel::load(&paths.weights).map_err(|e| TrainError::Data(e.to_string()))?;
    Ok((model, report))
}
