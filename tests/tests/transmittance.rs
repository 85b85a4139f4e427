//! Delta tracking, ratio tracking and ray marching against closed-form transmittance,
//! and free-flight distances against the exponential law. Tolerances are z-scores of
//! the estimators' own standard errors at family-wise alpha = 0.01 (Sidak), or, for
//! the deterministic ray marcher, the midpoint rule's error bound.

use engine::stats::{Welford, chi2_test, z_bound};
use engine::{FreeFlight, Medium, PhaseFunction, Rng};
use glam::Vec3;
use nimbus_tests::{ramp_grid, slab_grid};
use std::sync::Arc;

const N: usize = 1_000_000;

struct Case {
    name: &'static str,
    medium: Medium,
    o: Vec3,
    d: Vec3,
    t_max: f32,
    tau: f64,
    /// Bound on the midpoint rule's error at the step used.
    march_tol: f64,
}

fn cases() -> Vec<Case> {
    let mut out = Vec::new();
    // Homogeneous slab, 8 voxels, thickness 0.5: normal and oblique rays, two densities.
    let (ny, h) = (8u32, 0.5f32);
    let slab = Arc::new(slab_grid(ny, h));
    // The same slab in sparse bricks (majorants from brick maxima).
    let sparse_slab = Arc::new(slab.to_sparse());
    for &rho in &[2.0f32, 5.0] {
        for (&angle, (name, grid)) in
            [0.0f32, 50.0, 50.0].iter().zip([("slab", &slab), ("slab", &slab), ("slab, sparse", &sparse_slab)])
        {
            let a = angle.to_radians();
            let d = Vec3::new(a.sin(), a.cos(), 0.0);
            let o = Vec3::new(0.0, -1.0, 0.0);
            let tau = rho as f64 * h as f64 / a.cos() as f64;
            // Midpoint error: the profile is piecewise linear with 4 kinks (ramps at
            // each face), each costing at most h^2/8 times the slope jump rho / vs.
            let vs = (h / ny as f32) as f64;
            let step = vs / 8.0 / a.cos() as f64;
            let tol = 4.0 * step * step / 8.0 * (rho as f64 / vs) * (1.0 / a.cos() as f64) + 1e-5 * tau;
            out.push(Case {
                name,
                medium: Medium::new(grid.clone(), rho, 1.0, PhaseFunction::Isotropic).unwrap(),
                o,
                d,
                t_max: f32::INFINITY,
                tau,
                march_tol: tol,
            });
        }
    }
    // Linear ramp d(y) = 0.5 + 0.8 y, between voxel centres (no taper on the way):
    // tau = rho * integral over t of d(o.y + t d.y).
    let (a0, b0) = (0.5f32, 0.8f32);
    let ramp = Arc::new(ramp_grid(16, a0, b0));
    for &(rho, angle) in &[(4.0f32, 0.0f32), (6.0, 35.0)] {
        let ang = angle.to_radians();
        let d = Vec3::new(ang.sin(), ang.cos(), 0.0);
        let o = Vec3::new(0.1, -0.45, 0.2);
        let t_max = 0.9 / ang.cos();
        let y0 = o.y as f64;
        let y1 = (o.y + d.y * t_max) as f64;
        let integral_dy = a0 as f64 * (y1 - y0) + 0.5 * b0 as f64 * (y1 * y1 - y0 * y0);
        let tau = rho as f64 * integral_dy / d.y as f64;
        // Tight (cells of 8 voxels) and loose (one cell for the whole grid) majorants: the loose
        // one makes ratio tracking multiply many factors below 1 and play roulette.
        let sparse_ramp = Arc::new(ramp.to_sparse());
        for (name, grid, cells) in
            [("ramp", &ramp, 8), ("ramp, loose majorant", &ramp, 1024), ("ramp, sparse", &sparse_ramp, 8)]
        {
            out.push(Case {
                name,
                medium: Medium::with_majorant_cells(grid.clone(), rho, 1.0, PhaseFunction::Isotropic, cells).unwrap(),
                o,
                d,
                t_max,
                tau,
                // Linear along the ray inside the interior: the midpoint rule is exact
                // up to float rounding.
                march_tol: 1e-4 * tau,
            });
        }
    }
    // The same ramp finer along y: its interior cells have a positive minimum, so the
    // trackers handle that part in closed form (a control density) and track the rest.
    let (rho, o, d) = (4.0f32, Vec3::new(0.1, -0.45, 0.2), Vec3::Y);
    let fine = Arc::new(ramp_grid(64, a0, b0));
    for (name, grid) in [("fine ramp", fine.clone()), ("fine ramp, sparse", Arc::new(fine.to_sparse()))] {
        let (y0, y1) = (o.y as f64, o.y as f64 + 0.9);
        let tau = rho as f64 * (a0 as f64 * (y1 - y0) + 0.5 * b0 as f64 * (y1 * y1 - y0 * y0));
        let medium = Medium::new(grid, rho, 1.0, PhaseFunction::Isotropic).unwrap();
        out.push(Case { name, medium, o, d, t_max: 0.9, tau, march_tol: 1e-4 * tau });
    }
    // Two homogeneous layers: rays from inside the lower one start in a homogeneous
    // block, tracked in closed form, and go on across the step by the ball and the DDA.
    let layers = Arc::new(layer_grid());
    for (name, grid, d) in [
        ("layers", layers.clone(), Vec3::Y),
        ("layers, oblique", layers.clone(), Vec3::new(0.3, 1.0, 0.1).normalize()),
        ("layers, sparse", Arc::new(layers.to_sparse()), Vec3::new(-0.2, 1.0, 0.3).normalize()),
    ] {
        let rho = 1.5f32;
        let (o, t_max) = (LAYER_ORIGIN, 2.0f32);
        let tau = rho as f64 * layer_depth(o.y as f64 + (d.y * t_max) as f64) / d.y as f64;
        // Two kinks (the ends of the step's ramp), each costing at most h^2/8 times the
        // slope jump rho / vs along y.
        let vs = LAYER_VOXEL as f64;
        let step = vs / 8.0 / d.y as f64;
        let march_tol = 2.0 * step * step / 8.0 * (rho as f64 / vs) / d.y as f64 + 1e-5 * tau;
        let medium = Medium::new(grid, rho, 1.0, PhaseFunction::Isotropic).unwrap();
        out.push(Case { name, medium, o, d, t_max, tau, march_tol });
    }
    out
}

/// Edge of the layer grid's voxels.
const LAYER_VOXEL: f32 = 1.0 / 16.0;
/// Where the layer cases' rays start: inside the lower layer.
const LAYER_ORIGIN: Vec3 = Vec3::new(0.1, -1.0, 0.2);

/// Density 1 below y = 0 and 2 above (the step on a voxel face), 64^3 voxels over
/// [-2, 2]^3.
fn layer_grid() -> engine::DensityGrid {
    let b = engine::Bounds3::new(Vec3::splat(-2.0), Vec3::splat(2.0));
    engine::DensityGrid::from_fn(glam::UVec3::splat(64), b, |p| if p.y < 0.0 { 1.0 } else { 2.0 }).unwrap()
}

/// The integral of the layer grid's density along y from the layer cases' origin to
/// `y` (inside the two layers' cores): 1 up to the last voxel centre below the step,
/// linear from 1 to 2 between the centres either side of it, 2 beyond.
fn layer_depth(y: f64) -> f64 {
    let (y0, h) = (LAYER_ORIGIN.y as f64, 0.5 * LAYER_VOXEL as f64);
    if y <= -h {
        y - y0
    } else if y <= h {
        let s = y + h;
        (-h - y0) + s + 0.5 * s * s / (2.0 * h)
    } else {
        (-h - y0) + 3.0 * h + 2.0 * (y - h)
    }
}

/// The layer cases start in a homogeneous block whose stretch ends before the step,
/// so their trackers go from the block to the ball and the DDA.
#[test]
fn layer_cases_start_in_a_homogeneous_block() {
    let layers: Vec<_> = cases().into_iter().filter(|c| c.name.starts_with("layers")).collect();
    assert_eq!(layers.len(), 3);
    for c in layers {
        let s = c.medium.blocks().and_then(|b| b.stretch(c.o, c.d, c.t_max));
        assert!(s.is_some_and(|s| s.t_max > 0.1 && s.t_max < 0.9 * c.t_max), "{}: {s:?}", c.name);
        assert_eq!(c.medium.clone().without_blocks().blocks().map(|b| b.dims()), None);
    }
}

/// The fine ramp has cells with a positive control density along the cases' rays
/// (else those cases would not exercise it).
#[test]
fn fine_ramp_cases_have_a_control_density() {
    for c in cases().iter().filter(|c| c.name.starts_with("fine ramp")) {
        let segs: Vec<_> = c.medium.majorant().segments(c.o, c.d, 0.0, c.t_max).collect();
        let covered: f32 =
            segs.iter().filter(|s| s.min_density > 0.0).map(|s| s.t_max - s.t_min).sum::<f32>() / c.t_max;
        assert!(covered > 0.5, "{}: {covered} of the ray has a control density", c.name);
    }
}

/// The cases that start inside the grid start in a local ball, so the trackers' first
/// stretch, tracked without the DDA, is what their closed forms check.
#[test]
fn cases_inside_the_grid_start_in_a_local_ball() {
    let inside: Vec<_> = cases().into_iter().filter(|c| c.name.contains("ramp")).collect();
    assert_eq!(inside.len(), 8);
    for c in inside {
        let ball = c.medium.majorant().local_ball(c.o);
        assert!(ball.is_some_and(|b| b.radius > 0.0), "{}: {ball:?}", c.name);
    }
}

/// Through homogeneous interior cells the control density is the whole medium: the
/// transmittance comes out in closed form, the same value every time.
#[test]
fn homogeneous_cells_give_exact_transmittance() {
    // 64 voxels over 4 units: cells of 8 voxels, the interior ones y in [-1.53, 1.47].
    let slab = Arc::new(slab_grid(64, 4.0));
    for grid in [slab.clone(), Arc::new(slab.to_sparse())] {
        let medium = Medium::new(grid, 0.5, 1.0, PhaseFunction::Isotropic).unwrap();
        let (o, l) = (Vec3::new(0.1, -1.4, 0.2), 2.8f32);
        let exact = (-0.5 * l as f64).exp();
        let mut rng = Rng::new(9, 0, 0);
        for _ in 0..1000 {
            let t = medium.transmittance_ratio(o, Vec3::Y, l, &mut rng) as f64;
            assert!((t - exact).abs() < 1e-5, "{t} vs {exact}");
        }
        // Without the control, ratio tracking at the majorant is binary here.
        let plain = medium.clone().without_control().with_ratio_oversampling(1.0);
        let zeros = (0..1000).filter(|_| plain.transmittance_ratio(o, Vec3::Y, l, &mut rng) == 0.0).count();
        assert!(zeros > 500, "{zeros} of 1000 plain estimates were 0");
    }
}

/// Chi-square of 10^6 free-flight distances along `o + t d` against the closed form
/// F(t) = 1 - exp(-tau(t)): 50 equal-probability bins on [0, l] and one for "beyond l".
fn flight_distances_chi2(
    medium: &Medium,
    o: Vec3,
    d: Vec3,
    l: f64,
    tau: impl Fn(f64) -> f64,
    mut rng: Rng,
) -> engine::stats::Chi2 {
    let f_l = 1.0 - (-tau(l)).exp();
    let (bins, n) = (50usize, 1_000_000);
    let mut obs = vec![0.0f64; bins + 1];
    for _ in 0..n {
        match medium.sample_free_flight(o, d, f32::INFINITY, &mut rng) {
            FreeFlight::Collision { t } if (t as f64) < l => {
                let b = ((1.0 - (-tau(t as f64)).exp()) / f_l * bins as f64) as usize;
                obs[b.min(bins - 1)] += 1.0;
            }
            _ => obs[bins] += 1.0,
        }
    }
    let mut exp = vec![n as f64 * f_l / bins as f64; bins + 1];
    exp[bins] = n as f64 * (1.0 - f_l);
    chi2_test(&obs, &exp, 5.0)
}

/// Free-flight distances where the medium is part control, part tracked residual
/// (the fine ramp, d(y) = 0.5 + 0.8 y, straight up), dense and sparse storage with
/// their own random streams: chi-square against the closed form F(t) = 1 -
/// exp(-tau(t)) over 50 equal-probability bins on [0, L] and one for "beyond L", at a
/// family-wise alpha of 0.01 over the two (Sidak).
#[test]
fn free_flight_distances_follow_the_ramp() {
    let (a0, b0, rho) = (0.5f64, 0.8f64, 4.0f32);
    let grid = Arc::new(ramp_grid(64, a0 as f32, b0 as f32));
    let alpha = 1.0 - 0.99f64.powf(0.5);
    for (stream, medium) in [
        Medium::new(grid.clone(), rho, 1.0, PhaseFunction::Isotropic).unwrap(),
        Medium::new(Arc::new(grid.to_sparse()), rho, 1.0, PhaseFunction::Isotropic).unwrap(),
    ]
    .into_iter()
    .enumerate()
    {
        let (o, l) = (Vec3::new(0.1, -0.45, 0.2), 0.9f64);
        let y0 = o.y as f64;
        let tau = |t: f64| rho as f64 * (a0 * t + 0.5 * b0 * ((y0 + t).powi(2) - y0 * y0));
        let r = flight_distances_chi2(&medium, o, Vec3::Y, l, tau, Rng::new(17, stream as u64, 0));
        assert!(r.p_value > alpha, "stream {stream}: {r:?}");
    }
}

/// Free-flight distances from inside a homogeneous block (the layer grid, the step
/// ahead), with and without the blocks, on their own random streams: chi-square
/// against the closed form, as for the ramp.
#[test]
fn free_flight_distances_from_a_homogeneous_block() {
    let rho = 1.5f32;
    let grid = Arc::new(layer_grid());
    let d = Vec3::new(0.3, 1.0, 0.1).normalize();
    let (o, l) = (LAYER_ORIGIN, 2.0f64);
    let tau = |t: f64| rho as f64 * layer_depth(o.y as f64 + d.y as f64 * t) / d.y as f64;
    let alpha = 1.0 - 0.99f64.powf(0.5);
    let with = Medium::new(grid, rho, 1.0, PhaseFunction::Isotropic).unwrap();
    assert!(with.blocks().is_some());
    for (stream, medium) in [with.clone(), with.without_blocks()].into_iter().enumerate() {
        let r = flight_distances_chi2(&medium, o, d, l, tau, Rng::new(23, stream as u64, 0));
        assert!(r.p_value > alpha, "stream {stream}: {r:?}");
    }
}

/// Both trackers, with the one-voxel lookups (the default) and with trilinear ones,
/// and ratio tracking at the majorant itself as well as oversampled (the default).
#[test]
fn tracking_estimators_match_closed_form() {
    let cases = cases();
    let z = z_bound(0.01, 6 * cases.len());
    for (i, c) in cases.iter().enumerate() {
        let exact = (-c.tau).exp();
        let variants = [
            ("one-voxel lookups", c.medium.clone()),
            ("trilinear lookups", c.medium.clone().with_trilinear_lookups()),
            ("ratio tracking at the majorant", c.medium.clone().with_ratio_oversampling(1.0)),
        ];
        for (v, (variant, medium)) in variants.iter().enumerate() {
            let name = format!("{} ({variant})", c.name);
            // Delta tracking: a Bernoulli estimator with variance T (1 - T).
            let mut rng = Rng::new(42, i as u64, v as u64);
            let mut delta = Welford::default();
            let mut ratio = Welford::default();
            for _ in 0..N {
                delta.add(medium.transmittance_delta(c.o, c.d, c.t_max, &mut rng) as f64);
                ratio.add(medium.transmittance_ratio(c.o, c.d, c.t_max, &mut rng) as f64);
            }
            let se_delta = (exact * (1.0 - exact) / N as f64).sqrt();
            assert!(
                (delta.mean - exact).abs() < z * se_delta,
                "{name} case {i}: delta tracking {} vs exact {exact} (se {se_delta})",
                delta.mean
            );
            assert!(
                (ratio.mean - exact).abs() < z * ratio.std_error().max(1e-7),
                "{name} case {i}: ratio tracking {} vs exact {exact} (se {})",
                ratio.mean,
                ratio.std_error()
            );
            // Ratio tracking never has more variance than delta tracking (equal where
            // the majorant is tight and the medium homogeneous: both are then binary).
            assert!(ratio.variance() <= delta.variance() * 1.02, "{name} case {i}");
        }
    }
}

/// Oversampled ratio tracking has less variance than ratio tracking at the majorant
/// where the majorant is reached: a hard-edged slab in one majorant cell that also
/// holds empty space, so the cell's control is 0 and the slab's density its
/// majorant. With one-voxel lookups (every voxel 0 or 1) the estimate at the majorant
/// is binary, variance T (1 - T) = 0.23 for tau = 1; at twice it each weight is 1 or
/// 1/2, the estimate 2^-K with K Poisson of mean 2 tau, variance e^(-1.5 tau) -
/// e^(-2 tau) = 0.088 (a little more with the roulette below 0.1). Compared by the
/// second moments, each with its own standard error, after both means agree with
/// the closed form.
#[test]
fn oversampled_ratio_tracking_lowers_the_variance_through_a_hard_edge() {
    let b = engine::Bounds3::new(Vec3::splat(-1.0), Vec3::splat(1.0));
    let grid =
        engine::DensityGrid::from_fn(glam::UVec3::splat(32), b, |p| if p.y.abs() < 0.25 { 1.0 } else { 0.0 }).unwrap();
    let medium =
        Medium::with_majorant_cells(Arc::new(grid), 2.0, 1.0, PhaseFunction::Isotropic, 64).unwrap().without_blocks();
    let (o, d) = (Vec3::new(0.1, -0.9, 0.2), Vec3::Y);
    // Eight voxels of 1 and a ramp of one voxel at each face: optical depth 2 x 0.5.
    let exact = (-1.0f64).exp();
    let z = z_bound(0.01, 3);
    let mut second = Vec::new();
    for (i, m) in [1.0f32, 2.0].into_iter().enumerate() {
        let medium = medium.clone().with_ratio_oversampling(m);
        let mut rng = Rng::new(3, i as u64, 0);
        let (mut mean, mut sq) = (Welford::default(), Welford::default());
        for _ in 0..N {
            let t = medium.transmittance_ratio(o, d, f32::INFINITY, &mut rng) as f64;
            mean.add(t);
            sq.add(t * t);
        }
        assert!((mean.mean - exact).abs() < z * mean.std_error(), "m {m}: {} against {exact}", mean.mean);
        second.push((mean.mean, sq.mean, sq.std_error()));
    }
    let ((m1, s1, e1), (m2, s2, e2)) = (second[0], second[1]);
    // Binary: the second moment is about the mean itself; oversampled, well below.
    assert!(s1 > 0.9 * m1, "at the majorant: E[T^2] {s1} against E[T] {m1}");
    assert!(
        s1 - s2 > z * (e1 * e1 + e2 * e2).sqrt(),
        "E[T^2] at the majorant {s1} (se {e1}), at twice it {s2} (se {e2})"
    );
    assert!(s2 - m2 * m2 < 0.5 * (s1 - m1 * m1), "variance {} oversampled against {}", s2 - m2 * m2, s1 - m1 * m1);
}

#[test]
fn ray_marching_matches_closed_form() {
    for (i, c) in cases().iter().enumerate() {
        let vs = c.medium.grid().voxel_size().y;
        let tau = c.medium.optical_depth(c.o, c.d, c.t_max, vs / 8.0, f32::INFINITY) as f64;
        assert!(
            (tau - c.tau).abs() <= c.march_tol,
            "{} case {i}: marched {tau} vs exact {} (tol {})",
            c.name,
            c.tau,
            c.march_tol
        );
        // Early exit: stops once past tau_stop, reporting at least tau_stop.
        let partial = c.medium.optical_depth(c.o, c.d, c.t_max, vs / 8.0, 0.5) as f64;
        assert!(partial >= 0.5 && partial <= tau + 1e-6);
    }
}

/// Free-flight distances in a homogeneous region follow rho exp(-rho t): chi-square
/// over 50 equal-probability bins of the exponential law on [0, L], plus one bin for
/// "beyond L".
#[test]
fn free_flight_distances_are_exponential() {
    let slab = Arc::new(slab_grid(64, 4.0)); // 4 units thick, y in [-2, 2]
    let rho = 1.5f32;
    let medium = Medium::new(slab, rho, 1.0, PhaseFunction::Isotropic).unwrap();
    // From inside the interior, straight up; the taper starts 2 - vs/2 above o.
    let o = Vec3::new(0.0, -1.9, 0.0);
    let l = 3.8f64; // stays in the constant region
    // o lies in a homogeneous block, the flight's first stretch in closed form; where
    // that ends, a local ball (its cell reaches past the grid, so it is tracked
    // against a control of 0) without the DDA; then the DDA.
    let block = medium.blocks().and_then(|b| b.stretch(o, Vec3::Y, f32::INFINITY)).expect("a homogeneous block");
    assert!(block.t_max > 0.0 && (block.t_max as f64) < l, "{block:?}");
    let ball = medium.majorant().local_ball(o + Vec3::Y * block.t_max).expect("a local ball");
    assert!(ball.radius > 0.0, "{ball:?}");
    let bins = 50usize;
    let p_beyond = (-(rho as f64) * l).exp();
    let mut obs = vec![0.0f64; bins + 1];
    let mut rng = Rng::new(5, 0, 0);
    let n = 1_000_000;
    for _ in 0..n {
        match medium.sample_free_flight(o, Vec3::Y, f32::INFINITY, &mut rng) {
            FreeFlight::Collision { t } if (t as f64) < l => {
                let cdf = 1.0 - (-(rho as f64) * t as f64).exp();
                let b = (cdf / (1.0 - p_beyond) * bins as f64) as usize;
                obs[b.min(bins - 1)] += 1.0;
            }
            _ => obs[bins] += 1.0,
        }
    }
    let mut exp = vec![n as f64 * (1.0 - p_beyond) / bins as f64; bins + 1];
    exp[bins] = n as f64 * p_beyond;
    let r = chi2_test(&obs, &exp, 5.0);
    assert!(r.p_value > 0.01, "{r:?}");
}

/// The weighted first collision (ratio tracking along the whole ray, one tentative
/// collision kept by its weight): on every case its transmittance estimate has mean
/// T = exp(-tau) and its weight W has mean 1 - T (the integral of T sigma_t over the
/// ray); on the fine ramp (straight up, closed-form tau(t)) W times the indicator of
/// the kept distance's bin has mean F(b1) - F(b0), F(t) = 1 - exp(-tau(t)), in each of
/// 10 equal-probability bins, with the collision kept by weight alone and guided by a
/// function of the position (resampled, W divided by the guide there). Tolerances: z-scores of each estimator's own standard
/// error at family-wise alpha = 0.01.
#[test]
fn weighted_first_collision_matches_closed_form() {
    let cases = cases();
    let bins = 10usize;
    let z = z_bound(0.01, 2 * cases.len() + 2 * bins);
    for (i, c) in cases.iter().enumerate() {
        let exact = (-c.tau).exp();
        let mut rng = Rng::new(43, i as u64, 0);
        let (mut tr, mut w) = (Welford::default(), Welford::default());
        for _ in 0..N / 2 {
            let (kept, t) = c.medium.sample_collision_weighted(c.o, c.d, c.t_max, &mut rng);
            tr.add(t as f64);
            w.add(kept.map_or(0.0, |(_, w)| w as f64));
        }
        let what = format!("{} case {i}", c.name);
        assert!((tr.mean - exact).abs() < z * tr.std_error().max(1e-7), "{what}: T {} vs {exact}", tr.mean);
        let want = 1.0 - exact;
        assert!((w.mean - want).abs() < z * w.std_error().max(1e-7), "{what}: W {} vs {want}", w.mean);
    }
    let (a0, b0, rho) = (0.5f64, 0.8f64, 4.0f32);
    let medium =
        Medium::new(Arc::new(ramp_grid(64, a0 as f32, b0 as f32)), rho, 1.0, PhaseFunction::Isotropic).unwrap();
    let (o, l) = (Vec3::new(0.1, -0.45, 0.2), 0.9f64);
    let y0 = o.y as f64;
    let tau = |t: f64| rho as f64 * (a0 * t + 0.5 * b0 * ((y0 + t).powi(2) - y0 * y0));
    let f = |t: f64| 1.0 - (-tau(t)).exp();
    let f_l = f(l);
    // By weight alone, and guided by a positive function of the position.
    for (g, guide) in
        [&(|_: Vec3| 1.0f32) as &dyn Fn(Vec3) -> f32, &|x: Vec3| 0.3 + (x.y + 0.5).powi(2)].into_iter().enumerate()
    {
        let mut per_bin = vec![Welford::default(); bins];
        let mut rng = Rng::new(44, g as u64, 0);
        for _ in 0..N {
            let (kept, _) = medium.sample_collision_guided(o, Vec3::Y, l as f32, &mut rng, guide);
            let bin = kept.map(|(t, _)| (((f(t as f64) / f_l) * bins as f64) as usize).min(bins - 1));
            for (b, acc) in per_bin.iter_mut().enumerate() {
                acc.add(match (bin, kept) {
                    (Some(k), Some((_, w))) if k == b => w as f64,
                    _ => 0.0,
                });
            }
        }
        for (b, acc) in per_bin.iter().enumerate() {
            let want = f_l / bins as f64;
            assert!(
                (acc.mean - want).abs() < z * acc.std_error(),
                "guide {g}, bin {b}: {} vs {want} (se {})",
                acc.mean,
                acc.std_error()
            );
        }
    }
}
