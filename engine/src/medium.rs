//! The heterogeneous medium: sigma_t(x) = rho * d(x), a majorant grid (each cell's
//! largest and smallest density) traversed by a 3D DDA, and the three ways to get at
//! transmittance along a ray: delta tracking for free flights (decomposition tracking
//! where a cell has a positive minimum), ratio tracking for shadow rays (residual
//! ratio tracking there), and deterministic ray marching for the optical depth the
//! learned model's features use.
//!
//! A flight or shadow ray walks its ray in up to three parts, each tracked as above:
//! the stretch inside a homogeneous block around its start, in closed form
//! ([`crate::blocks`]); the local ball of its majorant cell, without the DDA
//! ([`MajorantGrid::local_ball`]); and the majorant cells by the DDA for the rest.
//!
//! A medium answers two questions (pbrt-v4 `SamplePoint` / `SampleRay`): the
//! coefficients at a point, and the majorant segments along a ray. Within a segment
//! the trackers draw tentative collisions at a constant rate ([`tentative_collisions`]);
//! [`Medium::sample_t_maj`] offers the plain loop (every tentative collision against
//! the majorant) to callers that decide absorb, scatter or null themselves.
//!
//! The free-flight and ratio trackers read, at each tentative collision, one corner of
//! the trilinear stencil drawn with probability its weight
//! ([`Medium::sigma_t_estimate`]): the estimate's expectation is sigma_t, and both
//! trackers are linear in it (an acceptance probability, a factor of the running
//! product), so they stay unbiased; a free flight's distribution is exactly that of
//! the eight-voxel lookup, and a shadow ray's variance grows only where a cell's
//! voxels differ a lot. One voxel's read in place of eight is what a big grid's
//! lookups, which miss the caches, cost least with (docs/benchmarks.md).
//!
//! Parameters ([`Medium::with_majorant_cells`]): `rho` the density scale, per world
//! unit, finite and >= 0 (sigma_t = rho d); `albedo` in [0, 1] (sigma_s = albedo
//! sigma_t); `phase` ([`crate::phase`]); `cell_voxels` the majorant cell edge in
//! voxels, >= 1 (default [`MajorantGrid::default_cell_voxels`]: about an eighth of the
//! grid's largest axis). Bad values are
//! errors naming the parameter.

use crate::blocks::HomogeneousBlocks;
use crate::grid::{Bounds3, DensityGrid, floor_i32};
use crate::phase::PhaseFunction;
use crate::rng::Rng;
use crate::sampling::{INV_4PI, sample_exponential};
use glam::{IVec3, UVec3, Vec3};
use std::sync::Arc;

/// Coarse grid of density maxima and minima, each cell covering `cell_voxels`^3
/// voxels of the density grid plus the one-voxel trilinear footprint around them
/// (pbrt-v4 `SampledGrid::MaxValue` widens the same way), over the grid's support.
/// The minimum (0 for a cell whose footprint reaches past the grid, where the density
/// tapers to zero) is the control density of the trackers: what every point of the
/// cell has at least is handled in closed form, only the rest by sampling.
#[derive(Clone, Debug)]
pub struct MajorantGrid {
    dims: UVec3,
    max_density: Vec<f32>,
    min_density: Vec<f32>,
    /// World box covered (the density grid's support).
    bounds: Bounds3,
    cell_size: Vec3,
    inv_cell_size: Vec3,
    /// Per cell, 1 + r, with r (at most [`MAX_REACH`]) a radius in cells within which
    /// every cell's densities lie within this cell's bounds (majorant at most its
    /// majorant, control at least its control); 0 for an empty cell
    /// ([`MajorantGrid::local_ball`]).
    reach: Vec<u8>,
}

/// The largest radius, in cells, that [`MajorantGrid::local_ball`] looks around a
/// point: a flight or shadow ray that gets this far goes on by the DDA.
pub const MAX_REACH: u8 = 8;

/// A ball around a point within which the medium's density lies between
/// `min_density` and `max_density` (those of the point's majorant cell): a flight or
/// shadow ray from the point can track the ball as one stretch, without the DDA.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalBall {
    pub radius: f32,
    pub max_density: f32,
    pub min_density: f32,
}

impl LocalBall {
    /// The stretch [t_min, t_max] of a ray through the ball (within its radius of the
    /// centre), as a majorant segment with the ball's bounds.
    #[inline(always)]
    pub fn stretch(&self, t_min: f32, t_max: f32) -> MajorantSegment {
        MajorantSegment { t_min, t_max, max_density: self.max_density, min_density: self.min_density }
    }
}

/// Per cell, 1 + a radius r in cells such that every cell within Chebyshev distance r
/// has its densities within the cell's bounds (0 for an empty cell). An erosion, one
/// ring per round: a cell of radius r gets r + 1 when each of its 26 neighbours lies
/// within its bounds and has radius r itself (the neighbours' blocks of radius r,
/// whose cells lie within the neighbours' bounds and so within the cell's, cover its
/// block of r + 1). Conservative: a radius can be larger than the one found.
fn local_reach(dims: UVec3, max_density: &[f32], min_density: &[f32]) -> Vec<u8> {
    // Every cell starts at radius 0 (stored 1), the empty ones included (they bound
    // their empty neighbours); empty cells get 0 at the end.
    let within = |i: usize, j: usize| max_density[j] <= max_density[i] && min_density[j] >= min_density[i];
    let rad = crate::blocks::erode(dims, vec![1; max_density.len()], MAX_REACH as u32 + 1, within);
    rad.iter().zip(max_density).map(|(&r, &m)| if m <= 0.0 { 0 } else { r as u8 }).collect()
}

impl MajorantGrid {
    /// The smallest default cell edge in voxels, and the step of the default edges
    /// (the brick edge, so sparse grids build from brick maxima).
    pub const DEFAULT_CELL_VOXELS: u32 = 8;

    /// The default cell edge for a grid: about an eighth of its largest axis in
    /// multiples of [`Self::DEFAULT_CELL_VOXELS`] (8 voxels at 64^3, 16 at 128^3, 32 at
    /// 256^3, 128 at 1024^3), so every cloud has about as many cells, and its rays as
    /// many DDA steps, whatever its resolution. With the trackers' local balls
    /// ([`MajorantGrid::local_ball`]) coarser cells cost less DDA and give wider
    /// balls for about the same tightness (`nimbus bench render --compare-cells`).
    pub fn default_cell_voxels(grid: &DensityGrid) -> u32 {
        let n = grid.dims().max_element();
        Self::DEFAULT_CELL_VOXELS * ((n + 32) / 64).max(1)
    }

    pub fn new(grid: &DensityGrid, cell_voxels: u32) -> Self {
        let b = cell_voxels.max(1);
        let (dims, max_density, min_density) = grid.cell_bounds(b);
        let support = grid.support_bounds();
        let cell_size = grid.voxel_size() * b as f32;
        let reach = local_reach(dims, &max_density, &min_density);
        MajorantGrid {
            dims,
            max_density,
            min_density,
            bounds: support,
            cell_size,
            inv_cell_size: cell_size.recip(),
            reach,
        }
    }

    pub fn dims(&self) -> UVec3 {
        self.dims
    }

    /// The largest majorant density over the cells that overlap `b` (0 where `b` lies
    /// outside the grid's support).
    pub fn max_in(&self, b: Bounds3) -> f32 {
        let (lo, hi) = (b.min.max(self.bounds.min), b.max.min(self.bounds.max));
        if !(lo.cmple(hi).all()) {
            return 0.0;
        }
        let top = self.dims.as_ivec3() - 1;
        let cell_of = |p: Vec3| {
            let q = (p - self.bounds.min) * self.inv_cell_size;
            IVec3::new(floor_i32(q.x), floor_i32(q.y), floor_i32(q.z)).clamp(IVec3::ZERO, top)
        };
        let (c0, c1) = (cell_of(lo), cell_of(hi));
        let mut m = 0.0f32;
        for z in c0.z..=c1.z {
            for y in c0.y..=c1.y {
                for x in c0.x..=c1.x {
                    m = m.max(self.cell(IVec3::new(x, y, z)));
                }
            }
        }
        m
    }

    /// The ball around `o` within which the density lies within the bounds of
    /// `o`'s majorant cell: the block of cells around it that [`local_reach`] found
    /// (at most [`MAX_REACH`] cells in radius), less the part of `o`'s own cell on the
    /// far side of it. None outside the grid and in empty cells.
    #[inline(always)]
    pub fn local_ball(&self, o: Vec3) -> Option<LocalBall> {
        let q = (o - self.bounds.min) * self.inv_cell_size;
        if !(q.cmpge(Vec3::ZERO).all() && q.cmplt(self.dims.as_vec3()).all()) {
            return None;
        }
        let c = q.as_uvec3().min(self.dims - UVec3::ONE);
        let i = self.cell_index(c.as_ivec3());
        let r = self.reach[i];
        if r == 0 {
            return None;
        }
        // Distance to the block's faces: the rings beyond its own cell, plus the
        // nearer face of its own cell on each axis.
        let f = (q - c.as_vec3()).clamp(Vec3::ZERO, Vec3::ONE);
        let inner = f.min(Vec3::ONE - f) + Vec3::splat((r - 1) as f32);
        Some(LocalBall {
            radius: (inner * self.cell_size).min_element(),
            max_density: self.max_density[i],
            min_density: self.min_density[i],
        })
    }

    #[inline]
    fn cell(&self, c: IVec3) -> f32 {
        self.max_density[self.cell_index(c)]
    }

    #[inline]
    fn cell_index(&self, c: IVec3) -> usize {
        (c.x as u32 + self.dims.x * (c.y as u32 + self.dims.y * c.z as u32)) as usize
    }

    /// Iterates the segments of the ray `o + t d`, t in [t_min, t_max], over the
    /// majorant cells it crosses, in order.
    #[inline]
    pub fn segments(&self, o: Vec3, d: Vec3, t_min: f32, t_max: f32) -> MajorantIter<'_> {
        let inv_d = d.recip();
        let Some((t0, t1)) = self.bounds.intersect(o, inv_d, t_min, t_max) else {
            return MajorantIter::empty(self);
        };
        // Position in cell units at entry.
        let q = (o + d * t0 - self.bounds.min) * self.inv_cell_size;
        let dims = self.dims.as_ivec3();
        let cell = IVec3::new(floor_i32(q.x), floor_i32(q.y), floor_i32(q.z)).clamp(IVec3::ZERO, dims - 1);
        // Per axis: the ray parameter of the next cell face and the parameter per cell,
        // from 1 / dq = inv_d times the cell size (no division per axis), branch-free;
        // an axis the ray does not move along never steps (infinite next face), nor one
        // it moves along so slowly (a subnormal component) that 1 / dq overflows.
        let inv_dq = inv_d * self.cell_size;
        let (pos, neg) = (d.cmpgt(Vec3::ZERO), d.cmplt(Vec3::ZERO));
        let moving = (pos | neg) & inv_dq.is_finite_mask();
        let cellf = cell.as_vec3();
        let face = Vec3::select(pos, cellf + Vec3::ONE, cellf);
        let next_t = Vec3::select(moving, Vec3::splat(t0) + (face - q) * inv_dq, Vec3::INFINITY);
        let delta_t = Vec3::select(moving, inv_dq.abs(), Vec3::INFINITY);
        let step = IVec3::select(pos, IVec3::ONE, IVec3::select(neg, IVec3::NEG_ONE, IVec3::ZERO));
        let stop = IVec3::select(pos, dims, IVec3::select(neg, IVec3::NEG_ONE, IVec3::splat(i32::MIN)));
        MajorantIter { grid: self, cell, step, stop, next_t, delta_t, t: t0, t_end: t1, done: false }
    }
}

/// One stretch of a ray with a constant majorant density and a constant lower bound
/// of the density (multiply by rho).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MajorantSegment {
    pub t_min: f32,
    pub t_max: f32,
    pub max_density: f32,
    pub min_density: f32,
}

/// The 3D DDA (Amanatides and Woo) over the majorant grid.
pub struct MajorantIter<'a> {
    grid: &'a MajorantGrid,
    cell: IVec3,
    step: IVec3,
    stop: IVec3,
    next_t: Vec3,
    delta_t: Vec3,
    t: f32,
    t_end: f32,
    done: bool,
}

impl<'a> MajorantIter<'a> {
    fn empty(grid: &'a MajorantGrid) -> Self {
        MajorantIter {
            grid,
            cell: IVec3::ZERO,
            step: IVec3::ZERO,
            stop: IVec3::ZERO,
            next_t: Vec3::ZERO,
            delta_t: Vec3::ZERO,
            t: 0.0,
            t_end: 0.0,
            done: true,
        }
    }
}

impl Iterator for MajorantIter<'_> {
    type Item = MajorantSegment;

    #[inline]
    fn next(&mut self) -> Option<MajorantSegment> {
        if self.done {
            return None;
        }
        let axis = if self.next_t.x < self.next_t.y {
            if self.next_t.x < self.next_t.z { 0 } else { 2 }
        } else if self.next_t.y < self.next_t.z {
            1
        } else {
            2
        };
        let exit = self.next_t[axis].min(self.t_end);
        let i = self.grid.cell_index(self.cell);
        let seg = MajorantSegment {
            t_min: self.t,
            t_max: exit,
            max_density: self.grid.max_density[i],
            min_density: self.grid.min_density[i],
        };
        self.t = exit;
        if exit >= self.t_end {
            self.done = true;
        } else {
            self.cell[axis] += self.step[axis];
            if self.cell[axis] == self.stop[axis] {
                self.done = true;
            }
            self.next_t[axis] += self.delta_t[axis];
        }
        Some(seg)
    }
}

/// Tentative collisions at rate `sigma` (> 0) after `t`, up to `end`: calls `f(t, rng)`
/// at each until it returns false. Returns false if `f` stopped the walk, true if it
/// reached `end`. Each step draws one uniform number.
#[inline(always)]
pub fn tentative_collisions(
    mut t: f32,
    end: f32,
    sigma: f32,
    rng: &mut Rng,
    mut f: impl FnMut(f32, &mut Rng) -> bool,
) -> bool {
    loop {
        let next = t + sample_exponential(rng.uniform(), sigma);
        // A step below the float spacing at t would not move: take one spacing (far
        // from the origin, with a capped but large majorant).
        t = if next > t { next } else { t.next_up() };
        if t >= end {
            return true;
        }
        if !f(t, rng) {
            return false;
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MediumError {
    #[error("density scale rho must be finite and >= 0, got {0}")]
    BadRho(f32),
    #[error("albedo must lie in [0, 1], got {0}")]
    BadAlbedo(f32),
}

/// What happened to a free flight.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FreeFlight {
    /// A real collision at distance `t`.
    Collision { t: f32 },
    /// The ray left the medium (or passed t_max) without a real collision.
    Escaped,
}

/// Optical depth per voxel edge at which extinction is capped: a voxel this thick
/// lets through e^-32 (1e-14) of the light, opaque for all purposes. The cap bounds
/// the work of tracking through any majorant cell (about 32 tentative collisions per
/// voxel crossed) whatever the grid holds, so a grid with a huge or infinite density
/// renders in bounded time; below it (every cloud the modeler makes: rho d per voxel
/// is a few at most) nothing changes.
pub const MAX_TAU_PER_VOXEL: f32 = 32.0;

/// A heterogeneous cloud: a density grid scaled by rho, a constant albedo and phase
/// function, and the majorant grid used for tracking.
#[derive(Clone, Debug)]
pub struct Medium {
    grid: Arc<DensityGrid>,
    majorant: MajorantGrid,
    rho: f32,
    /// The largest extinction (per world unit): [`MAX_TAU_PER_VOXEL`] over the
    /// smallest voxel edge.
    sigma_cap: f32,
    /// The trackers read one trilinear corner drawn by its weight
    /// ([`Medium::sigma_t_estimate`]): true unless turned off or the cap could bind
    /// (rho times the grid's largest value above it), where sigma_t is not linear in
    /// the voxels' values.
    one_voxel: bool,
    /// Free flights settle a tentative collision's test from the drawn voxel's brick
    /// bounds before reading the voxel ([`DensityGrid::stochastic_test`]): on for
    /// sparse grids bigger than [`BRICK_BOUNDS_MIN_BYTES`], whose reads miss the
    /// caches; off for smaller ones, where the read is cheaper than the extra test.
    brick_bounds: bool,
    /// Where the density is constant over fine cells, the stretch a flight or shadow
    /// ray starting there tracks in closed form before its local ball
    /// ([`crate::blocks`]); None for a cloud without such cells, or turned off.
    blocks: Option<HomogeneousBlocks>,
    /// Ratio tracking's rate over the residual majorant (at least 1; default
    /// [`RATIO_TRACKING_OVERSAMPLING`]).
    ratio_oversampling: f32,
    /// The phase value below which next event estimation casts its shadow ray by
    /// Russian roulette ([`Medium::shadow_roulette_floor`]).
    shadow_floor: f32,
    albedo: f32,
    phase: PhaseFunction,
}

/// The grid size (values and table) from which free flights test brick bounds
/// before reading a voxel: a few times the last-level cache of a desktop processor,
/// past which most reads in a cloud's varying shell go to memory. Measured with
/// `nimbus bench render --compare-resolutions 256,512,1024 --compare-bounds`
/// (docs/benchmarks.md).
pub const BRICK_BOUNDS_MIN_BYTES: usize = 32 << 20;

/// Transmittance below which ratio tracking plays Russian roulette (unbiased).
const RATIO_TRACKING_RR_THRESHOLD: f32 = 0.1;

/// Ratio tracking's tentative collisions come at this multiple of the residual
/// majorant. At the majorant itself (1) a stretch whose density sits at its majorant,
/// as the dense side of a hard edge does in a cell that also holds empty space, gives
/// weights of 0, and the estimate is binary (0 or 1) as delta tracking's; at a rate
/// m times the majorant every weight is at least 1 - 1/m. The relative variance over a
/// homogeneous residual of optical depth tau is e^(tau / m) - 1 for m tau lookups.
/// Measured per cloud with `nimbus bench render --compare-oversampling 1`
/// (docs/benchmarks.md): at 2, efficiency 1.13x on the hard-edged sphere, 1.02x on
/// the cumulus, 1.00x on the modeler cloud against 1.
pub const RATIO_TRACKING_OVERSAMPLING: f32 = 2.0;

/// Next event estimation casts a shadow ray with probability p / floor where the phase
/// toward the light p is below the floor, weighted by floor / p (Russian roulette), so
/// every shadow ray cast carries at least the floor's weight. The floor is the larger
/// of the isotropic phase 1 / (4 pi) and the phase's peak over this: an isotropic
/// medium, or a mildly anisotropic one (HG g below about 0.68), casts every shadow ray
/// toward directions at or above the isotropic value, while a forward-peaked one (g =
/// 0.85: a peak 82 times the isotropic value, a floor of 5.1 times it) casts few where
/// they carry little. Measured with `nimbus bench render --compare-shadow-floor 1`
/// (docs/benchmarks.md, "Shadow-ray roulette by the phase").
pub const SHADOW_ROULETTE_PEAK_FRACTION: f32 = 16.0;

/// The shadow-roulette floor for `phase` ([`SHADOW_ROULETTE_PEAK_FRACTION`]).
pub fn default_shadow_floor(phase: PhaseFunction) -> f32 {
    INV_4PI.max(phase.peak() / SHADOW_ROULETTE_PEAK_FRACTION)
}

/// Russian roulette on a ratio-tracking product below [`RATIO_TRACKING_RR_THRESHOLD`]:
/// it survives with probability 1/2 and is doubled. False when it ends.
#[inline(always)]
fn roulette_product(tr: &mut f32, rng: &mut Rng) -> bool {
    if *tr < RATIO_TRACKING_RR_THRESHOLD {
        if rng.uniform() < 0.5 {
            return false;
        }
        *tr *= 2.0;
    }
    true
}

impl Medium {
    pub fn new(grid: Arc<DensityGrid>, rho: f32, albedo: f32, phase: PhaseFunction) -> Result<Self, MediumError> {
        let cells = MajorantGrid::default_cell_voxels(&grid);
        Self::with_majorant_cells(grid, rho, albedo, phase, cells)
    }

    pub fn with_majorant_cells(
        grid: Arc<DensityGrid>,
        rho: f32,
        albedo: f32,
        phase: PhaseFunction,
        cell_voxels: u32,
    ) -> Result<Self, MediumError> {
        if !(rho.is_finite() && rho >= 0.0) {
            return Err(MediumError::BadRho(rho));
        }
        if !(0.0..=1.0).contains(&albedo) {
            return Err(MediumError::BadAlbedo(albedo));
        }
        let majorant = MajorantGrid::new(&grid, cell_voxels);
        let sigma_cap = MAX_TAU_PER_VOXEL / grid.voxel_size().min_element();
        let one_voxel = rho * grid.max_value() <= sigma_cap;
        let brick_bounds = grid.is_sparse() && grid.memory_bytes() >= BRICK_BOUNDS_MIN_BYTES;
        let blocks = HomogeneousBlocks::new(&grid, HomogeneousBlocks::cell_voxels_for(cell_voxels));
        Ok(Medium {
            grid,
            majorant,
            rho,
            albedo,
            phase,
            sigma_cap,
            one_voxel,
            brick_bounds,
            blocks,
            ratio_oversampling: RATIO_TRACKING_OVERSAMPLING,
            shadow_floor: default_shadow_floor(phase),
        })
    }

    /// The same medium tracked without a control density (every cell's minimum set to
    /// 0): plain delta and ratio tracking, the baseline `nimbus bench render
    /// --compare-control` measures against.
    pub fn without_control(mut self) -> Self {
        // The balls stay as they are: a ball's cells lie below its cell's majorant, and
        // a control of 0 bounds every density from below. Homogeneous blocks go: they
        // are a control over their stretch.
        self.majorant.min_density.fill(0.0);
        self.blocks = None;
        self
    }

    /// The same medium without homogeneous blocks: flights and shadow rays start with
    /// the local ball wherever they start. The same estimates with other random
    /// numbers; the baseline of `nimbus bench render --compare-blocks`.
    pub fn without_blocks(mut self) -> Self {
        self.blocks = None;
        self
    }

    /// The same medium whose ratio tracking samples tentative collisions at `m` times
    /// the residual majorant (clamped to at least 1; [`RATIO_TRACKING_OVERSAMPLING`]
    /// by default): the same estimates with other variance and cost, for `nimbus bench
    /// render --compare-oversampling` and the tests (1 is plain ratio tracking).
    pub fn with_ratio_oversampling(mut self, m: f32) -> Self {
        self.ratio_oversampling = if m.is_finite() { m.max(1.0) } else { 1.0 };
        self
    }

    /// The phase value below which next event estimation casts its shadow ray by
    /// Russian roulette, with probability phase / floor and weight floor / phase
    /// ([`SHADOW_ROULETTE_PEAK_FRACTION`]).
    #[inline]
    pub fn shadow_roulette_floor(&self) -> f32 {
        self.shadow_floor
    }

    /// The same medium with the shadow-roulette floor at `floor` (at least 0, where
    /// every shadow ray is cast): the same estimates with other variance and cost, for
    /// `nimbus bench render --compare-shadow-floor`.
    pub fn with_shadow_roulette_floor(mut self, floor: f32) -> Self {
        self.shadow_floor = if floor.is_finite() { floor.max(0.0) } else { default_shadow_floor(self.phase) };
        self
    }

    /// The same medium with homogeneous blocks of `cell_voxels`^3 voxels (`nimbus
    /// bench render --compare-block-cells`).
    pub fn with_block_cells(mut self, cell_voxels: u32) -> Self {
        self.blocks = HomogeneousBlocks::new(&self.grid, cell_voxels);
        self
    }

    /// The stretch [0, t] of `o + t d` inside the homogeneous block around `o`, as a
    /// segment whose majorant and control are the block's density; None outside
    /// blocks.
    #[inline(always)]
    fn block_stretch(&self, o: Vec3, d: Vec3, t_max: f32) -> Option<MajorantSegment> {
        let s = self.blocks.as_ref()?.stretch(o, d, t_max)?;
        Some(MajorantSegment { t_min: 0.0, t_max: s.t_max, max_density: s.density, min_density: s.density })
    }

    /// The homogeneous blocks, if the cloud has any.
    pub fn blocks(&self) -> Option<&HomogeneousBlocks> {
        self.blocks.as_ref()
    }

    /// The same medium tracked without local balls ([`MajorantGrid::local_ball`]):
    /// every flight and shadow ray walks the majorant cells by the DDA from its
    /// origin, or from the end of its homogeneous block's stretch (the blocks stay;
    /// [`Medium::without_blocks`] removes them). The same estimates with other random
    /// numbers; the baseline `nimbus bench render --compare-balls` measures against,
    /// and an independent estimator for the tests.
    pub fn without_local_balls(mut self) -> Self {
        self.majorant.reach.fill(0);
        self
    }

    /// The same medium whose trackers read sigma_t itself (eight voxels, trilinear) at
    /// every tentative collision: the same estimates with other variance and cost, the
    /// baseline `nimbus bench render --compare-lookups` measures against.
    pub fn with_trilinear_lookups(mut self) -> Self {
        self.one_voxel = false;
        self
    }

    /// The same medium with free flights' brick-bounds test on or off (the default
    /// follows the grid's size, [`BRICK_BOUNDS_MIN_BYTES`]): the same random numbers
    /// and the same images bit for bit, other cost; `nimbus bench render
    /// --compare-bounds` measures both. Dense grids have no bricks and ignore it.
    pub fn with_brick_bounds(mut self, on: bool) -> Self {
        self.brick_bounds = on;
        self
    }

    /// Whether free flights test brick bounds before reading a voxel.
    pub fn uses_brick_bounds(&self) -> bool {
        self.brick_bounds
    }

    pub fn grid(&self) -> &Arc<DensityGrid> {
        &self.grid
    }
    pub fn majorant(&self) -> &MajorantGrid {
        &self.majorant
    }
    pub fn rho(&self) -> f32 {
        self.rho
    }
    pub fn albedo(&self) -> f32 {
        self.albedo
    }
    pub fn phase(&self) -> PhaseFunction {
        self.phase
    }
    /// Where sigma_t can be non-zero.
    pub fn bounds(&self) -> Bounds3 {
        self.grid.support_bounds()
    }

    /// Extinction coefficient sigma_t(x) = rho * d(x), at most [`Medium::sigma_cap`].
    #[inline]
    pub fn sigma_t(&self, p: Vec3) -> f32 {
        (self.rho * self.grid.lookup(p)).min(self.sigma_cap)
    }

    /// An unbiased estimate of sigma_t(p) from one voxel: rho times the trilinear corner
    /// drawn by its weight ([`DensityGrid::lookup_stochastic`]). Every corner lies in
    /// the footprint of p's majorant cell, so the estimate lies between the cell's
    /// control density and its majorant. Where the cap could bind, sigma_t(p) itself.
    #[inline]
    pub fn sigma_t_estimate(&self, p: Vec3, rng: &mut Rng) -> f32 {
        if self.one_voxel {
            let bits = rng.next_u64();
            self.rho * self.grid.lookup_stochastic(p, bits)
        } else {
            self.sigma_t(p)
        }
    }

    /// Delta tracking's choice at a tentative collision at `p` of a residual tracked at
    /// rate `sigma_r` above the control `sigma_c` (majorant `sigma_maj`): real with
    /// probability (sigma_t - sigma_c) / sigma_r, for the one-voxel estimate of
    /// sigma_t. The same random numbers and the same answer as comparing a uniform
    /// with [`Medium::sigma_t_estimate`]; the test is monotone in the voxel's value, so
    /// with `BOUNDS` a sparse grid settles most of them from the voxel's brick bounds
    /// without reading the voxel ([`DensityGrid::stochastic_test`]).
    #[inline(always)]
    fn collision_is_real<const BOUNDS: bool>(
        &self,
        p: Vec3,
        sigma_c: f32,
        sigma_r: f32,
        sigma_maj: f32,
        rng: &mut Rng,
    ) -> bool {
        if BOUNDS && self.one_voxel {
            let bits = rng.next_u64();
            let x = rng.uniform() * sigma_r;
            debug_assert!({
                let sigma_t = self.rho * self.grid.lookup_stochastic(p, bits);
                sigma_t <= sigma_maj * (1.0 + 1e-4) + 1e-6
            });
            self.grid.stochastic_test(p, bits, |v| x < self.rho * v - sigma_c)
        } else {
            let sigma_t = self.sigma_t_estimate(p, rng);
            debug_assert!(sigma_t <= sigma_maj * (1.0 + 1e-4) + 1e-6, "majorant {sigma_maj} < sigma_t {sigma_t}");
            rng.uniform() * sigma_r < sigma_t - sigma_c
        }
    }

    /// The largest extinction the medium has: [`MAX_TAU_PER_VOXEL`] per voxel edge.
    pub fn sigma_cap(&self) -> f32 {
        self.sigma_cap
    }

    /// The largest density before rho: [`Medium::sigma_cap`] / rho (infinite for
    /// rho = 0). Every reader of the grid that integrates extinction clamps to it.
    pub fn density_cap(&self) -> f32 {
        self.sigma_cap / self.rho
    }

    /// The extinction majorant of a majorant segment, capped like sigma_t.
    #[inline]
    pub fn sigma_maj(&self, seg: &MajorantSegment) -> f32 {
        (self.rho * seg.max_density).min(self.sigma_cap)
    }

    /// The control extinction of a majorant segment: sigma_t is at least this at every
    /// point of it (capped like sigma_t, so at most [`Medium::sigma_maj`]), up to
    /// rounding: an interpolation between corners of very different values, or a DDA
    /// step that drifts a fraction of a voxel past a cell face, can read a few units in
    /// the last place below it. The trackers tolerate that (a residual a hair below 0
    /// is no collision, a ratio a hair above 1), as they tolerate the majorant's
    /// rounding above.
    #[inline]
    pub fn sigma_min(&self, seg: &MajorantSegment) -> f32 {
        (self.rho * seg.min_density).min(self.sigma_cap)
    }

    /// The tracking loop: walks the majorant segments of `o + t d` (d unit length),
    /// samples tentative collisions with the local majorant, and calls
    /// `f(t, p, sigma_t, sigma_maj, rng)` at each one, with sigma_t the one-voxel
    /// estimate of sigma_t(p) the trackers read ([`Medium::sigma_t_estimate`]; its
    /// expectation is sigma_t(p), so a caller linear in it stays unbiased). `f` returns
    /// false to stop. Returns true if the ray passed `t_max` or left the medium.
    #[inline]
    pub fn sample_t_maj<F>(&self, o: Vec3, d: Vec3, t_max: f32, rng: &mut Rng, mut f: F) -> bool
    where
        F: FnMut(f32, Vec3, f32, f32, &mut Rng) -> bool,
    {
        for seg in self.majorant.segments(o, d, 0.0, t_max) {
            let sigma_maj = self.sigma_maj(&seg);
            if sigma_maj <= 0.0 {
                continue;
            }
            let going = tentative_collisions(seg.t_min, seg.t_max, sigma_maj, rng, |t, rng| {
                let p = o + d * t;
                let sigma_t = self.sigma_t_estimate(p, rng);
                debug_assert!(sigma_t <= sigma_maj * (1.0 + 1e-4) + 1e-6, "majorant {sigma_maj} < sigma_t {sigma_t}");
                f(t, p, sigma_t, sigma_maj, rng)
            });
            if !going {
                return false;
            }
        }
        true
    }

    /// Free-flight sampling: the distance to the next real collision, distributed as
    /// sigma_t(t) T(t). Decomposition tracking (Kutz et al. 2017): in each majorant
    /// segment the medium is a homogeneous control part, sigma_c = [`Medium::sigma_min`],
    /// plus a residual; a collision with the control part is drawn in closed form
    /// (no density lookup), the residual's by delta tracking against sigma_maj -
    /// sigma_c up to it, and the first of the two is the collision. A homogeneous
    /// segment takes no lookup at all; where sigma_c = 0 this is delta tracking, with
    /// the same random numbers.
    #[inline]
    pub fn sample_free_flight(&self, o: Vec3, d: Vec3, t_max: f32, rng: &mut Rng) -> FreeFlight {
        // Two instances of the tracker, chosen once per flight: the brick-bounds test
        // inlined where it pays (big grids), and absent from the loop where it does not.
        if self.brick_bounds {
            self.free_flight::<true>(o, d, t_max, rng)
        } else {
            self.free_flight::<false>(o, d, t_max, rng)
        }
    }

    /// [`Medium::sample_free_flight`], with the brick-bounds test (`BOUNDS`) or without.
    #[inline(always)]
    fn free_flight<const BOUNDS: bool>(&self, o: Vec3, d: Vec3, t_max: f32, rng: &mut Rng) -> FreeFlight {
        // The same walk as `transmittance_ratio`'s, written out in both: shared, as a
        // closure taking the tracker or as an iterator over the stretches, it measured
        // 3 % and 9 % fewer samples per second.
        // A start in a homogeneous block tracks the block's stretch in closed form
        // first; then the local ball around where the ray stands, as one stretch of
        // its cell's majorant and control without the DDA; then the DDA for what gets
        // past the ball (the trackers are memoryless, so each part goes on from where
        // the last left off).
        let mut start = 0.0;
        if let Some(seg) = self.block_stretch(o, d, t_max) {
            if let Some(t) = self.flight_in::<BOUNDS>(o, d, &seg, rng) {
                return FreeFlight::Collision { t };
            }
            if seg.t_max >= t_max {
                return FreeFlight::Escaped;
            }
            start = seg.t_max;
        }
        if let Some(ball) = self.majorant.local_ball(o + d * start) {
            let reach = (start + ball.radius).min(t_max);
            let seg = ball.stretch(start, reach);
            if let Some(t) = self.flight_in::<BOUNDS>(o, d, &seg, rng) {
                return FreeFlight::Collision { t };
            }
            if reach >= t_max {
                return FreeFlight::Escaped;
            }
            start = reach;
        }
        for seg in self.majorant.segments(o, d, start, t_max) {
            if let Some(t) = self.flight_in::<BOUNDS>(o, d, &seg, rng) {
                return FreeFlight::Collision { t };
            }
        }
        FreeFlight::Escaped
    }

    /// Decomposition tracking over the stretch `seg` of `o + t d` (its densities lie
    /// between its bounds): the distance of the collision in it, if any.
    #[inline(always)]
    fn flight_in<const BOUNDS: bool>(&self, o: Vec3, d: Vec3, seg: &MajorantSegment, rng: &mut Rng) -> Option<f32> {
        let (t0, t1) = (seg.t_min, seg.t_max);
        let sigma_maj = self.sigma_maj(seg);
        if sigma_maj <= 0.0 {
            return None;
        }
        let sigma_c = self.sigma_min(seg);
        let t_control = if sigma_c > 0.0 { t0 + sample_exponential(rng.uniform(), sigma_c) } else { f32::INFINITY };
        let end = t1.min(t_control);
        let sigma_r = sigma_maj - sigma_c;
        if sigma_r > 0.0 {
            let mut hit = None;
            tentative_collisions(t0, end, sigma_r, rng, |t, rng| {
                let real = self.collision_is_real::<BOUNDS>(o + d * t, sigma_c, sigma_r, sigma_maj, rng);
                if real {
                    hit = Some(t);
                }
                !real
            });
            if hit.is_some() {
                return hit;
            }
        }
        (t_control < t1).then_some(t_control)
    }

    /// One step of a random walk: at a scattering vertex `x` whose path came from
    /// direction `wo` (pointing back toward the previous vertex), samples the phase
    /// function (weight p / pdf = 1) and the free flight to the next real collision.
    /// Returns the next vertex and its own `wo`, or, when the walk leaves the medium,
    /// the direction it leaves in (where the sky is seen). Shared by the path tracer,
    /// BDPT's subpaths and the point-to-point walks.
    #[inline]
    pub fn scatter(&self, x: Vec3, wo: Vec3, rng: &mut Rng) -> Result<(Vec3, Vec3), Vec3> {
        let wi = self.phase.sample(wo, rng.uniform2()).wi;
        match self.sample_free_flight(x, wi, f32::INFINITY, rng) {
            FreeFlight::Collision { t } => Ok((x + wi * t, -wi)),
            FreeFlight::Escaped => Err(wi),
        }
    }

    /// Transmittance estimate by residual ratio tracking (Novak et al. 2014): in each
    /// majorant segment the control part sigma_c = [`Medium::sigma_min`] is attenuated
    /// in closed form, exp(-sigma_c length), and the residual sigma_t - sigma_c is
    /// ratio-tracked against sigma_maj - sigma_c, its tentative collisions at
    /// [`RATIO_TRACKING_OVERSAMPLING`] times that rate; Russian roulette once the
    /// running product falls below a threshold. Unbiased; a homogeneous segment adds no
    /// variance and takes no lookup. Where sigma_c = 0 this is (oversampled) ratio
    /// tracking, with the same random numbers.
    #[inline]
    pub fn transmittance_ratio(&self, o: Vec3, d: Vec3, t_max: f32, rng: &mut Rng) -> f32 {
        let mut tr = 1.0f32;
        // The homogeneous block's stretch, the local ball and the DDA, as in
        // `free_flight` (the DDA set up only for rays that get past the ball).
        let mut start = 0.0;
        if let Some(seg) = self.block_stretch(o, d, t_max) {
            if !self.ratio_in(o, d, &seg, &mut tr, rng) {
                return 0.0;
            }
            if seg.t_max >= t_max {
                return tr;
            }
            start = seg.t_max;
        }
        if let Some(ball) = self.majorant.local_ball(o + d * start) {
            let reach = (start + ball.radius).min(t_max);
            let seg = ball.stretch(start, reach);
            if !self.ratio_in(o, d, &seg, &mut tr, rng) {
                return 0.0;
            }
            if reach >= t_max {
                return tr;
            }
            start = reach;
        }
        for seg in self.majorant.segments(o, d, start, t_max) {
            if !self.ratio_in(o, d, &seg, &mut tr, rng) {
                return 0.0;
            }
        }
        tr
    }

    /// Residual ratio tracking over the stretch `seg` of `o + t d` (its densities lie
    /// between its bounds): multiplies `tr` by its transmittance estimate; false when
    /// the product ended (0, or lost at roulette).
    #[inline(always)]
    fn ratio_in(&self, o: Vec3, d: Vec3, seg: &MajorantSegment, tr: &mut f32, rng: &mut Rng) -> bool {
        let (t0, t1) = (seg.t_min, seg.t_max);
        let sigma_maj = self.sigma_maj(seg);
        if sigma_maj <= 0.0 {
            return true;
        }
        let sigma_c = self.sigma_min(seg);
        if sigma_c > 0.0 {
            *tr *= (-sigma_c * (t1 - t0)).exp();
            // Roulette with survival tr / threshold: a product far below the
            // threshold (a long homogeneous stretch) ends here at once.
            if *tr < RATIO_TRACKING_RR_THRESHOLD {
                if rng.uniform() * RATIO_TRACKING_RR_THRESHOLD >= *tr {
                    return false;
                }
                *tr = RATIO_TRACKING_RR_THRESHOLD;
            }
        }
        let sigma_r = sigma_maj - sigma_c;
        if sigma_r <= 0.0 {
            return true;
        }
        // Oversampled (`RATIO_TRACKING_OVERSAMPLING`): every weight stays in [1 - 1/m, 1].
        let rate = sigma_r * self.ratio_oversampling;
        tentative_collisions(t0, t1, rate, rng, |t, rng| {
            let sigma_t = self.sigma_t_estimate(o + d * t, rng);
            debug_assert!(sigma_t <= sigma_maj * (1.0 + 1e-4) + 1e-6, "majorant {sigma_maj} < sigma_t {sigma_t}");
            *tr *= 1.0 - (sigma_t - sigma_c) / rate;
            roulette_product(tr, rng)
        })
    }

    /// The first collision along a ray as a weighted sample, with no binary choice
    /// between colliding and passing through: ratio tracking along the whole ray
    /// (tentative collisions at the majorant, each real density read once) gives at
    /// every tentative collision t_i the weight w_i = T^(t_i) sigma_t(t_i) / sigma_maj,
    /// with T^ the running ratio-tracking product before t_i, so that sum_i w_i f(t_i)
    /// estimates the integral of T(t) sigma_t(t) f(t) dt without bias for any f (the
    /// collision estimator). One t_i is kept, drawn with probability w_i / W by
    /// reservoir sampling, with W = sum_i w_i: W f(t) is then an unbiased estimate of the
    /// same integral that evaluates f once. Returns (the kept distance, W) or None when
    /// every weight is 0, and the transmittance estimate T^ of the whole ray, all
    /// within `t_max`. Russian roulette as in [`Medium::transmittance_ratio`] once the
    /// product falls below its threshold.
    pub fn sample_collision_weighted(&self, o: Vec3, d: Vec3, t_max: f32, rng: &mut Rng) -> (Option<(f32, f32)>, f32) {
        self.sample_collision_guided(o, d, t_max, rng, |_| 1.0)
    }

    /// [`Medium::sample_collision_weighted`] with the kept collision drawn in
    /// proportion to w_i g(x_i) for a guide g > 0 (resampled importance sampling):
    /// the returned weight is then sum_j w_j g(x_j) / g(x_i), so that it times f(x_i)
    /// is still an unbiased estimate of the integral of T sigma_t f, with less variance
    /// where g follows f. The guide is read at every tentative collision with a weight.
    pub fn sample_collision_guided(
        &self,
        o: Vec3,
        d: Vec3,
        t_max: f32,
        rng: &mut Rng,
        guide: impl Fn(Vec3) -> f32,
    ) -> (Option<(f32, f32)>, f32) {
        let mut tr = 1.0f32;
        let (mut total, mut kept) = (0.0f32, None);
        self.sample_t_maj(o, d, t_max, rng, |t, x, sigma_t, sigma_maj, rng| {
            let ratio = (sigma_t / sigma_maj).clamp(0.0, 1.0);
            let w = tr * ratio;
            if w > 0.0 {
                let g = guide(x);
                let wg = w * g;
                if wg > 0.0 && wg.is_finite() {
                    total += wg;
                    if rng.uniform() * total < wg {
                        kept = Some((t, g));
                    }
                }
            }
            tr *= 1.0 - ratio;
            if tr > 0.0 && roulette_product(&mut tr, rng) {
                return true;
            }
            tr = 0.0;
            false
        });
        (kept.map(|(t, g)| (t, total / g)), tr)
    }

    /// Transmittance estimate by delta tracking: 1 if the free flight escapes, else 0.
    #[inline]
    pub fn transmittance_delta(&self, o: Vec3, d: Vec3, t_max: f32, rng: &mut Rng) -> f32 {
        match self.sample_free_flight(o, d, t_max, rng) {
            FreeFlight::Escaped => 1.0,
            FreeFlight::Collision { .. } => 0.0,
        }
    }

    /// Deterministic optical depth tau = integral of sigma_t along `o + t d`, t in
    /// [0, t_max], by the midpoint rule with steps of at most `step` world units.
    /// Empty majorant cells are skipped. Stops early once tau exceeds `tau_stop`
    /// (pass `f32::INFINITY` for the full integral).
    pub fn optical_depth(&self, o: Vec3, d: Vec3, t_max: f32, step: f32, tau_stop: f32) -> f32 {
        debug_assert!(step > 0.0);
        let cap = self.density_cap();
        let mut tau = 0.0f64;
        for seg in self.majorant.segments(o, d, 0.0, t_max) {
            if seg.max_density <= 0.0 {
                continue;
            }
            let len = seg.t_max - seg.t_min;
            if len <= 0.0 {
                continue;
            }
            let n = (len / step).ceil().max(1.0) as u32;
            let h = len / n as f32;
            let mut sum = 0.0f32;
            for i in 0..n {
                sum += self.grid.lookup(o + d * (seg.t_min + (i as f32 + 0.5) * h)).min(cap);
            }
            tau += (sum * h * self.rho) as f64;
            if tau as f32 > tau_stop {
                break;
            }
        }
        tau as f32
    }

    /// Distance from `o` along `d` to where the ray leaves the medium's support, or
    /// 0 if it starts outside and misses.
    pub fn exit_distance(&self, o: Vec3, d: Vec3) -> f32 {
        self.bounds().intersect(o, d.recip(), 0.0, f32::INFINITY).map(|(_, t1)| t1).unwrap_or(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random_grid(n: u32, seed: u64) -> DensityGrid {
        let mut rng = Rng::new(seed, 0, 0);
        let data: Vec<f32> = (0..n * n * n).map(|_| if rng.uniform() < 0.3 { 0.0 } else { rng.uniform() }).collect();
        DensityGrid::from_bounds(UVec3::splat(n), data, Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5))).unwrap()
    }

    /// A grid of 0.5 with one voxel of a huge density (1e30, the largest finite
    /// float): tracking through it takes bounded work (at most about
    /// MAX_TAU_PER_VOXEL tentative collisions per voxel crossed, where the uncapped
    /// majorant would take ~1e30 steps, forever at float precision), the spike is
    /// opaque, and ordinary densities are untouched by the cap.
    #[test]
    fn a_huge_density_is_opaque_and_bounded() {
        let n = 16u32;
        let bounds = Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5));
        let ordinary = random_grid(n, 7);
        let m = Medium::new(Arc::new(ordinary.clone()), 40.0, 1.0, PhaseFunction::Isotropic).unwrap();
        let mut rng = Rng::new(3, 0, 0);
        for _ in 0..10_000 {
            let p = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5;
            assert_eq!(m.sigma_t(p), 40.0 * ordinary.lookup(p), "the cap changed an ordinary density at {p}");
        }
        for spike in [1e30f32, f32::MAX] {
            let mut data = vec![0.5f32; (n * n * n) as usize];
            data[(8 + n * (8 + n * 8)) as usize] = spike;
            let grid = DensityGrid::from_bounds(UVec3::splat(n), data, bounds).unwrap();
            let m = Medium::new(Arc::new(grid.clone()), 40.0, 1.0, PhaseFunction::Isotropic).unwrap();
            let centre = grid.origin() + (Vec3::splat(8.0) + 0.5) * grid.voxel_size();
            assert!(m.sigma_t(centre).is_finite() && m.sigma_t(centre) == m.sigma_cap());
            // Tentative collisions along rays through the spike, all taken as null:
            // bounded by the capped majorant times the diagonal.
            // (Stopped at the bound, so that without the cap this fails, not hangs.)
            // 32 per voxel edge, written out: the bound must not move with the cap.
            let bound = (4.0 * 32.0 * n as f32 * bounds.extent().length()) as u32;
            let mut worst = 0u32;
            for i in 0..200 {
                let mut r = Rng::new(5, i, 0);
                let d = crate::sampling::sample_uniform_sphere(r.uniform2());
                let mut count = 0u32;
                m.sample_t_maj(centre - 2.0 * d, d, f32::INFINITY, &mut r, |_, _, _, _, _| {
                    count += 1;
                    count < bound
                });
                worst = worst.max(count);
            }
            assert!(worst < bound, "spike {spike}: {worst} tentative collisions on one ray (bound {bound})");
            // Opaque: ratio-tracked transmittance along an axis through its centre.
            let mut sum = 0.0f64;
            for i in 0..2000 {
                let mut r = Rng::new(6, i, 0);
                sum += m.transmittance_ratio(centre - Vec3::X, Vec3::X, 2.0, &mut r) as f64;
            }
            assert!(sum / 2000.0 < 1e-6, "spike {spike}: transmittance {}", sum / 2000.0);
            // A free flight toward it stops at the spike at the latest.
            let mut r = Rng::new(8, 0, 0);
            for _ in 0..1000 {
                match m.sample_free_flight(centre - Vec3::X, Vec3::X, f32::INFINITY, &mut r) {
                    FreeFlight::Collision { t } => assert!(t <= 1.0 + 1.5 * grid.voxel_size().x, "{t}"),
                    FreeFlight::Escaped => panic!("a ray through the spike escaped"),
                }
            }
        }
    }

    /// max_in bounds the density at every point of its box, is 0 for a box outside
    /// the support, and for a box inside one cell is that cell's majorant.
    #[test]
    fn max_in_bounds_the_box() {
        let grid = random_grid(24, 11);
        let maj = MajorantGrid::new(&grid, 8);
        let support = grid.support_bounds();
        let mut rng = Rng::new(12, 0, 0);
        let mut rv = || Vec3::new(rng.uniform(), rng.uniform(), rng.uniform());
        for _ in 0..300 {
            let (a, b) = (support.min + rv() * support.extent(), support.min + rv() * support.extent());
            let bx = Bounds3::new(a.min(b), a.max(b));
            let m = maj.max_in(bx);
            for _ in 0..50 {
                let p = bx.min + rv() * bx.extent();
                assert!(grid.lookup(p) <= m, "density {} above max_in {m} at {p}", grid.lookup(p));
            }
        }
        let far = Bounds3::new(support.max + 1.0, support.max + 2.0);
        assert_eq!(maj.max_in(far), 0.0);
        // A point box: its own cell's majorant, which the segments report there too.
        let p = support.min + Vec3::new(0.3, 0.55, 0.7) * support.extent();
        let seg = maj.segments(p - Vec3::X * 1e-3, Vec3::X, 0.0, 2e-3).next().unwrap();
        assert_eq!(maj.max_in(Bounds3::new(p, p)), seg.max_density);
    }

    /// The majorant bounds the interpolated density everywhere, including the
    /// trilinear footprint across cell borders and the half-voxel taper outside.
    #[test]
    fn majorant_bounds_density() {
        let dense = random_grid(13, 3);
        let sparse = dense.to_sparse();
        // Sparse grids answer whole bricks from their slots.
        for (g, cells) in
            [(&dense, 1), (&dense, 2), (&dense, 4), (&dense, 5), (&sparse, 8), (&sparse, 16), (&sparse, 5)]
        {
            let m = MajorantGrid::new(g, cells);
            let mut rng = Rng::new(9, cells as u64, 0);
            for _ in 0..20_000 {
                let p = m.bounds.min + Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * m.bounds.extent();
                let c =
                    ((p - m.bounds.min) * m.inv_cell_size).floor().as_ivec3().clamp(IVec3::ZERO, m.dims.as_ivec3() - 1);
                assert!(g.lookup(p) <= m.cell(c) + 1e-6, "cells={cells} sparse={} p={p}", g.is_sparse());
            }
        }
    }

    /// The cells' minima bound the interpolated density from below everywhere in
    /// the cell (the trackers' control density must never exceed it), sparse storage
    /// gives the same minima as dense, and a smooth positive cloud has cells with a
    /// positive minimum in its interior and 0 where the footprint leaves the grid.
    #[test]
    fn minima_bound_density_from_below() {
        let unit = Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5));
        let smooth = DensityGrid::from_fn(UVec3::new(40, 33, 24), unit, |p| {
            0.5 + 0.3 * (7.0 * p.x).sin() * (5.0 * p.y).cos() + 0.2 * p.z
        })
        .unwrap();
        // Random values without zeros: every interior minimum positive and different.
        let mut rng = Rng::new(4, 0, 0);
        let dims = UVec3::new(29, 23, 19);
        let data = (0..dims.x * dims.y * dims.z).map(|_| 0.1 + rng.uniform()).collect();
        let noisy = DensityGrid::from_bounds(dims, data, unit).unwrap();
        // Blocks of 8^3 voxels of one value each (constant bricks of different values
        // in sparse storage), with a varying layer through them.
        let blocky = DensityGrid::from_fn(UVec3::splat(40), unit, |p| {
            let b = ((p + 0.5) * 5.0).floor();
            let v = 0.2 + 0.15 * (b.x + 2.0 * b.y + 3.0 * b.z).rem_euclid(5.0);
            if p.y.abs() < 0.05 { v + 0.3 * (11.0 * p.x).sin().abs() } else { v }
        })
        .unwrap();
        for dense in [random_grid(23, 4), smooth, noisy, blocky] {
            let sparse = dense.to_sparse();
            for cells in [2, 4, 8] {
                let (a, b) = (MajorantGrid::new(&dense, cells), MajorantGrid::new(&sparse, cells));
                assert_eq!(a.min_density, b.min_density, "cells {cells}");
                let positive = a.min_density.iter().filter(|m| **m > 0.0).count();
                let mut rng = Rng::new(31, cells as u64, 0);
                for _ in 0..20_000 {
                    let p = a.bounds.min + Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * a.bounds.extent();
                    let c = ((p - a.bounds.min) * a.inv_cell_size)
                        .floor()
                        .as_ivec3()
                        .clamp(IVec3::ZERO, a.dims.as_ivec3() - 1);
                    let (lo, hi) = (a.min_density[a.cell_index(c)], a.cell(c));
                    assert!(lo <= dense.lookup(p) && lo <= sparse.lookup(p), "cells {cells} at {p}: min {lo}");
                    assert!(lo <= hi);
                }
                if dense.min_in_box(UVec3::ZERO, dense.dims() - 1) > 0.0 {
                    assert!(positive > 0, "cells {cells}: no positive minimum in a positive cloud");
                    // Cells whose footprint reaches past the grid taper to zero.
                    assert_eq!(a.min_density[0], 0.0);
                    assert_eq!(*a.min_density.last().unwrap(), 0.0);
                }
            }
        }
    }

    /// Isotropic and mildly anisotropic media keep the isotropic floor; a
    /// forward-peaked one gets its peak over the fraction (5.14 times the isotropic
    /// phase at g = 0.85: a peak of (1 + g) / (1 - g)^2 = 82.2 times it, over 16).
    #[test]
    fn shadow_floor_follows_the_phase_peak() {
        assert_eq!(default_shadow_floor(PhaseFunction::Isotropic), INV_4PI);
        assert_eq!(default_shadow_floor(PhaseFunction::HenyeyGreenstein { g: 0.5 }), INV_4PI);
        let hg = PhaseFunction::HenyeyGreenstein { g: 0.85 };
        assert_eq!(default_shadow_floor(hg), hg.peak() / SHADOW_ROULETTE_PEAK_FRACTION);
        assert!((default_shadow_floor(hg) / INV_4PI - 82.2 / 16.0).abs() < 0.01, "{}", default_shadow_floor(hg));
    }

    /// Every point within a local ball has its density, and every voxel a one-voxel
    /// lookup can read there, within the ball's bounds; the balls reach beyond their
    /// own cells where the neighbours allow (a sphere's interior and the shell around
    /// it), and none is given beyond the majorant cells or in an empty cell.
    #[test]
    fn local_balls_bound_the_density_within_them() {
        let unit = Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5));
        let sphere =
            DensityGrid::from_fn(UVec3::splat(48), unit, |p| if p.length() < 0.4 { 1.0 } else { 0.0 }).unwrap();
        let blocky = DensityGrid::from_fn(UVec3::splat(40), unit, |p| {
            let b = ((p + 0.5) * 5.0).floor();
            0.2 + 0.15 * (b.x + 2.0 * b.y + 3.0 * b.z).rem_euclid(5.0)
        })
        .unwrap();
        let sparse_sphere = sphere.to_sparse();
        // Voxels (and so cells) of three different edges.
        let flat = Bounds3::new(Vec3::new(-0.5, -0.2, -0.6), Vec3::new(0.5, 0.2, 0.6));
        let stretched = DensityGrid::from_fn(UVec3::new(40, 24, 56), flat, |p| {
            if (p / Vec3::new(0.45, 0.18, 0.55)).length() < 1.0 { 0.8 } else { 0.0 }
        })
        .unwrap();
        for (name, grid) in [
            ("random", random_grid(23, 9)),
            ("sphere", sphere),
            ("sparse sphere", sparse_sphere),
            ("blocky", blocky),
            ("stretched sphere", stretched),
        ] {
            for cells in [4u32, 8] {
                let m = MajorantGrid::new(&grid, cells);
                let mut rng = Rng::new(41, cells as u64, 0);
                let (mut balls, mut wide) = (0, 0);
                for _ in 0..4000 {
                    let o = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1.2 - 0.6;
                    let Some(ball) = m.local_ball(o) else {
                        continue;
                    };
                    balls += 1;
                    assert!(ball.max_density > 0.0 && ball.min_density <= ball.max_density);
                    if ball.radius > cells as f32 * grid.voxel_size().min_element() {
                        wide += 1;
                    }
                    for _ in 0..16 {
                        let dir = crate::sampling::sample_uniform_sphere(rng.uniform2());
                        let p = o + dir * ball.radius * rng.uniform();
                        let v = grid.lookup(p);
                        let tol = 1e-6 * ball.max_density.max(1.0);
                        assert!(
                            v <= ball.max_density + tol && v >= ball.min_density - tol,
                            "{name}, cells {cells}: {v} at {p} outside [{}, {}]",
                            ball.min_density,
                            ball.max_density
                        );
                        let bits = rng.next_u64();
                        let corner = grid.lookup_stochastic(p, bits);
                        assert!(
                            corner <= ball.max_density && corner >= ball.min_density,
                            "{name}, cells {cells}: corner {corner} at {p}"
                        );
                    }
                }
                assert!(balls > 500, "{name}, cells {cells}: {balls} balls");
                if name.contains("sphere") {
                    assert!(wide > balls / 4, "{name}, cells {cells}: {wide} of {balls} balls wider than a cell");
                }
            }
        }
        // Outside the grid and in an empty corner: none.
        let m = MajorantGrid::new(&random_grid(16, 2), 4);
        assert_eq!(m.local_ball(Vec3::splat(0.9)), None);
        assert_eq!(m.local_ball(Vec3::splat(-0.6)), None);
        assert_eq!(m.local_ball(Vec3::splat(f32::NAN)), None);
        let empty = DensityGrid::from_fn(UVec3::splat(32), unit, |p| if p.x < 0.0 { 1.0 } else { 0.0 }).unwrap();
        assert_eq!(MajorantGrid::new(&empty, 4).local_ball(Vec3::new(0.4, 0.0, 0.0)), None);
        assert!(MajorantGrid::new(&empty, 4).local_ball(Vec3::new(-0.3, 0.0, 0.0)).is_some());
    }

    /// Sparse storage builds the same majorants as dense storage, bit for bit.
    #[test]
    fn sparse_majorants_equal_dense() {
        let mut rng = Rng::new(21, 0, 0);
        let dims = UVec3::new(37, 20, 29);
        let data: Vec<f32> = (0..dims.x * dims.y * dims.z)
            .map(|i| if i % 37 < 12 || rng.uniform() < 0.5 { 0.0 } else { rng.uniform() })
            .collect();
        let dense = DensityGrid::new(dims, data, Vec3::ZERO, Vec3::splat(0.1)).unwrap();
        let sparse = dense.to_sparse();
        for cells in [1, 3, 8, 13, 16] {
            let (a, b) = (MajorantGrid::new(&dense, cells), MajorantGrid::new(&sparse, cells));
            assert_eq!(a.max_density, b.max_density, "cells {cells}");
            assert_eq!(a.min_density, b.min_density, "cells {cells}");
            assert_eq!(a.reach, b.reach, "cells {cells}");
        }
    }

    /// The DDA covers [t0, t1] without gaps or overlaps and visits cells in order.
    #[test]
    fn dda_segments_tile_the_ray() {
        let g = random_grid(16, 5);
        let m = MajorantGrid::new(&g, 4);
        let mut rng = Rng::new(11, 0, 0);
        for _ in 0..2000 {
            let o = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 3.0 - 1.5;
            let d = crate::sampling::sample_uniform_sphere(rng.uniform2());
            let segs: Vec<_> = m.segments(o, d, 0.0, f32::INFINITY).collect();
            let inv = d.recip();
            match m.bounds.intersect(o, inv, 0.0, f32::INFINITY) {
                None => assert!(segs.is_empty()),
                Some((t0, t1)) => {
                    assert!(!segs.is_empty());
                    assert!((segs[0].t_min - t0).abs() < 1e-5);
                    assert!((segs.last().unwrap().t_max - t1).abs() < 1e-4, "{segs:?} {t1}");
                    for w in segs.windows(2) {
                        assert_eq!(w[0].t_max, w[1].t_min);
                    }
                    for s in &segs {
                        assert!(s.t_max >= s.t_min);
                        // Midpoint density is bounded by the segment's majorant.
                        let p = o + d * 0.5 * (s.t_min + s.t_max);
                        assert!(g.lookup(p) <= s.max_density + 1e-6);
                    }
                }
            }
            // Axis-aligned rays (zero direction components) terminate too.
            let axis = [Vec3::X, -Vec3::Y, Vec3::Z][(rng.uniform() * 3.0) as usize % 3];
            assert!(m.segments(o * 0.2, axis, 0.0, f32::INFINITY).count() <= 20);
        }
        // A subnormal component (1 / dq overflows) from a point on a cell face along
        // that axis: the ray crosses the same cells as without it, each with its own
        // bounds, not one segment of the first cell's (0 times infinity).
        for (at, d, flat, axis) in [
            (Vec3::new(0.25, 2.0, 0.5), Vec3::new(1.0, -1e-40, 0.0), Vec3::X, 1),
            (Vec3::new(0.25, 0.5, 3.0), Vec3::new(0.0, 0.6, -1e-39), Vec3::Y, 2),
        ] {
            // Exactly on the face (the case that made 0 times infinity): the float
            // nearest the face whose cell coordinate rounds to the face's.
            let mut o = m.bounds.min + at * m.cell_size;
            let face = |o: Vec3| (o - m.bounds.min)[axis] * m.inv_cell_size[axis];
            for _ in 0..64 {
                if face(o) == at[axis] {
                    break;
                }
                o[axis] = if face(o) < at[axis] { o[axis].next_up() } else { o[axis].next_down() };
            }
            assert_eq!(face(o), at[axis]);
            let segs: Vec<_> = m.segments(o, d, 0.0, f32::INFINITY).collect();
            let want: Vec<_> = m.segments(o, flat, 0.0, f32::INFINITY).collect();
            assert_eq!(segs.len(), want.len(), "{segs:?}");
            for (a, b) in segs.iter().zip(&want) {
                assert_eq!((a.max_density, a.min_density), (b.max_density, b.min_density));
                assert!(a.t_min.is_finite() && a.t_max.is_finite() && a.t_max >= a.t_min, "{a:?}");
            }
        }
    }

    #[test]
    fn rejects_bad_parameters() {
        let g = Arc::new(random_grid(4, 1));
        assert!(Medium::new(g.clone(), -1.0, 1.0, PhaseFunction::Isotropic).is_err());
        assert!(Medium::new(g.clone(), f32::NAN, 1.0, PhaseFunction::Isotropic).is_err());
        assert!(Medium::new(g.clone(), 10.0, 1.5, PhaseFunction::Isotropic).is_err());
        assert!(Medium::new(g, 10.0, 1.0, PhaseFunction::Isotropic).is_ok());
    }
}
