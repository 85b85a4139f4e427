//! `nimbus bench datagen` and `nimbus bench datagen-p2p`: seconds per ground-truth
//! data point on one thread, beside the thesis's tables 5.1 and 6.1.

use anyhow::{Result, bail};
use clap::Args;
use models::global::datagen::{self, GlobalSpec, ShapeKind};
use std::sync::Arc;

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
    use engine::MisHeuristic;
    use engine::P2pQuery;
    use engine::integrator::p2p::{ConnectionScheme, P2pSettings, sample_query_end, sample_transport};
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
            let fe = models::global::features::FeatureExtractor::new(spec.n_dirs).expect("64 directions");
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
