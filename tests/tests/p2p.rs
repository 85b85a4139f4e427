//! The point-to-point transport estimator (thesis eqs. 6.1-6.2): the closed form of
//! a purely absorbing medium, and agreement between independent estimators on a
//! heterogeneous cloud (the three connection schemes, both heuristics, different
//! sensor subpath lengths, and emitter and sensor exchanged, which makes different
//! random walks estimate the same symmetric T).

use engine::MisHeuristic;
use engine::P2pQuery;
use engine::integrator::p2p::{ConnectionScheme, P2pSettings, sample_transport};
use engine::stats::{Welford, z_bound};
use engine::{Medium, PhaseFunction, Rng};
use glam::{UVec3, Vec3};
use std::sync::Arc;

fn estimate(medium: &Medium, q: &P2pQuery, set: &P2pSettings, n: u64, seed: u64) -> Welford {
    let mut w = Welford::default();
    let mut rng = Rng::new(seed, 0, 0);
    for _ in 0..n {
        let v = sample_transport(medium, q, set, &mut rng);
        assert!(v.is_finite() && v >= 0.0);
        w.add(v as f64);
    }
    w
}

/// Albedo 0: only the direct segment, T = p(w_e, d) p(w_s, -d) exp(-sigma d) / d^2.
#[test]
fn absorbing_medium_matches_the_closed_form() {
    let b = engine::Bounds3::new(Vec3::splat(-1.0), Vec3::splat(1.0));
    let grid = Arc::new(engine::DensityGrid::from_fn(UVec3::splat(8), b, |_| 1.0).unwrap());
    let phase = PhaseFunction::HenyeyGreenstein { g: 0.4 };
    let medium = Medium::new(grid, 3.0, 0.0, phase).unwrap();
    let q = P2pQuery {
        emitter: Vec3::new(-0.3, 0.1, 0.0),
        omega_e: Vec3::new(0.0, 1.0, 0.0),
        sensor: Vec3::new(0.4, -0.2, 0.1),
        omega_s: Vec3::new(0.6, 0.0, 0.8),
    };
    let d = q.sensor - q.emitter;
    let dir = d.normalize();
    let want = (phase.eval(q.omega_e, dir) * phase.eval(q.omega_s, -dir) * (-3.0 * d.length()).exp()
        / d.length_squared()) as f64;
    let w = estimate(&medium, &q, &P2pSettings { scheme: ConnectionScheme::All, ..Default::default() }, 200_000, 1);
    let z = (w.mean - want) / w.std_error();
    assert!(z.abs() < z_bound(0.01, 1), "{} vs {want}: z {z:.2}", w.mean);
}

/// On a heterogeneous cloud, every scheme and heuristic, a shorter sensor subpath,
/// and the exchanged query estimate the same T.
#[test]
fn independent_estimators_agree() {
    let grid = Arc::new(app::cloud::Builtin::Cumulus.grid(24));
    let medium = Medium::new(grid, 8.0, 0.95, PhaseFunction::HenyeyGreenstein { g: 0.5 }).unwrap();
    let q = P2pQuery {
        emitter: Vec3::new(-0.15, 0.0, 0.05),
        omega_e: Vec3::new(0.0, 1.0, 0.0),
        sensor: Vec3::new(0.12, 0.08, -0.05),
        omega_s: Vec3::new(-0.6, 0.0, 0.8),
    };
    assert!(medium.sigma_t(q.emitter) > 0.0 && medium.sigma_t(q.sensor) > 0.0, "the points are inside the cloud");
    let base = P2pSettings::default();
    let variants: Vec<(&str, P2pQuery, P2pSettings)> = vec![
        ("all, power", q, P2pSettings { scheme: ConnectionScheme::All, ..base }),
        ("RR1", q, P2pSettings { scheme: ConnectionScheme::Rr1, ..base }),
        ("RR2, balance", q, P2pSettings { heuristic: MisHeuristic::Balance, ..base }),
        ("RR2, 2 sensor vertices", q, P2pSettings { max_sensor_vertices: 2, ..base }),
        ("exchanged", q.swapped(), base),
    ];
    let n = 200_000;
    let reference = estimate(&medium, &q, &base, n, 100);
    let bound = z_bound(0.01, variants.len());
    for (i, (name, query, set)) in variants.iter().enumerate() {
        let w = estimate(&medium, query, set, n, 200 + i as u64);
        let z = (w.mean - reference.mean) / (w.std_error().powi(2) + reference.std_error().powi(2)).sqrt();
        println!(
            "{name}: {:.5} +- {:.5} vs {:.5} +- {:.5}, z {z:+.2}",
            w.mean,
            w.std_error(),
            reference.mean,
            reference.std_error()
        );
        assert!(z.abs() < bound, "{name}: {} vs {}: z {z:.2} beyond {bound:.2}", w.mean, reference.mean);
    }
    // Most of it comes from scattered paths, not the direct segment.
    let direct = estimate(&medium, &q, &P2pSettings { max_segments: Some(1), ..base }, 20_000, 7);
    assert!(direct.mean < 0.8 * reference.mean, "direct {} of {}", direct.mean, reference.mean);
}
