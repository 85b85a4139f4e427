//! The point-to-point model's density features (thesis 6.1.1): pyramid lookups
//! against brute-force Gaussian convolution, constant features in a homogeneous
//! medium, the local frame, and the diffusion feature's closed form.

use engine::{Bounds3, DensityGrid, Rng};
use glam::{UVec3, Vec3};
use models::p2p::features::diffusion_fluence;
use models::p2p::{DensityPyramid, LocalFrame, P2pFeatures};

fn blobs(n: u32) -> DensityGrid {
    let b = Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5));
    DensityGrid::from_fn(UVec3::splat(n), b, |p| {
        let a = (-(p - Vec3::new(0.05, -0.03, 0.02)).length_squared() / (2.0 * 0.1 * 0.1)).exp();
        let c = 0.6 * (-(p - Vec3::new(-0.2, 0.15, -0.1)).length_squared() / (2.0 * 0.05 * 0.05)).exp();
        a + c
    })
    .unwrap()
}

/// Sum over voxels of value x Gaussian(std) x voxel volume: the grid convolved with
/// the Gaussian, evaluated directly.
fn direct(grid: &DensityGrid, p: Vec3, std: f32) -> f32 {
    let d = grid.dims();
    let h = grid.voxel_size();
    let norm = (2.0 * std::f64::consts::PI * (std as f64).powi(2)).powf(1.5);
    let mut sum = 0.0f64;
    for z in 0..d.z {
        for y in 0..d.y {
            for x in 0..d.x {
                let c = grid.origin() + (UVec3::new(x, y, z).as_vec3() + 0.5) * h;
                let r2 = (c - p).length_squared() as f64;
                sum += grid.voxel(x, y, z) as f64 * (-r2 / (2.0 * (std as f64).powi(2))).exp();
            }
        }
    }
    (sum * (h.x * h.y * h.z) as f64 / norm) as f32
}

/// Filtered lookups agree with direct convolution within 1/32 of the largest value
/// at that width, for widths from 1.6 to 16 voxels, inside and outside the cloud.
/// With 32-bit and with 16-bit samples. The pyramid is exact in the filter's second moment, but linear interpolation
/// between samples h apart errs by up to h^2 |f''| / 8, and a field filtered to
/// width s has |f''| <= f_max / s^2 at its peak: with samples half a width apart
/// (h = s / 2) that is f_max / 32, the bound tested here.
#[test]
fn pyramid_lookups_match_direct_convolution() {
    let grid = blobs(40);
    let full = DensityPyramid::new(&grid, 1.0);
    assert!(full.levels() >= 6, "{} levels", full.levels());
    let half = full.quantized();
    let mut rng = Rng::new(3, 0, 0);
    let points: Vec<Vec3> =
        (0..24).map(|_| Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1.2 - 0.6).collect();
    let mut worst = 0.0f32;
    for std in [0.04f32, 0.07, 0.1, 0.15, 0.2, 0.3, 0.4] {
        let d: Vec<f32> = points.iter().map(|p| direct(&grid, *p, std)).collect();
        let peak = d.iter().copied().fold(0.0, f32::max).max(direct(&grid, Vec3::new(0.05, -0.03, 0.02), std));
        for (p, want) in points.iter().zip(&d) {
            // The 32-bit pyramid and the 16-bit one lookups read.
            for pyr in [&full, &half] {
                let got = pyr.lookup(*p, std);
                let err = (got - want).abs() / peak;
                worst = worst.max(err);
                assert!(err < 1.0 / 32.0, "std {std} at {p}: pyramid {got} direct {want} (peak {peak})");
            }
        }
    }
    println!("largest error: {:.2} % of the peak", 100.0 * worst);
}

/// A homogeneous medium gives constant densities, distance x rho x density, at every
/// feature point and level, and phi_D is the closed form at that density.
#[test]
fn homogeneous_medium_gives_constant_features() {
    let b = Bounds3::new(Vec3::splat(-6.0), Vec3::splat(6.0));
    let grid = DensityGrid::from_fn(UVec3::splat(48), b, |_| 0.5).unwrap();
    let spec = P2pFeatures::default();
    let (rho, albedo, dist) = (40.0f32, 0.99f32, 0.1f32);
    let pyr = models::p2p::features::pyramid_for(&grid, &spec, dist);
    let mut out = vec![0.0; spec.len()];
    let mut rng = Rng::new(4, 0, 0);
    for _ in 0..5 {
        let e = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 0.4 - 0.2;
        let dir = engine::sampling::sample_uniform_sphere(rng.uniform2());
        let frame = LocalFrame::new(e, e + dir * dist, 6.0 * rng.uniform()).unwrap();
        spec.write(&pyr, rho, albedo, &frame, &mut out);
        let want = dist * rho * 0.5;
        for (i, v) in out[..spec.densities()].iter().enumerate() {
            assert!((v / want - 1.0).abs() < 2e-3, "feature {i}: {v} vs {want}");
        }
        let phi = out[spec.densities()];
        assert!((phi / diffusion_fluence(want, albedo, 1.0) - 1.0).abs() < 2e-3);
    }
}

/// F takes the emitter and sensor exactly to (0, 0, -1/2) and (0, 0, 1/2), is
/// inverted by `to_world`, preserves angles, and its free angle turns about the axis.
#[test]
fn local_frame_maps_emitter_and_sensor() {
    let mut rng = Rng::new(5, 0, 0);
    for _ in 0..100 {
        let r = |rng: &mut Rng| Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 2.0 - 1.0;
        let (e, s, q) = (r(&mut rng), r(&mut rng), r(&mut rng));
        let angle = std::f32::consts::TAU * rng.uniform();
        let f = LocalFrame::new(e, s, angle).unwrap();
        assert!((f.to_local(e) - Vec3::new(0.0, 0.0, -0.5)).length() < 1e-5);
        assert!((f.to_local(s) - Vec3::new(0.0, 0.0, 0.5)).length() < 1e-5);
        assert!((f.to_world(f.to_local(q)) - q).length() < 1e-5);
        assert!(((f.to_local(q) - f.to_local(e)).length() * f.scale - (q - e).length()).abs() < 1e-4);
        let g = LocalFrame::new(e, s, angle + 1.0).unwrap();
        let (a, b) = (f.to_local(q), g.to_local(q));
        assert!((a.z - b.z).abs() < 1e-5 && (a.truncate().length() - b.truncate().length()).abs() < 1e-5);
        assert!((a.truncate().angle_to(b.truncate()).abs() - 1.0).abs() < 1e-3 || a.truncate().length() < 1e-3);
    }
    assert!(LocalFrame::new(Vec3::ONE, Vec3::ONE, 0.0).is_none());
}

/// 351 densities for the thesis's 3, 3, 4, 5, grouped per level for the network.
#[test]
fn feature_layout() {
    let spec = P2pFeatures::default();
    assert_eq!(spec.densities(), 351);
    assert_eq!(spec.len(), 352);
    let slices = spec.slices();
    assert_eq!(slices.len(), 9);
    assert_eq!(slices.iter().map(|s| s.len).sum::<usize>(), 351);
    assert!(slices.windows(2).all(|w| w[0].start + w[0].len == w[1].start));
    // Diffusion: albedo 1 gives 3 sigma_t / (4 pi r); absorption makes it fall faster.
    let phi = diffusion_fluence(10.0, 1.0, 0.5);
    assert!((phi - 3.0 * 10.0 / (4.0 * std::f32::consts::PI * 0.5)).abs() < 1e-4 * phi);
    assert!(diffusion_fluence(10.0, 0.9, 2.0) / diffusion_fluence(10.0, 0.9, 1.0) < 0.5);
    assert_eq!(diffusion_fluence(0.0, 1.0, 1.0), 0.0);
}
