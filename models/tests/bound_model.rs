//! The renderer's fast path for the global model (features from a precomputed depth
//! field) against the direct path (n_D ray marches per prediction) on a smooth
//! heterogeneous cloud: the features agree to within the field's discretization and
//! the predictions agree closely.

use engine::{Bounds3, DensityGrid, InScatterPredictor, Medium, PhaseFunction, Rng, Sun};
use glam::{UVec3, Vec3};
use models::global::{BoundGlobalModel, GlobalModel};
use std::sync::Arc;

fn blob(n: u32) -> DensityGrid {
    DensityGrid::from_fn(UVec3::splat(n), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
        let r = (p * Vec3::new(1.0, 1.4, 1.0)).length();
        let wobble = 0.5 + 0.5 * (7.0 * p.x).sin() * (5.0 * p.z).cos();
        ((0.42 - r) * 12.0).clamp(0.0, 1.0) * (0.4 + 0.6 * wobble)
    })
    .unwrap()
}

#[test]
fn depth_field_features_and_predictions_match_ray_marching() {
    let medium = Medium::new(Arc::new(blob(96)), 40.0, 1.0, PhaseFunction::HenyeyGreenstein { g: 0.85 }).unwrap();
    let sun = Sun::new(Vec3::new(0.3, -1.0, 0.2), Vec3::ONE, 0.0).unwrap();
    let model = GlobalModel::shipped().unwrap();
    let bound = BoundGlobalModel::new(model.clone(), &medium, &sun, 64);
    let n = model.feature_extractor().len();
    let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
    let mut rng = Rng::new(17, 0, 0);
    let (mut feat_err, mut count) = (0.0f64, 0usize);
    let mut rel = vec![];
    let mut queries = vec![];
    while rel.len() < 300 {
        let x = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5;
        if medium.grid().lookup(x) < 0.05 {
            continue;
        }
        let w = engine::sampling::sample_uniform_sphere(rng.uniform2());
        bound.features(&medium, x, w, &mut a);
        model.feature_extractor().extract_grid(&medium, sun.direction(), x, w, &mut b);
        assert_eq!(&a[..4], &b[..4]);
        for i in 4..n {
            feat_err += (a[i] - b[i]).abs() as f64;
            count += 1;
        }
        queries.push((x, w));
        let (pf, pm) = (bound.predict(&medium, &sun, x, w), model.predict(&medium, &sun, x, w));
        assert!(pf.is_finite() && pf >= 0.0);
        rel.push(((pf - pm) / pm.max(1e-6)).abs());
    }
    let mean_feat = feat_err / count as f64;
    // Node spacing 1/63 at sigma 40 moves tau by at most ~0.6 across a node near the
    // surface; in tau_hat units the average is far smaller.
    assert!(mean_feat < 0.05, "mean |tau_hat field - tau_hat march| = {mean_feat}");
    rel.sort_by(f32::total_cmp);
    let median = rel[rel.len() / 2];
    let p90 = rel[rel.len() * 9 / 10];
    assert!(median < 0.03 && p90 < 0.10, "prediction difference: median {median}, p90 {p90}");
    // Another sun or medium falls back to marching: the same answer as the model itself.
    let other = Sun::new(Vec3::NEG_Y, Vec3::ONE, 0.0).unwrap();
    let x = Vec3::ZERO;
    assert_eq!(bound.predict(&medium, &other, x, Vec3::X), model.predict(&medium, &other, x, Vec3::X));
    // A batch (37 points: two full batches of the network's rows and a tail) gives each
    // point the bits of a single prediction, for the bound sun and for another.
    let (xs, ws): (Vec<_>, Vec<_>) = queries[..37].iter().copied().unzip();
    for light in [&sun, &other] {
        let mut many = vec![f32::NAN; 37];
        bound.predict_many(&medium, light, &xs, &ws, &mut many);
        for (i, &(x, w)) in queries[..37].iter().enumerate() {
            assert_eq!(many[i].to_bits(), bound.predict(&medium, light, x, w).to_bits(), "point {i}");
        }
    }
}

/// The point-to-point model bound to a cloud answers a batch (how the renderer asks
/// for a tile's predictions) exactly as it answers the same queries one by one with
/// the same streams, including a degenerate pair (emitter = sensor: zero).
#[test]
fn batched_point_to_point_predictions_match_single_ones() {
    use engine::P2pQuery;
    use engine::TransportPredictor;
    use models::p2p::model::{BoundP2pModel, P2pModel};
    let medium = Medium::new(Arc::new(blob(48)), 25.0, 0.99, PhaseFunction::Isotropic).unwrap();
    let bound = BoundP2pModel::new(P2pModel::shipped().unwrap(), &medium);
    let mut rng = Rng::new(23, 0, 0);
    let mut point = || Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 0.6 - 0.3;
    let mut queries: Vec<P2pQuery> =
        (0..37).map(|_| P2pQuery { emitter: point(), omega_e: Vec3::Z, sensor: point(), omega_s: -Vec3::Z }).collect();
    queries[5].sensor = queries[5].emitter;
    let streams: Vec<Rng> = (0..queries.len() as u64).map(|i| Rng::new(29, i, 0)).collect();
    let single: Vec<f32> =
        queries.iter().zip(streams.clone()).map(|(q, mut r)| bound.predict(&medium, q, &mut r)).collect();
    let mut batched = vec![f32::NAN; queries.len()];
    bound.predict_batch(&medium, &queries, &mut streams.clone(), &mut batched);
    assert_eq!(single[5], 0.0);
    assert_eq!(batched[5], 0.0);
    for (i, (a, b)) in single.iter().zip(&batched).enumerate() {
        assert!(a.is_finite() && (i == 5 || *a > 0.0), "query {i}: {a}");
        assert!((a - b).abs() <= 1e-4 * a.abs(), "query {i}: single {a}, batched {b}");
    }
}

/// The all-direction field (sky directions, a soft sun's disk) against ray-marched
/// features for random lights on the same cloud: the features agree to within the
/// coarser lattice and the blend across directions, and so do the predictions. A
/// light within 2 degrees of the sun is answered from the sun's own field.
#[test]
fn all_direction_field_predictions_match_ray_marching_for_any_light() {
    let medium = Medium::new(Arc::new(blob(96)), 40.0, 1.0, PhaseFunction::HenyeyGreenstein { g: 0.85 }).unwrap();
    let sun = Sun::new(Vec3::new(0.3, -1.0, 0.2), Vec3::ONE, 0.0).unwrap();
    let model = GlobalModel::shipped().unwrap();
    let bound = BoundGlobalModel::new(model.clone(), &medium, &sun, 64).with_other_lights(
        &medium,
        models::global::sky_field::DEFAULT_TEXELS,
        32,
    );
    let mut rng = Rng::new(19, 0, 0);
    let mut rel = vec![];
    while rel.len() < 300 {
        let x = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5;
        if medium.grid().lookup(x) < 0.05 {
            continue;
        }
        let w = engine::sampling::sample_uniform_sphere(rng.uniform2());
        let light = Sun::new(engine::sampling::sample_uniform_sphere(rng.uniform2()), Vec3::ONE, 0.0).unwrap();
        let (pf, pm) = (bound.predict(&medium, &light, x, w), model.predict(&medium, &light, x, w));
        assert!(pf.is_finite() && pf >= 0.0);
        rel.push(((pf - pm) / pm.max(1e-6)).abs());
    }
    rel.sort_by(f32::total_cmp);
    let (median, p90) = (rel[rel.len() / 2], rel[rel.len() * 9 / 10]);
    eprintln!("all-direction field: median {median}, p90 {p90}");
    assert!(median < 0.05 && p90 < 0.15, "prediction difference: median {median}, p90 {p90}");
    // Within 2 degrees of the sun: the sun's field, bit for bit.
    let near = Sun::new((sun.direction() + Vec3::new(0.02, 0.0, 0.0)).normalize(), Vec3::ONE, 0.0).unwrap();
    assert!(near.direction().dot(sun.direction()) > 0.035f32.cos());
    let (x, w) = (Vec3::new(0.05, 0.1, 0.0), Vec3::X);
    assert_eq!(bound.predict(&medium, &near, x, w), bound.predict(&medium, &sun, x, w));
    // Another medium still falls back to marching.
    let other = Medium::new(medium.grid().clone(), 20.0, 1.0, PhaseFunction::HenyeyGreenstein { g: 0.85 }).unwrap();
    assert_eq!(bound.predict(&other, &sun, x, w), model.predict(&other, &sun, x, w));
}
