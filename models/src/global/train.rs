//! Training the global model with candle (thesis section 5.2): the transformations of
//! eqs. 5.7-5.9 plus standardization, an MLP with Glorot-uniform initialization
//! (eq. 2.50), mean squared error, mini-batches, SGD with momentum or Adam, a
//! per-epoch learning-rate decay, a seeded shuffle and a seeded held-out test split;
//! per-epoch history, checkpoints every epoch and resume.

use super::datagen::Dataset;
use super::model::{
    FeatureLayout, GlobalModel, MODEL_FORMAT, MODEL_FORMAT_VERSION, Sidecar, Standardization, TargetKind,
    predicted_l_i, transform_target,
};
use crate::dataset::npy::write_bytes_atomically;
use crate::nn::dense::Activation;
use crate::nn::mlp::Mlp;
use crate::nn::optim::{OptState, Optimizer, check_schedule};
use candle_core::{DType, Device, Tensor, Var};
use engine::Rng;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
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

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{0}")]
    Data(String),
    #[error("{flag}: {why}")]
    Setting { flag: &'static str, why: String },
    #[error("candle: {0}")]
    Candle(#[from] candle_core::Error),
    #[error("{path}: {why}")]
    File { path: PathBuf, why: String },
    #[error("cancelled after epoch {0}; run again with --resume to continue")]
    Cancelled(usize),
}

impl From<std::io::Error> for TrainError {
    fn from(e: std::io::Error) -> Self {
        TrainError::Data(e.to_string())
    }
}

impl TrainConfig {
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |flag, why: &str| Err(TrainError::Setting { flag, why: why.into() });
        if self.hidden.is_empty() || self.hidden.contains(&0) {
            return bad("--hidden", "needs at least one layer, each at least 1 wide");
        }
        if let Err((flag, why)) = check_schedule(self.epochs, self.batch, self.lr, self.lr_decay, self.test_fraction) {
            return bad(flag, why);
        }
        if let Optimizer::Sgd { momentum } = self.optimizer {
            if !(0.0..1.0).contains(&momentum) {
                return bad("--momentum", "must lie in [0, 1)");
            }
        }
        Ok(())
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

/// Per-epoch record.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EpochRecord {
    pub epoch: usize,
    pub lr: f64,
    /// Mean squared error in the transformed, standardized space.
    pub train_mse: f64,
    pub test_mse: f64,
    pub seconds: f64,
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

fn shuffle<T>(v: &mut [T], rng: &mut Rng) {
    for i in (1..v.len()).rev() {
        let j = (rng.uniform_f64() * (i + 1) as f64) as usize;
        v.swap(i, j.min(i));
    }
}

/// The network's parameters as candle variables, layer by layer (weight [out, in], bias).
pub struct Network {
    pub params: Vec<(Var, Var)>,
    pub activation: Activation,
}

impl Network {
    /// Glorot-uniform weights (limit sqrt(6 / (in + out)), eq. 2.50), zero biases, from
    /// our own seeded generator.
    pub fn glorot(widths: &[usize], activation: Activation, seed: u64, dev: &Device) -> Result<Self, TrainError> {
        let mut rng = Rng::new(seed, 0x676c6f726f74, 0); // "glorot"
        let mut params = vec![];
        for l in 0..widths.len() - 1 {
            let (i, o) = (widths[l], widths[l + 1]);
            let limit = (6.0 / (i + o) as f64).sqrt() as f32;
            let w: Vec<f32> = (0..i * o).map(|_| (2.0 * rng.uniform() - 1.0) * limit).collect();
            params.push((
                Var::from_tensor(&Tensor::from_vec(w, (o, i), dev)?)?,
                Var::from_tensor(&Tensor::zeros(o, DType::F32, dev)?)?,
            ));
        }
        Ok(Network { params, activation })
    }

    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let mut h = x.clone();
        let last = self.params.len() - 1;
        for (l, (w, b)) in self.params.iter().enumerate() {
            h = h.matmul(&w.as_tensor().t()?)?.broadcast_add(b.as_tensor())?;
            if l < last {
                h = match self.activation {
                    Activation::Relu => h.relu()?,
                    Activation::Tanh => h.tanh()?,
                    Activation::Silu => h.silu()?,
                };
            }
        }
        h.squeeze(1)
    }

    /// Named tensors in the model file's convention: layers.L.weight / layers.L.bias.
    pub fn named(&self) -> HashMap<String, Tensor> {
        let mut m = HashMap::new();
        for (l, (w, b)) in self.params.iter().enumerate() {
            m.insert(format!("layers.{l}.weight"), w.as_tensor().clone());
            m.insert(format!("layers.{l}.bias"), b.as_tensor().clone());
        }
        m
    }

    /// The fast evaluator of the same weights.
    pub fn to_mlp(&self) -> candle_core::Result<Mlp> {
        let mut layers = vec![];
        for (w, b) in &self.params {
            let (o, i) = w.as_tensor().dims2()?;
            layers.push((i, o, w.as_tensor().flatten_all()?.to_vec1()?, b.as_tensor().to_vec1()?));
        }
        Ok(Mlp::new(&layers, self.activation))
    }
}

/// Where training writes: OUT.safetensors, OUT.json, OUT.loss.csv, OUT.loss.png and the
/// checkpoint OUT.checkpoint/.
pub struct TrainPaths {
    pub weights: PathBuf,
    pub sidecar: PathBuf,
    pub csv: PathBuf,
    pub plot: PathBuf,
    pub checkpoint: PathBuf,
}

impl TrainPaths {
    pub fn new(out: &Path) -> Self {
        let with = |ext: &str| {
            let mut s = out.as_os_str().to_owned();
            s.push(ext);
            PathBuf::from(s)
        };
        TrainPaths {
            weights: with(".safetensors"),
            sidecar: with(".json"),
            csv: with(".loss.csv"),
            plot: with(".loss.png"),
            checkpoint: with(".checkpoint"),
        }
    }
}

#[derive(Serialize, Deserialize)]
struct CheckpointState {
    config: TrainConfig,
    sources: Vec<String>,
    points: usize,
    epoch: usize,
    step: u64,
    history: Vec<EpochRecord>,
}

fn save_tensors(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<(), TrainError> {
    crate::nn::optim::save_safetensors(tensors, path)
        .map_err(|e| TrainError::File { path: path.to_owned(), why: e.to_string() })
}

fn write_text(path: &Path, text: &str) -> Result<(), TrainError> {
    write_bytes_atomically(path, text.as_bytes())
        .map_err(|e| TrainError::File { path: path.to_owned(), why: e.to_string() })
}

/// Progress callbacks of a training run.
pub trait TrainObserver: Sync {
    /// Batches done in this epoch, of `total`.
    fn batch(&self, _epoch: usize, _done: usize, _total: usize) {}
    fn epoch(&self, _record: &EpochRecord) {}
    fn cancelled(&self) -> bool {
        false
    }
}

pub struct Quiet;
impl TrainObserver for Quiet {}

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
    let dev = Device::Cpu;
    let paths = TrainPaths::new(out);
    let prep = prepare(data, cfg)?;
    let n_f = prep.n_f;
    let mut widths = vec![n_f];
    widths.extend(&cfg.hidden);
    widths.push(1);
    let net = Network::glorot(&widths, cfg.activation, cfg.seed, &dev)?;
    let vars: Vec<&Var> = net.params.iter().flat_map(|(w, b)| [w, b]).collect();
    let mut opt = OptState::new(&vars)?;
    let mut history: Vec<EpochRecord> = vec![];
    let mut first_epoch = 0;
    let state_path = paths.checkpoint.join("state.json");
    if resume && state_path.exists() {
        let text = std::fs::read_to_string(&state_path)
            .map_err(|e| TrainError::File { path: state_path.clone(), why: e.to_string() })?;
        let st: CheckpointState = serde_json::from_str(&text)
            .map_err(|e| TrainError::File { path: state_path.clone(), why: e.to_string() })?;
        if st.config != *cfg || st.sources != data.sources || st.points != data.len() {
            return Err(TrainError::File {
                path: state_path,
                why: "the checkpoint was made with other settings or data; train without --resume to start over".into(),
            });
        }
        let t = candle_core::safetensors::load(paths.checkpoint.join("state.safetensors"), &dev)?;
        for (k, var) in vars.iter().enumerate() {
            let get = |name: String| {
                t.get(&name)
                    .cloned()
                    .ok_or_else(|| TrainError::File { path: paths.checkpoint.clone(), why: format!("{name} missing") })
            };
            var.set(&get(format!("param.{k}"))?)?;
            opt.m[k] = get(format!("m.{k}"))?;
            opt.v[k] = get(format!("v.{k}"))?;
        }
        opt.step = st.step;
        first_epoch = st.epoch;
        history = st.history;
    }
    let n_train = prep.y_train.len();
    let x_test = Tensor::from_slice(&prep.x_test, (prep.y_test.len(), n_f), &dev)?;
    let y_test = Tensor::from_slice(&prep.y_test, prep.y_test.len(), &dev)?;
    let test_mse = |net: &Network| -> candle_core::Result<f64> {
        let p = net.forward(&x_test)?;
        candle_nn::loss::mse(&p, &y_test)?.to_scalar::<f32>().map(|v| v as f64)
    };
    let mut order: Vec<usize> = (0..n_train).collect();
    let n_batches = n_train.div_ceil(cfg.batch);
    let mut xb = Vec::with_capacity(cfg.batch * n_f);
    let mut yb = Vec::with_capacity(cfg.batch);
    let mut trained_samples = 0u64;
    let train_started = std::time::Instant::now();
    for epoch in first_epoch..cfg.epochs {
        let t0 = std::time::Instant::now();
        let lr = cfg.lr * cfg.lr_decay.powi(epoch as i32);
        let mut rng = Rng::new(cfg.seed, 0x65706f6368, epoch as u64); // "epoch"
        order.iter_mut().enumerate().for_each(|(i, o)| *o = i);
        shuffle(&mut order, &mut rng);
        let mut loss_sum = 0.0f64;
        for (b, idx) in order.chunks(cfg.batch).enumerate() {
            if observer.cancelled() {
                return Err(TrainError::Cancelled(epoch));
            }
            xb.clear();
            yb.clear();
            for &i in idx {
                xb.extend_from_slice(&prep.x_train[i * n_f..(i + 1) * n_f]);
                yb.push(prep.y_train[i]);
            }
            let x = Tensor::from_slice(&xb, (idx.len(), n_f), &dev)?;
            let y = Tensor::from_slice(&yb, idx.len(), &dev)?;
            let loss = candle_nn::loss::mse(&net.forward(&x)?, &y)?;
            let grads = loss.backward()?;
            opt.apply(cfg.optimizer, lr, &vars, &grads)?;
            loss_sum += loss.to_scalar::<f32>()? as f64 * idx.len() as f64;
            trained_samples += idx.len() as u64;
            observer.batch(epoch, b + 1, n_batches);
        }
        let record = EpochRecord {
            epoch: epoch + 1,
            lr,
            train_mse: loss_sum / n_train as f64,
            test_mse: test_mse(&net)?,
            seconds: t0.elapsed().as_secs_f64(),
        };
        if !record.train_mse.is_finite() {
            return Err(TrainError::Data(format!(
                "training diverged in epoch {} (loss {}); lower --lr",
                epoch + 1,
                record.train_mse
            )));
        }
        observer.epoch(&record);
        history.push(record);
        // Checkpoint: parameters, optimizer moments and history.
        let mut t = HashMap::new();
        for (k, var) in vars.iter().enumerate() {
            t.insert(format!("param.{k}"), var.as_tensor().clone());
            t.insert(format!("m.{k}"), opt.m[k].clone());
            t.insert(format!("v.{k}"), opt.v[k].clone());
        }
        save_tensors(&t, &paths.checkpoint.join("state.safetensors"))?;
        let st = CheckpointState {
            config: cfg.clone(),
            sources: data.sources.clone(),
            points: data.len(),
            epoch: epoch + 1,
            step: opt.step,
            history: history.clone(),
        };
        write_text(&state_path, &serde_json::to_string_pretty(&st).expect("serializes"))?;
        write_history(&paths, &history)?;
    }
    let train_seconds = train_started.elapsed().as_secs_f64();
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
        samples_per_second: trained_samples as f64 / train_seconds.max(1e-9),
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

fn write_history(paths: &TrainPaths, history: &[EpochRecord]) -> Result<(), TrainError> {
    let mut csv = String::from("epoch,lr,train_mse,test_mse,seconds\n");
    for h in history {
        csv += &format!("{},{},{},{},{:.3}\n", h.epoch, h.lr, h.train_mse, h.test_mse, h.seconds);
    }
    write_text(&paths.csv, &csv)?;
    let points: Vec<(f64, f64, f64)> = history.iter().map(|h| (h.epoch as f64, h.train_mse, h.test_mse)).collect();
    let png = crate::plot::loss_plot_png("", "MSE", [crate::plot::TRAIN_COLOUR, crate::plot::TEST_COLOUR], &points);
    write_bytes_atomically(&paths.plot, &png)
        .map_err(|e| TrainError::File { path: paths.plot.clone(), why: e.to_string() })
}
