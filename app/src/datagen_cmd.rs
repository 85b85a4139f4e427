//! `nimbus datagen global|merge` and `nimbus bench datagen`.

use crate::cli::{init_threads, progress_bar};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use models::datagen::{self, GlobalSpec, ShapeKind, Shard, parse_range};
use models::directions::DirectionSetKind;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Nimbus version and the commit it was built from.
pub fn code_version() -> String {
    format!("nimbus {} ({})", env!("CARGO_PKG_VERSION"), option_env!("NIMBUS_GIT_COMMIT").unwrap_or("unknown commit"))
}

#[derive(Subcommand, Debug)]
pub enum DatagenCommand {
    /// Ground truth for the global model: random homogeneous convex media lit by a unit
    /// directional light along (0, 0, -1); features + in-scattered radiance per point.
    Global(GlobalArgs),
    /// Join the shard directories of one data set into a complete one.
    Merge(MergeArgs),
    /// Ground truth for the point-to-point model (thesis 6.3), resumable and shardable.
    P2p(P2pArgs),
}

#[derive(Args, Debug)]
pub struct GlobalArgs {
    /// Number of data points.
    #[arg(long, default_value_t = 10_000)]
    pub points: u64,
    /// Extinction sigma_S range, MIN..MAX (or one value).
    #[arg(long, default_value = "1..100")]
    pub sigma: String,
    /// Scattering albedo range.
    #[arg(long, default_value = "1")]
    pub albedo: String,
    /// Henyey-Greenstein g range, inside (-1, 1).
    #[arg(long, default_value = "0..0.9")]
    pub g: String,
    /// Shapes, comma separated: sphere, box, ellipsoid.
    #[arg(long, default_value = "sphere,box,ellipsoid")]
    pub shapes: String,
    /// Keep the shapes axis-aligned (no random rotation).
    #[arg(long)]
    pub no_rotate: bool,
    /// Scale factor range (per axis for boxes and ellipsoids); 1 keeps unit shapes.
    #[arg(long, default_value = "1")]
    pub scale: String,
    /// Directions of the optical-depth features: 4, 16 or 64 (tetrahedron).
    #[arg(long, default_value_t = 64)]
    pub n_dirs: usize,
    /// Direction set: tetrahedron (the thesis's) or fibonacci.
    #[arg(long, default_value = "tetrahedron")]
    pub directions: String,
    /// Maximum relative half-width of the confidence interval of each target.
    #[arg(long, default_value_t = 0.05)]
    pub max_rel_error: f64,
    /// Confidence level of that interval.
    #[arg(long, default_value_t = 0.95)]
    pub confidence: f64,
    #[arg(long, default_value_t = 1000)]
    pub min_samples: u64,
    #[arg(long, default_value_t = 10_000_000)]
    pub max_samples: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Points per chunk file (the unit of resuming and sharding).
    #[arg(long, default_value_t = 200)]
    pub chunk_size: u64,
    /// Fraction of points sampled like the renderer's queries at k = 1 (first collision
    /// of a ray entering the shape, looking back along it); the rest uniform.
    #[arg(long, default_value_t = 0.0)]
    pub first_collision: f32,
    /// Make only part i of N (0-based), e.g. --shard 3/16; join with `nimbus datagen merge`.
    #[arg(long, default_value = "0/1")]
    pub shard: String,
    #[arg(long)]
    pub threads: Option<usize>,
    /// Output directory (created; an existing one with the same settings is resumed).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct MergeArgs {
    /// Shard directories.
    #[arg(required = true)]
    pub shards: Vec<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
}

impl GlobalArgs {
    pub fn spec(&self) -> Result<GlobalSpec> {
        let shapes = self
            .shapes
            .split(',')
            .map(|s| {
                ShapeKind::parse(s).with_context(|| format!("--shapes: unknown shape {s:?} (sphere, box, ellipsoid)"))
            })
            .collect::<Result<Vec<_>>>()?;
        let directions = DirectionSetKind::parse(&self.directions)
            .with_context(|| format!("--directions: unknown set {:?} (tetrahedron, fibonacci)", self.directions))?;
        let spec = GlobalSpec {
            points: self.points,
            sigma: parse_range("--sigma", &self.sigma)?,
            albedo: parse_range("--albedo", &self.albedo)?,
            g: parse_range("--g", &self.g)?,
            shapes,
            rotate: !self.no_rotate,
            scale: parse_range("--scale", &self.scale)?,
            n_dirs: self.n_dirs,
            directions,
            max_rel_error: self.max_rel_error,
            confidence: self.confidence,
            min_samples: self.min_samples,
            max_samples: self.max_samples,
            seed: self.seed,
            chunk_size: self.chunk_size,
            first_collision: self.first_collision,
        };
        spec.validate()?;
        Ok(spec)
    }
}

/// Ctrl-C sets the flag: the chunks on disk are kept, the run can be resumed.
fn cancel_on_ctrl_c() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    let _ = ctrlc::set_handler(move || {
        eprintln!("\nstopping: finished chunks are kept; run the same command again to resume");
        f.store(true, Ordering::Relaxed);
    });
    flag
}

pub fn datagen(cmd: DatagenCommand) -> Result<()> {
    match cmd {
        DatagenCommand::Global(args) => {
            let spec = args.spec()?;
            let shard = Shard::parse(&args.shard)?;
            let threads = init_threads(args.threads)?;
            let what = format!("data set: {} points", spec.points);
            let run = Run { owned: spec.shard_points(shard), shard, threads, out: &args.out, quiet: args.quiet };
            run.go(&what, |progress, cancel| {
                let m = datagen::generate(&spec, shard, &args.out, &code_version(), progress, cancel)?;
                Ok((m.complete, m.counts))
            })
        }
        DatagenCommand::Merge(args) => {
            let first = args.shards.first().context("name the shard directories")?;
            let text = std::fs::read_to_string(first.join("manifest.json")).unwrap_or_default();
            let points = if text.contains(models::p2p_datagen::FORMAT) {
                models::p2p_datagen::merge(&args.shards, &args.out)?.counts.points
            } else {
                datagen::merge(&args.shards, &args.out)?.counts.points
            };
            println!("merged {} shards: {points} points into {}", args.shards.len(), args.out.display());
            Ok(())
        }
        DatagenCommand::P2p(args) => datagen_p2p(args),
    }
}

/// One data-generation run: what it announces, its progress bar, Ctrl-C, and its
/// closing line (both generators).
struct Run<'a> {
    owned: u64,
    shard: Shard,
    threads: usize,
    out: &'a std::path::Path,
    quiet: bool,
}

impl Run<'_> {
    /// Runs `generate` (given the progress callback and the cancel flag; it returns
    /// whether the data set is complete and the manifest's counts).
    fn go(
        &self,
        what: &str,
        generate: impl FnOnce(&(dyn Fn(u64) + Sync), &std::sync::atomic::AtomicBool) -> Result<(bool, datagen::Counts)>,
    ) -> Result<()> {
        eprintln!(
            "{what} ({} points in shard {}/{}), {} threads, into {}",
            self.owned,
            self.shard.index,
            self.shard.count,
            self.threads,
            self.out.display()
        );
        let bar = progress_bar(self.owned, "points", self.quiet);
        let cancel = cancel_on_ctrl_c();
        let started = std::time::Instant::now();
        let (complete, counts) = generate(&|n| bar.set_position(n), &cancel)?;
        bar.finish_and_clear();
        println!(
            "{} {} points in {:.1} s this run ({:.1} s total), {} path samples; {}",
            if complete { "complete:" } else { "shard done:" },
            self.owned,
            started.elapsed().as_secs_f64(),
            counts.seconds,
            counts.path_samples,
            self.out.display()
        );
        Ok(())
    }
}

/// The cloud of `nimbus datagen p2p --cloud`: a built-in cloud, a modeler preset or a
/// VDB file.
pub fn cloud_grid(name: &str, resolution: u32) -> Result<engine::DensityGrid> {
    if let Some(b) = crate::cloud::Builtin::from_name(name) {
        return Ok(b.grid(resolution));
    }
    if let Some(params) = modeler::preset(name) {
        return Ok(modeler::build_grid(&params, resolution)?);
    }
    if name.ends_with(".vdb") {
        return Ok(modeler::vdb::read_vdb(std::path::Path::new(name), None)?.grid);
    }
    bail!(
        "--cloud {name:?} is neither a built-in cloud ({}), a modeler preset ({}) nor a .vdb file",
        crate::cloud::Builtin::NAMES.join(", "),
        modeler::PRESET_NAMES.join(", ")
    )
}

fn datagen_p2p(args: P2pArgs) -> Result<()> {
    let spec = models::p2p_datagen::P2pSpec {
        points: args.points,
        cloud: args.cloud.clone(),
        resolution: args.resolution,
        rho: args.rho,
        albedo: args.albedo,
        g: args.g,
        k: args.k,
        rotations: args.rotations,
        features: Default::default(),
        max_rel_error: args.max_rel_error,
        confidence: args.confidence,
        min_samples: args.min_samples,
        max_samples: args.max_samples,
        seed: args.seed,
        chunk_size: args.chunk_size,
    };
    spec.validate()?;
    let grid = Arc::new(cloud_grid(&args.cloud, args.resolution)?);
    let shard = Shard::parse(&args.shard)?;
    let threads = init_threads(args.threads)?;
    let what = format!("point-to-point data set: {} points x {} rotations", spec.points, spec.rotations);
    let run = Run { owned: spec.shard_points(shard), shard, threads, out: &args.out, quiet: args.quiet };
    run.go(&what, |progress, cancel| {
        let m = models::p2p_datagen::generate(&spec, grid, shard, &args.out, &code_version(), progress, cancel)?;
        Ok((m.complete, m.counts))
    })
}

/// `nimbus datagen p2p`: ground truth for the point-to-point model (thesis 6.3).
#[derive(Args, Debug)]
pub struct P2pArgs {
    /// A built-in cloud, a modeler preset (scene-a .. set-12) or a .vdb file.
    #[arg(long, default_value = "scene-a")]
    pub cloud: String,
    /// Voxels per axis of generated clouds.
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
    #[arg(long, default_value_t = 1000)]
    pub points: u64,
    #[arg(long, default_value_t = 25.0)]
    pub rho: f32,
    #[arg(long, default_value_t = 0.99)]
    pub albedo: f32,
    /// Henyey-Greenstein g (the thesis's model: 0).
    #[arg(long, default_value_t = 0.0)]
    pub g: f32,
    /// Segments of the walks that place emitter and sensor.
    #[arg(long, default_value_t = 2)]
    pub k: u32,
    /// Feature rows per point (random rotations about the emitter-sensor axis).
    #[arg(long, default_value_t = 50)]
    pub rotations: u32,
    #[arg(long, default_value_t = 0.1)]
    pub max_rel_error: f64,
    #[arg(long, default_value_t = 0.95)]
    pub confidence: f64,
    #[arg(long, default_value_t = 1000)]
    pub min_samples: u64,
    #[arg(long, default_value_t = 20_000_000)]
    pub max_samples: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long, default_value_t = 20)]
    pub chunk_size: u64,
    /// This run's part, i/N (chunks c with c mod N == i).
    #[arg(long, default_value = "0/1")]
    pub shard: String,
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct BenchDatagenArgs {
    /// Data points per cell of the table.
    #[arg(long, default_value_t = 24)]
    pub points: u64,
    /// sigma_S values (the thesis's table 5.1: 10, 25, 50, 100).
    #[arg(long, value_delimiter = ',', default_value = "10,25,50,100")]
    pub sigma: Vec<f32>,
    /// g values (the thesis's: 0, 0.85).
    #[arg(long, value_delimiter = ',', default_value = "0,0.85")]
    pub g: Vec<f32>,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Args, Debug)]
pub struct BenchDatagenP2pArgs {
    /// Data points per cell (the same queries for every column).
    #[arg(long, default_value_t = 3)]
    pub points: u32,
    /// A data point taking longer than this (seconds) marks its cell as not
    /// finished ("-"), as the thesis's table does.
    #[arg(long, default_value_t = 20.0)]
    pub max_seconds: f64,
    /// Segments of the walks that place emitter and sensor.
    #[arg(long, default_value_t = 2)]
    pub k: u32,
    /// Density scales (the thesis's: 10, 20, 40).
    #[arg(long, value_delimiter = ',', default_value = "10,20,40")]
    pub rho: Vec<f32>,
    /// Relative half-width of the 95 % confidence interval.
    #[arg(long, default_value_t = 0.1)]
    pub max_rel_error: f64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Thesis table 6.1 (seconds per data point, one thread of a Xeon E5-2697 v2):
/// PT, BDPT ray marching all, BDPT Woodcock all, RR1, RR2; None where not reported.
fn thesis_p2p(rho: f32, albedo: f32, g: f32) -> Option<[Option<f64>; 5]> {
    let n = None;
    let row = |a: [f64; 5]| a.map(|v| if v < 0.0 { None } else { Some(v) });
    Some(match (rho as i32, (albedo * 100.0).round() as i32, (g * 100.0).round() as i32) {
        (10, 99, 0) => row([8.43, 22.78, 1.65, 0.60, 0.57]),
        (10, 99, 85) => [n, Some(53.83), Some(3.64), Some(3.93), Some(1.82)],
        (10, 100, 0) => row([3.99, 24.41, 1.73, 0.52, 0.53]),
        (10, 100, 85) => [n, Some(50.44), Some(4.30), Some(3.81), Some(1.84)],
        (20, 99, 0) => row([164.95, 230.84, 40.81, 8.48, 6.77]),
        (20, 99, 85) => [n, Some(144.56), Some(18.13), Some(10.94), Some(7.22)],
        (20, 100, 0) => row([47.11, 279.45, 56.72, 9.74, 10.51]),
        (20, 100, 85) => [n, Some(121.44), Some(18.45), Some(11.30), Some(5.13)],
        (40, 99, 0) => [Some(207.72), n, n, Some(142.10), Some(133.49)],
        (40, 99, 85) => [n, n, Some(161.08), Some(46.11), Some(33.03)],
        (40, 100, 0) => [Some(160.66), n, n, Some(312.34), Some(373.34)],
        (40, 100, 85) => [n, Some(392.06), Some(144.36), Some(44.13), Some(29.85)],
        _ => return None,
    })
}

/// Reproduces the thesis's table 6.1 on one thread: the built-in cumulus (diameter
/// about 1), emitter and sensor at the ends of k-segment walks from outside, T to
/// 10 % at 95 % by confidence-interval stopping.
pub fn bench_datagen_p2p(args: BenchDatagenP2pArgs) -> Result<()> {
    use engine::bdpt::MisHeuristic;
    use engine::p2p::{ConnectionScheme, P2pQuery, P2pSettings, sample_query_end, sample_transport};
    if args.points == 0 || !(args.max_seconds > 0.0) {
        bail!("--points and --max-seconds must be positive");
    }
    let grid = Arc::new(crate::cloud::Builtin::Cumulus.grid(64));
    println!(
        "# nimbus bench datagen-p2p: seconds per data point, one thread (cumulus 64^3, diameter ~1, k {}, {:.0} % at 95 %, {} points per cell, cells over {} s per point marked -)",
        args.k,
        100.0 * args.max_rel_error,
        args.points,
        args.max_seconds
    );
    println!("| rho | albedo | g | PT | BDPT all | BDPT RR1 | BDPT RR2 | thesis best | ratio |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let columns = [
        P2pSettings { scheme: ConnectionScheme::All, max_sensor_vertices: 0, ..Default::default() },
        P2pSettings { scheme: ConnectionScheme::All, heuristic: MisHeuristic::Power, ..Default::default() },
        P2pSettings { scheme: ConnectionScheme::Rr1, ..Default::default() },
        P2pSettings { scheme: ConnectionScheme::Rr2, ..Default::default() },
    ];
    for &rho in &args.rho {
        for albedo in [0.99f32, 1.0] {
            for g in [0.0f32, 0.85] {
                let phase = engine::PhaseFunction::henyey_greenstein(g).map_err(anyhow::Error::msg)?;
                let medium = engine::Medium::new(grid.clone(), rho, albedo, phase)?;
                let mut rng = engine::Rng::new(args.seed, (rho * 100.0) as u64, (albedo * 100.0 + g * 10.0) as u64);
                let mut queries = vec![];
                while queries.len() < args.points as usize {
                    if let (Some((e, we)), Some((s, ws))) =
                        (sample_query_end(&medium, args.k, &mut rng), sample_query_end(&medium, args.k, &mut rng))
                    {
                        if (e - s).length() > 1e-3 {
                            queries.push(P2pQuery { emitter: e, omega_e: we, sensor: s, omega_s: ws });
                        }
                    }
                }
                let mut cells = vec![];
                for (ci, set) in columns.iter().enumerate() {
                    let mut total = 0.0;
                    let mut finished = true;
                    for (qi, q) in queries.iter().enumerate() {
                        let mut r = engine::Rng::new(args.seed, 1000 + ci as u64, qi as u64);
                        let t0 = std::time::Instant::now();
                        let mut w = engine::stats::Welford::default();
                        loop {
                            for _ in 0..64 {
                                w.add(sample_transport(&medium, q, set, &mut r) as f64);
                            }
                            if w.n >= 1000 && w.mean > 0.0 && 1.96 * w.std_error() <= args.max_rel_error * w.mean {
                                break;
                            }
                            if t0.elapsed().as_secs_f64() > args.max_seconds {
                                finished = false;
                                break;
                            }
                        }
                        total += t0.elapsed().as_secs_f64();
                        if !finished {
                            break;
                        }
                    }
                    cells.push(finished.then(|| total / queries.len() as f64));
                }
                let best_ours = cells.iter().flatten().copied().fold(f64::INFINITY, f64::min);
                let thesis_best = thesis_p2p(rho, albedo, g).and_then(|r| r.iter().flatten().copied().reduce(f64::min));
                let fmt = |c: &Option<f64>| c.map(|v| format!("{v:.3}")).unwrap_or_else(|| "-".into());
                println!(
                    "| {rho} | {albedo} | {g} | {} | {} | {} | {} | {} | {} |",
                    fmt(&cells[0]),
                    fmt(&cells[1]),
                    fmt(&cells[2]),
                    fmt(&cells[3]),
                    thesis_best.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into()),
                    match thesis_best {
                        Some(t) if best_ours.is_finite() => format!("{:.0}x", t / best_ours),
                        _ => "-".into(),
                    }
                );
            }
        }
    }
    Ok(())
}

/// Thesis table 5.1: seconds per data point, one thread of a Xeon E5-2697 v2.
fn thesis_seconds(sigma: f32, g: f32) -> Option<f64> {
    let col = [10.0, 25.0, 50.0, 100.0].iter().position(|&s| s == sigma)?;
    match g {
        0.0 => Some([0.15, 0.79, 3.19, 13.66][col]),
        0.85 => Some([0.12, 0.44, 1.71, 6.39][col]),
        _ => None,
    }
}

/// Reproduces the thesis's table 5.1 on one thread: unit sphere, albedo 1, 5 % at 95 %.
pub fn bench_datagen(args: BenchDatagenArgs) -> Result<()> {
    if args.points == 0 {
        bail!("--points must be at least 1");
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    println!("# nimbus bench datagen: seconds per data point, one thread (unit sphere, albedo 1, 5 % at 95 %)");
    println!("# {} points per cell; thesis: Xeon E5-2697 v2 (2013), this run: another processor", args.points);
    println!("| sigma_S | g | Nimbus s/point | mean samples/point | thesis s/point | thesis / Nimbus |");
    println!("|---|---|---|---|---|---|");
    for &g in &args.g {
        for &sigma in &args.sigma {
            let spec = GlobalSpec {
                points: args.points,
                sigma: [sigma, sigma],
                albedo: [1.0, 1.0],
                g: [g, g],
                shapes: vec![ShapeKind::Sphere],
                rotate: false,
                seed: args.seed,
                ..Default::default()
            };
            spec.validate()?;
            let fe = models::features::FeatureExtractor::new(spec.n_dirs).expect("64 directions");
            let t = std::time::Instant::now();
            let samples: u64 =
                pool.install(|| (0..args.points).map(|i| datagen::generate_point(&spec, &fe, i).samples).sum());
            let per = t.elapsed().as_secs_f64() / args.points as f64;
            let thesis = thesis_seconds(sigma, g);
            println!(
                "| {sigma} | {g} | {per:.4} | {} | {} | {} |",
                samples / args.points,
                thesis.map_or("-".into(), |s| format!("{s}")),
                thesis.map_or("-".into(), |s| format!("{:.1}x", s / per))
            );
        }
    }
    Ok(())
}
