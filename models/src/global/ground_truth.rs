//! Ground truth for the global transport model (thesis section 5.3): the in-scattered
//! radiance L_i(x -> omega) (eq. 5.5) at a point inside a homogeneous convex shape lit
//! by one directional light of unit radiance, estimated by path tracing with next
//! event estimation, using the closed-form transmittance and exact free-flight
//! sampling that a homogeneous convex medium allows, and confidence-interval stopping
//! (thesis 2.2.6).

pub use crate::dataset::stopping::{Estimate, Stopping};
use engine::{PhaseFunction, Rng};
use glam::{Mat3, Vec3};

/// The unit shapes: sphere of radius 1, box [-1, 1]^3 (an ellipsoid is a scaled
/// sphere).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    Sphere,
    Box,
}

/// A homogeneous convex medium: a unit shape under `world_from_local` (rotation and
/// scale) around the origin.
#[derive(Clone, Copy, Debug)]
pub struct ConvexMedium {
    pub shape: Shape,
    world_from_local: Mat3,
    local_from_world: Mat3,
    pub sigma_t: f32,
    pub albedo: f32,
    pub phase: PhaseFunction,
}

impl ConvexMedium {
    pub fn new(shape: Shape, world_from_local: Mat3, sigma_t: f32, albedo: f32, phase: PhaseFunction) -> Option<Self> {
        let det = world_from_local.determinant();
        (det.abs() > 1e-9 && sigma_t >= 0.0 && (0.0..=1.0).contains(&albedo)).then(|| ConvexMedium {
            shape,
            world_from_local,
            local_from_world: world_from_local.inverse(),
            sigma_t,
            albedo,
            phase,
        })
    }

    /// Is `x` inside?
    pub fn contains(&self, x: Vec3) -> bool {
        let l = self.local_from_world * x;
        match self.shape {
            Shape::Sphere => l.length_squared() <= 1.0,
            Shape::Box => l.abs().max_element() <= 1.0,
        }
    }

    /// A uniformly distributed point inside.
    pub fn sample_inside(&self, rng: &mut Rng) -> Vec3 {
        loop {
            let l = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 2.0 - 1.0;
            if self.shape == Shape::Box || l.length_squared() <= 1.0 {
                return self.world_from_local * l;
            }
        }
    }

    /// Distance from `x` (inside) along unit `d` to the boundary. The ray parameter is
    /// the same in local space when the direction is mapped linearly.
    pub fn exit_distance(&self, x: Vec3, d: Vec3) -> f32 {
        let (o, v) = (self.local_from_world * x, self.local_from_world * d);
        let t = match self.shape {
            Shape::Sphere => {
                let a = v.length_squared();
                let b = o.dot(v);
                let c = o.length_squared() - 1.0;
                let disc = (b * b - a * c).max(0.0);
                (-b + disc.sqrt()) / a
            }
            Shape::Box => {
                let mut t = f32::INFINITY;
                for k in 0..3 {
                    if v[k] > 0.0 {
                        t = t.min((1.0 - o[k]) / v[k]);
                    } else if v[k] < 0.0 {
                        t = t.min((-1.0 - o[k]) / v[k]);
                    }
                }
                t
            }
        };
        t.max(0.0)
    }

    /// Closed-form transmittance from `x` to the boundary along `d`.
    pub fn transmittance_to_boundary(&self, x: Vec3, d: Vec3) -> f32 {
        (-self.sigma_t * self.exit_distance(x, d)).exp()
    }
}

/// One sample of L_i(x -> wo) for a light of unit radiance travelling along `omega_l`:
/// NEE at x (single scattering), then a random walk with exact free flights, NEE at
/// every vertex and Russian roulette on throughput.
///
/// [`sample_in_scattered_with`] can add a light-lobe technique for peaked phase
/// functions (off by default, see the body): the
/// NEE at vertex j+1 carries the factor p(-w, l) of the direction w chosen at vertex
/// j, which is huge when w points at the light (HG at g = 0.85 peaks at 6.5 against a
/// mean of 1/(4 pi)). So each vertex also samples a second direction from that lobe,
/// p(-w, l), flies to a collision and does NEE there; the two techniques for that
/// two-segment subpath are combined with the balance heuristic (one-sample MIS per
/// technique), so the estimator stays unbiased while the peak is sampled directly.
/// The walk itself always continues along the phase-sampled direction (throughput
/// weights stay 1), so long paths in dense media keep their variance.
pub fn sample_in_scattered(m: &ConvexMedium, omega_l: Vec3, x: Vec3, wo: Vec3, rng: &mut Rng) -> f32 {
    // The light-lobe MIS is off by default: it halves the samples per point but doubles
    // the cost per sample (no net gain measured), and the engine cross-check at 600k
    // samples per query (tests/tests/ground_truth.rs) showed a 3.2 sigma difference with
    // it on that is not yet explained. Investigate before switching it back on.
    sample_in_scattered_with(m, omega_l, x, wo, rng, false)
}

/// [`sample_in_scattered`] with the light-lobe technique switched on or off.
pub fn sample_in_scattered_with(m: &ConvexMedium, omega_l: Vec3, x: Vec3, wo: Vec3, rng: &mut Rng, lobe: bool) -> f32 {
    let to_light = -omega_l;
    let (mut x, mut wo, mut beta, mut sum) = (x, wo, 1.0f32, 0.0f32);
    // MIS weight of the NEE at the current vertex (1 at the query point).
    let mut nee_weight = 1.0f32;
    let mut order = 1u32;
    loop {
        sum += beta * nee_weight * m.phase.eval(wo, to_light) * m.transmittance_to_boundary(x, to_light);
        if lobe {
            // Technique B: direction from the light lobe of the next vertex's NEE.
            let wb = m.phase.sample(-to_light, rng.uniform2()).wi;
            let (pdf_a, pdf_b) = (m.phase.eval(wo, wb), m.phase.eval(-to_light, wb));
            let t = engine::sampling::sample_exponential(rng.uniform(), m.sigma_t);
            if t < m.exit_distance(x, wb) {
                let y = x + wb * t;
                // f / pdf_b * w_b = albedo p(wo, wb) p(-wb, l) T / pdf_b * pdf_b / (pdf_a + pdf_b)
                let w = pdf_a * pdf_b / (pdf_a + pdf_b);
                sum += beta * m.albedo * w * m.transmittance_to_boundary(y, to_light);
            }
        }
        let wi = m.phase.sample(wo, rng.uniform2()).wi;
        if lobe {
            let (pdf_a, pdf_b) = (m.phase.eval(wo, wi), m.phase.eval(-to_light, wi));
            nee_weight = pdf_a / (pdf_a + pdf_b);
        }
        let exit = m.exit_distance(x, wi);
        let t = engine::sampling::sample_exponential(rng.uniform(), m.sigma_t);
        if !(t < exit) {
            return sum; // escapes; the environment is black
        }
        x += wi * t;
        wo = -wi;
        beta *= m.albedo;
        order += 1;
        if order > 3 && beta < 1.0 {
            let q = beta.max(0.05);
            if rng.uniform() >= q {
                return sum;
            }
            beta /= q;
        }
        if beta <= 0.0 {
            return sum;
        }
    }
}

/// Estimates L_i with confidence-interval stopping, in batches of 256 samples.
pub fn estimate_in_scattered(
    m: &ConvexMedium,
    omega_l: Vec3,
    x: Vec3,
    wo: Vec3,
    stop: &Stopping,
    rng: &mut Rng,
) -> Estimate {
    stop.estimate(256, || sample_in_scattered(m, omega_l, x, wo, rng) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::stats::{Welford, z_bound};

    #[test]
    fn exit_distances_are_exact() {
        let rot = Mat3::from_axis_angle(Vec3::new(1.0, 2.0, 0.5).normalize(), 0.7);
        let m = ConvexMedium::new(
            Shape::Box,
            rot * Mat3::from_diagonal(Vec3::new(0.5, 0.3, 0.4)),
            1.0,
            1.0,
            PhaseFunction::Isotropic,
        )
        .unwrap();
        let mut rng = Rng::new(3, 0, 0);
        for _ in 0..1000 {
            let x = m.sample_inside(&mut rng);
            assert!(m.contains(x));
            let d = engine::sampling::sample_uniform_sphere(rng.uniform2());
            let t = m.exit_distance(x, d);
            assert!(m.contains(x + d * (t * 0.999)));
            assert!(!m.contains(x + d * (t * 1.001 + 1e-4)));
        }
        let s =
            ConvexMedium::new(Shape::Sphere, Mat3::from_diagonal(Vec3::splat(2.0)), 1.0, 1.0, PhaseFunction::Isotropic)
                .unwrap();
        assert!((s.exit_distance(Vec3::ZERO, Vec3::X) - 2.0).abs() < 1e-6);
        assert!((s.exit_distance(Vec3::new(1.0, 0.0, 0.0), -Vec3::X) - 3.0).abs() < 1e-6);
    }

    /// In the optically thin limit L_i tends to the single-scattering term
    /// p(wo, -omega_l) T(x, -omega_l); the multiple-scattering excess is O(sigma).
    #[test]
    fn thin_limit_is_single_scattering() {
        let m = ConvexMedium::new(Shape::Sphere, Mat3::IDENTITY, 0.01, 1.0, PhaseFunction::HenyeyGreenstein { g: 0.6 })
            .unwrap();
        let omega_l = Vec3::NEG_Y;
        let (x, wo) = (Vec3::new(0.2, -0.1, 0.3), Vec3::new(0.0, 0.6, 0.8));
        let single = (m.phase.eval(wo, -omega_l) * m.transmittance_to_boundary(x, -omega_l)) as f64;
        let mut rng = Rng::new(5, 0, 0);
        let e = estimate_in_scattered(
            &m,
            omega_l,
            x,
            wo,
            &Stopping { max_rel_error: 0.002, ..Default::default() },
            &mut rng,
        );
        // Excess at most sigma * diameter (one more scattering in a unit-radius ball)
        // times the largest phase value, plus the estimator's error.
        let bound = 0.01 * 2.0 * m.phase.eval_cos(-1.0) as f64;
        assert!(
            e.mean >= single - 4.0 * e.std_error && e.mean <= single + bound + 4.0 * e.std_error,
            "{e:?} vs {single}"
        );
    }

    /// The light-lobe MIS and the plain walk estimate the same L_i (forward and
    /// backward scattering), and the MIS has lower variance for a peaked phase function.
    #[test]
    fn light_lobe_mis_is_unbiased_and_reduces_variance() {
        let rot = Mat3::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.4);
        let queries = [(Vec3::new(0.1, 0.2, -0.3), Vec3::new(0.0, 0.6, 0.8)), (Vec3::ZERO, Vec3::X)];
        let n = 200_000;
        let m_tests = 2 * queries.len();
        let mut var_ratio = vec![];
        for g in [0.85f32, -0.7] {
            let m = ConvexMedium::new(
                Shape::Box,
                rot * Mat3::from_diagonal(Vec3::new(1.0, 0.7, 0.8)),
                4.0,
                0.95,
                PhaseFunction::HenyeyGreenstein { g },
            )
            .unwrap();
            for (i, &(x, wo)) in queries.iter().enumerate() {
                let (mut a, mut b) = (Welford::default(), Welford::default());
                let mut rng = Rng::new(11, i as u64, (g * 100.0) as u64);
                for _ in 0..n {
                    a.add(sample_in_scattered_with(&m, Vec3::NEG_Z, x, wo, &mut rng, false) as f64);
                    b.add(sample_in_scattered_with(&m, Vec3::NEG_Z, x, wo, &mut rng, true) as f64);
                }
                let se = (a.std_error().powi(2) + b.std_error().powi(2)).sqrt();
                assert!(
                    (a.mean - b.mean).abs() < z_bound(0.01, m_tests) * se,
                    "g {g}: {} vs {} (se {se})",
                    a.mean,
                    b.mean
                );
                var_ratio.push(a.variance() / b.variance());
            }
        }
        // Forward-peaked g = 0.85: the MIS estimator's variance is markedly lower.
        assert!(var_ratio[0] > 2.0 && var_ratio[1] > 2.0, "{var_ratio:?}");
    }

    #[test]
    fn stopping_reaches_the_requested_precision() {
        let m = ConvexMedium::new(Shape::Box, Mat3::IDENTITY, 3.0, 0.9, PhaseFunction::HenyeyGreenstein { g: 0.3 })
            .unwrap();
        let mut rng = Rng::new(9, 0, 0);
        let stop = Stopping { max_rel_error: 0.05, ..Default::default() };
        let e = estimate_in_scattered(&m, Vec3::NEG_Z, Vec3::ZERO, Vec3::X, &stop, &mut rng);
        assert!(e.samples >= stop.min_samples && e.samples < stop.max_samples);
        assert!(1.96 * e.std_error <= 0.05 * e.mean);
        // A tighter target needs more samples (about 1 / error^2).
        let e2 = estimate_in_scattered(
            &m,
            Vec3::NEG_Z,
            Vec3::ZERO,
            Vec3::X,
            &Stopping { max_rel_error: 0.0125, ..stop },
            &mut rng,
        );
        assert!(e2.samples > 8 * e.samples.max(stop.min_samples) / 2, "{} vs {}", e2.samples, e.samples);
        assert!((e2.mean - e.mean).abs() < z_bound(0.01, 1) * (e.std_error.powi(2) + e2.std_error.powi(2)).sqrt());
    }
}
