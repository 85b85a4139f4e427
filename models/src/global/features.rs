//! The global transport model's feature vector (thesis eqs. 5.6-5.7):
//! `[albedo, g, theta, phi, tau_hat_1 .. tau_hat_nD]`, with theta, phi the query
//! direction's angles in the light frame and tau_hat_i = log(1 / (1 + tau_i)) the
//! transformed optical depth from the query point along direction d_i to the edge of
//! the medium. One implementation serves both sides: data generation passes an
//! analytic optical depth (homogeneous convex shapes), the renderer a ray-marched one
//! through the density grid.

use super::directions::{DirectionSetKind, LightFrame};
use engine::Medium;
use glam::Vec3;

/// eq. 5.7
#[inline]
pub fn tau_hat(tau: f32) -> f32 {
    -(1.0 + tau.max(0.0)).ln()
}

/// Feature extraction for one direction-set size; reusable, allocation free per call.
#[derive(Clone, Debug)]
pub struct FeatureExtractor {
    /// Directions in the light frame (d_1 = +z = toward the light).
    directions: Vec<Vec3>,
}

impl FeatureExtractor {
    /// The thesis's tetrahedron set, n_d in {4, 16, 64}.
    pub fn new(n_d: usize) -> Option<Self> {
        Self::with_set(DirectionSetKind::Tetrahedron, n_d)
    }

    pub fn with_set(kind: DirectionSetKind, n_d: usize) -> Option<Self> {
        Some(FeatureExtractor { directions: kind.directions(n_d)? })
    }

    /// The directions in the light frame (d_1 = +z).
    pub fn directions(&self) -> &[Vec3] {
        &self.directions
    }

    pub fn n_directions(&self) -> usize {
        self.directions.len()
    }

    /// Length of the feature vector.
    pub fn len(&self) -> usize {
        4 + self.directions.len()
    }

    pub fn is_empty(&self) -> bool {
        false
    }

    /// The first four features, [albedo, g, theta, phi], with the query direction's
    /// angles in `frame`.
    #[inline]
    pub fn write_head(albedo: f32, g: f32, frame: &LightFrame, omega_q: Vec3, out: &mut [f32]) {
        let (theta, phi) = frame.angles(omega_q);
        out[..4].copy_from_slice(&[albedo, g, theta, phi]);
    }

    /// Fills `out` (length `len()`) given an optical-depth function of a world direction.
    pub fn extract_with(
        &self,
        albedo: f32,
        g: f32,
        omega_l: Vec3,
        omega_q: Vec3,
        mut tau: impl FnMut(Vec3) -> f32,
        out: &mut [f32],
    ) {
        assert_eq!(out.len(), self.len());
        let frame = LightFrame::new(omega_l);
        Self::write_head(albedo, g, &frame, omega_q, out);
        for (o, d) in out[4..].iter_mut().zip(&self.directions) {
            *o = tau_hat(tau(frame.to_world(*d)));
        }
    }

    /// Features at `x` in a grid medium, optical depths ray marched with steps of half
    /// a voxel.
    pub fn extract_grid(&self, medium: &Medium, omega_l: Vec3, x: Vec3, omega_q: Vec3, out: &mut [f32]) {
        let step = 0.5 * medium.grid().voxel_size().min_element();
        let g = medium.phase().mean_cosine();
        self.extract_with(
            medium.albedo(),
            g,
            omega_l,
            omega_q,
            |d| medium.optical_depth(x, d, f32::INFINITY, step, f32::INFINITY),
            out,
        );
    }
}

/// Distance from `x` inside a sphere (centre `c`, radius `r`) along unit `d` to its
/// surface; 0 outside.
pub fn sphere_exit_distance(c: Vec3, r: f32, x: Vec3, d: Vec3) -> f32 {
    let o = x - c;
    let b = o.dot(d);
    let disc = b * b - (o.length_squared() - r * r);
    if disc < 0.0 { 0.0 } else { (-b + disc.sqrt()).max(0.0) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::{Bounds3, DensityGrid, PhaseFunction};
    use glam::UVec3;
    use std::sync::Arc;

    #[test]
    fn layout_and_transform() {
        let f = FeatureExtractor::new(16).unwrap();
        assert_eq!(f.len(), 20);
        assert_eq!(tau_hat(0.0), 0.0);
        assert!((tau_hat(std::f32::consts::E - 1.0) + 1.0).abs() < 1e-6);
        let mut out = vec![0.0; 20];
        let omega_l = Vec3::NEG_Y;
        f.extract_with(0.9, 0.85, omega_l, Vec3::Y, |_| 0.0, &mut out);
        assert_eq!(&out[..2], &[0.9, 0.85]);
        assert!(out[2].abs() < 1e-3, "query toward the light has theta 0");
        assert!(out[4..].iter().all(|t| *t == 0.0));
        // tau along d_1 is the optical depth toward the light.
        f.extract_with(1.0, 0.0, omega_l, Vec3::Y, |d| if d.dot(Vec3::Y) > 0.999 { 3.0 } else { 0.0 }, &mut out);
        assert!((out[4] - tau_hat(3.0)).abs() < 1e-6);
        assert!(out[5..].iter().all(|t| *t == 0.0));
    }

    /// Ray-marched features on a voxelized sphere agree with the analytic ones within
    /// the voxelization error: trilinear interpolation moves the boundary by at most
    /// one voxel, so |tau_grid - tau_exact| <= sigma * voxel along each ray.
    #[test]
    fn grid_features_match_analytic_sphere() {
        let n = 64;
        let r = 0.4f32;
        let grid = DensityGrid::from_fn(UVec3::splat(n), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
            if p.length() <= r { 1.0 } else { 0.0 }
        })
        .unwrap();
        let vs = grid.voxel_size().x;
        let sigma = 10.0f32;
        let medium = Medium::new(Arc::new(grid), sigma, 0.95, PhaseFunction::HenyeyGreenstein { g: 0.85 }).unwrap();
        let f = FeatureExtractor::new(64).unwrap();
        let (mut a, mut b) = (vec![0.0; f.len()], vec![0.0; f.len()]);
        let omega_l = Vec3::new(0.2, -1.0, 0.1).normalize();
        let mut rng = engine::Rng::new(1, 0, 0);
        for _ in 0..50 {
            let x = engine::sampling::sample_uniform_sphere(rng.uniform2()) * (r - 3.0 * vs) * rng.uniform().cbrt();
            let q = engine::sampling::sample_uniform_sphere(rng.uniform2());
            f.extract_grid(&medium, omega_l, x, q, &mut a);
            f.extract_with(0.95, 0.85, omega_l, q, |d| sigma * sphere_exit_distance(Vec3::ZERO, r, x, d), &mut b);
            assert_eq!(&a[..4], &b[..4]);
            for i in 4..f.len() {
                let (tg, te) = ((-a[i]).exp() - 1.0, (-b[i]).exp() - 1.0);
                assert!((tg - te).abs() <= sigma * vs * 1.01, "direction {}: {tg} vs {te}", i - 4);
            }
        }
    }
}
