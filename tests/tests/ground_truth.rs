//! The ground-truth estimator of the global model (closed-form transmittance in a
//! homogeneous box) against the engine's general heterogeneous path tracer on a grid
//! holding the same box: independent estimators of the same L_i must agree within
//! their error bars. A grid of ones tapers over half a voxel at the faces with the
//! same optical depth across any face, so the box is represented exactly up to
//! collision positions inside that half voxel (O(sigma * voxel) per crossing).

use engine::stats::{Welford, z_bound};
use engine::{Bounds3, Camera, DensityGrid, Integrator, Medium, PhaseFunction, RenderSettings, Rng, Scene, Sky, Sun};
use glam::{Mat3, UVec3, Vec3};
use models::global::ground_truth::{ConvexMedium, Shape, sample_in_scattered};
use std::sync::Arc;

#[test]
fn box_ground_truth_matches_the_engine() {
    let (sigma, albedo) = (4.0f32, 0.9f32);
    let phase = PhaseFunction::HenyeyGreenstein { g: 0.6 };
    let omega_l = Vec3::new(0.3, -1.0, 0.2).normalize();
    let gt = ConvexMedium::new(Shape::Box, Mat3::from_diagonal(Vec3::splat(0.5)), sigma, albedo, phase).unwrap();
    let n = 128;
    let grid = DensityGrid::from_bounds(
        UVec3::splat(n),
        vec![1.0; (n * n * n) as usize],
        Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
    )
    .unwrap();
    let scene = Scene {
        medium: Medium::new(Arc::new(grid), sigma, albedo, phase).unwrap(),
        sun: Some(Sun::new(omega_l, Vec3::ONE, 0.0).unwrap()),
        sky: Sky::default(),
        camera: Camera::new(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 30.0, 4, 4).unwrap(),
    };
    let engine = Integrator::new(RenderSettings::default(), None).unwrap();
    let queries = [
        (Vec3::ZERO, Vec3::X),
        (Vec3::new(0.2, 0.3, -0.1), Vec3::new(0.0, 0.6, 0.8)),
        (Vec3::new(-0.35, -0.4, 0.25), Vec3::new(-0.48, 0.6, -0.64)),
    ];
    let z = z_bound(0.01, queries.len());
    for (i, &(x, wo)) in queries.iter().enumerate() {
        let (mut a, mut b) = (Welford::default(), Welford::default());
        let mut rng = Rng::new(21, i as u64, 0);
        for _ in 0..600_000 {
            a.add(sample_in_scattered(&gt, omega_l, x, wo, &mut rng) as f64);
            b.add(engine.in_scattered_radiance(&scene, x, wo, &mut rng).x as f64);
        }
        let se = (a.std_error().powi(2) + b.std_error().powi(2)).sqrt();
        assert!((a.mean - b.mean).abs() < z * se, "query {i}: ground truth {} vs engine {} (se {se})", a.mean, b.mean);
        assert!(a.mean > 0.0);
    }
}
