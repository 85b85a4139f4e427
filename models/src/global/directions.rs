//! Direction sets over the sphere from a subdivided tetrahedron (thesis figure 5.2),
//! n_D in {4, 16, 64}, nested: the first 4 directions of the 16-set are the 4-set, the
//! first 16 of the 64-set are the 16-set.
//!
//! Construction: the directions are the (normalized) centroids of the faces of a
//! regular tetrahedron whose faces are split into four by their edge midpoints, once
//! for 16 and twice for 64. The split is done on the flat faces, so the middle child
//! of a face has exactly its parent's centroid: that is what nests the sets. Order:
//! the parent directions first, then each subdivision's new faces face by face. The
//! tetrahedron is rotated so that d_1 = (0, 0, 1), which the light frame maps to
//! -omega_L (thesis 5.1: "d_1 = -omega_L = (0, 0, 1)").

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};

/// Which construction spreads the n_D directions over the sphere.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum DirectionSetKind {
    /// The thesis's subdivided tetrahedron (default): n_D in {4, 16, 64}, nested.
    #[default]
    Tetrahedron,
    /// A spherical Fibonacci set (more uniform, not nested), any n_D in 4..=256, rotated
    /// so that its first point is d_1 = (0, 0, 1).
    Fibonacci,
}

impl DirectionSetKind {
    pub fn name(self) -> &'static str {
        match self {
            DirectionSetKind::Tetrahedron => "tetrahedron",
            DirectionSetKind::Fibonacci => "fibonacci",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "tetrahedron" => Some(DirectionSetKind::Tetrahedron),
            "fibonacci" => Some(DirectionSetKind::Fibonacci),
            _ => None,
        }
    }

    /// The directions in the light frame, or None if n is not offered by this set.
    pub fn directions(self, n: usize) -> Option<Vec<Vec3>> {
        match self {
            DirectionSetKind::Tetrahedron => direction_set(n),
            DirectionSetKind::Fibonacci => fibonacci_set(n),
        }
    }
}

/// Spherical Fibonacci points z_i = 1 - (2 i + 1) / n, phi_i = i * golden angle, rotated
/// about the x axis so that the first point becomes (0, 0, 1) exactly.
pub fn fibonacci_set(n: usize) -> Option<Vec<Vec3>> {
    if !(4..=256).contains(&n) {
        return None;
    }
    let golden = std::f64::consts::PI * (3.0 - 5.0f64.sqrt());
    let raw: Vec<DVec3> = (0..n)
        .map(|i| {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = golden * i as f64;
            DVec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect();
    // The first point has phi = 0: it lies in the xz plane, so a rotation about y takes
    // it to +z.
    let angle = raw[0].x.atan2(raw[0].z);
    let rot = glam::DMat3::from_rotation_y(-angle);
    Some(raw.into_iter().map(|d| (rot * d).normalize().as_vec3()).collect())
}

/// Number of directions: 4, 16 or 64.
pub fn direction_set(n: usize) -> Option<Vec<Vec3>> {
    let levels = match n {
        4 => 0,
        16 => 1,
        64 => 2,
        _ => return None,
    };
    // Regular tetrahedron with a face centred on +z: the opposite vertex at -z.
    let a = (8.0f64 / 9.0).sqrt();
    let b = (2.0f64 / 9.0).sqrt();
    let c = (2.0f64 / 3.0).sqrt();
    let v = [
        DVec3::new(0.0, 0.0, -1.0),
        DVec3::new(a, 0.0, 1.0 / 3.0),
        DVec3::new(-b, c, 1.0 / 3.0),
        DVec3::new(-b, -c, 1.0 / 3.0),
    ];
    // Faces, the top one (+z) first.
    let mut faces: Vec<[DVec3; 3]> =
        vec![[v[1], v[2], v[3]], [v[0], v[2], v[1]], [v[0], v[3], v[2]], [v[0], v[1], v[3]]];
    let centroid = |f: &[DVec3; 3]| (f[0] + f[1] + f[2]) / 3.0;
    let mut dirs: Vec<DVec3> = faces.iter().map(|f| centroid(f).normalize()).collect();
    for _ in 0..levels {
        let mut next = Vec::with_capacity(faces.len() * 4);
        // The middle children keep their parents' order (and directions) ...
        for f in &faces {
            let (m01, m12, m20) = ((f[0] + f[1]) / 2.0, (f[1] + f[2]) / 2.0, (f[2] + f[0]) / 2.0);
            next.push([m01, m12, m20]);
        }
        // ... and the corner children follow, face by face.
        for f in &faces {
            let (m01, m12, m20) = ((f[0] + f[1]) / 2.0, (f[1] + f[2]) / 2.0, (f[2] + f[0]) / 2.0);
            for child in [[f[0], m01, m20], [m01, f[1], m12], [m20, m12, f[2]]] {
                dirs.push(centroid(&child).normalize());
                next.push(child);
            }
        }
        faces = next;
    }
    debug_assert_eq!(dirs.len(), n);
    Some(dirs.into_iter().map(|d| d.as_vec3()).collect())
}

/// An orthonormal frame whose +z axis is -omega_L (toward the light), used to express
/// the direction set and the query direction (thesis 5.1, figure 5.3).
#[derive(Clone, Copy, Debug)]
pub struct LightFrame {
    pub x: Vec3,
    pub y: Vec3,
    pub z: Vec3,
}

impl LightFrame {
    /// `omega_l` is the direction the light travels (unit).
    pub fn new(omega_l: Vec3) -> Self {
        let z = -omega_l.normalize();
        let (x, y) = engine::sampling::coordinate_system(z);
        LightFrame { x, y, z }
    }

    pub fn to_world(&self, local: Vec3) -> Vec3 {
        self.x * local.x + self.y * local.y + self.z * local.z
    }

    pub fn to_local(&self, world: Vec3) -> Vec3 {
        Vec3::new(world.dot(self.x), world.dot(self.y), world.dot(self.z))
    }

    /// Spherical angles (theta from +z, phi in [0, 2 pi)) of a world direction.
    pub fn angles(&self, world: Vec3) -> (f32, f32) {
        let l = self.to_local(world);
        (l.z.clamp(-1.0, 1.0).acos(), l.y.atan2(l.x).rem_euclid(std::f32::consts::TAU))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sets_are_unit_distinct_and_nested() {
        let s4 = direction_set(4).unwrap();
        let s16 = direction_set(16).unwrap();
        let s64 = direction_set(64).unwrap();
        assert!(direction_set(8).is_none());
        assert_eq!(s4[0], Vec3::Z);
        for set in [&s4, &s16, &s64] {
            for (i, a) in set.iter().enumerate() {
                assert!((a.length() - 1.0).abs() < 1e-6);
                for b in &set[..i] {
                    assert!(a.dot(*b) < 1.0 - 1e-4, "duplicate direction");
                }
            }
            // Spread over the whole sphere: the mean direction is near zero.
            let mean: Vec3 = set.iter().copied().sum::<Vec3>() / set.len() as f32;
            assert!(mean.length() < 0.05, "{mean}");
        }
        for i in 0..4 {
            assert!((s16[i] - s4[i]).length() < 1e-6, "4 not nested in 16");
        }
        for i in 0..16 {
            assert!((s64[i] - s16[i]).length() < 1e-6, "16 not nested in 64");
        }
        // The regular tetrahedron's face normals are 109.47 degrees apart.
        assert!((s4[1].dot(s4[0]) + 1.0 / 3.0).abs() < 1e-6);
    }

    #[test]
    fn fibonacci_sets_are_unit_distinct_and_even() {
        assert!(fibonacci_set(3).is_none());
        for n in [4, 16, 64, 100] {
            let s = fibonacci_set(n).unwrap();
            assert!((s[0] - Vec3::Z).length() < 1e-6, "d_1 = +z");
            // Balanced: the mean direction is small (4 points cannot cancel exactly).
            let mean: Vec3 = s.iter().copied().sum::<Vec3>() / n as f32;
            assert!(mean.length() < 0.5 / (n as f32).sqrt(), "{n}: {mean}");
            // Nearest-neighbour angles are within a factor 2.5 of each other (even spread).
            let nn: Vec<f32> = s
                .iter()
                .enumerate()
                .map(|(i, a)| {
                    s.iter().enumerate().filter(|&(j, _)| j != i).map(|(_, b)| a.dot(*b)).fold(-1.0, f32::max).acos()
                })
                .collect();
            let (lo, hi) = nn.iter().fold((f32::MAX, 0.0f32), |(l, h), &v| (l.min(v), h.max(v)));
            assert!(lo > 0.0 && hi / lo < 2.5, "{n}: {lo} .. {hi}");
            for a in &s {
                assert!((a.length() - 1.0).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn light_frame_maps_d1_to_the_light() {
        let omega = Vec3::new(0.3, -0.9, 0.2).normalize();
        let f = LightFrame::new(omega);
        assert!((f.to_world(Vec3::Z) + omega).length() < 1e-6);
        let w = Vec3::new(-0.2, 0.5, 0.84).normalize();
        assert!((f.to_world(f.to_local(w)) - w).length() < 1e-6);
        let (theta, _) = f.angles(-omega);
        assert!(theta.abs() < 1e-3);
        let (theta, _) = f.angles(omega);
        assert!((theta - std::f32::consts::PI).abs() < 1e-3);
    }
}
