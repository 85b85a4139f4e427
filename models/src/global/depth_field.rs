//! Precomputed optical depths for the global model's features in a grid medium.
//!
//! The feature vector needs tau_i(x), the optical depth from x along the n_D
//! directions d_i to the edge of the medium. The directions live in the light frame,
//! which depends only on the sun, so for one cloud and one sun they are n_D fixed
//! world directions. Ray marching all of them at every prediction costs n_D marches
//! through the grid (tens of microseconds at 128^3); instead this field stores
//! tau_hat_i = ln(1 / (1 + tau_i)) on a coarse lattice of nodes over the grid's
//! support, node-major, and a prediction reads it by trilinear interpolation: 8 nodes
//! times n_D contiguous floats, a few hundred nanoseconds.
//!
//! Construction: per direction (in parallel over directions), the engine's slice
//! sweep [`engine::field::optical_depth_sweep`]. The cost is O(nodes * n_D * few
//! lookups), about a second on two cores at 64^3 nodes and n_D = 64.
//!
//! The bilinear reads add a little numerical diffusion across d (the upstream value is
//! an average of its four neighbours); `tests` bounds the difference from direct ray
//! marching on a voxelized sphere and on a preset cloud.

use super::directions::LightFrame;
use engine::field::{lattice_over, optical_depth_sweep};
use engine::{Cancel, Medium};
use glam::{UVec3, Vec3};
use rayon::prelude::*;

/// Most nodes along one axis (64^3 nodes x 64 directions x 4 bytes = 64 MiB).
pub const DEFAULT_MAX_NODES: u32 = 64;

/// tau_hat along a fixed set of world directions on a lattice over a medium.
#[derive(Clone, Debug)]
pub struct DepthField {
    n: UVec3,
    origin: Vec3,
    spacing: Vec3,
    inv_spacing: Vec3,
    n_dirs: usize,
    /// [node][direction] tau_hat, node index x + n.x (y + n.y z).
    data: Vec<f32>,
}

impl DepthField {
    /// Builds the field of `medium` for the world directions `dirs`, with at most
    /// `max_nodes` nodes per axis (at most one per grid voxel).
    pub fn build(medium: &Medium, dirs: &[Vec3], max_nodes: u32) -> DepthField {
        Self::build_until(medium, dirs, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`DepthField::build`], or None when `cancel` asks to stop (checked before every
    /// slice of every direction's sweep, a few milliseconds apart).
    pub fn build_until(medium: &Medium, dirs: &[Vec3], max_nodes: u32, cancel: Cancel) -> Option<DepthField> {
        let support = medium.grid().support_bounds();
        let (n, spacing) = lattice_over(medium, max_nodes);
        let nodes = (n.x * n.y * n.z) as usize;
        let per_dir: Vec<Vec<f32>> = dirs
            .par_iter()
            .map(|&d| optical_depth_sweep(medium, support, n, spacing, d.normalize(), cancel))
            .collect::<Option<_>>()?;
        let n_dirs = dirs.len();
        let mut data = vec![0.0f32; nodes * n_dirs];
        data.par_chunks_mut(n_dirs).enumerate().for_each(|(i, row)| {
            for (k, v) in row.iter_mut().enumerate() {
                *v = super::features::tau_hat(per_dir[k][i]);
            }
        });
        Some(DepthField { n, origin: support.min, spacing, inv_spacing: spacing.recip(), n_dirs, data })
    }

    /// The field for the global model's directions (light frame of `omega_l`).
    pub fn for_light(medium: &Medium, local_dirs: &[Vec3], omega_l: Vec3, max_nodes: u32) -> DepthField {
        Self::for_light_until(medium, local_dirs, omega_l, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`DepthField::for_light`], or None when `cancel` asks to stop.
    pub fn for_light_until(
        medium: &Medium,
        local_dirs: &[Vec3],
        omega_l: Vec3,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<DepthField> {
        let frame = LightFrame::new(omega_l);
        let world: Vec<Vec3> = local_dirs.iter().map(|d| frame.to_world(*d)).collect();
        Self::build_until(medium, &world, max_nodes, cancel)
    }

    pub fn n_dirs(&self) -> usize {
        self.n_dirs
    }

    /// Nodes per axis.
    pub fn nodes(&self) -> UVec3 {
        self.n
    }

    /// Distance between nodes along each axis (world units).
    pub fn spacing(&self) -> Vec3 {
        self.spacing
    }

    pub fn memory_bytes(&self) -> usize {
        self.data.len() * 4
    }

    /// The eight lattice nodes around `x` (clamped to the lattice) and their
    /// trilinear weights.
    #[inline]
    fn corners(&self, x: Vec3) -> [(usize, f32); 8] {
        let u = ((x - self.origin) * self.inv_spacing).clamp(Vec3::ZERO, (self.n - UVec3::ONE).as_vec3());
        let i0 = u.floor().as_uvec3().min(self.n - UVec3::splat(2).min(self.n));
        let f = u - i0.as_vec3();
        std::array::from_fn(|c| {
            let c = c as u32;
            let (dx, dy, dz) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
            let w = (if dx == 1 { f.x } else { 1.0 - f.x })
                * (if dy == 1 { f.y } else { 1.0 - f.y })
                * (if dz == 1 { f.z } else { 1.0 - f.z });
            let idx = (i0.x + dx) as usize
                + self.n.x as usize * ((i0.y + dy) as usize + self.n.y as usize * (i0.z + dz) as usize);
            (idx, w)
        })
    }

    /// tau_hat at `x` for every direction (trilinear between nodes; positions outside
    /// the lattice are clamped to it), written to `out[..n_dirs]`.
    #[inline]
    pub fn lookup(&self, x: Vec3, out: &mut [f32]) {
        let out = &mut out[..self.n_dirs];
        out.fill(0.0);
        let nd = self.n_dirs;
        for (idx, w) in self.corners(x) {
            if w == 0.0 {
                continue;
            }
            let row = &self.data[idx * nd..(idx + 1) * nd];
            for (o, v) in out.iter_mut().zip(row) {
                *o = v.mul_add(w, *o);
            }
        }
    }

    /// Like [`DepthField::lookup`] for directions between the field's own: `out[k]` is
    /// the trilinear lookup of the blend sum_t w_t tau_hat[taps[k][t].0] with weights
    /// `taps[k][t].1` (the four directions around a wanted one and their bilinear
    /// weights).
    #[inline]
    pub fn lookup_blend(&self, x: Vec3, taps: &[[(u32, f32); 4]], out: &mut [f32]) {
        let out = &mut out[..taps.len()];
        out.fill(0.0);
        let nd = self.n_dirs;
        for (idx, w) in self.corners(x) {
            if w == 0.0 {
                continue;
            }
            let row = &self.data[idx * nd..(idx + 1) * nd];
            for (o, t) in out.iter_mut().zip(taps) {
                let v = t.iter().fold(0.0f32, |a, &(i, wt)| row[i as usize].mul_add(wt, a));
                *o = v.mul_add(w, *o);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::grid::Bounds3;
    use engine::{DensityGrid, PhaseFunction};
    use std::sync::Arc;

    fn sphere_medium(n: u32, r: f32, sigma: f32) -> Medium {
        let grid = DensityGrid::from_fn(UVec3::splat(n), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
            if p.length() <= r { 1.0 } else { 0.0 }
        })
        .unwrap();
        Medium::new(Arc::new(grid), sigma, 1.0, PhaseFunction::HenyeyGreenstein { g: 0.85 }).unwrap()
    }

    /// A homogeneous slab along one axis: the sweep is exact there up to the midpoint
    /// rule (no lateral variation, so interpolation adds nothing).
    #[test]
    fn axis_direction_in_a_constant_grid_is_exact() {
        let n = 32;
        let grid = DensityGrid::from_bounds(
            UVec3::splat(n),
            vec![1.0; (n * n * n) as usize],
            Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
        )
        .unwrap();
        let sigma = 3.0;
        let m = Medium::new(Arc::new(grid), sigma, 1.0, PhaseFunction::Isotropic).unwrap();
        let dirs = [Vec3::X, Vec3::NEG_Y, Vec3::new(0.0, 0.6, 0.8)];
        let f = DepthField::build(&m, &dirs, 33);
        let mut out = [0.0f32; 3];
        let step = 0.25 * m.grid().voxel_size().x;
        for x in [Vec3::ZERO, Vec3::new(0.1, -0.2, 0.3), Vec3::new(-0.3, 0.2, -0.1)] {
            f.lookup(x, &mut out);
            for (k, d) in dirs.iter().enumerate() {
                let exact = m.optical_depth(x, *d, f32::INFINITY, step, f32::INFINITY);
                // tau = exp(-tau_hat) - 1
                let got = (-out[k]).exp_m1();
                let tol = if k < 2 { 1e-3 * exact.max(1.0) } else { 0.02 * exact.max(1.0) };
                assert!((got - exact).abs() <= tol, "dir {k} at {x}: field {got} vs march {exact}");
            }
        }
    }

    /// On a voxelized sphere the field agrees with direct ray marching to within the
    /// lattice's discretization: a node spacing of s moves the sphere's edge by at
    /// most ~s along a ray, so |tau_field - tau_march| <= sigma * (2 s) per ray, and
    /// far less on average.
    #[test]
    fn matches_ray_marching_on_a_sphere() {
        let (r, sigma) = (0.4f32, 10.0f32);
        let m = sphere_medium(64, r, sigma);
        let dirs = crate::global::directions::direction_set(64).unwrap();
        let omega_l = Vec3::new(0.3, -1.0, 0.2).normalize();
        let f = DepthField::for_light(&m, &dirs, omega_l, 33);
        let frame = LightFrame::new(omega_l);
        let s = f.spacing.max_element();
        let step = 0.5 * m.grid().voxel_size().x;
        let mut rng = engine::Rng::new(4, 0, 0);
        let mut out = vec![0.0f32; 64];
        let (mut sum_err, mut count) = (0.0f64, 0);
        for _ in 0..200 {
            let x = engine::sampling::sample_uniform_sphere(rng.uniform2()) * r * rng.uniform().cbrt();
            f.lookup(x, &mut out);
            for (k, d) in dirs.iter().enumerate() {
                let exact = m.optical_depth(x, frame.to_world(*d), f32::INFINITY, step, f32::INFINITY);
                let got = (-out[k]).exp_m1();
                assert!((got - exact).abs() <= 2.0 * sigma * s + 0.02 * exact, "dir {k} at {x}: {got} vs {exact}");
                sum_err += ((-out[k]) - (1.0 + exact).ln()).abs() as f64;
                count += 1;
            }
        }
        // In the features' own units (tau_hat), the mean error is small.
        let mean = sum_err / count as f64;
        assert!(mean < 0.05, "mean |tau_hat error| {mean}");
    }

    /// A build for a generation still current gives the same bits as one that cannot
    /// be cancelled; one for a generation already superseded gives nothing; and one
    /// superseded a tenth of the way in gives nothing either (it stopped instead of
    /// finishing: a finished build is returned).  How soon it stops is the window's
    /// concern, measured by `nimbus bench latency`, not timed here.
    #[test]
    fn a_superseded_build_stops() {
        use engine::{Cancel, RenderControl};
        let m = sphere_medium(64, 0.4, 10.0);
        let dirs = crate::global::directions::direction_set(64).unwrap();
        let omega_l = Vec3::new(0.3, -1.0, 0.2).normalize();
        let control = RenderControl::new();
        let g = control.bump();
        let t = std::time::Instant::now();
        let whole = DepthField::for_light(&m, &dirs, omega_l, 64);
        let whole_secs = t.elapsed().as_secs_f64();
        let current = DepthField::for_light_until(&m, &dirs, omega_l, 64, Cancel::on(&control, g)).unwrap();
        assert!(whole.data.iter().zip(&current.data).all(|(a, b)| a.to_bits() == b.to_bits()));
        control.bump();
        assert!(DepthField::for_light_until(&m, &dirs, omega_l, 64, Cancel::on(&control, g)).is_none());

        // Superseded a tenth of the way into the build, from another thread.
        let g = control.bump();
        let cut = std::thread::scope(|scope| {
            let build = scope.spawn(|| DepthField::for_light_until(&m, &dirs, omega_l, 64, Cancel::on(&control, g)));
            std::thread::sleep(std::time::Duration::from_secs_f64(0.1 * whole_secs));
            control.bump();
            build.join().unwrap()
        });
        assert!(cut.is_none(), "the build finished although superseded");
    }
}
