//! Optical depths along every direction, for the global model under lights other than
//! its bound sun: sky directions sampled as directional lights (thesis chapter 7) and
//! points of a soft sun's disk.
//!
//! The model's features for a light travelling along omega_L are tau_hat along the n_D
//! directions of omega_L's light frame. A [`DepthField`] serves one light; this one
//! holds tau_hat along a fixed set of world directions, the texel centres of an
//! octahedral map of the sphere (m x m texels), on a coarser lattice of nodes, and
//! answers any light: each feature direction is blended bilinearly from the four
//! texels around it (the map's edges fold onto themselves, so a texel's neighbour
//! across an edge is its mirror image along that edge), then interpolated trilinearly
//! between nodes. The blend across directions smooths the optical depths a little;
//! `tests` bound its error against ray marching. At m = 16 (256 directions) and 32^3
//! nodes it holds 32 MiB and costs about as much to build as the sun's field at 64^3
//! nodes and 64 directions.

use super::DepthField;
use super::directions::LightFrame;
use engine::{Cancel, Medium};
use glam::{Vec2, Vec3};

/// Texels per side of the octahedral direction map.
pub const DEFAULT_TEXELS: u32 = 16;

/// Octahedral map of the unit sphere onto [0, 1]^2 (z up: the upper hemisphere is the
/// inner diamond).
pub fn oct_encode(d: Vec3) -> Vec2 {
    let p = Vec2::new(d.x, d.y) / (d.x.abs() + d.y.abs() + d.z.abs());
    let p = if d.z < 0.0 { Vec2::new((1.0 - p.y.abs()) * sign(p.x), (1.0 - p.x.abs()) * sign(p.y)) } else { p };
    p * 0.5 + Vec2::splat(0.5)
}

/// The inverse of [`oct_encode`] (unit length).
pub fn oct_decode(u: Vec2) -> Vec3 {
    let p = u * 2.0 - Vec2::ONE;
    let z = 1.0 - p.x.abs() - p.y.abs();
    let (x, y) = if z < 0.0 { ((1.0 - p.y.abs()) * sign(p.x), (1.0 - p.x.abs()) * sign(p.y)) } else { (p.x, p.y) };
    Vec3::new(x, y, z).normalize()
}

fn sign(v: f32) -> f32 {
    if v >= 0.0 { 1.0 } else { -1.0 }
}

/// tau_hat along all directions on a lattice over a medium.
#[derive(Clone, Debug)]
pub struct SkyDepthField {
    texels: u32,
    field: DepthField,
}

impl SkyDepthField {
    /// Builds the field of `medium` over `texels` x `texels` directions, with at most
    /// `max_nodes` nodes per axis.
    pub fn build(medium: &Medium, texels: u32, max_nodes: u32) -> Self {
        Self::build_until(medium, texels, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`SkyDepthField::build`], or None when `cancel` asks to stop.
    pub fn build_until(medium: &Medium, texels: u32, max_nodes: u32, cancel: Cancel) -> Option<Self> {
        let texels = texels.max(2);
        let dirs: Vec<Vec3> = (0..texels * texels)
            .map(|t| {
                let (i, j) = (t % texels, t / texels);
                oct_decode(Vec2::new((i as f32 + 0.5) / texels as f32, (j as f32 + 0.5) / texels as f32))
            })
            .collect();
        Some(SkyDepthField { texels, field: DepthField::build_until(medium, &dirs, max_nodes, cancel)? })
    }

    pub fn memory_bytes(&self) -> usize {
        self.field.memory_bytes()
    }

    pub fn field(&self) -> &DepthField {
        &self.field
    }

    /// The four texels around world direction `d` and their bilinear weights.
    #[inline]
    pub fn taps(&self, d: Vec3) -> [(u32, f32); 4] {
        let m = self.texels as i32;
        let s = oct_encode(d) * m as f32 - Vec2::splat(0.5);
        let i0 = s.floor();
        let f = s - i0;
        let (i0, j0) = (i0.x as i32, i0.y as i32);
        let texel = |i: i32, j: i32| -> u32 {
            // Across an edge of the map: the mirror image along that edge.
            let (mut i, mut j) = (i, j);
            if i < 0 || i >= m {
                i = i.clamp(0, m - 1);
                j = m - 1 - j;
            }
            if j < 0 || j >= m {
                j = j.clamp(0, m - 1);
                i = m - 1 - i;
            }
            (i.clamp(0, m - 1) + m * j.clamp(0, m - 1)) as u32
        };
        [
            (texel(i0, j0), (1.0 - f.x) * (1.0 - f.y)),
            (texel(i0 + 1, j0), f.x * (1.0 - f.y)),
            (texel(i0, j0 + 1), (1.0 - f.x) * f.y),
            (texel(i0 + 1, j0 + 1), f.x * f.y),
        ]
    }

    /// tau_hat at `x` along `frame.to_world(local_dirs[k])` for every k, to `out`.
    /// Directions go in chunks of 64 (the global model's n_D: one pass over the
    /// nodes), so the taps live in a small stack array.
    pub fn lookup(&self, x: Vec3, frame: &LightFrame, local_dirs: &[Vec3], out: &mut [f32]) {
        let mut taps = [[(0u32, 0.0f32); 4]; 64];
        for (dirs, out) in local_dirs.chunks(64).zip(out.chunks_mut(64)) {
            for (t, d) in taps.iter_mut().zip(dirs) {
                *t = self.taps(frame.to_world(*d));
            }
            self.field.lookup_blend(x, &taps[..dirs.len()], out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::grid::Bounds3;
    use engine::{DensityGrid, PhaseFunction};
    use std::sync::Arc;

    #[test]
    fn octahedral_map_round_trips_and_covers_the_sphere() {
        let mut rng = engine::Rng::new(3, 0, 0);
        for _ in 0..10_000 {
            let d = engine::sampling::sample_uniform_sphere(rng.uniform2());
            let u = oct_encode(d);
            assert!(u.min_element() >= 0.0 && u.max_element() <= 1.0);
            assert!((oct_decode(u) - d).length() < 1e-5, "{d} -> {u} -> {}", oct_decode(u));
        }
    }

    /// The taps of a texel centre are that texel alone; weights always sum to 1; and a
    /// direction next to an edge of the map blends texels that lie next to it on the
    /// sphere (within two texel spacings), the edge folding included.
    #[test]
    fn taps_are_neighbours_on_the_sphere() {
        let grid = DensityGrid::from_bounds(
            glam::UVec3::splat(4),
            vec![1.0; 64],
            Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
        )
        .unwrap();
        let m = Medium::new(Arc::new(grid), 1.0, 1.0, PhaseFunction::Isotropic).unwrap();
        let texels = 8;
        let f = SkyDepthField::build(&m, texels, 3);
        let dir_of = |t: u32| {
            oct_decode(Vec2::new(
                ((t % texels) as f32 + 0.5) / texels as f32,
                ((t / texels) as f32 + 0.5) / texels as f32,
            ))
        };
        for t in 0..texels * texels {
            let taps = f.taps(dir_of(t));
            let top = taps.iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
            assert_eq!(top.0, t);
            assert!((top.1 - 1.0).abs() < 1e-4, "{taps:?}");
        }
        // The mean texel spacing on the sphere; the map stretches texels near the
        // corners (the pole opposite the centre) to about twice that.
        let spacing = (4.0 * std::f32::consts::PI).sqrt() / texels as f32;
        let mut worst = 0.0f32;
        let mut rng = engine::Rng::new(5, 0, 0);
        for _ in 0..5_000 {
            let d = engine::sampling::sample_uniform_sphere(rng.uniform2());
            let taps = f.taps(d);
            assert!((taps.iter().map(|t| t.1).sum::<f32>() - 1.0).abs() < 1e-5);
            for (t, w) in taps {
                if w > 1e-6 {
                    let angle = dir_of(t).dot(d).clamp(-1.0, 1.0).acos();
                    worst = worst.max(angle / spacing);
                }
            }
        }
        assert!(worst < 2.5, "a tap {worst} texel spacings away");
    }

    /// On a voxelized sphere the features of an arbitrary light agree with ray
    /// marching within the lattice's and the direction blend's discretization: mean
    /// |tau_hat error| below 0.06 (the sun's own field, at twice the nodes and no
    /// blend, is bounded at 0.05 by `depth_field::tests`).
    #[test]
    fn features_of_any_light_match_ray_marching_on_a_sphere() {
        let (r, sigma) = (0.4f32, 10.0f32);
        let grid =
            DensityGrid::from_fn(glam::UVec3::splat(64), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
                if p.length() <= r { 1.0 } else { 0.0 }
            })
            .unwrap();
        let m = Medium::new(Arc::new(grid), sigma, 1.0, PhaseFunction::HenyeyGreenstein { g: 0.85 }).unwrap();
        let f = SkyDepthField::build(&m, DEFAULT_TEXELS, 17);
        let dirs = crate::global::directions::direction_set(64).unwrap();
        let step = 0.5 * m.grid().voxel_size().x;
        let mut rng = engine::Rng::new(4, 0, 0);
        let mut out = vec![0.0f32; 64];
        let (mut sum_err, mut count) = (0.0f64, 0);
        for _ in 0..200 {
            let x = engine::sampling::sample_uniform_sphere(rng.uniform2()) * r * rng.uniform().cbrt();
            let light = engine::sampling::sample_uniform_sphere(rng.uniform2());
            let frame = LightFrame::new(light);
            f.lookup(x, &frame, &dirs, &mut out);
            for (k, d) in dirs.iter().enumerate() {
                let exact = m.optical_depth(x, frame.to_world(*d), f32::INFINITY, step, f32::INFINITY);
                sum_err += ((-out[k]) - (1.0 + exact).ln()).abs() as f64;
                count += 1;
            }
        }
        let mean = sum_err / count as f64;
        assert!(mean < 0.06, "mean |tau_hat error| {mean}");
    }
}
