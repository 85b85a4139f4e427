//! The data generator's first-collision queries (`--first-collision`): the distance t
//! from the entry point to the query point, given the ray's chord c through the shape,
//! is a free flight truncated at c, so its probability-integral transform
//! u = (1 - exp(-sigma t)) / (1 - exp(-sigma c)) is exactly uniform (chi-square), and
//! the query direction points back along the ray (so t = distance to the boundary
//! along it).

use engine::stats::{chi2_test, sidak};
use models::global::datagen::{GlobalSpec, ShapeKind, sample_setup};

#[test]
fn first_collision_queries_are_truncated_free_flights() {
    let shapes = [ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Ellipsoid];
    for (si, shape) in shapes.iter().enumerate() {
        let spec = GlobalSpec {
            sigma: [0.5, 30.0],
            shapes: vec![*shape],
            scale: [0.5, 1.0],
            first_collision: 1.0,
            seed: 5 + si as u64,
            ..Default::default()
        };
        let bins = 20;
        let n = 40_000;
        let mut counts = vec![0.0f64; bins];
        for i in 0..n {
            let (medium, _, x, wo, _) = sample_setup(&spec, i);
            assert!(medium.contains(x - wo * 1e-4) || medium.contains(x), "{shape:?}: point outside");
            let t = medium.exit_distance(x, wo);
            let c = t + medium.exit_distance(x, -wo);
            let s = medium.sigma_t as f64;
            let u = (1.0 - (-s * t as f64).exp()) / (1.0 - (-s * c as f64).exp());
            counts[((u * bins as f64) as usize).min(bins - 1)] += 1.0;
        }
        let chi = chi2_test(&counts, &vec![n as f64 / bins as f64; bins], 5.0);
        assert!(chi.p_value > sidak(0.01, shapes.len()), "{shape:?}: {chi:?} {counts:?}");
    }
}
