//! The thesis's local frame F of the point-to-point model (thesis 6.1.1): the emitter
//! goes to (0, 0, -1/2) and the sensor to (0, 0, 1/2), with a free rotation about
//! their axis; lengths are divided by the emitter-sensor distance.

use glam::Vec3;

/// The thesis's local frame F: translation, rotation and uniform scaling taking the
/// emitter to (0, 0, -1/2) and the sensor to (0, 0, 1/2).
#[derive(Clone, Copy, Debug)]
pub struct LocalFrame {
    mid: Vec3,
    ex: Vec3,
    ey: Vec3,
    ez: Vec3,
    /// Emitter-sensor distance: one local unit in world units.
    pub scale: f32,
}

impl LocalFrame {
    /// `angle` (radians) fixes the rotation about the emitter-sensor axis. None when
    /// the two points coincide or are not finite.
    pub fn new(emitter: Vec3, sensor: Vec3, angle: f32) -> Option<Self> {
        let axis = sensor - emitter;
        let scale = axis.length();
        if !(scale > 1e-9 && scale.is_finite()) {
            return None;
        }
        let ez = axis / scale;
        let (t, b) = engine::sampling::coordinate_system(ez);
        let (s, c) = angle.sin_cos();
        let (ex, ey) = (t * c + b * s, b * c - t * s);
        Some(LocalFrame { mid: 0.5 * (emitter + sensor), ex, ey, ez, scale })
    }

    pub fn to_local(&self, p: Vec3) -> Vec3 {
        let d = (p - self.mid) / self.scale;
        Vec3::new(d.dot(self.ex), d.dot(self.ey), d.dot(self.ez))
    }

    pub fn to_world(&self, q: Vec3) -> Vec3 {
        self.mid + self.scale * (self.ex * q.x + self.ey * q.y + self.ez * q.z)
    }
}
