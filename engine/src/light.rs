//! Lights: a directional sun (optionally a soft disk) and a constant sky.
//!
//! Parameters ([`Sun::new`]): `direction` the direction the light travels, any
//! non-zero finite vector (normalized); `radiance` per channel, finite and >= 0
//! (default in scene files 1, the thesis's L_L); `angular_radius` in radians,
//! [0, 0.5] (0: a delta light). [`Sky`]: a constant `radiance` per channel (black by
//! default), seen by paths that leave the medium.

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

/// Constant environment radiance (black by default).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sky {
    pub radiance: Vec3,
}

impl Sky {
    pub fn is_black(&self) -> bool {
        self.radiance == Vec3::ZERO
    }
}
