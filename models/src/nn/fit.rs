//! The training loop both MLP models share (the global model of thesis 5.2 and the
//! cloud-aware model): a Glorot-initialized network, mini-batches in a seeded shuffle,
//! mean squared error on standardized targets, SGD with momentum or Adam with a
//! per-epoch learning-rate decay, optionally the average of the weights over the last
//! epochs (tail averaging), per-epoch history, and a checkpoint after every epoch from
//! which a run resumes to the same weights.

use crate::dataset::npy::write_bytes_atomically;
use crate::nn::dense::Activation;
use crate::nn::mlp::Mlp;
use crate::nn::optim::{OptState, Optimizer};
use candle_core::{DType, Device, Tensor, Var};
use engine::Rng;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Per-epoch record.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EpochRecord {
    pub epoch: usize,
    pub lr: f64,
    /// Mean squared error in the transformed, standardized space.
    pub train_mse: f64,
    pub test_mse: f64,
    /// The test loss of the averaged weights, in the epochs that average.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub averaged_test_mse: Option<f64>,
    pub seconds: f64,
}

impl EpochRecord {
    /// The test loss of the network the fit returns if it ended after this epoch.
    pub fn final_test_mse(&self) -> f64 {
        self.averaged_test_mse.unwrap_or(self.test_mse)
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

/// Fisher-Yates shuffle from our own seeded generator.
pub fn shuffle<T>(v: &mut [T], rng: &mut Rng) {
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
        let (w, b) = self.params.last().expect("a network has an output layer");
        self.hidden(x)?.matmul(&w.as_tensor().t()?)?.broadcast_add(b.as_tensor())?.squeeze(1)
    }

    /// The activations of the last hidden layer: every layer but the output one.
    pub fn hidden(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let mut h = x.clone();
        for (w, b) in &self.params[..self.params.len() - 1] {
            h = h.matmul(&w.as_tensor().t()?)?.broadcast_add(b.as_tensor())?;
            h = match self.activation {
                Activation::Relu => h.relu()?,
                Activation::Tanh => h.tanh()?,
                Activation::Silu => h.silu()?,
            };
        }
        Ok(h)
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

    /// A network with the given parameter values, in `params` order (weight, bias per
    /// layer), as f32.
    fn with_values(&self, values: &[Tensor]) -> candle_core::Result<Network> {
        let mut params = vec![];
        for pair in values.chunks_exact(2) {
            params.push((
                Var::from_tensor(&pair[0].to_dtype(DType::F32)?)?,
                Var::from_tensor(&pair[1].to_dtype(DType::F32)?)?,
            ));
        }
        Ok(Network { params, activation: self.activation })
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
struct CheckpointState<C> {
    config: C,
    sources: Vec<String>,
    points: usize,
    epoch: usize,
    step: u64,
    history: Vec<EpochRecord>,
    /// Steps summed into the average so far.
    #[serde(default)]
    averaged_steps: u64,
}

// The writers' errors name the file.
pub fn save_tensors(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<(), TrainError> {
    Ok(crate::nn::optim::save_safetensors(tensors, path)?)
}

pub fn write_text(path: &Path, text: &str) -> Result<(), TrainError> {
    Ok(write_bytes_atomically(path, text.as_bytes())?)
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

/// Asks the run to stop once this many epochs have finished (a stop at a known
/// point, as Ctrl-C would make one, for resume checks).
#[derive(Debug, Default)]
pub struct StopAfterEpochs {
    epochs: usize,
    done: std::sync::atomic::AtomicUsize,
}

impl StopAfterEpochs {
    pub fn new(epochs: usize) -> Self {
        StopAfterEpochs { epochs, done: Default::default() }
    }
}

impl TrainObserver for StopAfterEpochs {
    fn epoch(&self, r: &EpochRecord) {
        self.done.store(r.epoch, std::sync::atomic::Ordering::SeqCst);
    }
    fn cancelled(&self) -> bool {
        self.done.load(std::sync::atomic::Ordering::SeqCst) >= self.epochs
    }
}

/// Standardized training and test rows, and the targets the loss compares with.
pub struct FitData {
    pub n_f: usize,
    pub x_train: Vec<f32>,
    pub y_train: Vec<f32>,
    pub x_test: Vec<f32>,
    pub y_test: Vec<f32>,
    pub loss: Loss,
    /// Start from these layers, (weights [out][in] row-major, bias) each, instead of
    /// a random initialization (fine-tuning); a checkpoint being resumed wins.
    pub init: Option<Vec<(Vec<f32>, Vec<f32>)>>,
    /// Per-row weights of the loss (training rows, then test rows), or None for equal
    /// weights. Weights that depend on a row's features alone leave the minimizer at
    /// every input E[y | x] (each input's rows share one weight), so they do not bias
    /// the fit; they move where a network of finite size spends its capacity and how
    /// much each row's noise counts in what it pools.
    pub weights: Option<(Vec<f32>, Vec<f32>)>,
}

/// What a fit minimizes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Loss {
    /// Mean squared error between the network's output and y (standardized,
    /// transformed targets).
    Mse,
    /// Relative squared error in linear space: the network's output o stands for
    /// v = exp(o std + mean) - 1, y holds raw values, and the loss is
    /// (v - y)^2 / (sg(v)^2 + eps) with sg the value without its gradient (as neural
    /// radiance caches train). The denominator does not depend on y, so the expected
    /// gradient vanishes where v = E[y]: noisy unbiased targets train an unbiased
    /// model. With `power` p the denominator is (sg(v)^2 + eps)^(p / 2): 2 weighs
    /// every point's relative error alike, 1 weighs absolute errors by 1 / v, nearer
    /// to how an image sums them (bright points count more), still unbiased.
    RelativeL2 { mean: f32, std: f32, eps: f32, power: f32 },
}

impl Loss {
    /// The loss of outputs `out` against targets `y`, each row's term times its weight
    /// in `w` where given (the mean of weighted terms).
    fn eval(&self, out: &Tensor, y: &Tensor, w: Option<&Tensor>) -> candle_core::Result<Tensor> {
        let terms = match *self {
            Loss::Mse if w.is_none() => return candle_nn::loss::mse(out, y),
            Loss::Mse => (out - y)?.sqr()?,
            Loss::RelativeL2 { mean, std, eps, power } => {
                let v = out.affine(std as f64, mean as f64)?.exp()?.affine(1.0, -1.0)?;
                let mut den = v.detach().sqr()?.affine(1.0, eps as f64)?;
                if power != 2.0 {
                    den = den.powf(0.5 * power as f64)?;
                }
                (v - y)?.sqr()?.div(&den)?
            }
        };
        match w {
            Some(w) => terms.mul(w)?.mean_all(),
            None => terms.mean_all(),
        }
    }
}

/// The network and schedule of a fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitSchedule {
    pub hidden: Vec<usize>,
    pub activation: Activation,
    pub epochs: usize,
    pub batch: usize,
    pub optimizer: Optimizer,
    pub lr: f64,
    pub lr_decay: f64,
    pub seed: u64,
    /// The fit returns the mean of the weights after every step of the last this many
    /// epochs (0: the last weights). Adam's steps stay about the learning rate in size
    /// whatever the gradient, so late weights wander around the minimum; their mean
    /// sits nearer its centre.
    #[serde(default)]
    pub average_last: usize,
}

impl FitSchedule {
    /// Checks the network and schedule (with the test split's `test_fraction`); the
    /// error names the flag.
    pub fn validate(&self, test_fraction: f64) -> Result<(), TrainError> {
        let bad = |flag, why: &str| Err(TrainError::Setting { flag, why: why.into() });
        if self.hidden.is_empty() || self.hidden.contains(&0) {
            return bad("--hidden", "needs at least one layer, each at least 1 wide");
        }
        if let Err((flag, why)) =
            crate::nn::optim::check_schedule(self.epochs, self.batch, self.lr, self.lr_decay, test_fraction)
        {
            return bad(flag, why);
        }
        if self.average_last > self.epochs {
            return bad("--average-last", "must be at most --epochs");
        }
        if let Optimizer::Sgd { momentum } = self.optimizer {
            if !(0.0..1.0).contains(&momentum) {
                return bad("--momentum", "must lie in [0, 1)");
            }
        }
        Ok(())
    }
}

/// What a checkpoint must match to be resumed: the run's configuration, its data
/// sources and their size.
pub struct RunIdentity<'a, C> {
    pub config: &'a C,
    pub sources: &'a [String],
    pub points: usize,
}

/// The fitted network and how the fit went.
pub struct Fitted {
    pub net: Network,
    pub history: Vec<EpochRecord>,
    /// Rows trained on per second, over this run's epochs.
    pub samples_per_second: f64,
}

/// Fits an MLP to `data` under `schedule`, writing the checkpoint and the loss history
/// after every epoch; with `resume`, continues from the checkpoint if it was made by
/// the same run (`identity`).
pub fn fit<C: Clone + PartialEq + Serialize + DeserializeOwned>(
    data: &FitData,
    schedule: &FitSchedule,
    paths: &TrainPaths,
    resume: bool,
    identity: RunIdentity<'_, C>,
    observer: &dyn TrainObserver,
) -> Result<Fitted, TrainError> {
    let dev = Device::Cpu;
    let cfg = schedule;
    let checkpoint = paths.checkpoint.as_path();
    let n_f = data.n_f;
    let mut widths = vec![n_f];
    widths.extend(&cfg.hidden);
    widths.push(1);
    let net = Network::glorot(&widths, cfg.activation, cfg.seed, &dev)?;
    if let Some(layers) = &data.init {
        if layers.len() != net.params.len() {
            return Err(TrainError::Data(format!(
                "the starting network has {} layers, this one {}",
                layers.len(),
                net.params.len()
            )));
        }
        for (l, ((w, b), (wv, bv))) in layers.iter().zip(&net.params).enumerate() {
            let (o, i) = wv.as_tensor().dims2()?;
            if w.len() != o * i || b.len() != o {
                return Err(TrainError::Data(format!("the starting network's layer {l} is not {o} x {i}")));
            }
            wv.set(&Tensor::from_slice(w, (o, i), &dev)?)?;
            bv.set(&Tensor::from_slice(b, o, &dev)?)?;
        }
    }
    let vars: Vec<&Var> = net.params.iter().flat_map(|(w, b)| [w, b]).collect();
    let mut opt = OptState::new(&vars)?;
    let mut history: Vec<EpochRecord> = vec![];
    let mut first_epoch = 0;
    // Tail averaging: running sums of the parameters in f64, from this epoch on.
    let average_from = cfg.epochs - cfg.average_last;
    let mut avg_sum: Vec<Tensor> =
        vars.iter().map(|v| v.as_tensor().zeros_like()?.to_dtype(DType::F64)).collect::<candle_core::Result<_>>()?;
    let mut averaged_steps = 0u64;
    let state_path = checkpoint.join("state.json");
    if resume && state_path.exists() {
        let text = std::fs::read_to_string(&state_path)
            .map_err(|e| TrainError::File { path: state_path.clone(), why: e.to_string() })?;
        let st: CheckpointState<C> = serde_json::from_str(&text)
            .map_err(|e| TrainError::File { path: state_path.clone(), why: e.to_string() })?;
        if st.config != *identity.config || st.sources != identity.sources || st.points != identity.points {
            return Err(TrainError::File {
                path: state_path,
                why: "the checkpoint was made with other settings or data; train without --resume to start over".into(),
            });
        }
        let t = candle_core::safetensors::load(checkpoint.join("state.safetensors"), &dev)?;
        for (k, var) in vars.iter().enumerate() {
            let get = |name: String| {
                t.get(&name)
                    .cloned()
                    .ok_or_else(|| TrainError::File { path: checkpoint.to_owned(), why: format!("{name} missing") })
            };
            var.set(&get(format!("param.{k}"))?)?;
            opt.m[k] = get(format!("m.{k}"))?;
            opt.v[k] = get(format!("v.{k}"))?;
            if st.averaged_steps > 0 {
                avg_sum[k] = get(format!("avg.{k}"))?;
            }
        }
        opt.step = st.step;
        averaged_steps = st.averaged_steps;
        first_epoch = st.epoch;
        history = st.history;
    }
    let n_train = data.y_train.len();
    if let Some((wt, we)) = &data.weights {
        if wt.len() != n_train || we.len() != data.y_test.len() {
            return Err(TrainError::Data(format!(
                "{} training and {} test weights for {n_train} and {} rows",
                wt.len(),
                we.len(),
                data.y_test.len()
            )));
        }
    }
    let x_test = Tensor::from_slice(&data.x_test, (data.y_test.len(), n_f), &dev)?;
    let y_test = Tensor::from_slice(&data.y_test, data.y_test.len(), &dev)?;
    let w_test = data.weights.as_ref().map(|(_, we)| Tensor::from_slice(we, we.len(), &dev)).transpose()?;
    let test_mse = |net: &Network| -> candle_core::Result<f64> {
        let p = net.forward(&x_test)?;
        data.loss.eval(&p, &y_test, w_test.as_ref())?.to_scalar::<f32>().map(|v| v as f64)
    };
    let mut order: Vec<usize> = (0..n_train).collect();
    let n_batches = n_train.div_ceil(cfg.batch);
    let mut xb = Vec::with_capacity(cfg.batch * n_f);
    let mut yb = Vec::with_capacity(cfg.batch);
    let mut wb = Vec::with_capacity(cfg.batch);
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
            wb.clear();
            for &i in idx {
                xb.extend_from_slice(&data.x_train[i * n_f..(i + 1) * n_f]);
                yb.push(data.y_train[i]);
                if let Some((wt, _)) = &data.weights {
                    wb.push(wt[i]);
                }
            }
            let x = Tensor::from_slice(&xb, (idx.len(), n_f), &dev)?;
            let y = Tensor::from_slice(&yb, idx.len(), &dev)?;
            let w = data.weights.as_ref().map(|_| Tensor::from_slice(&wb, idx.len(), &dev)).transpose()?;
            let loss = data.loss.eval(&net.forward(&x)?, &y, w.as_ref())?;
            let grads = loss.backward()?;
            opt.apply(cfg.optimizer, lr, &vars, &grads)?;
            if epoch >= average_from {
                for (sum, var) in avg_sum.iter_mut().zip(&vars) {
                    *sum = (&*sum + var.as_tensor().to_dtype(DType::F64)?)?;
                }
                averaged_steps += 1;
            }
            loss_sum += loss.to_scalar::<f32>()? as f64 * idx.len() as f64;
            trained_samples += idx.len() as u64;
            observer.batch(epoch, b + 1, n_batches);
        }
        let averaged_test_mse = match averaged_steps {
            0 => None,
            n => Some(test_mse(&net.with_values(&averages(&avg_sum, n)?)?)?),
        };
        let record = EpochRecord {
            epoch: epoch + 1,
            lr,
            train_mse: loss_sum / n_train as f64,
            test_mse: test_mse(&net)?,
            averaged_test_mse,
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
            if averaged_steps > 0 {
                t.insert(format!("avg.{k}"), avg_sum[k].clone());
            }
        }
        save_tensors(&t, &checkpoint.join("state.safetensors"))?;
        let st = CheckpointState {
            config: identity.config.clone(),
            sources: identity.sources.to_vec(),
            points: identity.points,
            epoch: epoch + 1,
            step: opt.step,
            history: history.clone(),
            averaged_steps,
        };
        write_text(&state_path, &serde_json::to_string_pretty(&st).expect("serializes"))?;
        write_history(paths, &history)?;
    }
    let samples_per_second = trained_samples as f64 / train_started.elapsed().as_secs_f64().max(1e-9);
    let net = match averaged_steps {
        0 => net,
        n => net.with_values(&averages(&avg_sum, n)?)?,
    };
    Ok(Fitted { net, history, samples_per_second })
}

/// The running sums divided by the number of steps summed.
fn averages(sums: &[Tensor], steps: u64) -> candle_core::Result<Vec<Tensor>> {
    sums.iter().map(|s| s.affine(1.0 / steps as f64, 0.0)).collect()
}

/// Writes OUT.loss.csv and OUT.loss.png from the history.
pub fn write_history(paths: &TrainPaths, history: &[EpochRecord]) -> Result<(), TrainError> {
    let mut csv = String::from("epoch,lr,train_mse,test_mse,averaged_test_mse,seconds\n");
    for h in history {
        let avg = h.averaged_test_mse.map(|v| v.to_string()).unwrap_or_default();
        csv += &format!("{},{},{},{},{avg},{:.3}\n", h.epoch, h.lr, h.train_mse, h.test_mse, h.seconds);
    }
    write_text(&paths.csv, &csv)?;
    let points: Vec<(f64, f64, f64)> = history.iter().map(|h| (h.epoch as f64, h.train_mse, h.test_mse)).collect();
    let png = crate::plot::loss_plot_png("", "MSE", [crate::plot::TRAIN_COLOUR, crate::plot::TEST_COLOUR], &points);
    Ok(write_bytes_atomically(&paths.plot, &png)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn data() -> FitData {
        let mut rng = Rng::new(7, 0, 0);
        let n = 64;
        let x: Vec<f32> = (0..n * 3).map(|_| rng.uniform() * 2.0 - 1.0).collect();
        let y: Vec<f32> = x.chunks_exact(3).map(|r| r[0] * r[1] - 0.5 * r[2]).collect();
        FitData {
            n_f: 3,
            x_train: x.clone(),
            y_train: y.clone(),
            x_test: x,
            y_test: y,
            loss: Loss::Mse,
            init: None,
            weights: None,
        }
    }

    fn run(schedule: &FitSchedule, dir: &Path, name: &str, resume: bool, observer: &dyn TrainObserver) -> Fitted {
        let config = schedule.clone();
        let identity = RunIdentity { config: &config, sources: &[], points: 64 };
        fit(&data(), schedule, &TrainPaths::new(&dir.join(name)), resume, identity, observer).unwrap()
    }

    fn values(net: &Network) -> Vec<f32> {
        net.params
            .iter()
            .flat_map(|(w, b)| [w, b])
            .flat_map(|v| v.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap())
            .collect()
    }

    fn schedule(epochs: usize, average_last: usize) -> FitSchedule {
        FitSchedule {
            hidden: vec![8],
            activation: Activation::Tanh,
            epochs,
            batch: 64,
            optimizer: Optimizer::Adam,
            lr: 1e-2,
            lr_decay: 0.9,
            seed: 3,
            average_last,
        }
    }

    /// One step per epoch (the batch holds every row): averaging the last two epochs
    /// returns the mean of the weights after the first and after the second step,
    /// which runs of one and two epochs without averaging give independently.
    #[test]
    fn tail_averaging_returns_the_mean_of_the_last_weights() {
        let dir = tempfile::tempdir().unwrap();
        let one = values(&run(&schedule(1, 0), dir.path(), "one", false, &Quiet).net);
        let two = values(&run(&schedule(2, 0), dir.path(), "two", false, &Quiet).net);
        let fitted = run(&schedule(2, 2), dir.path(), "avg", false, &Quiet);
        let avg = values(&fitted.net);
        assert_ne!(one, two);
        for ((a, b), m) in one.iter().zip(&two).zip(&avg) {
            let want = 0.5 * (a + b);
            assert!((m - want).abs() <= 1e-6 * want.abs().max(1.0), "{m} vs {want}");
        }
        // The averaged loss is recorded in the averaging epochs only.
        let h = &fitted.history;
        assert!(h.iter().all(|r| r.averaged_test_mse.is_some()));
        let last = values(&run(&schedule(2, 1), dir.path(), "last", false, &Quiet).net);
        assert_eq!(last, two, "averaging one step is that step's weights");
        assert!(schedule(2, 3).validate(0.1).unwrap_err().to_string().contains("--average-last"));
    }

    /// Stopped inside the averaging window and resumed: the same averaged weights as
    /// the straight run.
    #[test]
    fn an_averaging_run_resumes_to_the_same_weights() {
        let dir = tempfile::tempdir().unwrap();
        let s = FitSchedule { batch: 16, ..schedule(5, 3) };
        let straight = values(&run(&s, dir.path(), "a", false, &Quiet).net);
        let config = s.clone();
        let identity = RunIdentity { config: &config, sources: &[], points: 64 };
        let stop = StopAfterEpochs::new(3);
        let paths = TrainPaths::new(&dir.path().join("b"));
        assert!(matches!(fit(&data(), &s, &paths, false, identity, &stop), Err(TrainError::Cancelled(3))));
        let resumed = run(&s, dir.path(), "b", true, &Quiet);
        assert_eq!(resumed.history.len(), 5);
        assert_eq!(values(&resumed.net), straight, "resumed averaging differs");
    }

    /// Row weights reach the loss through the shuffle and the batches: at one input
    /// whose rows read 0 (weight 1) and 1 (weight 10) in equal numbers, the fit
    /// settles at their weighted mean, 10 / 11, and without weights at 1 / 2; mismatched
    /// weights are refused.
    #[test]
    fn row_weights_follow_their_rows() {
        let n = 64;
        let x: Vec<f32> = (0..n).map(|i| if i % 2 == 0 { 0.5 } else { -0.5 }).collect();
        let y: Vec<f32> = (0..n).map(|i| ((i / 2) % 2) as f32).collect();
        let w: Vec<f32> = y.iter().map(|v| if *v > 0.5 { 10.0 } else { 1.0 }).collect();
        let s = FitSchedule { hidden: vec![4], epochs: 300, batch: 16, lr: 1e-2, lr_decay: 0.99, ..schedule(1, 0) };
        let fit_with = |weights: Option<(Vec<f32>, Vec<f32>)>, name: &str| {
            let dir = tempfile::tempdir().unwrap();
            let data = FitData {
                n_f: 1,
                x_train: x.clone(),
                y_train: y.clone(),
                x_test: x.clone(),
                y_test: y.clone(),
                loss: Loss::Mse,
                init: None,
                weights,
            };
            let identity = RunIdentity { config: &s, sources: &[], points: n };
            fit(&data, &s, &TrainPaths::new(&dir.path().join(name)), false, identity, &Quiet)
        };
        let at = |net: &Network| {
            let out = net.forward(&Tensor::new(&[[0.5f32], [-0.5]], &Device::Cpu).unwrap()).unwrap();
            out.to_vec1::<f32>().unwrap()
        };
        let weighted = at(&fit_with(Some((w.clone(), w.clone())), "w").unwrap().net);
        let plain = at(&fit_with(None, "p").unwrap().net);
        for (&v, want) in weighted.iter().zip([10.0 / 11.0, 10.0 / 11.0]) {
            assert!((v - want).abs() < 0.03, "weighted fit {weighted:?}, want {want}");
        }
        for &v in &plain {
            assert!((v - 0.5).abs() < 0.03, "plain fit {plain:?}");
        }
        assert!(fit_with(Some((w[1..].to_vec(), w.clone())), "bad").is_err());
    }
}
