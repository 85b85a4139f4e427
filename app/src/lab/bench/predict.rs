//! `nimbus bench predict`, `predict-cloud` and `predict-p2p`: the cost of one prediction
//! of each model on one thread (features, network), beside the cost of a path-traced
//! scattering event in the same cloud.

use anyhow::{Context, Result, bail};
use clap::Args;
use engine::{InScatterPredictor, Rng};
use models::global::GlobalModel;
use models::nn::Activation;
use std::path::PathBuf;
use std::sync::Arc;

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
    let layout = models::global::model::FeatureLayout::current(Default::default(), 64);
    let net =
        models::global::train::Network::glorot(&[68, 200, 100, 1], Activation::Relu, 1, &candle_core::Device::Cpu)?;
    let sidecar = models::global::model::Sidecar {
        format: models::global::model::MODEL_FORMAT.into(),
        format_version: models::global::model::MODEL_FORMAT_VERSION,
        features: layout,
        standardization: models::global::model::Standardization {
            feature_mean: vec![0.0; 68],
            feature_std: vec![1.0; 68],
            target: models::global::model::TARGET_TRANSFORM.into(),
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
        models::global::depth_field::DEFAULT_MAX_NODES,
    );
    let field_secs = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    for i in 0..n / 4 {
        let (p, w) = points[i % points.len()];
        sink += bound.predict(&medium, &sun, p, w);
    }
    let bound_ns = t.elapsed().as_secs_f64() * 1e9 / (n / 4) as f64;
    // Lights other than the sun (sky directions, a soft sun's disk): the all-direction
    // field, one random light per prediction.
    let t = std::time::Instant::now();
    let bound = bound.with_other_lights(
        &medium,
        models::global::sky_field::DEFAULT_TEXELS,
        models::global::depth_field::DEFAULT_MAX_NODES / 2,
    );
    let sky_field_secs = t.elapsed().as_secs_f64();
    let lights: Vec<engine::Sun> = (0..1024)
        .map(|_| engine::Sun::new(engine::sampling::sample_uniform_sphere(rng.uniform2()), glam::Vec3::ONE, 0.0))
        .collect::<Result<_, _>>()?;
    let t = std::time::Instant::now();
    for i in 0..n / 4 {
        let (p, w) = points[i % points.len()];
        sink += bound.predict(&medium, &lights[i % lights.len()], p, w);
    }
    let sky_ns = t.elapsed().as_secs_f64() * 1e9 / (n / 4) as f64;
    // Its accuracy: the same random lights answered with ray-marched features.
    let (mut diff, mut total) = (0.0f64, 0.0f64);
    for i in 0..400 {
        let (p, w) = points[i % points.len()];
        let light = &lights[i % lights.len()];
        let marched = model.predict(&medium, light, p, w) as f64;
        diff += (bound.predict(&medium, light, p, w) as f64 - marched).abs();
        total += marched;
    }
    let sky_rel_diff = diff / total.max(1e-30);
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
    println!(
        "| features alone, all-direction field, any light | {:.0} = {:.2} path-traced scattering events | |",
        sky_ns - net_ns,
        (sky_ns - net_ns) / event_ns
    );
    println!(
        "| all-direction field against ray-marched features, 400 random lights | mean abs. difference {:.1} % of the mean prediction | |",
        100.0 * sky_rel_diff
    );
    let f = bound.field();
    println!(
        "| depth field build ({}^3 nodes x {} directions, {:.0} MiB, one thread) | {:.2} s once per cloud and sun | |",
        f.nodes().x,
        f.n_dirs(),
        f.memory_bytes() as f64 / 1048576.0,
        field_secs
    );
    let f = bound.sky_field().expect("built above").field();
    println!(
        "| all-direction field build ({}^3 nodes x {} directions, {:.0} MiB, one thread) | {:.2} s once per cloud, with a sky or a soft sun | |",
        f.nodes().x,
        f.n_dirs(),
        f.memory_bytes() as f64 / 1048576.0,
        sky_field_secs
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
    use models::p2p::net::{P2pArch, P2pNetwork};
    use models::p2p::{DensityPyramid, LocalFrame, P2pFeatures};
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
            let a = engine::integrator::p2p::sample_query_end(&medium, 2, &mut rng);
            let b = engine::integrator::p2p::sample_query_end(&medium, 2, &mut rng);
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

#[derive(Args, Debug)]
pub struct BenchPredictCloudArgs {
    /// Model to time (default: the shipped cloud-aware model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Predictions per measurement.
    #[arg(long, default_value_t = 100_000)]
    pub n: usize,
    /// Grid resolution of the benchmark cloud (scene-a).
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
    #[arg(long, default_value_t = 40.0)]
    pub rho: f32,
    /// Timed rounds (after one warm-up); the medians are reported.
    #[arg(long, default_value_t = 5)]
    pub rounds: usize,
}

/// The cloud-aware model's cost: the fields built per cloud and sun (2 threads, as on
/// the target machine, and 1), then features and network per prediction on one
/// thread, in the order a render asks (first vertices of a view, tile by tile) and in
/// random order (camera-path vertices of random views), beside a path-traced
/// scattering event.
pub fn bench_predict_cloud(args: BenchPredictCloudArgs) -> Result<()> {
    use models::cloud::{BoundCloudModel, CloudModel};
    if args.n == 0 {
        bail!("--n must be at least 1");
    }
    if args.rounds == 0 {
        bail!("--rounds must be at least 1");
    }
    let model = match &args.model {
        Some(p) => Arc::new(CloudModel::load(p)?),
        None => CloudModel::shipped()?,
    };
    let params = modeler::preset("scene-a").context("scene-a preset")?;
    let grid = Arc::new(modeler::build_grid(&params, args.resolution)?);
    let medium_of =
        |grid| engine::Medium::new(grid, args.rho, 1.0, engine::PhaseFunction::HenyeyGreenstein { g: 0.85 });
    let medium = medium_of(grid)?;
    let sun = engine::Sun::new(glam::Vec3::new(0.3, -1.0, 0.2), glam::Vec3::ONE, 0.0)?;
    let nodes = 2 * models::global::depth_field::DEFAULT_MAX_NODES;
    // A new cloud: a copy of the grid (made before the clock starts), whose density
    // pyramid no earlier binding has built (`models::cloud::features::shared_pyramid`).
    let build = |threads: usize, new_cloud: bool| -> Result<(BoundCloudModel, f64)> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let m = if new_cloud { medium_of(Arc::new((**medium.grid()).clone()))? } else { medium.clone() };
        let t = std::time::Instant::now();
        let b = pool.install(|| BoundCloudModel::new(model.clone(), &m, &sun, nodes));
        Ok((b, t.elapsed().as_secs_f64()))
    };
    // Alternated builds, the median of each: one build is a second of work on a
    // machine whose other load comes and goes.
    let (mut s2, mut s1, mut shared) = (vec![], vec![], vec![]);
    // A first binding of `medium`, untimed: it builds the pyramid the timed rebinds share.
    let mut bound = Some(build(2, false)?.0);
    for _ in 0..args.rounds.min(3) {
        s2.push(build(2, true)?.1);
        s1.push(build(1, true)?.1);
        // The binding the predictions below use is of `medium` itself.
        let (b, secs) = build(2, false)?;
        shared.push(secs);
        bound = Some(b);
    }
    let bound = bound.expect("at least one round");
    let (secs2, secs1, secs_shared) = (median(&mut s2), median(&mut s1), median(&mut shared));
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    pool.install(|| {
        let mut rng = Rng::new(7, 0, 0);
        let queries: Vec<_> =
            (0..4096).map(|_| models::cloud::datagen::camera_path_query(&medium, 1, None, &mut rng)).collect();
        // The renderer's order: the first scattering vertices of the camera rays of a
        // 256x256 toplit view, tile by tile, pixels in rows (neighbouring queries read
        // neighbouring parts of the fields, as in a render).
        let view = crate::scene::CameraPreset::Toplit.view_direction(sun.direction());
        let target = medium.bounds().center();
        let camera = engine::Camera::new(target - view * 2.8, target, crate::scene::default_up(view), 30.0, 256, 256)?;
        let tile = engine::render::TILE_SIZE;
        let mut ordered = vec![];
        for (ty, tx) in (0..256 / tile).flat_map(|ty| (0..256 / tile).map(move |tx| (ty, tx))) {
            for (y, x) in (ty * tile..(ty + 1) * tile).flat_map(|y| (tx * tile..(tx + 1) * tile).map(move |x| (y, x))) {
                let (o, d) = camera.generate_ray(x, y, rng.uniform2());
                if let engine::medium::FreeFlight::Collision { t } =
                    medium.sample_free_flight(o, d, f32::INFINITY, &mut rng)
                {
                    ordered.push((o + d * t, -d));
                }
            }
        }
        if ordered.is_empty() {
            bail!("no camera ray of the benchmark view scatters");
        }
        // What prediction at bounce 1 fills: the nodes of a lattice of the model's answers
        // toward the camera (128 per axis over the cloud), in the lazy lattice's fill
        // blocks of 2^3 nodes: the blocks that hold the lower corner of each first
        // vertex's cell, in the order the vertices reach them.
        let (lat_n, lat_spacing) = engine::field::lattice_over(&medium, 128);
        let lat_origin = medium.grid().support_bounds().min;
        let mut blocks: Vec<glam::UVec3> = vec![];
        let mut seen = std::collections::HashSet::new();
        for &(p, _) in &ordered {
            let q = ((p - lat_origin) / lat_spacing).floor().as_uvec3().min(lat_n - glam::UVec3::splat(2));
            if seen.insert(q / 2) {
                blocks.push(q / 2);
            }
        }
        let block_nodes: Vec<Vec<(glam::Vec3, glam::Vec3)>> = blocks
            .iter()
            .map(|b| {
                (0..8u32)
                    .map(|j| b * 2 + glam::UVec3::new(j & 1, (j >> 1) & 1, j >> 2))
                    .filter(|g| g.cmplt(lat_n).all())
                    .map(|g| lat_origin + g.as_vec3() * lat_spacing)
                    .filter_map(|x| Some((x, (camera.position() - x).try_normalize()?)))
                    .collect()
            })
            .collect();
        // As many blocks as make about n nodes.
        let fill_blocks = (args.n / 8).clamp(1, block_nodes.len());
        let fill_nodes: usize = block_nodes[..fill_blocks].iter().map(Vec::len).sum();
        let nf = models::cloud::features::N_FEATURES;
        let mut rows = vec![0.0; queries.len() * nf];
        for (row, &(p, w)) in rows.chunks_exact_mut(nf).zip(&queries) {
            bound.field().features(1.0, 0.85, p, w, row);
        }
        let mut scratch = model.mlp.scratch();
        let mut feat = vec![0.0; nf];
        let phase = medium.phase();
        let m = args.n.max(1000);
        let mut sink = 0.0f32;
        // Each round times the four measurements one after another, after a warm-up
        // round; the medians over rounds are reported (the spread beside them), so a
        // burst of other load lands in one round of one measurement, not in a
        // difference of two.
        let (mut total, mut features, mut network, mut event) = (vec![], vec![], vec![], vec![]);
        let kernels: Vec<models::nn::Kernel> =
            // The portable kernel (CPUs without AVX2) is two orders of magnitude slower
            // and left out.
            [models::nn::Kernel::Avx2, models::nn::Kernel::Avx512]
                .into_iter()
                .filter(|k| k.available())
                .collect();
        let mut kernel_us: Vec<Vec<f64>> = vec![vec![]; kernels.len()];
        let mut in_order = vec![];
        let (mut fill_one, mut fill_many) = (vec![], vec![]);
        let mut block_out = [0.0f32; 8];
        let (mut block_xs, mut block_ws) = ([glam::Vec3::ZERO; 8], [glam::Vec3::ZERO; 8]);
        for round in 0..=args.rounds {
            // The lattice's blocks node by node, then each block in one batch.
            let t = std::time::Instant::now();
            for nodes in &block_nodes[..fill_blocks] {
                for &(p, w) in nodes {
                    sink += bound.predict(&medium, &sun, p, w);
                }
            }
            let fill_one_us = t.elapsed().as_secs_f64() * 1e6 / fill_nodes as f64;
            let t = std::time::Instant::now();
            for nodes in &block_nodes[..fill_blocks] {
                for (k, &(p, w)) in nodes.iter().enumerate() {
                    (block_xs[k], block_ws[k]) = (p, w);
                }
                let m = nodes.len();
                bound.predict_many(&medium, &sun, &block_xs[..m], &block_ws[..m], &mut block_out[..m]);
                sink += block_out[0];
            }
            let fill_many_us = t.elapsed().as_secs_f64() * 1e6 / fill_nodes as f64;
            let t = std::time::Instant::now();
            for i in 0..args.n {
                let (p, w) = ordered[i % ordered.len()];
                sink += bound.predict(&medium, &sun, p, w);
            }
            let in_order_us = t.elapsed().as_secs_f64() * 1e6 / args.n as f64;
            let t = std::time::Instant::now();
            for i in 0..args.n {
                let (p, w) = queries[i % queries.len()];
                sink += bound.predict(&medium, &sun, p, w);
            }
            let total_us = t.elapsed().as_secs_f64() * 1e6 / args.n as f64;
            let t = std::time::Instant::now();
            for i in 0..args.n {
                let (p, w) = queries[i % queries.len()];
                bound.field().features(1.0, 0.85, p, w, &mut feat);
                sink += feat[3];
            }
            let features_us = t.elapsed().as_secs_f64() * 1e6 / args.n as f64;
            let t = std::time::Instant::now();
            for i in 0..args.n {
                let k = i % queries.len();
                sink += model.predict_features(&rows[k * nf..(k + 1) * nf], &mut scratch);
            }
            let network_us = t.elapsed().as_secs_f64() * 1e6 / args.n as f64;
            // The network alone with each layer kernel this CPU runs (the rows as
            // they are: the cost does not depend on the values).
            let mut per_kernel = vec![];
            for &k in &kernels {
                let t = std::time::Instant::now();
                for i in 0..args.n {
                    let j = i % queries.len();
                    sink += model
                        .mlp
                        .forward_with_kernel(k, &rows[j * nf..j * nf + model.inputs()], &mut scratch)
                        .unwrap_or(0.0);
                }
                per_kernel.push(t.elapsed().as_secs_f64() * 1e6 / args.n as f64);
            }
            let t = std::time::Instant::now();
            for i in 0..m {
                let (p, w) = queries[i % queries.len()];
                let wi = phase.sample(w, rng.uniform2()).wi;
                if let engine::medium::FreeFlight::Collision { t } =
                    medium.sample_free_flight(p, wi, medium.exit_distance(p, wi), &mut rng)
                {
                    sink += t;
                }
                let to_sun = -sun.direction();
                sink += medium.transmittance_ratio(p, to_sun, medium.exit_distance(p, to_sun), &mut rng);
            }
            let event_us = t.elapsed().as_secs_f64() * 1e6 / m as f64;
            if round > 0 {
                fill_one.push(fill_one_us);
                fill_many.push(fill_many_us);
                in_order.push(in_order_us);
                total.push(total_us);
                features.push(features_us);
                network.push(network_us);
                event.push(event_us);
                for (v, us) in kernel_us.iter_mut().zip(per_kernel) {
                    v.push(us);
                }
            }
        }
        std::hint::black_box(sink);
        let spread = |v: &[f64]| {
            let (lo, hi) = v.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| (lo.min(x), hi.max(x)));
            format!("{lo:.2} - {hi:.2}")
        };
        let (total_range, features_range, network_range, event_range, in_order_range) =
            (spread(&total), spread(&features), spread(&network), spread(&event), spread(&in_order));
        let in_order_us = median(&mut in_order);
        let (total_us, features_us, network_us, event_us) =
            (median(&mut total), median(&mut features), median(&mut network), median(&mut event));
        println!(
            "# nimbus bench predict-cloud: scene-a {}^3, rho {}, {} features, hidden {:?}",
            args.resolution,
            args.rho,
            model.inputs(),
            model.sidecar.hidden
        );
        println!(
            "# medians of {} rounds after a warm-up (range in brackets); builds: {} alternated pairs",
            args.rounds,
            s2.len()
        );
        println!("| measurement | value | goal |");
        println!("|---|---|---|");
        println!("| fields per cloud and sun, 2 threads | {secs2:.3} s | <= 1 s |");
        println!("| fields per cloud and sun, 1 thread | {secs1:.3} s | |");
        println!("| fields for a new sun or rho (the cloud's pyramid shared), 2 threads | {secs_shared:.3} s | |");
        println!("| field memory | {:.1} MiB | |", bound.field().memory_bytes() as f64 / 1048576.0);
        println!(
            "| features + network per prediction, 1 thread, in the renderer's order ({} first vertices of a \
             256x256 toplit view, tile by tile) | {in_order_us:.2} us ({in_order_range}) = {:.1} path-traced \
             scattering events | <= 20 us |",
            ordered.len(),
            in_order_us / event_us
        );
        println!(
            "| features + network per prediction, 1 thread, in random order (camera-path vertices of random \
             views) | {total_us:.2} us ({total_range}) = {:.1} path-traced scattering events | |",
            total_us / event_us
        );
        let (fill_one_range, fill_many_range) = (spread(&fill_one), spread(&fill_many));
        let (fill_one_us, fill_many_us) = (median(&mut fill_one), median(&mut fill_many));
        println!(
            "| a lattice of answers toward the camera (prediction at bounce 1, 128 nodes per axis), per node, \
             1 thread, node by node ({fill_blocks} blocks of 2^3 nodes the view's first vertices read, \
             {fill_nodes} nodes) | {fill_one_us:.2} us ({fill_one_range}) | |"
        );
        println!(
            "| the same blocks, each block's nodes in one batch (features, then the network on the 8 rows \
             together) | {fill_many_us:.2} us ({fill_many_range}) = {:.2}x node by node | |",
            fill_many_us / fill_one_us
        );
        println!("| features alone | {features_us:.2} us ({features_range}) | |");
        println!(
            "| network alone, on precomputed features ({} kernel) | {network_us:.2} us ({network_range}) | |",
            models::nn::Kernel::best().name()
        );
        // Each kernel's median against the one the networks run, both from the loop above.
        let kernel_medians: Vec<(String, f64)> = kernel_us.iter_mut().map(|v| (spread(v), median(v))).collect();
        let best_us =
            kernels.iter().zip(&kernel_medians).find(|(k, _)| **k == models::nn::Kernel::best()).map(|(_, m)| m.1);
        for (k, (range, us)) in kernels.iter().zip(&kernel_medians) {
            let ratio = best_us
                .map(|b| format!(" = {:.2}x the time of the {} kernel", us / b, models::nn::Kernel::best().name()));
            println!("| network alone, {} kernel | {us:.2} us ({range}){} | |", k.name(), ratio.unwrap_or_default());
        }
        println!("| path-traced scattering event (free flight + NEE) | {event_us:.3} us ({event_range}) | |");
        Ok(())
    })
}

/// The median of `v` (reordered in place; the mean of the middle two for an even count).
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}
