//! Phase functions (thesis section 2.1.4, eqs. 2.9-2.13).
//!
//! # Direction convention
//! `p(wo, wi)` takes both directions pointing AWAY from the scattering point
//! (docs/conventions.md, thesis 2.1.4), and `cos_theta = dot(wo, wi)`. In a path tracer
//! `wo = -ray.direction` (back toward the camera) and `wi` is the direction the path
//! continues in. Light that keeps going straight has `wi = -wo`, so
//! `cos_theta = -1` is FORWARD scattering. Henyey-Greenstein is implemented exactly
//! as eq. 2.10 (plus sign in the denominator), which makes g > 0 forward-scattering
//! under this convention (as pbrt-v4 `util/scattering.h`; Tungsten's propagation
//! convention flips the sign instead).
//!
//! Departure: eqs. 2.12-2.13 (hazy and murky Mie approximations, Nishita et al. 1987)
//! are written with `(1 + cos_theta) / 2`, which under the away/away convention would
//! peak BACKWARD. They model forward-peaked aerosol scattering, so we evaluate them
//! with the scattering angle `cos_s = -cos_theta` (the angle between the incoming and
//! outgoing propagation directions), i.e. forward-peaked like HG with g > 0.
//!
//! The samplers take uniform numbers, not a sampler object, and draw exactly from the
//! pdf, so the sampling weight `p / pdf` is always 1.

use crate::sampling::{INV_4PI, spherical_direction};
use glam::{Vec2, Vec3};
use std::f32::consts::PI;

/// A phase function: a closed set, matched rather than dispatched through a vtable.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PhaseFunction {
    /// Eq. 2.9.
    Isotropic,
    /// Eq. 2.10, asymmetry `g` in (-1, 1); g > 0 scatters forward.
    HenyeyGreenstein { g: f32 },
    /// Eq. 2.11.
    Rayleigh,
    /// Eq. 2.12 (forward-peaked, see the module notes).
    Hazy,
    /// Eq. 2.13 (forward-peaked, see the module notes).
    Murky,
}

/// A sampled direction: `wi` points away from the scattering point, `pdf` in 1/sr.
#[derive(Clone, Copy, Debug)]
pub struct PhaseSample {
    pub wi: Vec3,
    pub pdf: f32,
    pub p: f32,
}

/// Below this |g| the HG inversion loses precision; sample isotropically instead
/// (the pdf differs from isotropic by O(g), so we still report the HG value).
const HG_ISOTROPIC_EPS: f32 = 1e-3;

impl PhaseFunction {
    /// Henyey-Greenstein with validated g (|g| < 1, finite).
    pub fn henyey_greenstein(g: f32) -> Result<Self, String> {
        if g.is_finite() && g > -1.0 && g < 1.0 {
            Ok(PhaseFunction::HenyeyGreenstein { g })
        } else {
            Err(format!("Henyey-Greenstein g must lie in (-1, 1), got {g}"))
        }
    }

    /// p(cos_theta) with cos_theta = dot(wo, wi), both pointing away.
    #[inline]
    pub fn eval_cos(&self, cos_theta: f32) -> f32 {
        match *self {
            PhaseFunction::Isotropic => INV_4PI,
            PhaseFunction::HenyeyGreenstein { g } => {
                // thesis eq. 2.10
                let denom = 1.0 + g * g + 2.0 * g * cos_theta;
                INV_4PI * (1.0 - g * g) / (denom * denom.max(1e-12).sqrt()).max(1e-12)
            }
            PhaseFunction::Rayleigh => 3.0 / (16.0 * PI) * (1.0 + cos_theta * cos_theta), // eq. 2.11
            PhaseFunction::Hazy => {
                // eq. 2.12 in the scattering angle cos_s = -cos_theta
                let x = 0.5 * (1.0 - cos_theta);
                INV_4PI * (0.5 + 4.5 * x.powi(8))
            }
            PhaseFunction::Murky => {
                // eq. 2.13 in the scattering angle cos_s = -cos_theta
                let x = 0.5 * (1.0 - cos_theta);
                INV_4PI * (0.5 + 16.5 * x.powi(32))
            }
        }
    }

    #[inline]
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> f32 {
        self.eval_cos(wo.dot(wi))
    }

    /// Sampling is exact, so the pdf equals the phase function.
    #[inline]
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        self.eval(wo, wi)
    }

    /// Draws the cosine of the scattering angle cos_s = dot(-wo, wi) (1 = straight on)
    /// from the marginal of the phase function, using one uniform number in [0, 1).
    #[inline]
    pub fn sample_cos_scatter(&self, u: f32) -> f32 {
        let c = match *self {
            PhaseFunction::Isotropic => 1.0 - 2.0 * u,
            PhaseFunction::HenyeyGreenstein { g } => {
                if g.abs() < HG_ISOTROPIC_EPS {
                    1.0 - 2.0 * u
                } else {
                    // Inverse CDF of HG in the scattering angle.
                    let s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u);
                    (1.0 + g * g - s * s) / (2.0 * g)
                }
            }
            PhaseFunction::Rayleigh => {
                // CDF(mu) = 1/2 + 3/8 (mu + mu^3 / 3); solve the depressed cubic
                // mu^3 + 3 mu - (8u - 4) = 0 by Cardano: mu = A - 1/A.
                let z = 4.0 * u - 2.0;
                let a = (z + (z * z + 1.0).sqrt()).cbrt();
                a - 1.0 / a
            }
            PhaseFunction::Hazy => sample_mie_mixture(u, 9.0),
            PhaseFunction::Murky => sample_mie_mixture(u, 33.0),
        };
        c.clamp(-1.0, 1.0)
    }

    /// Samples `wi` given `wo` (both away from the scattering point).
    #[inline]
    pub fn sample(&self, wo: Vec3, u: Vec2) -> PhaseSample {
        let cos_s = self.sample_cos_scatter(u.x);
        let wi = spherical_direction(cos_s, 2.0 * PI * u.y, -wo);
        let p = self.eval_cos(-cos_s);
        PhaseSample { wi, pdf: p, p }
    }

    /// The largest value over all directions: straight on or straight back, as every
    /// phase function here is monotone in the scattering angle (Rayleigh symmetric).
    pub fn peak(&self) -> f32 {
        self.eval_cos(-1.0).max(self.eval_cos(1.0))
    }

    /// Mean cosine of the scattering angle (g for HG; 0 for the symmetric ones).
    pub fn mean_cosine(&self) -> f32 {
        match *self {
            PhaseFunction::Isotropic | PhaseFunction::Rayleigh => 0.0,
            PhaseFunction::HenyeyGreenstein { g } => g,
            // E[2x - 1] over the lobe x ~ (n+1) x^n is 2 (n+1)/(n+2) - 1, weighted 1/2.
            PhaseFunction::Hazy => 0.5 * (2.0 * 9.0 / 10.0 - 1.0),
            PhaseFunction::Murky => 0.5 * (2.0 * 33.0 / 34.0 - 1.0),
        }
    }
}

/// Eqs. 2.12/2.13 are an equal mixture: half isotropic, half the lobe
/// (n / 2)(x)^(n - 1) / (4 pi) with x = (1 + cos_s) / 2, whose marginal in x is
/// n x^(n-1) on [0, 1], sampled by x = v^(1/n).
#[inline]
fn sample_mie_mixture(u: f32, n: f32) -> f32 {
    if u < 0.5 {
        1.0 - 2.0 * (2.0 * u)
    } else {
        let v = (2.0 * u - 1.0).min(1.0);
        2.0 * v.powf(1.0 / n) - 1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all() -> Vec<PhaseFunction> {
        vec![
            PhaseFunction::Isotropic,
            PhaseFunction::HenyeyGreenstein { g: -0.6 },
            PhaseFunction::HenyeyGreenstein { g: 0.0 },
            PhaseFunction::HenyeyGreenstein { g: 0.6 },
            PhaseFunction::HenyeyGreenstein { g: 0.85 },
            PhaseFunction::Rayleigh,
            PhaseFunction::Hazy,
            PhaseFunction::Murky,
        ]
    }

    /// Integral over the sphere by Simpson's rule in cos_theta (phi is symmetric).
    fn integrate(f: impl Fn(f64) -> f64) -> f64 {
        let n = 200_000;
        let h = 2.0 / n as f64;
        let mut s = f(-1.0) + f(1.0);
        for i in 1..n {
            let x = -1.0 + i as f64 * h;
            s += if i % 2 == 1 { 4.0 } else { 2.0 } * f(x);
        }
        s * h / 3.0
    }

    /// The peak is the largest value over a fine sweep of the angle, and HG's equals
    /// its closed form (1 + |g|) / (4 pi (1 - |g|)^2).
    #[test]
    fn peak_is_the_largest_value() {
        for p in all() {
            let swept = (0..=20_000).map(|i| p.eval_cos(-1.0 + i as f32 / 10_000.0)).fold(0.0f32, f32::max);
            assert!((p.peak() - swept).abs() <= 1e-6 * swept, "{p:?}: peak {} against {swept}", p.peak());
            if let PhaseFunction::HenyeyGreenstein { g } = p {
                let closed = (1.0 + g.abs()) / (4.0 * PI * (1.0 - g.abs()).powi(2));
                assert!((p.peak() - closed).abs() <= 1e-5 * closed, "{p:?}: {} against {closed}", p.peak());
            }
        }
    }

    #[test]
    fn pdfs_integrate_to_one() {
        for p in all() {
            let i = integrate(|c| 2.0 * std::f64::consts::PI * p.eval_cos(c as f32) as f64);
            assert!((i - 1.0).abs() < 1e-4, "{p:?} integrates to {i}");
        }
    }

    #[test]
    fn mean_cosine_matches_closed_form() {
        for p in all() {
            // E[cos_s] with cos_s = -cos_theta.
            let m = integrate(|c| -c * 2.0 * std::f64::consts::PI * p.eval_cos(c as f32) as f64);
            assert!((m - p.mean_cosine() as f64).abs() < 1e-4, "{p:?}: {m} vs {}", p.mean_cosine());
        }
    }

    #[test]
    fn forward_orientation() {
        // Straight-on continuation (wi = -wo) must be the most likely for g > 0.
        let wo = Vec3::new(0.0, 0.0, 1.0);
        for p in [PhaseFunction::HenyeyGreenstein { g: 0.85 }, PhaseFunction::Hazy, PhaseFunction::Murky] {
            assert!(p.eval(wo, -wo) > 5.0 * p.eval(wo, wo), "{p:?} not forward");
            // Samples continue forward on average.
            let mut sum = 0.0;
            for i in 0..1000 {
                let u = Vec2::new((i as f32 + 0.5) / 1000.0, 0.37);
                sum += p.sample(wo, u).wi.dot(-wo);
            }
            assert!(sum / 1000.0 > 0.3);
        }
        let back = PhaseFunction::HenyeyGreenstein { g: -0.6 };
        assert!(back.eval(wo, wo) > back.eval(wo, -wo));
    }

    #[test]
    fn extremes_are_finite() {
        let wo = Vec3::new(0.0, 0.6, 0.8);
        for p in all().into_iter().chain([
            PhaseFunction::HenyeyGreenstein { g: 0.999 },
            PhaseFunction::HenyeyGreenstein { g: -0.999 },
            PhaseFunction::HenyeyGreenstein { g: 1e-5 },
        ]) {
            for u0 in [0.0f32, 1.0 - f32::EPSILON, 0.5] {
                for u1 in [0.0f32, 1.0 - f32::EPSILON] {
                    let s = p.sample(wo, Vec2::new(u0, u1));
                    assert!(s.wi.is_finite() && s.pdf.is_finite() && s.pdf > 0.0, "{p:?} u=({u0},{u1}) {s:?}");
                    assert!((s.wi.length() - 1.0).abs() < 1e-4);
                }
            }
        }
    }

    #[test]
    fn rejects_bad_g() {
        assert!(PhaseFunction::henyey_greenstein(1.0).is_err());
        assert!(PhaseFunction::henyey_greenstein(f32::NAN).is_err());
        assert!(PhaseFunction::henyey_greenstein(0.85).is_ok());
    }

    /// Chi-square goodness of fit of the sampled directions against the pdf, binned in
    /// (cos of the scattering angle, azimuth about -wo): 10^6 samples per phase
    /// function, sparse cells pooled, alpha = 0.01 with Sidak correction over all
    /// phase functions tested.
    #[test]
    fn chi_square_sampling() {
        use crate::rng::Rng;
        use crate::sampling::coordinate_system;
        use crate::stats::{chi2_test, sidak};
        let funcs = all();
        let alpha = sidak(0.01, funcs.len());
        let (n_cos, n_phi) = (64usize, 32usize);
        let n = 1_000_000usize;
        let wo = Vec3::new(0.48, -0.6, 0.64).normalize();
        let axis = -wo;
        let (t, b) = coordinate_system(axis);
        for (fi, p) in funcs.iter().enumerate() {
            let mut rng = Rng::new(1234, fi as u64, 0);
            let mut observed = vec![0.0f64; n_cos * n_phi];
            for _ in 0..n {
                let s = p.sample(wo, rng.uniform2());
                let c = s.wi.dot(axis).clamp(-1.0, 1.0);
                let phi = s.wi.dot(b).atan2(s.wi.dot(t)).rem_euclid(2.0 * PI);
                let ic = (((c + 1.0) * 0.5 * n_cos as f32) as usize).min(n_cos - 1);
                let ip = ((phi / (2.0 * PI) * n_phi as f32) as usize).min(n_phi - 1);
                observed[ic * n_phi + ip] += 1.0;
            }
            // Expected counts: n * (2 pi / n_phi) * integral of p over the cos bin
            // (Simpson, in the scattering angle cos_s = -cos_theta).
            let mut expected = vec![0.0f64; n_cos * n_phi];
            for ic in 0..n_cos {
                let (c0, c1) = (-1.0 + 2.0 * ic as f64 / n_cos as f64, -1.0 + 2.0 * (ic + 1) as f64 / n_cos as f64);
                let m = 200;
                let h = (c1 - c0) / m as f64;
                let f = |c: f64| p.eval_cos(-c as f32) as f64;
                let mut s = f(c0) + f(c1);
                for j in 1..m {
                    s += if j % 2 == 1 { 4.0 } else { 2.0 } * f(c0 + j as f64 * h);
                }
                let integral = s * h / 3.0 * 2.0 * std::f64::consts::PI / n_phi as f64;
                for ip in 0..n_phi {
                    expected[ic * n_phi + ip] = n as f64 * integral;
                }
            }
            let r = chi2_test(&observed, &expected, 5.0);
            assert!(r.p_value > alpha, "{p:?}: chi2 = {:.1}, dof = {}, p = {:.3e}", r.statistic, r.dof, r.p_value);
        }
    }
}
