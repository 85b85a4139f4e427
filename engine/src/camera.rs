//! Pinhole camera: position, target, up, vertical field of view, resolution.
//! Pixel (0, 0) is the top-left pixel; x grows to the camera's right and y downward.
//!
//! Parameters ([`Camera::new`]): `position` and `target` finite and apart; `up` not
//! parallel to the view direction; `fov_y_deg` in (0, 179] degrees (scene files: 30);
//! `width` and `height` in 1 ..= 16384 pixels (scene files: 256).

use glam::{Vec2, Vec3};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    #[error("camera position and target must differ and be finite")]
    Degenerate,
    #[error("camera up vector must not be parallel to the viewing direction")]
    UpParallel,
    #[error("vertical field of view must lie in (0, 179] degrees, got {0}")]
    BadFov(f32),
    #[error("resolution must be between 1x1 and 16384x16384, got {0}x{1}")]
    BadResolution(u32, u32),
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    position: Vec3,
    target: Vec3,
    up: Vec3,
    fov_y_deg: f32,
    width: u32,
    height: u32,
    forward: Vec3,
    right: Vec3,
    true_up: Vec3,
    tan_half: f32,
}

impl Camera {
    pub fn new(
        position: Vec3,
        target: Vec3,
        up: Vec3,
        fov_y_deg: f32,
        width: u32,
        height: u32,
    ) -> Result<Self, CameraError> {
        if !(position.is_finite() && target.is_finite()) {
            return Err(CameraError::Degenerate);
        }
        let forward = (target - position).try_normalize().ok_or(CameraError::Degenerate)?;
        let right = forward.cross(up).try_normalize().ok_or(CameraError::UpParallel)?;
        let true_up = right.cross(forward);
        if !(fov_y_deg > 0.0 && fov_y_deg <= 179.0) {
            return Err(CameraError::BadFov(fov_y_deg));
        }
        if width == 0 || height == 0 || width > 16384 || height > 16384 {
            return Err(CameraError::BadResolution(width, height));
        }
        Ok(Camera {
            position,
            target,
            up,
            fov_y_deg,
            width,
            height,
            forward,
            right,
            true_up,
            tan_half: (0.5 * fov_y_deg.to_radians()).tan(),
        })
    }

    pub fn position(&self) -> Vec3 {
        self.position
    }
    pub fn target(&self) -> Vec3 {
        self.target
    }
    pub fn up(&self) -> Vec3 {
        self.up
    }
    pub fn fov_y_deg(&self) -> f32 {
        self.fov_y_deg
    }
    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn forward(&self) -> Vec3 {
        self.forward
    }

    /// Same view at another resolution.
    pub fn with_resolution(&self, width: u32, height: u32) -> Result<Self, CameraError> {
        Camera::new(self.position, self.target, self.up, self.fov_y_deg, width, height)
    }

    /// Unit direction through the image-plane point (x, y) in pixels (continuous).
    #[inline]
    pub fn direction(&self, film: Vec2) -> Vec3 {
        let aspect = self.width as f32 / self.height as f32;
        let sx = (2.0 * film.x / self.width as f32 - 1.0) * self.tan_half * aspect;
        let sy = (1.0 - 2.0 * film.y / self.height as f32) * self.tan_half;
        (self.forward + self.right * sx + self.true_up * sy).normalize()
    }

    /// Ray through pixel (px, py), jittered uniformly within the pixel (box filter).
    #[inline]
    pub fn generate_ray(&self, px: u32, py: u32, jitter: Vec2) -> (Vec3, Vec3) {
        (self.position, self.direction(Vec2::new(px as f32, py as f32) + jitter))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orientation() {
        let c = Camera::new(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 40.0, 64, 32).unwrap();
        assert!((c.direction(Vec2::new(32.0, 16.0)) - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
        // Top-left pixel looks up and to the left (-x when looking down -z with y up).
        let d = c.direction(Vec2::ZERO);
        assert!(d.x < 0.0 && d.y > 0.0);
        // Vertical fov: the top edge is fov/2 above the axis.
        let top = c.direction(Vec2::new(32.0, 0.0));
        assert!((top.dot(c.forward()).acos().to_degrees() - 20.0).abs() < 1e-3);
        assert!(Camera::new(Vec3::ZERO, Vec3::ZERO, Vec3::Y, 40.0, 8, 8).is_err());
        assert!(Camera::new(Vec3::ZERO, Vec3::Y, Vec3::Y, 40.0, 8, 8).is_err());
        assert!(Camera::new(Vec3::ZERO, Vec3::X, Vec3::Y, 0.0, 8, 8).is_err());
        assert!(Camera::new(Vec3::ZERO, Vec3::X, Vec3::Y, 40.0, 0, 8).is_err());
    }
}
