//! `nimbus train global|p2p|cloud`: training with candle, a progress bar, Ctrl-C after the
//! current epoch, checkpoints and `--resume`.

use super::common::{RunArgs, cancel_on_ctrl_c, code_version, init_threads, progress_bar};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use indicatif::ProgressBar;
use models::global::train::{EpochRecord, TrainConfig, TrainData, TrainObserver};
use models::nn::Activation;
use models::nn::Optimizer;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

#[derive(Subcommand, Debug)]
pub enum TrainCommand {
    /// Train the global model (thesis chapter 5) on data sets from `nimbus datagen global`.
    Global(TrainGlobalArgs),
    /// Train the point-to-point model (thesis chapter 6) on data sets from
    /// `nimbus datagen p2p`.
    P2p(TrainP2pArgs),
    /// Train the cloud-aware model on data sets from `nimbus datagen cloud`.
    Cloud(TrainCloudArgs),
}

#[derive(Args, Debug)]
pub struct TrainCloudArgs {
    /// Data-set directories from `nimbus datagen cloud`.
    #[arg(required = true)]
    pub data: Vec<PathBuf>,
    /// A data set made with `nimbus datagen cloud --held-out`, reported on (never
    /// trained on).
    #[arg(long)]
    pub held_out: Option<PathBuf>,
    /// Distil: train on the mean of these cloud-aware models' predictions at the data's
    /// features instead of the path-traced targets (comma separated .safetensors; the
    /// test and held-out reports keep the path-traced targets).
    #[arg(long, value_delimiter = ',')]
    pub teacher: Vec<PathBuf>,
    /// Fine-tune: start from this cloud-aware model (.safetensors) and keep its
    /// standardization, instead of random weights; its network must be this run's.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Output prefix: PREFIX.safetensors, .json, .loss.csv, .loss.png, .checkpoint/.
    #[arg(long)]
    pub out: PathBuf,
    /// Hidden layers' widths, comma separated (default: the shipped model's, those of
    /// `CloudTrainConfig::default`).
    #[arg(long, value_delimiter = ',')]
    pub hidden: Option<Vec<usize>>,
    /// relu, tanh or silu.
    #[arg(long, default_value = "relu")]
    pub activation: String,
    #[arg(long, default_value_t = 20)]
    pub epochs: usize,
    #[arg(long, default_value_t = 512)]
    pub batch: usize,
    #[arg(long, default_value_t = 2e-3)]
    pub lr: f64,
    #[arg(long, default_value_t = 0.85)]
    pub lr_decay: f64,
    /// Fraction of the clouds held out as the test split.
    #[arg(long, default_value_t = 0.1)]
    pub test_fraction: f64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// mean (the mean of each point's paths) or one-path (the first path alone).
    #[arg(long, default_value = "mean")]
    pub target: String,
    /// eps of the relative loss, in units of (4 pi L_ms)^2.
    #[arg(long, default_value_t = 2.5e-3)]
    pub eps: f32,
    /// Train on at most this many points (0: all).
    #[arg(long, default_value_t = 0)]
    pub max_points: usize,
    /// Return the mean of the weights over every step of the last N epochs (0: the
    /// last weights).
    #[arg(long, default_value_t = 0)]
    pub average_last: usize,
    /// Power of the relative loss's denominator: 2 weighs relative errors alike, 1
    /// absolute errors over the value (bright points count more, as in an image).
    #[arg(long, default_value_t = 1.0)]
    pub loss_power: f32,
    /// After training, refit the output layer on the whole training split with this
    /// many Gauss-Newton iterations (0: none): the exact gradient, unbiased where
    /// Adam's steps cut the heavy tails of noisy targets.
    #[arg(long, default_value_t = 10)]
    pub refit_output: usize,
    /// Derived features the network reads beside the stored ones (computed from them on
    /// loading): coupling (each phase term times the sun's transmittance at the point,
    /// at three attenuations) or none.
    #[arg(long, default_value = "coupling")]
    pub derived: String,
    /// Weigh each row's loss by 1 / (its target's relative noise variance, predicted
    /// from its features by a ridge regression fitted to the rows' measured noise,
    /// plus FLOOR): the noisiest targets then count less in what the network pools. A
    /// weight that depends on the features alone leaves the fit unbiased. FLOOR is the
    /// relative variance no number of paths removes (about the model's own squared
    /// error; 0.003 for a 5 % error). Measured in docs/cloud-model.md: lower held-out
    /// per-cloud bias, higher point errors in dense toplit views; not the shipped recipe.
    #[arg(long, value_name = "FLOOR")]
    pub noise_weights: Option<f32>,
    /// Continue from PREFIX.checkpoint/ (same settings and data).
    #[arg(long)]
    pub resume: bool,
    #[command(flatten)]
    pub run: RunArgs,
}

fn train_cloud(args: TrainCloudArgs) -> Result<()> {
    use models::cloud::features::DerivedInputs;
    use models::cloud::train::{BiasReport, CloudTrainConfig, CloudTrainData, TargetColumn};
    let cfg = CloudTrainConfig {
        schedule: models::nn::fit::FitSchedule {
            hidden: args.hidden.clone().unwrap_or_else(|| CloudTrainConfig::default().schedule.hidden),
            activation: Activation::parse(&args.activation)
                .with_context(|| format!("--activation: unknown {:?} (relu, tanh, silu)", args.activation))?,
            epochs: args.epochs,
            batch: args.batch,
            optimizer: Optimizer::Adam,
            lr: args.lr,
            lr_decay: args.lr_decay,
            seed: args.seed,
            average_last: args.average_last,
        },
        test_fraction: args.test_fraction,
        target: TargetColumn::parse(&args.target)
            .with_context(|| format!("--target {:?}: choose mean or one-path", args.target))?,
        eps: args.eps,
        max_points: args.max_points,
        refit_output: args.refit_output,
        loss_power: args.loss_power,
        derived: DerivedInputs::parse(&args.derived).with_context(|| {
            format!("--derived {:?}: choose one of {}", args.derived, DerivedInputs::NAMES.join(", "))
        })?,
        noise_weights: args.noise_weights,
    };
    cfg.validate()?;
    let threads = init_threads(args.run.threads)?;
    let t = std::time::Instant::now();
    let mut data = CloudTrainData::load(&args.data)?;
    if !args.teacher.is_empty() {
        if cfg.target != TargetColumn::Mean {
            bail!("--teacher replaces the path-traced targets: --target {} does not apply", args.target);
        }
        let mut teachers = vec![];
        let mut fingerprints = vec![];
        for p in &args.teacher {
            // Each file read once: the model and its fingerprint from the same bytes.
            let named = || format!("--teacher {}", p.display());
            let (bytes, sidecar) = models::global::model::read_model_files(p).with_context(named)?;
            teachers.push(models::cloud::model::CloudModel::from_bytes(&bytes, &sidecar, p).with_context(named)?);
            fingerprints.push(format!("{:016x}", models::fingerprint::fingerprint(&[&bytes, sidecar.as_bytes()])));
        }
        let t = std::time::Instant::now();
        data.distill_from(&teachers.iter().collect::<Vec<_>>(), fingerprints)?;
        eprintln!(
            "targets: the mean of {} teachers' predictions, in {:.1} s",
            teachers.len(),
            t.elapsed().as_secs_f64()
        );
    }
    if let Some(p) = &args.init {
        let named = || format!("--init {}", p.display());
        let (bytes, sidecar) = models::global::model::read_model_files(p).with_context(named)?;
        let model = models::cloud::model::CloudModel::from_bytes(&bytes, &sidecar, p).with_context(named)?;
        let fingerprint = format!("{:016x}", models::fingerprint::fingerprint(&[&bytes, sidecar.as_bytes()]));
        data.start_from(model, fingerprint);
    }
    let held_out = match &args.held_out {
        Some(d) => {
            let ds = models::cloud::datagen::CloudDataset::load(d)?;
            if !ds.manifest.settings.held_out {
                bail!(
                    "--held-out {}: not a held-out data set (make one with nimbus datagen cloud --held-out)",
                    d.display()
                );
            }
            Some(ds)
        }
        None => None,
    };
    eprintln!(
        "{} points from {} data set(s), loaded in {:.1} s; {threads} threads",
        data.len(),
        args.data.len(),
        t.elapsed().as_secs_f64()
    );
    let bar = progress_bar(1, "batches", args.run.quiet);
    let cancel = cancel_on_ctrl_c("stopping: the last finished epoch is checkpointed; continue with --resume");
    let command: Vec<String> = std::env::args().collect();
    let observer = BarObserver { bar, cancel };
    let (_, report) = models::cloud::train::train(
        data,
        held_out.as_ref(),
        &cfg,
        &args.out,
        args.resume,
        &command.join(" "),
        &code_version(),
        &observer,
    )?;
    observer.bar.finish_and_clear();
    let line = |what: &str, b: &BiasReport| {
        println!(
            "{what}: {} points of {} clouds, relative bias {:+.2} % (+- {:.2} %), per cloud |bias| median {:.2} %, p90 {:.2} %",
            b.points,
            b.clouds,
            100.0 * b.bias,
            100.0 * b.bias_std_error,
            100.0 * b.cloud_abs_bias_median,
            100.0 * b.cloud_abs_bias_p90
        )
    };
    println!(
        "trained on {} points in {:.1} s ({:.0} samples/s)",
        report.train_points, report.seconds, report.samples_per_second
    );
    if let Some(r) = &report.noise_weights {
        println!(
            "noise weights: model fitted on {} rows (R^2 {:.2} of ln variance), weights p10 / p50 / p90 {:.2} / {:.2} / {:.2}, pooled gain {:.2}x",
            r.fit_rows, r.r_squared, r.weight_quantiles[0], r.weight_quantiles[1], r.weight_quantiles[2], r.pooled_gain
        );
    }
    if let Some(r) = &report.refit {
        println!(
            "output layer refitted in {} iterations: training loss {:.4} -> {:.4}, training bias {:+.2} % -> {:+.2} %",
            r.iterations,
            r.loss_before,
            r.loss_after,
            100.0 * r.bias_before,
            100.0 * r.bias_after
        );
    }
    line("test clouds", &report.test);
    if let Some(h) = &report.held_out {
        line("held-out clouds", h);
    }
    println!("wrote {}.safetensors, .json, .loss.csv, .loss.png", args.out.display());
    Ok(())
}

#[derive(Args, Debug)]
pub struct TrainP2pArgs {
    /// Data-set directories (one albedo, g and feature set).
    #[arg(required = true)]
    pub data: Vec<PathBuf>,
    /// Output path without extension: OUT.safetensors, .json, .loss.csv, .loss.png.
    #[arg(long)]
    pub out: PathBuf,
    /// residual (thesis figure 6.4) or mlp.
    #[arg(long, default_value = "residual")]
    pub arch: String,
    /// Units per layer of the residual blocks.
    #[arg(long, default_value_t = 200)]
    pub width: usize,
    /// Layers per residual block.
    #[arg(long, default_value_t = 3)]
    pub layers: usize,
    /// Hidden widths of the MLP, e.g. 200,200.
    #[arg(long, value_delimiter = ',', default_value = "200,200")]
    pub hidden: Vec<usize>,
    #[arg(long, default_value_t = 20)]
    pub epochs: usize,
    #[arg(long, default_value_t = 250)]
    pub batch: usize,
    /// Learning rate of the first epoch.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Learning-rate factor per epoch (1: constant, as the shipped models were trained).
    #[arg(long, default_value_t = 1.0)]
    pub lr_decay: f64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Go on from OUT.checkpoint (same settings and data).
    #[arg(long)]
    pub resume: bool,
    #[command(flatten)]
    pub run: RunArgs,
}

fn train_p2p(args: TrainP2pArgs) -> Result<()> {
    use models::p2p::net::P2pArch;
    let arch = match args.arch.as_str() {
        "residual" if args.width > 0 && args.layers > 0 => P2pArch::Residual { width: args.width, layers: args.layers },
        "mlp" if args.hidden.iter().all(|h| *h > 0) => P2pArch::Mlp { hidden: args.hidden.clone() },
        other => bail!(
            "--arch {other:?} with these sizes is not valid: residual (--width, --layers > 0) or mlp (--hidden > 0)"
        ),
    };
    let cfg = models::p2p::train::P2pTrainConfig {
        arch,
        epochs: args.epochs,
        batch: args.batch,
        lr: args.lr,
        lr_decay: args.lr_decay,
        seed: args.seed,
        ..Default::default()
    };
    cfg.validate().map_err(anyhow::Error::msg)?;
    init_threads(args.run.threads)?;
    let t = std::time::Instant::now();
    let bar = progress_bar(args.epochs as u64, "epochs", args.run.quiet);
    let cancel = cancel_on_ctrl_c("stopping after this epoch; rerun with --resume to go on");
    let side = models::p2p::train::train(&args.data, &cfg, &args.out, args.resume, &cancel, &|e, test| {
        bar.set_position(e as u64);
        bar.set_message(format!("test mse {test:.4}"));
    })
    .map_err(anyhow::Error::msg)?;
    bar.finish_and_clear();
    println!(
        "trained in {:.1} s: test mse {:.4} (standardized ln T), relative error of T median {:.1} %, p90 {:.1} %; wrote {}.safetensors",
        t.elapsed().as_secs_f64(),
        side.test_mse,
        100.0 * side.test_rel_error_median,
        100.0 * side.test_rel_error_p90,
        args.out.display()
    );
    Ok(())
}

#[derive(Args, Debug)]
pub struct TrainGlobalArgs {
    /// Data-set directories (all of one feature layout).
    #[arg(required = true)]
    pub data: Vec<PathBuf>,
    /// Output prefix: writes PREFIX.safetensors, PREFIX.json (sidecar), PREFIX.loss.csv,
    /// PREFIX.loss.png and the checkpoint PREFIX.checkpoint/.
    #[arg(long)]
    pub out: PathBuf,
    /// Hidden layer widths.
    #[arg(long, value_delimiter = ',', default_value = "200,100")]
    pub hidden: Vec<usize>,
    /// relu, tanh or silu.
    #[arg(long, default_value = "relu")]
    pub activation: String,
    #[arg(long, default_value_t = 10)]
    pub epochs: usize,
    #[arg(long, default_value_t = 1000)]
    pub batch: usize,
    /// adam or sgd (with --momentum).
    #[arg(long, default_value = "adam")]
    pub optimizer: String,
    #[arg(long, default_value_t = 0.9)]
    pub momentum: f64,
    /// Learning rate of the first epoch.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Learning-rate factor per epoch.
    #[arg(long, default_value_t = 0.8)]
    pub lr_decay: f64,
    /// Held-out test fraction.
    #[arg(long, default_value_t = 0.2)]
    pub test_fraction: f64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// What the network learns: total (all of L_i, the thesis) or multiple (multiple
    /// scattering only; the renderer adds single scattering by NEE).
    #[arg(long, default_value = "total")]
    pub target: String,
    /// Continue from PREFIX.checkpoint/ (same settings and data).
    #[arg(long)]
    pub resume: bool,
    #[command(flatten)]
    pub run: RunArgs,
}

impl TrainGlobalArgs {
    pub fn config(&self) -> Result<TrainConfig> {
        let activation = Activation::parse(&self.activation)
            .with_context(|| format!("--activation: unknown {:?} (relu, tanh, silu)", self.activation))?;
        let optimizer = match self.optimizer.as_str() {
            "adam" => Optimizer::Adam,
            "sgd" => Optimizer::Sgd { momentum: self.momentum },
            o => bail!("--optimizer: unknown {o:?} (adam, sgd)"),
        };
        let cfg = TrainConfig {
            hidden: self.hidden.clone(),
            activation,
            epochs: self.epochs,
            batch: self.batch,
            optimizer,
            lr: self.lr,
            lr_decay: self.lr_decay,
            test_fraction: self.test_fraction,
            seed: self.seed,
            target: models::global::model::TargetKind::parse(&self.target)
                .with_context(|| format!("--target {}: choose total or multiple", self.target))?,
        };
        cfg.validate()?;
        Ok(cfg)
    }
}

struct BarObserver {
    bar: ProgressBar,
    cancel: Arc<AtomicBool>,
}

impl TrainObserver for BarObserver {
    fn batch(&self, epoch: usize, done: usize, total: usize) {
        if done == 1 {
            self.bar.set_length(total as u64);
            self.bar.set_message(format!("epoch {}", epoch + 1));
        }
        self.bar.set_position(done as u64);
    }

    fn epoch(&self, r: &EpochRecord) {
        let averaged = r.averaged_test_mse.map(|v| format!("  averaged {v:.5}")).unwrap_or_default();
        self.bar.println(format!(
            "epoch {:>3}  lr {:.2e}  train MSE {:.5}  test MSE {:.5}{averaged}  ({:.1} s)",
            r.epoch, r.lr, r.train_mse, r.test_mse, r.seconds
        ));
    }

    fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }
}

pub fn train(cmd: TrainCommand) -> Result<()> {
    let args = match cmd {
        TrainCommand::Global(args) => args,
        TrainCommand::P2p(args) => return train_p2p(args),
        TrainCommand::Cloud(args) => return train_cloud(args),
    };
    let cfg = args.config()?;
    let threads = init_threads(args.run.threads)?;
    let t = std::time::Instant::now();
    let data = TrainData::load(&args.data)?;
    eprintln!(
        "{} points ({} features) from {} data set(s), loaded in {:.1} s; {threads} threads",
        data.len(),
        data.n_features(),
        args.data.len(),
        t.elapsed().as_secs_f64()
    );
    let bar = progress_bar(1, "batches", args.run.quiet);
    let cancel = cancel_on_ctrl_c("stopping: the last finished epoch is checkpointed; continue with --resume");
    let command: Vec<String> = std::env::args().collect();
    let observer = BarObserver { bar, cancel };
    let (_, report) = models::global::train::train(
        &data,
        &cfg,
        &args.out,
        args.resume,
        &command.join(" "),
        &code_version(),
        &observer,
    )?;
    observer.bar.finish_and_clear();
    println!(
        "trained on {} points, tested on {} ({} dropped as non-finite) in {:.1} s ({:.0} samples/s)",
        report.train_points, report.test_points, report.dropped_points, report.seconds, report.samples_per_second
    );
    println!(
        "test MSE (transformed, standardized) {:.5} (target variance {:.3}); relative error of L_i: median {:.2} %, 90th percentile {:.2} %",
        report.test_mse,
        report.test_target_variance,
        100.0 * report.rel_error_median,
        100.0 * report.rel_error_p90
    );
    println!("wrote {}.safetensors, .json, .loss.csv, .loss.png", args.out.display());
    Ok(())
}
