//! Lights: a directional sun (optionally a soft disk) and a sky.
//!
//! Parameters ([`Sun::new`]): `direction` the direction the light travels, any
//! non-zero finite vector (normalized); `radiance` per channel, finite and >= 0
//! (default in scene files 1, the thesis's L_L); `angular_radius` in radians,
//! [0, 0.5] (0: a delta light). [`Sky`]: radiance per channel at the zenith, the
//! horizon and the ground (black by default; all three equal: uniform), seen by paths
//! that leave the medium.

use crate::sampling::{local_to_world, sample_uniform_cone};
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
}
