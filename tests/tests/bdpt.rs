//! Volumetric BDPT against the unidirectional path tracer: the same cloud gives the
//! same image, per scattering order and in full, and every connection strategy,
//! weighted against next event estimation alone, converges to the same answer.
//!
//! Each pass (one sample per pixel, its own random streams) gives one image average;
//! passes are independent, so the averages' mean and standard error give z-scores.
//! Bounds are Sidak-corrected two-sided normal quantiles at a family-wise 1 %.

use engine::stats::{Welford, z_bound};
use engine::{BdptSettings, MisHeuristic};
use engine::{Integrator, PhaseFunction, RenderSettings, Rng, Scene, Sun, Technique};
use glam::{Vec2, Vec3};
use nimbus_tests::cumulus_scene;

/// Per-pass image averages of (direct, low, high) for `passes` passes.
fn averages(scene: &Scene, integrator: &Integrator, passes: u32) -> [Welford; 3] {
    averages_pooled(scene, integrator, passes, None)
}

/// Per-pass image means; with `pool` = Some(n), in prediction mode the pass's
/// samples share one pool of n light subpath candidates (as in the renderer), so
/// the samples of a pass are correlated and only the passes are independent draws.
fn averages_pooled(scene: &Scene, integrator: &Integrator, passes: u32, pool: Option<u32>) -> [Welford; 3] {
    let cam = &scene.camera;
    let (w, h) = (cam.width(), cam.height());
    let seed = integrator.settings().seed;
    let mut out = [Welford::default(); 3];
    for pass in 0..passes {
        let mut sum = [0.0f64; 3];
        let pooled = pool.and_then(|n| integrator.light_pool(scene, pass, n));
        assert_eq!(pooled.is_some(), pool.is_some(), "a pool exactly when asked for");
        for y in 0..h {
            for x in 0..w {
                let mut rng = Rng::new(seed, pass as u64, (y * w + x) as u64);
                let (o, d) = cam.generate_ray(x, y, Vec2::new(rng.uniform(), rng.uniform()));
                let s = integrator.trace_deferring(scene, o, d, &mut rng, pooled.as_ref(), None);
                assert!(s.is_finite());
                for (i, v) in [s.direct, s.low, s.high].iter().enumerate() {
                    sum[i] += (v.x + v.y + v.z) as f64 / 3.0;
                }
            }
        }
        for i in 0..3 {
            out[i].add(sum[i] / (w * h) as f64);
        }
    }
    out
}

fn scene(sky: f32) -> Scene {
    let sun = Sun::new(Vec3::new(0.4, -1.0, -0.3), Vec3::new(1.0, 0.9, 0.8), 0.0).unwrap();
    cumulus_scene(24, 6.0, 0.95, PhaseFunction::HenyeyGreenstein { g: 0.6 }, Some(sun), Vec3::splat(sky), 12)
}

fn integrator(settings: RenderSettings, bdpt: Option<BdptSettings>) -> Integrator {
    let i = Integrator::new(settings, None).unwrap();
    match bdpt {
        Some(b) => i.with_technique(Technique::Bdpt(b)).unwrap(),
        None => i,
    }
}

fn z(a: &Welford, b: &Welford) -> f64 {
    (a.mean - b.mean) / (a.std_error().powi(2) + b.std_error().powi(2)).sqrt().max(1e-300)
}

/// Full transport with a sky, k = 4 (orders 1-3 in low, 4+ in high), and each of the
/// orders 1, 2, 3 alone: BDPT with the power and the balance heuristic agrees with
/// the path tracer.
#[test]
fn bdpt_agrees_with_path_tracing() {
    let scene = scene(0.15);
    let passes = 2000;
    let mut checks: Vec<(String, f64, f64, f64)> = vec![];
    let pt = averages(&scene, &integrator(RenderSettings { seed: 1, k: 4, ..Default::default() }, None), passes);
    for (hi, heuristic) in [MisHeuristic::Power, MisHeuristic::Balance].into_iter().enumerate() {
        let b = BdptSettings { heuristic, ..Default::default() };
        let settings = RenderSettings { seed: 2 + hi as u64, k: 4, ..Default::default() };
        let bd = averages(&scene, &integrator(settings, Some(b)), passes);
        for (i, name) in ["direct", "low (orders 1-3)", "high (orders 4+)"].iter().enumerate() {
            checks.push((format!("{heuristic:?} {name}"), z(&bd[i], &pt[i]), bd[i].mean, pt[i].mean));
        }
    }
    for n in 1..=3u32 {
        let only = RenderSettings { seed: 10 + n as u64, k: n, max_order: Some(n), ..Default::default() };
        let pt = averages(&scene, &integrator(only, None), passes);
        let bd = averages(
            &scene,
            &integrator(RenderSettings { seed: 20 + n as u64, ..only }, Some(Default::default())),
            passes,
        );
        checks.push((format!("order {n}"), z(&bd[2], &pt[2]), bd[2].mean, pt[2].mean));
    }
    let bound = z_bound(0.01, checks.len());
    for (name, z, bd, pt) in &checks {
        println!("{name}: BDPT {bd:.5} PT {pt:.5} z {z:+.2} (bound {bound:.2})");
    }
    for (name, z, bd, pt) in &checks {
        assert!(z.abs() < bound, "{name}: BDPT {bd} vs PT {pt}, z = {z:.2} beyond {bound:.2}");
    }
    // The high orders carry light here, so the agreement is not between zeros.
    assert!(checks.iter().all(|c| c.3 > 1e-3 || c.0.contains("direct")), "{checks:?}");
}

/// Every connection strategy (c camera vertices, n - c light vertices) at orders
/// 2, 3 and 4, weighed by the power heuristic against next event estimation only
/// (the caps max_camera_connect = c, max_light_vertices = n - c leave exactly these
/// two strategies for order n), converges to the path tracer's order-n image. An
/// error in one strategy's throughput, its light subpath or its weight would show
/// here alone. (Unweighted, a connection's 1 / d^2 has infinite variance in a
/// volume, so a z-test of a strategy with weight one would not be valid.)
#[test]
fn each_connection_strategy_converges_to_the_same_answer() {
    let scene = scene(0.0);
    let passes = std::env::var("BDPT_PASSES").ok().and_then(|v| v.parse().ok()).unwrap_or(6000);
    let mut checks = vec![];
    for n in 2..=4u32 {
        let only = RenderSettings { seed: 30 + n as u64, k: n, max_order: Some(n), ..Default::default() };
        let pt = averages(&scene, &integrator(only, None), passes);
        for c in 1..n {
            let b = BdptSettings { heuristic: MisHeuristic::Power, max_camera_connect: c, max_light_vertices: n - c };
            let bd = averages(
                &scene,
                &integrator(RenderSettings { seed: 40 + 10 * n as u64 + c as u64, ..only }, Some(b)),
                passes,
            );
            checks.push((n, c, z(&bd[2], &pt[2]), bd[2].mean, pt[2].mean));
        }
    }
    let bound = z_bound(0.01, checks.len());
    for (n, c, z, bd, pt) in &checks {
        println!(
            "order {n}, strategy c = {c}: {bd:.5} vs PT {pt:.5} (relative difference {:+.2} %), z {z:+.2} (bound {bound:.2})",
            100.0 * (bd / pt - 1.0)
        );
    }
    for (n, c, z, bd, pt) in &checks {
        assert!(z.abs() < bound, "order {n} strategy c = {c}: {bd} vs PT {pt}, z = {z:.2}");
    }
}

/// A "predictor" that is one sample of the unbiased point-to-point estimator: with it
/// BDPT's prediction mode must be unbiased, so any error in the plumbing (the caps
/// and weights of the low orders, the subpaths' throughputs, the one-segment term
/// taken out of T, the extension below r, the 1/p) shows against the path tracer.
use engine::integrator::p2p::EstimatedTransport as ExactTransport;

/// A predictor 30 % too high: the test must see it.
struct BiasedTransport;

impl engine::TransportPredictor for BiasedTransport {
    fn predict(&self, medium: &engine::Medium, q: &engine::P2pQuery, rng: &mut Rng) -> f32 {
        1.3 * engine::integrator::p2p::sample_transport(medium, q, &Default::default(), rng)
    }
}

fn predicting(seed: u64, k: u32, r: f32, p: f32) -> Integrator {
    predicting_with(seed, k, r, p, 1, engine::integrator::bdpt::Prediction::DEFAULT_EXTENSION_SAMPLES)
}

/// With `m` light subpath candidates per camera end vertex and `n` point-to-point
/// samples per extended pair.
fn predicting_with(seed: u64, k: u32, r: f32, p: f32, m: u32, n: u32) -> Integrator {
    let settings = RenderSettings { seed, k, mode: engine::Mode::Predict { p }, ..Default::default() };
    Integrator::bdpt_prediction(settings, Default::default(), std::sync::Arc::new(ExactTransport::default()), r)
        .unwrap()
        .with_light_candidates(m)
        .unwrap()
        .with_extension_samples(n)
        .unwrap()
}

/// BDPT's prediction mode (k segments per subpath: orders 1 ..= 2k by BDPT into low,
/// the transport between the end vertices into high) with an exact predictor agrees
/// with the path tracer split at 2k + 1: most pairs predicted (r = 0.1), all pairs
/// extended (r = infinity), and a mix (r = 0.3, about two mean free paths at the
/// cloud's mean density here), for k = 1 and 2, with p < 1; with 8 and 3 light
/// subpath candidates per camera end vertex (resampled pairing), each candidate its
/// own light subpath; and with candidates from a pool the pass's samples share (as
/// in the renderer): 32 picked from 256 subpaths, and 16 from 12 (all 12 taken).
/// Extended pairs average the default 8 point-to-point samples, and 1 in a second
/// all-extended run.
#[test]
fn bdpt_prediction_with_an_exact_predictor_is_unbiased() {
    let scene = scene(0.0);
    let passes = std::env::var("BDPT_PASSES").ok().and_then(|v| v.parse().ok()).unwrap_or(6000);
    let n = engine::integrator::bdpt::Prediction::DEFAULT_EXTENSION_SAMPLES;
    assert!(n > 1);
    let runs = [
        (1u32, 0.1f32, 0.5f32, 1u32, None, n),
        (1, f32::INFINITY, 1.0, 1, None, n),
        (1, f32::INFINITY, 1.0, 1, None, 1),
        (2, 0.3, 0.5, 1, None, n),
        (1, 0.1, 1.0, 8, None, n),
        (2, 0.3, 0.5, 3, None, n),
        (1, 0.1, 1.0, 32, Some(256u32), n),
        (2, 0.3, 0.5, 16, Some(12), n),
    ];
    let mut checks = vec![];
    for (i, &(k, r, p, m, pool, n)) in runs.iter().enumerate() {
        let integ = predicting_with(60 + i as u64, k, r, p, m, n);
        assert_eq!(integ.high_order_start(), 2 * k + 1);
        // The thesis's pairing (m = 1) joins close pairs as often as the geometry
        // makes them, and the transport between two close points grows like 1 / d:
        // the extension's values are heavy-tailed (at best a finite variance with an
        // infinite third moment; the variance itself may diverge slowly as pairs
        // get closer), so the mean's error is skewed and a z-test at the base count
        // undercovers: a run with another stream gave z -3.7 at 6,000 passes and
        // -1.7 at 24,000, whose first 6,000 were the same samples (the later ones
        // brought the rare large values). Four times the passes for these runs;
        // with candidates (m > 1) the close-pair target samples them in proportion
        // to 1 / d, which tames the tail.
        let passes = if m == 1 { 4 * passes } else { passes };
        let pt = averages(
            &scene,
            &integrator(RenderSettings { seed: 70 + i as u64, k: 2 * k + 1, ..Default::default() }, None),
            passes,
        );
        let bd = averages_pooled(&scene, &integ, passes, pool);
        for (b, name) in [(1, "low"), (2, "high")] {
            let label =
                format!("k {k} r {r} p {p} m {m}{} n {n} {name}", pool.map_or(String::new(), |n| format!(" pool {n}")));
            checks.push((label, z(&bd[b], &pt[b]), bd[b].mean, pt[b].mean));
        }
    }
    // The mixed run really takes both branches.
    let (mut predicted, mut extended) = (0, 0);
    let integ = predicting(1, 2, 0.3, 1.0);
    let cam = &scene.camera;
    for px in 0..cam.width() * cam.height() {
        let mut rng = Rng::new(3, 0, px as u64);
        let (o, d) = cam.generate_ray(px % cam.width(), px / cam.width(), Vec2::splat(0.5));
        for _ in 0..200 {
            engine::integrator::bdpt::trace_strategies(
                integ.settings(),
                &Default::default(),
                integ.transport_prediction(),
                &scene,
                o,
                d,
                &mut rng,
                None,
                None,
                &mut |c| match c.strategy {
                    engine::integrator::bdpt::Strategy::Predicted => predicted += 1,
                    engine::integrator::bdpt::Strategy::Extended => extended += 1,
                    _ => assert!(c.order <= 4, "BDPT made order {} beyond 2k with k = 2", c.order),
                },
            );
        }
    }
    println!("mixed run: {predicted} pairs predicted, {extended} extended");
    assert!(predicted > 50 && extended > 50, "predicted {predicted}, extended {extended}");
    let bound = z_bound(0.01, checks.len());
    for (name, z, bd, pt) in &checks {
        println!("{name}: BDPT-predict {bd:.5} PT {pt:.5} z {z:+.2} (bound {bound:.2})");
    }
    for (name, z, bd, pt) in &checks {
        assert!(z.abs() < bound, "{name}: BDPT-predict {bd} vs PT {pt}, z = {z:.2} beyond {bound:.2}");
    }
    assert!(checks.iter().all(|c| c.3 > 1e-3), "{checks:?}");
    // The same comparison sees a predictor that is 30 % off.
    let settings = RenderSettings { seed: 80, k: 1, mode: engine::Mode::Predict { p: 0.5 }, ..Default::default() };
    let biased = Integrator::bdpt_prediction(settings, Default::default(), std::sync::Arc::new(BiasedTransport), 0.1);
    let bd = averages(&scene, &biased.unwrap(), passes);
    let pt = averages(&scene, &integrator(RenderSettings { seed: 81, k: 3, ..Default::default() }, None), passes);
    let zb = z(&bd[2], &pt[2]);
    println!("30 % biased predictor: high {:.5} vs PT {:.5}, z {zb:+.2}", bd[2].mean, pt[2].mean);
    assert!(zb > bound, "a 30 % biased predictor went unseen: z = {zb:.2}");
}

/// Predictions deferred to a batch (how the renderer evaluates a tile's) give the
/// same samples as predictions evaluated on the spot: each has its own stream.
#[test]
fn deferred_predictions_match_immediate_ones() {
    let scene = scene(0.0);
    let integ = predicting_with(9, 1, 0.1, 0.5, 4, 2);
    let cam = &scene.camera;
    let (w, h) = (cam.width(), cam.height());
    let (mut deferred, mut batched, mut immediate) = (Vec::new(), Vec::new(), Vec::new());
    for pass in 0..200u64 {
        for px in 0..w * h {
            let start = || {
                let mut rng = Rng::new(9, pass, px as u64);
                let (o, d) = cam.generate_ray(px % w, px / w, Vec2::new(rng.uniform(), rng.uniform()));
                (o, d, rng)
            };
            let (o, d, mut rng) = start();
            immediate.push(integ.trace(&scene, o, d, &mut rng));
            let (o, d, mut rng) = start();
            let first = deferred.len();
            batched.push(integ.trace_deferring(&scene, o, d, &mut rng, None, Some(&mut deferred)));
            for p in &mut deferred[first..] {
                p.owner = (batched.len() - 1) as u32;
            }
        }
    }
    println!("{} predictions deferred", deferred.len());
    assert!(deferred.len() > 100, "only {} predictions", deferred.len());
    integ.resolve_deferred(&scene, &mut deferred, &mut batched);
    let mut differ = 0;
    for (a, b) in immediate.iter().zip(&batched) {
        for (x, y) in [(a.direct, b.direct), (a.low, b.low), (a.high, b.high)] {
            assert!((x - y).abs().max_element() <= 1e-5 * (1.0 + x.abs().max_element()), "{x} vs {y}");
            differ += (x != Vec3::ZERO) as usize;
        }
    }
    assert!(differ > 100);
}

/// BDPT refuses prediction mode and bad caps with a message, and is deterministic.
#[test]
fn bdpt_settings_are_checked_and_results_repeat() {
    let pred = Integrator::new(RenderSettings { mode: engine::Mode::Predict { p: 0.5 }, ..Default::default() }, None);
    assert!(pred.is_err(), "prediction needs a predictor anyway");
    let pred_settings = RenderSettings { mode: engine::Mode::Predict { p: 0.5 }, k: 40, ..Default::default() };
    let e = Integrator::bdpt_prediction(
        pred_settings,
        Default::default(),
        std::sync::Arc::new(ExactTransport::default()),
        0.08,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("segments"), "{e}");
    let e = Integrator::bdpt_prediction(
        RenderSettings::default(),
        Default::default(),
        std::sync::Arc::new(ExactTransport::default()),
        0.08,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("mode = predict"), "{e}");
    let i = Integrator::new(RenderSettings::default(), None).unwrap();
    let bad = BdptSettings { max_light_vertices: 0, ..Default::default() };
    let e = i.clone().with_technique(Technique::Bdpt(bad)).unwrap_err().to_string();
    assert!(e.contains("light subpath"), "{e}");
    let scene = scene(0.1);
    let bd = integrator(RenderSettings { seed: 5, ..Default::default() }, Some(Default::default()));
    let a = averages(&scene, &bd, 3);
    let b = averages(&scene, &bd, 3);
    assert_eq!(a.map(|w| w.mean), b.map(|w| w.mean));
}

/// Prediction mode through the renderer (tiles, batched predictions, the pass's shared
/// pool of light subpath candidates) gives the same image bit for bit with 1 and 2
/// threads, the candidate count matters, and a pass is what a loop over the pixels
/// gives with the pass's pool from `Integrator::light_pool` (so the renderer does
/// pass the pool: without it the candidates would be subpaths of their own).
#[test]
fn pooled_prediction_renders_repeat_across_thread_counts() {
    let scene = std::sync::Arc::new(scene(0.0));
    {
        let cam = &scene.camera;
        let (w, h) = (cam.width(), cam.height());
        let renderer = engine::Renderer::new(scene.clone(), predicting_with(21, 1, 0.1, 1.0, 16, 2)).unwrap();
        let control = engine::RenderControl::new();
        let integ = predicting_with(21, 1, 0.1, 1.0, 16, 2);
        for pass in 0..2u32 {
            let rendered = renderer.render_pass_samples(pass, &control, 0).unwrap();
            let pool = integ.light_pool(&scene, pass, w * h);
            assert!(pool.as_ref().is_some_and(|p| p.len() == (w * h) as usize), "one subpath per pixel");
            let (mut deferred, mut looped) = (Vec::new(), Vec::new());
            for px in 0..w * h {
                let mut rng = Rng::new(21, pass as u64, px as u64);
                let (o, d) = cam.generate_ray(px % w, px / w, Vec2::new(rng.uniform(), rng.uniform()));
                let first = deferred.len();
                looped.push(integ.trace_deferring(&scene, o, d, &mut rng, pool.as_ref(), Some(&mut deferred)));
                for p in &mut deferred[first..] {
                    p.owner = (looped.len() - 1) as u32;
                }
            }
            integ.resolve_deferred(&scene, &mut deferred, &mut looped);
            for (i, (a, b)) in rendered.iter().zip(&looped).enumerate() {
                for (x, y) in [(a.direct, b.direct), (a.low, b.low), (a.high, b.high)] {
                    assert!(
                        (x - y).abs().max_element() <= 1e-5 * (1.0 + x.abs().max_element()),
                        "pixel {i}: {x} vs {y}"
                    );
                }
            }
        }
    }
    let render = |m: u32, threads: usize| {
        let integ = predicting_with(21, 1, 0.1, 1.0, m, 2);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let mut r = engine::Renderer::new(scene.clone(), integ).unwrap();
            let control = engine::RenderControl::new();
            for _ in 0..3 {
                r.render_pass(&control, 0);
            }
            r.snapshot()
        })
    };
    let (a, b) = (render(16, 1), render(16, 2));
    for buf in engine::Buffer::ALL {
        assert!(a.sums(buf) == b.sums(buf), "{buf:?} differs between 1 and 2 threads");
    }
    let high = |f: &engine::Film| f.sums(engine::Buffer::High).iter().map(|p| p[0] as f64).sum::<f64>();
    assert!(high(&a) > 0.0, "the predictions reach the image");
    let c = render(4, 2);
    assert!(a.sums(engine::Buffer::High) != c.sums(engine::Buffer::High), "the candidates matter");
}
