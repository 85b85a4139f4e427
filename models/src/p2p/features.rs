//! The point-to-point model's input features (thesis 6.1.1): the set
//! Sigma_t^{n_l, n_g, l_l, l_g} of eqs. 6.4-6.6 (the thesis's defaults 3, 3, 4, 5 give
//! 351 densities), looked up in the [`DensityPyramid`] in the [`LocalFrame`], and the
//! diffusion feature phi_D.

use super::frame::LocalFrame;
use super::pyramid::DensityPyramid;
use engine::DensityGrid;
use glam::Vec3;

/// The feature set Sigma_t^{n_l, n_g, l_l, l_g} (eqs. 6.4-6.6) and phi_D.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct P2pFeatures {
    /// Grid points per axis of the local (emitter and sensor) levels.
    pub n_local: u32,
    /// Grid points per axis of the global levels.
    pub n_global: u32,
    pub local_levels: u32,
    pub global_levels: u32,
}

impl Default for P2pFeatures {
    /// The thesis's choice: 3, 3, 4, 5 (351 densities).
    fn default() -> Self {
        P2pFeatures { n_local: 3, n_global: 3, local_levels: 4, global_levels: 5 }
    }
}

/// One block of the network's input: the densities of one level (the emitter's and
/// the sensor's together for a local level).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LevelSlice {
    pub start: usize,
    pub len: usize,
}

impl P2pFeatures {
    /// Number of densities (351 for the defaults).
    pub fn densities(&self) -> usize {
        let (nl, ng) = (self.n_local.pow(3) as usize, self.n_global.pow(3) as usize);
        2 * nl * self.local_levels as usize + ng * self.global_levels as usize
    }

    /// Densities plus phi_D.
    pub fn len(&self) -> usize {
        self.densities() + 1
    }

    /// The widest filter any feature needs, in local units (the largest global
    /// level's sigma = 2^l / (n - 1)).
    pub fn max_local_std(&self) -> f32 {
        2f32.powi(self.global_levels as i32 - 1) / (self.n_global.max(2) - 1) as f32
    }

    /// The order of the features, the order the deep network takes them (thesis
    /// 6.2.1): local levels from the smallest neighbourhood (l = l_l - 1) to the
    /// largest, each with the emitter's then the sensor's grid; then the global levels
    /// from the smallest (l = 0) to the largest; then phi_D.
    pub fn slices(&self) -> Vec<LevelSlice> {
        let (nl, ng) = (self.n_local.pow(3) as usize, self.n_global.pow(3) as usize);
        let mut out = vec![];
        let mut start = 0;
        for _ in 0..self.local_levels {
            out.push(LevelSlice { start, len: 2 * nl });
            start += 2 * nl;
        }
        for _ in 0..self.global_levels {
            out.push(LevelSlice { start, len: ng });
            start += ng;
        }
        out
    }

    /// Writes the features of the emitter-sensor pair described by `frame` into
    /// `out` (length `len()`): the local-space densities rho d, scaled by the
    /// emitter-sensor distance, then phi_D for `albedo`.
    pub fn write(&self, pyramid: &DensityPyramid, rho: f32, albedo: f32, frame: &LocalFrame, out: &mut [f32]) {
        assert_eq!(out.len(), self.len(), "feature buffer length");
        let scale = frame.scale;
        let mut i = 0;
        let mut level = |origin: Vec3, n: u32, l: i32, out: &mut [f32]| {
            let extent = 2f32.powi(l);
            let std_local = extent / (n.max(2) - 1) as f32;
            let sel = pyramid.select(std_local * scale);
            let g = |k: u32| if n == 1 { 0.0 } else { 2.0 * k as f32 / (n - 1) as f32 - 1.0 };
            // The level's grid points in world space, looked up a chunk at a time
            // (on the stack: no allocation per prediction).
            let mut points = [Vec3::ZERO; 32];
            let total = (n * n * n) as usize;
            let mut done = 0;
            // Grid point k = (a n + b) n + c, counted without dividing.
            let (mut a, mut b, mut c) = (0, 0, 0);
            while done < total {
                let m = (total - done).min(points.len());
                for p in &mut points[..m] {
                    *p = frame.to_world(origin + extent * Vec3::new(g(a), g(b), g(c)));
                    c += 1;
                    if c == n {
                        (b, c) = (b + 1, 0);
                        if b == n {
                            (a, b) = (a + 1, 0);
                        }
                    }
                }
                let dst = &mut out[i + done..i + done + m];
                pyramid.lookup_many(sel, &points[..m], dst);
                for v in dst {
                    *v *= scale * rho;
                }
                done += m;
            }
            i += total;
        };
        let (xe, xs) = (Vec3::new(0.0, 0.0, -0.5), Vec3::new(0.0, 0.0, 0.5));
        for l in (0..self.local_levels as i32).rev() {
            level(xe, self.n_local, -l - 1, out);
            level(xs, self.n_local, -l - 1, out);
        }
        for l in 0..self.global_levels as i32 {
            level(Vec3::ZERO, self.n_global, l, out);
        }
        // phi_D from the density around the segment: the global level-0 filter
        // (sigma = 1/2 local unit) at the midpoint.
        let sigma_t = scale * rho * pyramid.lookup(frame.to_world(Vec3::ZERO), 0.5 * scale);
        out[i] = diffusion_fluence(sigma_t, albedo, 1.0);
    }
}

/// Fluence at distance `r` from a unit-power isotropic point source in an infinite
/// homogeneous isotropic medium, by the diffusion approximation with Grosjean's
/// diffusion coefficient D = (2 sigma_a + sigma_s) / (3 sigma_t^2), the coefficient
/// of the improved diffusion models the thesis cites (d'Eon and Irving 2011):
/// phi(r) = exp(-sigma_tr r) / (4 pi D r), sigma_tr = sqrt(sigma_a / D).
pub fn diffusion_fluence(sigma_t: f32, albedo: f32, r: f32) -> f32 {
    if !(sigma_t > 0.0 && r > 0.0) {
        return 0.0;
    }
    let (sigma_t, albedo, r) = (sigma_t as f64, albedo.clamp(0.0, 1.0) as f64, r as f64);
    let (sigma_s, sigma_a) = (albedo * sigma_t, (1.0 - albedo) * sigma_t);
    let d = (2.0 * sigma_a + sigma_s) / (3.0 * sigma_t * sigma_t);
    let sigma_tr = (sigma_a / d).sqrt();
    ((-sigma_tr * r).exp() / (4.0 * std::f64::consts::PI * d * r)) as f32
}

/// Builds the pyramid a feature set needs for clouds whose emitter-sensor distances
/// reach `max_distance` (world units).
/// Its samples are 16-bit (see [`DensityPyramid::quantized`]).
pub fn pyramid_for(grid: &DensityGrid, spec: &P2pFeatures, max_distance: f32) -> DensityPyramid {
    DensityPyramid::new(grid, spec.max_local_std() * max_distance).quantized()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The features come in the documented order, level by level (local levels from
    /// the smallest, emitter then sensor; then the global ones), and within a level
    /// grid point k = (a n + b) n + c at origin + extent (g(a), g(b), g(c)), also
    /// across the 32-point chunks the lookups go in (n = 4: 64 points, n = 5: 125).
    #[test]
    fn features_follow_the_grid_order() {
        let grid = DensityGrid::from_fn(
            glam::UVec3::splat(24),
            engine::Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
            |p| (1.0 - 2.0 * p.length()).max(0.0) * (1.6 + (7.0 * p.x + 3.0 * p.y).sin() + p.z),
        )
        .unwrap();
        let spec = P2pFeatures { n_local: 4, n_global: 5, local_levels: 2, global_levels: 2 };
        let pyramid = pyramid_for(&grid, &spec, 2.0);
        let frame = LocalFrame::new(Vec3::new(-0.1, 0.05, 0.0), Vec3::new(0.15, -0.05, 0.1), 0.7).unwrap();
        let rho = 25.0;
        let mut out = vec![0.0; spec.len()];
        spec.write(&pyramid, rho, 0.99, &frame, &mut out);
        let mut want = vec![];
        let mut level = |origin: Vec3, n: u32, l: i32| {
            let extent = 2f32.powi(l);
            let sel = pyramid.select(extent / (n - 1) as f32 * frame.scale);
            let g = |k: u32| 2.0 * k as f32 / (n - 1) as f32 - 1.0;
            for k in 0..n * n * n {
                let (a, b, c) = (k / (n * n), (k / n) % n, k % n);
                let p = frame.to_world(origin + extent * Vec3::new(g(a), g(b), g(c)));
                want.push(pyramid.lookup_in(sel, p) * (frame.scale * rho));
            }
        };
        let (xe, xs) = (Vec3::new(0.0, 0.0, -0.5), Vec3::new(0.0, 0.0, 0.5));
        for l in (0..2).rev() {
            level(xe, 4, -l - 1);
            level(xs, 4, -l - 1);
        }
        for l in 0..2 {
            level(Vec3::ZERO, 5, l);
        }
        assert_eq!(want.len(), spec.densities());
        for (i, (a, b)) in out.iter().zip(&want).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "feature {i}: {a} vs {b}");
        }
        // The points see the cloud, and its densities differ from point to point.
        let mut distinct: Vec<u32> = want.iter().filter(|v| **v > 0.0).map(|v| v.to_bits()).collect();
        distinct.sort_unstable();
        distinct.dedup();
        assert!(distinct.len() > want.len() / 2, "{} distinct of {}", distinct.len(), want.len());
    }
}
