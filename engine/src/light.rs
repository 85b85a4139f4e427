//! Lights: a directional sun (optionally a soft disk) and a sky.
//!
//! Parameters ([`Sun::new`]): `direction` the direction the light travels, any
//! non-zero finite vector (normalized); `radiance` per channel, finite and >= 0
//! (default in scene files 1, the thesis's L_L); `angular_radius` in radians,
//! [0, 0.5] (0: a delta light). [`Sky`]: radiance per channel at the zenith, the
//! horizon and the ground (black by default; all three equal: uniform), seen by paths
//! that leave the medium.

use crate::sampling::{local_to_world, sample_uniform_cone, sample_uniform_sphere, uniform_sphere_pdf};
use glam::{Vec2, Vec3};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LightError {
    #[error("sun direction must be a non-zero finite vector, got {0:?}")]
    BadDirection([f32; 3]),
    #[error("sun radiance must be finite and >= 0 in every channel, got {0:?}")]
    BadRadiance([f32; 3]),
    #[error("sun angular radius must lie in [0, 0.5] radians, got {0}")]
    BadAngularRadius(f32),
}

/// Directional light. `direction` is the direction the light TRAVELS (omega_L,
/// docs/conventions.md), so light arrives from `-direction`. `radiance` is the thesis's
/// L_L: the irradiance it delivers to a surface perpendicular to it (1 by default).
/// With a non-zero angular radius the same irradiance is spread uniformly over a disk
/// of that half-angle, so softening the sun does not change its brightness.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sun {
    direction: Vec3,
    radiance: Vec3,
    angular_radius: f32,
    cos_max: f32,
}

impl Sun {
    pub fn new(direction: Vec3, radiance: Vec3, angular_radius: f32) -> Result<Self, LightError> {
        let direction = direction.try_normalize().ok_or(LightError::BadDirection(direction.to_array()))?;
        if !(radiance.is_finite() && radiance.min_element() >= 0.0) {
            return Err(LightError::BadRadiance(radiance.to_array()));
        }
        if !(0.0..=0.5).contains(&angular_radius) {
            return Err(LightError::BadAngularRadius(angular_radius));
        }
        Ok(Sun { direction, radiance, angular_radius, cos_max: angular_radius.cos() })
    }

    /// Sun from elevation above the horizon and azimuth about +y (degrees); the
    /// light travels from that point in the sky toward the origin.
    pub fn from_angles(
        elevation_deg: f32,
        azimuth_deg: f32,
        radiance: Vec3,
        angular_radius: f32,
    ) -> Result<Self, LightError> {
        let (el, az) = (elevation_deg.to_radians(), azimuth_deg.to_radians());
        let to_sun = Vec3::new(el.cos() * az.sin(), el.sin(), el.cos() * az.cos());
        Sun::new(-to_sun, radiance, angular_radius)
    }

    pub fn direction(&self) -> Vec3 {
        self.direction
    }
    pub fn radiance(&self) -> Vec3 {
        self.radiance
    }
    pub fn angular_radius(&self) -> f32 {
        self.angular_radius
    }

    /// A direction from a point toward the sun (pointing away from the point), whose
    /// contribution is `radiance()` times the integrand: the pdf of the cone sample
    /// cancels against the disk's radiance E / solid angle.
    #[inline]
    pub fn sample_wi(&self, u: Vec2) -> Vec3 {
        if self.angular_radius == 0.0 {
            -self.direction
        } else {
            local_to_world(sample_uniform_cone(u, self.cos_max), -self.direction)
        }
    }
}

/// Environment radiance (black by default): a gradient from `horizon` to `zenith`
/// over the upper hemisphere, linear in the sine of the elevation, and `ground`
/// below the horizon. All three equal: a uniform sky.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sky {
    pub zenith: Vec3,
    pub horizon: Vec3,
    pub ground: Vec3,
}

impl Sky {
    /// A uniform sky of `radiance`.
    pub fn uniform(radiance: Vec3) -> Sky {
        Sky { zenith: radiance, horizon: radiance, ground: radiance }
    }

    pub fn is_black(&self) -> bool {
        self.zenith == Vec3::ZERO && self.horizon == Vec3::ZERO && self.ground == Vec3::ZERO
    }

    /// The radiance seen looking along `dir` (unit length): exactly `horizon` +
    /// (`zenith` - `horizon`) dir.y above the horizon (so a uniform sky gives its
    /// radiance bit for bit), `ground` below.
    #[inline]
    pub fn radiance(&self, dir: Vec3) -> Vec3 {
        if dir.y >= 0.0 { self.horizon + (self.zenith - self.horizon) * dir.y } else { self.ground }
    }

    /// The weight by which [`Sky::sample`] picks directions: the sum of the channels
    /// of `radiance(dir)`, so radiance / pdf stays bounded in every channel.
    #[inline]
    fn weight(&self, dir: Vec3) -> f32 {
        self.radiance(dir).element_sum()
    }

    /// The weights of the ground and of the upper hemisphere's gradient as functions
    /// of y = dir.y: w(y) = ground for y < 0, a + b y for y >= 0.
    #[inline]
    fn weight_terms(&self) -> (f32, f32, f32) {
        let a = self.horizon.element_sum();
        (self.ground.element_sum(), a, self.zenith.element_sum() - a)
    }

    /// A direction toward the sky with its solid-angle pdf, proportional to the sum
    /// of the radiance's channels (a sky depends only on dir.y, and y is uniform on
    /// the sphere: the pdf is w(y) / (2 pi int_-1^1 w)). For a black sky, uniform on
    /// the sphere.
    pub fn sample(&self, u: Vec2) -> (Vec3, f32) {
        let (ground, a, b) = self.weight_terms();
        let upper = a + 0.5 * b;
        let total = ground + upper;
        if !(total > 0.0) {
            return (sample_uniform_sphere(u), uniform_sphere_pdf());
        }
        // Pick the lower or upper half by its mass, then y within it.
        let split = ground / total;
        let y = if u.x < split {
            -(u.x / split).min(1.0)
        } else {
            // Invert the cdf of a + b y on [0, 1]: (a v + b v^2 / 2) / upper = s.
            let s = ((u.x - split) / (1.0 - split)).clamp(0.0, 1.0);
            let c = s * upper;
            let v = if b.abs() < 1e-6 * a.max(1e-30) {
                c / a
            } else {
                // The root of b/2 v^2 + a v - c = 0 in [0, 1], in the stable form.
                2.0 * c / (a + (a * a + 2.0 * b * c).max(0.0).sqrt())
            };
            v.clamp(0.0, 1.0)
        };
        let r = (1.0 - y * y).max(0.0).sqrt();
        let phi = 2.0 * std::f32::consts::PI * u.y;
        let dir = Vec3::new(r * phi.cos(), y, r * phi.sin());
        (dir, self.pdf(dir))
    }

    /// The solid-angle pdf of [`Sky::sample`].
    pub fn pdf(&self, dir: Vec3) -> f32 {
        let (ground, a, b) = self.weight_terms();
        let total = ground + a + 0.5 * b;
        if !(total > 0.0) {
            return uniform_sphere_pdf();
        }
        self.weight(dir) / (2.0 * std::f32::consts::PI * total)
    }

    /// Irradiance of the upper hemisphere on an upward-facing surface, unshadowed:
    /// 2 pi int_0^1 (h + (z - h) mu) mu dmu = pi h + 2 pi (z - h) / 3.
    pub fn upper_irradiance(&self) -> Vec3 {
        std::f32::consts::PI * self.horizon + 2.0 * std::f32::consts::PI * (self.zenith - self.horizon) / 3.0
    }
}

#[cfg(test)]
mod sky_tests {
    use super::*;

    #[test]
    fn sky_gradient_ground_and_irradiance() {
        let u = Sky::uniform(Vec3::new(0.3, 0.5, 0.7));
        for d in [Vec3::Y, Vec3::NEG_Y, Vec3::X, Vec3::new(0.6, 0.8, 0.0)] {
            assert_eq!(u.radiance(d), Vec3::new(0.3, 0.5, 0.7), "a uniform sky is the same bit for bit");
        }
        let s = Sky { zenith: Vec3::new(0.2, 0.4, 1.0), horizon: Vec3::splat(1.0), ground: Vec3::splat(0.1) };
        assert!((s.radiance(Vec3::Y) - s.zenith).abs().max_element() < 1e-6);
        assert_eq!(s.radiance(Vec3::Z), s.horizon);
        assert_eq!(s.radiance(Vec3::new(0.0, -0.5, 0.866)), s.ground);
        assert!((s.radiance(Vec3::new(0.8, 0.6, 0.0)) - Vec3::new(0.52, 0.64, 1.0)).length() < 1e-6);
        // The upper irradiance against a midpoint rule over mu = cos theta.
        let n = 100_000;
        let mut e = glam::DVec3::ZERO;
        for i in 0..n {
            let mu = (i as f32 + 0.5) / n as f32;
            e += (s.radiance(Vec3::new((1.0 - mu * mu).sqrt(), mu, 0.0)) * mu).as_dvec3();
        }
        let e = (e * (2.0 * std::f64::consts::PI / n as f64)).as_vec3();
        assert!((e - s.upper_irradiance()).abs().max_element() < 1e-4, "{e} vs {}", s.upper_irradiance());
        assert!(Sky::default().is_black() && !s.is_black());
    }

    /// Chi-square goodness of fit of `Sky::sample` against `Sky::pdf`, binned in
    /// (y, phi), for a gradient sky with a dim ground, one with a black ground, a
    /// uniform one and a black one (which samples uniformly); and the pdf integrates
    /// to 1 (midpoint rule over y).
    #[test]
    fn sky_sampling_chi_square() {
        use crate::stats::{chi2_test, sidak};
        let skies = [
            Sky { zenith: Vec3::new(0.2, 0.4, 1.0), horizon: Vec3::splat(1.0), ground: Vec3::splat(0.1) },
            Sky { zenith: Vec3::new(0.05, 0.1, 0.3), horizon: Vec3::new(0.3, 0.3, 0.35), ground: Vec3::ZERO },
            Sky { zenith: Vec3::splat(2.0), horizon: Vec3::splat(0.1), ground: Vec3::splat(0.5) },
            Sky::uniform(Vec3::splat(0.7)),
            Sky::default(),
        ];
        let alpha = sidak(0.01, skies.len());
        let (ny, nphi, n) = (24usize, 8usize, 200_000usize);
        for sky in skies {
            let mut observed = vec![0.0f64; ny * nphi];
            let mut rng = crate::rng::Rng::new(7, 0, 0);
            for _ in 0..n {
                let (d, pdf) = sky.sample(rng.uniform2());
                assert!((d.length() - 1.0).abs() < 1e-4 && pdf > 0.0 && (pdf - sky.pdf(d)).abs() < 1e-4 * pdf);
                let iy = (((d.y + 1.0) / 2.0 * ny as f32) as usize).min(ny - 1);
                let phi = d.z.atan2(d.x).rem_euclid(2.0 * std::f32::consts::PI);
                let ip = ((phi / (2.0 * std::f32::consts::PI) * nphi as f32) as usize).min(nphi - 1);
                observed[iy * nphi + ip] += 1.0;
            }
            // Expected counts: the pdf integrated over each bin (dOmega = dy dphi).
            let mut expected = vec![0.0f64; ny * nphi];
            let mut norm = 0.0f64;
            let sub = 64;
            for iy in 0..ny {
                let mut mass = 0.0f64;
                for j in 0..sub {
                    let y = -1.0 + 2.0 * (iy as f64 + (j as f64 + 0.5) / sub as f64) / ny as f64;
                    let d = Vec3::new((1.0 - y * y).sqrt() as f32, y as f32, 0.0);
                    mass += sky.pdf(d) as f64 * (2.0 / (ny * sub) as f64) * 2.0 * std::f64::consts::PI;
                }
                norm += mass;
                for ip in 0..nphi {
                    expected[iy * nphi + ip] = mass / nphi as f64 * n as f64;
                }
            }
            assert!((norm - 1.0).abs() < 1e-3, "{sky:?}: the pdf integrates to {norm}");
            let r = chi2_test(&observed, &expected, 5.0);
            assert!(r.p_value > alpha, "{sky:?}: chi2 = {:.1}, dof = {}, p = {:.3e}", r.statistic, r.dof, r.p_value);
        }
    }
}
