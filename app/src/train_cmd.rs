//! `nimbus train global` and `nimbus bench predict`.

use crate::cli::{init_threads, progress_bar};
use crate::datagen_cmd::code_version;
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use engine::{InScatterPredictor, Rng};
use indicatif::ProgressBar;
use models::global::{Activation, GlobalModel};
use models::train::{EpochRecord, Optimizer, TrainConfig, TrainData, TrainObserver};
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
    #[arg(long)]
    pub threads: Option<usize>,
    /// Go on from OUT.checkpoint (same settings and data).
    #[arg(long)]
    pub resume: bool,
}

fn train_p2p(args: TrainP2pArgs) -> Result<()> {
    use models::p2p_net::P2pArch;
    let arch = match args.arch.as_str() {
        "residual" if args.width > 0 && args.layers > 0 => P2pArch::Residual { width: args.width, layers: args.layers },
        "mlp" if args.hidden.iter().all(|h| *h > 0) => P2pArch::Mlp { hidden: args.hidden.clone() },
        other => bail!(
            "--arch {other:?} with these sizes is not valid: residual (--width, --layers > 0) or mlp (--hidden > 0)"
        ),
    };
    let cfg = models::p2p_train::P2pTrainConfig {
        arch,
        epochs: args.epochs,
        batch: args.batch,
        lr: args.lr,
        lr_decay: args.lr_decay,
        seed: args.seed,
        ..Default::default()
    };
    cfg.validate().map_err(anyhow::Error::msg)?;
    init_threads(args.threads)?;
    let t = std::time::Instant::now();
    let bar = progress_bar(args.epochs as u64, "epochs", false);
    let cancel = Arc::new(AtomicBool::new(false));
    let flag = cancel.clone();
    let _ = ctrlc::set_handler(move || {
        eprintln!("\nstopping after this epoch; rerun with --resume to go on");
        flag.store(true, Ordering::Relaxed);
    });
    let side = models::p2p_train::train(&args.data, &cfg, &args.out, args.resume, &cancel, &|e, test| {
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
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long)]
    pub quiet: bool,
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
            target: models::global::TargetKind::parse(&self.target)
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
    let threads = init_threads(args.threads)?;
    let t = std::time::Instant::now();
    let data = TrainData::load(&args.data)?;
    eprintln!(
        "{} points ({} features) from {} data set(s), loaded in {:.1} s; {threads} threads",
        data.len(),
        data.n_features(),
        args.data.len(),
        t.elapsed().as_secs_f64()
    );
    let bar = progress_bar(1, "batches", args.quiet);
    let cancel = Arc::new(AtomicBool::new(false));
    let c = cancel.clone();
    let _ = ctrlc::set_handler(move || {
        eprintln!("\nstopping: the last finished epoch is checkpointed; continue with --resume");
        c.store(true, Ordering::Relaxed);
    });
    let command: Vec<String> = std::env::args().collect();
    let observer = BarObserver { bar, cancel };
    let (_, report) =
        models::train::train(&data, &cfg, &args.out, args.resume, &command.join(" "), &code_version(), &observer)?;
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

#[derive(Args, Debug)]
pub struct BenchPredictArgs {
    /// Model to time (default: the shipped one; a Glorot-initialized [200, 100] network
    /// with n_D = 64 if it cannot be loaded).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Predictions per measurement.
    #[arg(long, default_value_t = 200_000)]
    pub n: usize,
    /// Density scale of the 128^3 benchmark cloud (scene-a).
    #[arg(long, default_value_t = 40.0)]
    pub rho: f32,
}

/// The model the renderer loads by default.
pub fn default_model_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../assets/models/global.safetensors")
}

/// Nanoseconds per prediction (network alone, features + network on a 128^3 cloud)
/// against the cost of a path-traced scattering event in the same cloud; one thread.
pub fn bench_predict(args: BenchPredictArgs) -> Result<()> {
    let path = args.model.clone().unwrap_or_else(default_model_path);
    let model = match GlobalModel::load(&path) {
        Ok(m) => m,
        Err(e) if args.model.is_none() => {
            eprintln!("note: {e}; timing an untrained [200, 100] network instead");
            untrained_model()?
        }
        Err(e) => return Err(e.into()),
    };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    pool.install(|| bench_predict_inner(&model, &args))
}

fn untrained_model() -> Result<GlobalModel> {
    let layout = models::global::FeatureLayout::current(Default::default(), 64);
    let net = models::train::Network::glorot(&[68, 200, 100, 1], Activation::Relu, 1, &candle_core::Device::Cpu)?;
    let sidecar = models::global::Sidecar {
        format: models::global::MODEL_FORMAT.into(),
        format_version: models::global::MODEL_FORMAT_VERSION,
        features: layout,
        standardization: models::global::Standardization {
            feature_mean: vec![0.0; 68],
            feature_std: vec![1.0; 68],
            target: models::global::TARGET_TRANSFORM.into(),
            target_mean: 0.0,
            target_std: 1.0,
        },
        hidden: vec![200, 100],
        activation: Activation::Relu,
        training: serde_json::Value::Null,
    };
    Ok(GlobalModel::new(sidecar, net.to_mlp()?))
}

fn bench_predict_inner(model: &GlobalModel, args: &BenchPredictArgs) -> Result<()> {
    let n = args.n.max(1000);
    let n_f = model.feature_extractor().len();
    let mut rng = Rng::new(1, 2, 3);
    let xs: Vec<f32> = (0..1024 * n_f).map(|_| 2.0 * rng.uniform() - 1.0).collect();
    let mut scratch = model.mlp.scratch();
    // Network alone.
    let t = std::time::Instant::now();
    let mut sink = 0.0f32;
    for i in 0..n {
        sink += model.mlp.forward(&xs[(i % 1024) * n_f..(i % 1024 + 1) * n_f], &mut scratch);
    }
    let net_ns = t.elapsed().as_secs_f64() * 1e9 / n as f64;
    // Batched entry point.
    let mut out = vec![0.0f32; 1024];
    let t = std::time::Instant::now();
    for _ in 0..n / 1024 {
        model.mlp.forward_batch(&xs, &mut out, &mut scratch);
        sink += out[7];
    }
    let batch_ns = t.elapsed().as_secs_f64() * 1e9 / (n / 1024 * 1024) as f64;
    // Features + network at points inside the cloud, against path-traced scattering
    // events (free flight by delta tracking + a sun shadow ray by ratio tracking, the
    // work of one vertex in the integrator).
    let params = modeler::preset("scene-a").context("scene-a preset")?;
    let grid = modeler::build_grid(&params, 128)?;
    let medium = engine::Medium::new(
        std::sync::Arc::new(grid),
        args.rho,
        1.0,
        engine::PhaseFunction::HenyeyGreenstein { g: 0.85 },
    )?;
    let sun = engine::Sun::new(glam::Vec3::new(0.0, -1.0, 0.0), glam::Vec3::ONE, 0.0)?;
    let mut points = vec![];
    let b = medium.bounds();
    while points.len() < 4096 {
        let p = b.min + (b.max - b.min) * glam::Vec3::new(rng.uniform(), rng.uniform(), rng.uniform());
        if medium.grid().lookup(p) > 0.05 {
            points.push((p, engine::sampling::sample_uniform_sphere(rng.uniform2())));
        }
    }
    let m = (n / 20).max(1000);
    let t = std::time::Instant::now();
    for i in 0..m {
        let (p, w) = points[i % points.len()];
        sink += model.predict(&medium, &sun, p, w);
    }
    let full_ns = t.elapsed().as_secs_f64() * 1e9 / m as f64;
    // The renderer's path: features from the depth field (built once per cloud and sun).
    let t = std::time::Instant::now();
    let bound = models::global::BoundGlobalModel::new(
        Arc::new(model.clone()),
        &medium,
        &sun,
        models::depth_field::DEFAULT_MAX_NODES,
    );
    let field_secs = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    for i in 0..n / 4 {
        let (p, w) = points[i % points.len()];
        sink += bound.predict(&medium, &sun, p, w);
    }
    let bound_ns = t.elapsed().as_secs_f64() * 1e9 / (n / 4) as f64;
    let t = std::time::Instant::now();
    let phase = medium.phase();
    for i in 0..m {
        let (p, w) = points[i % points.len()];
        let wi = phase.sample(w, rng.uniform2()).wi;
        let tmax = medium.exit_distance(p, wi);
        if let engine::medium::FreeFlight::Collision { t } = medium.sample_free_flight(p, wi, tmax, &mut rng) {
            sink += t;
        }
        let to_sun = -sun.direction();
        sink += medium.transmittance_ratio(p, to_sun, medium.exit_distance(p, to_sun), &mut rng);
    }
    let event_ns = t.elapsed().as_secs_f64() * 1e9 / m as f64;
    std::hint::black_box(sink);
    let features_ns = full_ns - net_ns;
    let field_features_ns = bound_ns - net_ns;
    println!("# nimbus bench predict: one thread, {} ({} features)", model.name(), n_f);
    println!("| measurement | ns per prediction | goal |");
    println!("|---|---|---|");
    println!("| network alone, one at a time | {net_ns:.0} | <= 3000 |");
    println!("| network alone, batched (1024) | {batch_ns:.0} | |");
    println!("| features + network, scene-a 128^3, rho {} | {full_ns:.0} | |", args.rho);
    println!(
        "| features alone, ray marched | {features_ns:.0} = {:.1} path-traced scattering events ({event_ns:.0} ns each) | |",
        features_ns / event_ns
    );
    println!("| features + network, depth field (the renderer's path) | {bound_ns:.0} | |");
    println!(
        "| features alone, depth field | {field_features_ns:.0} = {:.2} path-traced scattering events | <= 5 events |",
        field_features_ns / event_ns
    );
    let f = bound.field();
    println!(
        "| depth field build ({}^3 nodes x {} directions, {:.0} MiB, one thread) | {:.2} s once per cloud and sun | |",
        f.nodes().x,
        f.n_dirs(),
        f.memory_bytes() as f64 / 1048576.0,
        field_secs
    );
    Ok(())
}

#[derive(Args, Debug)]
pub struct BenchPredictP2pArgs {
    /// Predictions per measurement.
    #[arg(long, default_value_t = 2_000)]
    pub n: usize,
    /// Grid resolution of the benchmark cloud (scene-a).
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
}

/// Microseconds per point-to-point prediction on one thread: the density pyramid's
/// build, the 351 density features and phi_D, and the thesis's deep residual network
/// (Glorot-initialized: the cost does not depend on the weights) single and batched,
/// with the MLP baseline beside it.
pub fn bench_predict_p2p(args: BenchPredictP2pArgs) -> Result<()> {
    use models::density_features::{DensityPyramid, LocalFrame, P2pFeatures};
    use models::p2p_net::{P2pArch, P2pNetwork};
    if args.n == 0 {
        bail!("--n must be at least 1");
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    pool.install(|| -> Result<()> {
        let params = modeler::preset("scene-a").context("scene-a preset")?;
        let grid = modeler::build_grid(&params, args.resolution)?;
        let spec = P2pFeatures::default();
        let t = std::time::Instant::now();
        // What `pyramid_for` builds (unit distance), kept at 32 bits as the baseline.
        let full = DensityPyramid::new(&grid, spec.max_local_std());
        let pyramid = full.quantized();
        let build = t.elapsed().as_secs_f64();
        println!("# nimbus bench predict-p2p: one thread, scene-a {}^3", args.resolution);
        println!(
            "density pyramid: {} levels, {:.1} MiB with 16-bit samples ({:.1} MiB at 32 bits), built in {:.2} s",
            pyramid.levels(),
            pyramid.bytes() as f64 / (1 << 20) as f64,
            full.bytes() as f64 / (1 << 20) as f64,
            build
        );
        let medium = engine::Medium::new(Arc::new(grid), 25.0, 0.99, engine::PhaseFunction::Isotropic)?;
        let mut rng = Rng::new(1, 0, 0);
        let mut frames = vec![];
        while frames.len() < args.n {
            let a = engine::p2p::sample_query_end(&medium, 2, &mut rng);
            let b = engine::p2p::sample_query_end(&medium, 2, &mut rng);
            if let (Some((e, _)), Some((s, _))) = (a, b) {
                if let Some(f) = LocalFrame::new(e, s, 6.283 * rng.uniform()) {
                    frames.push(f);
                }
            }
        }
        let mut x = vec![0.0f32; args.n * spec.len()];
        // Both sample widths, alternating over three rounds (the best round of each),
        // so that both see the same machine.
        let (mut us16, mut us32) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..3 {
            for (p, best) in [(&full, &mut us32), (&pyramid, &mut us16)] {
                let t = std::time::Instant::now();
                for (f, row) in frames.iter().zip(x.chunks_mut(spec.len())) {
                    spec.write(p, 25.0, 0.99, f, row);
                }
                *best = best.min(t.elapsed().as_secs_f64() * 1e6 / args.n as f64);
            }
        }
        // `x` now holds the 16-bit features (the renderer's).
        let features_us = us16;
        println!(
            "features (351 densities + phi_D): {us16:.2} us per query with 16-bit samples, {us32:.2} us at 32 bits \
             ({:.2}x faster)",
            us32 / us16
        );
        println!("| network | parameters | single (us) | batched (us per prediction) | features + batched (us) |");
        println!("|---|---|---|---|---|");
        for (name, arch) in [
            ("deep residual, 9 blocks of 3 x 200 (thesis)", P2pArch::default()),
            ("deep residual, 9 blocks of 3 x 144", P2pArch::Residual { width: 144, layers: 3 }),
            ("deep residual, 9 blocks of 2 x 128", P2pArch::Residual { width: 128, layers: 2 }),
            ("MLP 2 x 200 (baseline)", P2pArch::Mlp { hidden: vec![200, 200] }),
        ] {
            let net = P2pNetwork::new(&spec, arch, 1, &candle_core::Device::Cpu)?;
            let eval = net.evaluator()?;
            let mut s = eval.scratch();
            let t = std::time::Instant::now();
            let mut sink = 0.0;
            for row in x.chunks(spec.len()) {
                sink += eval.forward(row, &mut s);
            }
            let single = t.elapsed().as_secs_f64() * 1e6 / args.n as f64;
            let mut out = vec![0.0; args.n];
            let mut bs = Default::default();
            let t = std::time::Instant::now();
            eval.forward_batch(&x, &mut out, &mut bs);
            let batched = t.elapsed().as_secs_f64() * 1e6 / args.n as f64;
            std::hint::black_box(sink + out[0]);
            println!("| {name} | {} | {single:.1} | {batched:.1} | {:.1} |", net.parameters(), features_us + batched);
        }
        Ok(())
    })
}
