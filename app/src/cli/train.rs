//! `nimbus train global|p2p`: training with candle, a progress bar, Ctrl-C after the
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
        self.bar.println(format!(
            "epoch {:>3}  lr {:.2e}  train MSE {:.5}  test MSE {:.5}  ({:.1} s)",
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
