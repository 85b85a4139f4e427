//! Training the point-to-point model (`nimbus train p2p`).
//!
//! Inputs: every feature through ln(1 + x) (densities and phi_D span decades), then
//! standardized with the training split's means and deviations. Target: ln of the
//! local-frame transport D^2 T (lengths divided by the emitter-sensor distance D,
//! which makes T scale-free), standardized. The split is by data point, not by row:
//! the rotations of one point share its target and must not straddle train and test.
//! Written like the global model: OUT.safetensors, OUT.json (architecture, feature
//! set, transforms, metrics), OUT.loss.csv and OUT.loss.png, and a checkpoint after
//! every epoch (OUT.checkpoint/) from which `--resume` goes on.

use super::datagen::P2pManifest;
use super::features::P2pFeatures;
use super::model::{ArchDesc, MODEL_FORMAT, P2pSidecar, constant_lr, err};
use super::net::{P2pArch, P2pNetwork};
use crate::nn::optim::OptState;
use candle_core::Device;
use engine::Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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
    /// schedule checks are the global trainer's, [`crate::nn::optim::check_schedule`]).
    pub fn validate(&self) -> Result<(), String> {
        crate::nn::optim::check_schedule(self.epochs, self.batch, self.lr, self.lr_decay, self.test_fraction)
            .map_err(|(flag, why)| format!("{flag} {why}"))
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
        let (fs, f) = crate::dataset::npy::read_f32(&d.join("features.npy")).map_err(err)?;
        let (ts, t) = crate::dataset::npy::read_f32(&d.join("targets.npy")).map_err(err)?;
        let n_f = s.features.len();
        if fs.len() != 2 || fs[1] != n_f || ts != [fs[0], 5] {
            return Err(format!("{}: features {fs:?} / targets {ts:?} do not match the manifest", d.display()));
        }
        for (r, (fr, tr)) in f.chunks_exact(n_f).zip(t.chunks_exact(5)).enumerate() {
            if !(tr[4] > 0.0 && tr[4].is_finite()) || fr.iter().any(|v| !v.is_finite()) {
                continue;
            }
            x.extend(fr.iter().map(|v| crate::nn::fastmath::ln_1p(*v)));
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
        crate::nn::optim::save_safetensors(&tensors, &state).map_err(err)?;
        let st = Checkpoint { key: key.clone(), step: opt.step, history: history.clone() };
        crate::dataset::npy::write_bytes_atomically(
            &ckpt.join("state.json"),
            serde_json::to_string(&st).unwrap().as_bytes(),
        )
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
    crate::nn::optim::save_safetensors(&net.named(), &weights).map_err(err)?;
    let text = serde_json::to_string_pretty(&sidecar).expect("sidecar serializes");
    crate::dataset::npy::write_bytes_atomically(&with(".json"), text.as_bytes()).map_err(err)?;
    crate::dataset::npy::write_bytes_atomically(&with(".loss.csv"), csv.as_bytes()).map_err(err)?;
    let png = crate::plot::loss_plot_png(
        "point-to-point model: loss (standardized ln T)",
        "mse",
        [crate::plot::PALETTE[0], crate::plot::PALETTE[1]],
        &history,
    );
    crate::dataset::npy::write_bytes_atomically(&with(".loss.png"), &png).map_err(err)?;
    Ok(sidecar)
}
