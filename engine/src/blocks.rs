//! Homogeneous blocks: where a cloud's density is constant over a region (the core of
//! a hard-edged or flat-topped cloud), a flight or shadow ray starting there tracks
//! the part of its ray inside that region in closed form, with no density lookup.
//!
//! The majorant cells (`MajorantGrid` in `medium`) are coarse, about an eighth of the
//! grid's axis, so that rays take few DDA steps; a hard edge then makes most of a
//! cloud's cells mixed (densities 0 and 1), and every tentative collision in them needs
//! a lookup, the core's included. Homogeneous blocks look at the density on a grid of
//! cells a quarter of the majorant cells' edge: each fine cell keeps the density it
//! holds when that is one constant over its region (the trilinear footprint included,
//! as the majorant cells' bounds), and a reach r >= 1 such that every cell within
//! Chebyshev distance r - 1 holds the same constant. A flight or shadow ray from a
//! point in such a cell tracks
//! the stretch of its ray inside that cube of 2 r - 1 cells (one exponential draw, or
//! one exp()), then goes on by the local ball and the DDA from where it left it (the
//! trackers are memoryless, so the estimate is the same).
//!
//! A cloud without such cells (interior noise everywhere) builds none, and its
//! trackers run as without ([`HomogeneousBlocks::new`] returns None).

use crate::grid::DensityGrid;
use glam::{IVec3, UVec3, Vec3};

/// The largest reach a block cell gets: a cube of up to 2 * 32 - 1 cells on an edge.
pub const MAX_BLOCK_REACH: u32 = 32;

/// The stretch [0, t_max] of a ray inside a homogeneous block, and the block's
/// density there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BlockStretch {
    pub t_max: f32,
    pub density: f32,
}

/// One fine cell: its constant density (0 where the density is not constant over
/// the cell, or the cell is empty) and the reach of its cube.
#[derive(Clone, Copy, Debug, PartialEq)]
struct BlockCell {
    density: f32,
    reach: u32,
}

/// Fine cells over a grid's support, each with the constant density it holds (if
/// any) and the reach of the cube of cells around it that holds the same.
#[derive(Clone, Debug)]
pub struct HomogeneousBlocks {
    dims: UVec3,
    cells: Vec<BlockCell>,
    origin: Vec3,
    cell_size: Vec3,
    inv_cell_size: Vec3,
}

/// An erosion over a grid of cells (x fastest), one ring per round: a cell of reach
/// r >= 1 (from `start`, where 0 marks a cell that never grows) gets r + 1 when each
/// of its 26 neighbours j `fits(i, j)` and has reach r itself, up to `max`; a
/// neighbour outside the grid stops it. Where `fits` is transitive enough that a
/// neighbour's fitting cells fit the cell too (equal densities, or bounds within
/// bounds), the cells within Chebyshev distance r - 1 of a cell of reach r all fit it:
/// the neighbours' cubes of r - 1 cover its cube of r.
pub(crate) fn erode(dims: UVec3, start: Vec<u32>, max: u32, fits: impl Fn(usize, usize) -> bool + Sync) -> Vec<u32> {
    use rayon::prelude::*;
    let d = dims.as_ivec3();
    let mut reach = start;
    for level in 1..max {
        let next: Vec<u32> = (0..reach.len())
            .into_par_iter()
            .map(|i| {
                if reach[i] != level {
                    return reach[i];
                }
                let c = IVec3::new(i as i32 % d.x, (i as i32 / d.x) % d.y, i as i32 / (d.x * d.y));
                for dz in -1..=1 {
                    for dy in -1..=1 {
                        for dx in -1..=1 {
                            let n = c + IVec3::new(dx, dy, dz);
                            if n.cmplt(IVec3::ZERO).any() || n.cmpge(d).any() {
                                return level;
                            }
                            let j = (n.x + d.x * (n.y + d.y * n.z)) as usize;
                            if reach[j] < level || !fits(i, j) {
                                return level;
                            }
                        }
                    }
                }
                level + 1
            })
            .collect();
        let grew = next.iter().zip(&reach).any(|(a, b)| a != b);
        reach = next;
        if !grew {
            break;
        }
    }
    reach
}

/// Per cell of constant density v > 0, a reach r >= 1 such that every cell within
/// Chebyshev distance r - 1 has the constant density v too (0 for the other cells),
/// up to [`MAX_BLOCK_REACH`] ([`erode`]). A cube never leaves the grid.
fn block_reach(dims: UVec3, density: &[f32]) -> Vec<u32> {
    let start = density.iter().map(|&v| (v > 0.0) as u32).collect();
    erode(dims, start, MAX_BLOCK_REACH, |i, j| density[j] == density[i])
}

impl HomogeneousBlocks {
    /// The fine cell edge for majorant cells of `majorant_cell_voxels`: a quarter,
    /// at least 2 voxels (4 voxels at 128^3 with the default cells, 32 at 1024^3;
    /// `nimbus bench render --compare-block-cells`).
    pub fn cell_voxels_for(majorant_cell_voxels: u32) -> u32 {
        (majorant_cell_voxels / 4).max(2)
    }

    /// The blocks of `grid` on cells of `cell_voxels`^3 voxels; None where no cell
    /// holds a constant density above 0.
    pub fn new(grid: &DensityGrid, cell_voxels: u32) -> Option<Self> {
        let b = cell_voxels.max(1);
        let (dims, max_density, min_density) = grid.cell_bounds(b);
        let density: Vec<f32> = max_density
            .iter()
            .zip(&min_density)
            .map(|(&hi, &lo)| if hi == lo && hi > 0.0 { hi } else { 0.0 })
            .collect();
        if !density.iter().any(|&v| v > 0.0) {
            return None;
        }
        let reach = block_reach(dims, &density);
        let cells = density.iter().zip(&reach).map(|(&density, &reach)| BlockCell { density, reach }).collect();
        let cell_size = grid.voxel_size() * b as f32;
        Some(HomogeneousBlocks {
            dims,
            cells,
            origin: grid.support_bounds().min,
            cell_size,
            inv_cell_size: cell_size.recip(),
        })
    }

    pub fn dims(&self) -> UVec3 {
        self.dims
    }

    /// How many cells hold a constant density above 0.
    pub fn homogeneous_cells(&self) -> usize {
        self.cells.iter().filter(|c| c.density > 0.0).count()
    }

    /// The stretch [0, t] of the ray `o + t d` (t at most `t_max`) inside the cube of
    /// constant density around `o`, when `o`'s cell holds one. None elsewhere, and
    /// outside the grid.
    #[inline(always)]
    pub fn stretch(&self, o: Vec3, d: Vec3, t_max: f32) -> Option<BlockStretch> {
        let q = (o - self.origin) * self.inv_cell_size;
        if !(q.cmpge(Vec3::ZERO).all() && q.cmplt(self.dims.as_vec3()).all()) {
            return None;
        }
        let c = q.as_uvec3().min(self.dims - UVec3::ONE);
        let cell = self.cells[(c.x + self.dims.x * (c.y + self.dims.y * c.z)) as usize];
        if cell.density <= 0.0 {
            return None;
        }
        // The exit through the cube's faces on the sides the ray moves to; an axis it
        // does not move along never bounds it (a subnormal component's NaN, 0 x inf on
        // a face, is dropped by the minimum).
        let (cf, r) = (c.as_vec3(), cell.reach as f32);
        let face = Vec3::select(d.cmpgt(Vec3::ZERO), cf + r, cf + 1.0 - r);
        let t_axis = Vec3::select(d.cmpne(Vec3::ZERO), (face - q) * (self.cell_size * d.recip()), Vec3::INFINITY);
        let exit = t_axis.x.min(t_axis.y).min(t_axis.z).min(t_max).max(0.0);
        Some(BlockStretch { t_max: exit, density: cell.density })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Bounds3;
    use crate::rng::Rng;
    use crate::sampling::sample_uniform_sphere;

    /// A sphere of density 1 with a hard edge and a soft cap, and a slab of constant
    /// 0.5 beside it, on anisotropic voxels.
    fn grid(sparse: bool) -> DensityGrid {
        let dims = UVec3::new(64, 48, 40);
        let b = Bounds3::new(Vec3::new(-0.6, -0.5, -0.4), Vec3::new(0.6, 0.5, 0.4));
        let f = |p: Vec3| {
            if p.length() <= 0.35 {
                if p.y > 0.25 { 0.6 + p.x } else { 1.0 }
            } else if p.x > 0.42 {
                0.5
            } else {
                0.0
            }
        };
        let g = DensityGrid::from_fn(dims, b, f).unwrap();
        if sparse { g.to_sparse() } else { g }
    }

    /// Every point of a stretch, and every voxel a one-voxel lookup there can read,
    /// holds the stretch's density: brute force over random rays from random points.
    #[test]
    fn stretches_hold_their_constant_density() {
        for sparse in [false, true] {
            let g = grid(sparse);
            let blocks = HomogeneousBlocks::new(&g, 4).expect("the sphere's core and the slab are homogeneous");
            assert!(blocks.homogeneous_cells() > 50, "{}", blocks.homogeneous_cells());
            let mut rng = Rng::new(7, 1, 2);
            let (mut found, mut long, mut deep) = (0, 0, 0);
            let bounds = g.support_bounds();
            for _ in 0..20_000 {
                let u = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform());
                let o = bounds.min + (bounds.max - bounds.min) * u;
                let d = sample_uniform_sphere(rng.uniform2());
                let Some(seg) = blocks.stretch(o, d, f32::INFINITY) else { continue };
                found += 1;
                assert!(seg.t_max >= 0.0 && seg.t_max.is_finite());
                long += (seg.t_max > 2.0 * g.voxel_size().max_element()) as u32;
                deep += (seg.t_max > 8.0 * g.voxel_size().max_element()) as u32;
                for i in 0..=16 {
                    let p = o + d * (seg.t_max * i as f32 / 16.0);
                    let v = g.lookup(p);
                    assert!((v - seg.density).abs() <= 1e-5, "{p}: {v} in a stretch of {}", seg.density);
                    for _ in 0..4 {
                        let w = g.lookup_stochastic(p, rng.next_u64());
                        assert_eq!(w, seg.density, "{p}: one-voxel read {w}");
                    }
                }
            }
            assert!(found > 2_000 && long > 500, "{found} stretches, {long} longer than two voxels");
            // Longer than a cell's diagonal (4 sqrt(3) voxels): cubes of reach > 1.
            assert!(deep > 20, "{deep} stretches longer than two cells");
        }
    }

    /// Cells that are not homogeneous give no stretch; a grid without any builds no
    /// blocks.
    #[test]
    fn mixed_and_varying_cells_give_none() {
        let g = grid(false);
        let blocks = HomogeneousBlocks::new(&g, 4).unwrap();
        // On the sphere's edge and in its soft cap.
        assert_eq!(blocks.stretch(Vec3::new(0.35, 0.0, 0.0), Vec3::X, 1.0), None);
        assert_eq!(blocks.stretch(Vec3::new(0.0, 0.3, 0.0), Vec3::X, 1.0), None);
        // Empty space and outside the grid.
        assert_eq!(blocks.stretch(Vec3::new(-0.55, 0.45, 0.0), Vec3::X, 1.0), None);
        assert_eq!(blocks.stretch(Vec3::new(2.0, 0.0, 0.0), Vec3::X, 1.0), None);
        // The core: a stretch up to t_max, or up to the cube's face.
        let s = blocks.stretch(Vec3::ZERO, Vec3::Y, 0.01).unwrap();
        assert_eq!((s.t_max, s.density), (0.01, 1.0));
        let s = blocks.stretch(Vec3::ZERO, Vec3::Y, f32::INFINITY).unwrap();
        assert!(s.t_max > 0.1 && s.t_max < 0.25, "{}", s.t_max);
        let noisy = DensityGrid::from_fn(UVec3::splat(24), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
            1.0 + 0.5 * (p.x * 40.0).sin()
        })
        .unwrap();
        assert!(HomogeneousBlocks::new(&noisy, 4).is_none());
    }
}
