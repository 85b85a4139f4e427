//! Density grids: f32 values at voxel centres, trilinear interpolation, zero outside.
//!
//! A grid carries its world transform as an axis-aligned placement (`origin` = the
//! world position of the grid's minimum corner, `voxel_size` per axis), the way a
//! VDB grid carries its transform. Voxel (i, j, k) has its centre at
//! `origin + (ijk + 0.5) * voxel_size`; storage is x fastest, then y, then z.
//!
//! Voxels outside the index range read as zero (OpenVDB's background value), so the
//! interpolated density tapers linearly to zero over the half voxel on either side of
//! the bounds' faces. This keeps density continuous and preserves mass: a ray along
//! an axis through n voxels of value 1 sees an optical depth of exactly n voxel
//! lengths times rho. Departure from docs/conventions.md's "zero outside its bounds": the
//! support is the bounds grown by half a voxel (`support_bounds`), as in OpenVDB and
//! pbrt-v4's `SampledGrid`, instead of a jump to zero at the bounds.
//!
//! Storage is dense (one array over the box) or sparse (bricks of 8^3 voxels, the
//! size of an OpenVDB leaf): a table over the box's bricks points each brick at a
//! slot in a pool, slot 0 being all zeros and every brick of one constant value
//! sharing one slot, so memory follows the voxels that vary. Both answer `voxel` and
//! `lookup` with the same values bit for bit; the dense form is the special case
//! that small grids keep (one indirection fewer per lookup).

use glam::{UVec3, Vec3};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GridError {
    #[error("grid dimensions must be at least 1 in every axis, got {0}x{1}x{2}")]
    EmptyDims(u32, u32, u32),
    #[error("grid of {dims:?} needs {expected} values, got {got}")]
    LengthMismatch { dims: [u32; 3], expected: usize, got: usize },
    #[error("grid voxel size must be finite and positive in every axis, got {0:?}")]
    BadVoxelSize([f32; 3]),
    #[error("grid origin must be finite, got {0:?}")]
    BadOrigin([f32; 3]),
    #[error("grid value at voxel ({x}, {y}, {z}) is {value}: densities must be finite")]
    NonFinite { x: u32, y: u32, z: u32, value: f32 },
    #[error("grid value at voxel ({x}, {y}, {z}) is {value}: densities must not be negative")]
    Negative { x: u32, y: u32, z: u32, value: f32 },
    #[error("grid bounds must have max > min in every axis, got min {min:?} max {max:?}")]
    BadBounds { min: [f32; 3], max: [f32; 3] },
}

/// Axis-aligned world box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds3 {
    pub min: Vec3,
    pub max: Vec3,
}

impl Bounds3 {
    pub fn new(min: Vec3, max: Vec3) -> Self {
        Bounds3 { min, max }
    }

    pub fn extent(&self) -> Vec3 {
        self.max - self.min
    }

    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }

    /// Whether `p` lies in the box (faces included).
    pub fn contains(&self, p: Vec3) -> bool {
        p.cmpge(self.min).all() && p.cmple(self.max).all()
    }

    /// Slab test: the parametric interval of the ray o + t d inside the box, clipped to
    /// [t_min, t_max]; None if it misses. `inv_d` is 1 / d per component.
    #[inline]
    pub fn intersect(&self, o: Vec3, inv_d: Vec3, t_min: f32, t_max: f32) -> Option<(f32, f32)> {
        let t0 = (self.min - o) * inv_d;
        let t1 = (self.max - o) * inv_d;
        let tnear = t0.min(t1);
        let tfar = t0.max(t1);
        // NaN (0 * inf when o lies on a slab plane) loses in max/min against finite values.
        let enter = tnear.max_element().max(t_min);
        let exit = tfar.min_element().min(t_max);
        (enter <= exit).then_some((enter, exit))
    }
}

/// Edge of a sparse grid's brick, in voxels.
pub const BRICK: u32 = 8;
const BRICK_LOG2: u32 = 3;
const BRICK_VOXELS: usize = (BRICK * BRICK * BRICK) as usize;

/// Bricks of a sparse grid: `table` (x fastest over `bdims`) holds a slot per brick,
/// `pool` the slots' values (slot * 512 + x + 8 y + 64 z within the brick).
#[derive(Clone, Debug)]
struct Bricks {
    bdims: UVec3,
    table: Vec<u32>,
    pool: Vec<f32>,
    /// The smallest and largest value of each slot (over the voxels inside the grid),
    /// side by side so that one read gives both.
    slot_range: Vec<[f32; 2]>,
    /// Slots whose values are all equal (0 is the zero brick).
    constant: Vec<bool>,
}

impl Bricks {
    /// The slot of brick `b` (brick coordinates).
    #[inline(always)]
    fn brick_slot(&self, b: UVec3) -> usize {
        self.table[(b.x + self.bdims.x * (b.y + self.bdims.y * b.z)) as usize] as usize
    }

    /// The slot of the brick holding voxel (x, y, z).
    #[inline(always)]
    fn slot_of(&self, x: u32, y: u32, z: u32) -> usize {
        self.brick_slot(UVec3::new(x >> BRICK_LOG2, y >> BRICK_LOG2, z >> BRICK_LOG2))
    }

    /// `pick` folded from `init` over the values of `slot` in the box `a ..= c` (voxel
    /// indices within the brick).
    fn fold_slot(&self, slot: usize, a: UVec3, c: UVec3, init: f32, pick: fn(f32, f32) -> f32) -> f32 {
        let base = slot * BRICK_VOXELS;
        let mut m = init;
        for z in a.z..=c.z {
            for y in a.y..=c.y {
                for x in a.x..=c.x {
                    m = pick(m, self.pool[base + (x + BRICK * (y + BRICK * z)) as usize]);
                }
            }
        }
        m
    }

    #[inline(always)]
    fn voxel(&self, x: u32, y: u32, z: u32) -> f32 {
        let m = BRICK - 1;
        self.pool[self.slot_of(x, y, z) * BRICK_VOXELS + ((x & m) + BRICK * ((y & m) + BRICK * (z & m))) as usize]
    }
}

#[derive(Clone, Debug)]
enum Storage {
    Dense(Vec<f32>),
    Sparse(Bricks),
}

/// A validated density grid.
#[derive(Clone, Debug)]
pub struct DensityGrid {
    dims: UVec3,
    storage: Storage,
    origin: Vec3,
    voxel_size: Vec3,
    inv_voxel_size: Vec3,
    max_value: f32,
}

impl DensityGrid {
    /// Builds a grid from values (x fastest), rejecting NaN, infinity and negative
    /// values with the first bad voxel named.
    pub fn new(dims: UVec3, data: Vec<f32>, origin: Vec3, voxel_size: Vec3) -> Result<Self, GridError> {
        Self::check_placement(dims, origin, voxel_size)?;
        let expected = dims.x as usize * dims.y as usize * dims.z as usize;
        if data.len() != expected {
            return Err(GridError::LengthMismatch { dims: dims.to_array(), expected, got: data.len() });
        }
        let mut max_value = 0.0f32;
        for (i, &v) in data.iter().enumerate() {
            if !(v >= 0.0 && v.is_finite()) {
                let (x, y, z) = unflatten(i, dims);
                check_value(x, y, z, v)?;
            }
            max_value = max_value.max(v);
        }
        Ok(DensityGrid {
            dims,
            storage: Storage::Dense(data),
            origin,
            voxel_size,
            inv_voxel_size: voxel_size.recip(),
            max_value,
        })
    }

    fn check_placement(dims: UVec3, origin: Vec3, voxel_size: Vec3) -> Result<(), GridError> {
        if dims.min_element() == 0 {
            return Err(GridError::EmptyDims(dims.x, dims.y, dims.z));
        }
        if !voxel_size.is_finite() || voxel_size.min_element() <= 0.0 {
            return Err(GridError::BadVoxelSize(voxel_size.to_array()));
        }
        if !origin.is_finite() {
            return Err(GridError::BadOrigin(origin.to_array()));
        }
        Ok(())
    }

    /// Bounds that are finite with max > min, for `dims` of at least one voxel per
    /// axis; returns the voxel size that tiles them.
    fn check_bounds(dims: UVec3, bounds: Bounds3) -> Result<Vec3, GridError> {
        if !(bounds.min.is_finite() && bounds.max.is_finite()) || bounds.extent().min_element() <= 0.0 {
            return Err(GridError::BadBounds { min: bounds.min.to_array(), max: bounds.max.to_array() });
        }
        if dims.min_element() == 0 {
            return Err(GridError::EmptyDims(dims.x, dims.y, dims.z));
        }
        Ok(bounds.extent() / dims.as_vec3())
    }

    /// Samples `f(world position of the voxel centre)` brick by brick into a sparse
    /// grid over `bounds`, never holding the dense box. `may_be_nonzero(brick box)`
    /// is a conservative test: a brick it rejects is stored as zeros without calling
    /// `f`. Bricks are evaluated in parallel and stored in table order, so the result
    /// does not depend on the thread count.
    pub fn from_fn_sparse(
        dims: UVec3,
        bounds: Bounds3,
        may_be_nonzero: impl Fn(Bounds3) -> bool + Sync,
        f: impl Fn(Vec3) -> f32 + Sync,
    ) -> Result<Self, GridError> {
        use rayon::prelude::*;
        let vs = Self::check_bounds(dims, bounds)?;
        let mut builder = SparseBuilder::new(dims, bounds.min, vs)?;
        let bd = builder.bricks.bdims;
        let brick_box = |b: UVec3| {
            let lo = b * BRICK;
            let hi = (lo + BRICK).min(dims);
            (lo, hi, Bounds3::new(bounds.min + lo.as_vec3() * vs, bounds.min + hi.as_vec3() * vs))
        };
        // The bricks the test accepts bound the slots needed: reserving them up front
        // keeps the pool from being reallocated (and copied) as it grows.
        let accepted: Vec<bool> = (0..bd.x * bd.y * bd.z)
            .into_par_iter()
            .map(|i| may_be_nonzero(brick_box(UVec3::new(i % bd.x, (i / bd.x) % bd.y, i / (bd.x * bd.y))).2))
            .collect();
        builder.reserve_slots(accepted.iter().filter(|&&a| a).count() + 1);
        // One z layer of bricks at a time bounds the memory held outside the pool.
        for bz in 0..bd.z {
            let layer: Vec<Option<Vec<f32>>> = (0..bd.x * bd.y)
                .into_par_iter()
                .map(|i| {
                    let (bx, by) = (i % bd.x, i / bd.x);
                    let (lo, hi, _) = brick_box(UVec3::new(bx, by, bz));
                    if !accepted[(i + bd.x * bd.y * bz) as usize] {
                        return None;
                    }
                    let mut v = vec![0.0f32; BRICK_VOXELS];
                    for z in lo.z..hi.z {
                        for y in lo.y..hi.y {
                            for x in lo.x..hi.x {
                                let p = bounds.min + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * vs;
                                v[((x - lo.x) + BRICK * ((y - lo.y) + BRICK * (z - lo.z))) as usize] = f(p);
                            }
                        }
                    }
                    Some(v)
                })
                .collect();
            for (i, v) in layer.into_iter().enumerate() {
                if let Some(v) = v {
                    builder.set_brick(UVec3::new(i as u32 % bd.x, i as u32 / bd.x, bz), &v)?;
                }
            }
        }
        builder.finish()
    }

    /// The same values in sparse storage (bricks of [`BRICK`]^3).
    pub fn to_sparse(&self) -> DensityGrid {
        if self.is_sparse() {
            return self.clone();
        }
        let mut builder = SparseBuilder::new(self.dims, self.origin, self.voxel_size).expect("validated placement");
        let bd = builder.bricks.bdims;
        let mut v = vec![0.0f32; BRICK_VOXELS];
        for bz in 0..bd.z {
            for by in 0..bd.y {
                for bx in 0..bd.x {
                    let lo = UVec3::new(bx, by, bz) * BRICK;
                    v.fill(0.0);
                    for z in lo.z..(lo.z + BRICK).min(self.dims.z) {
                        for y in lo.y..(lo.y + BRICK).min(self.dims.y) {
                            for x in lo.x..(lo.x + BRICK).min(self.dims.x) {
                                v[((x - lo.x) + BRICK * ((y - lo.y) + BRICK * (z - lo.z))) as usize] =
                                    self.voxel(x, y, z);
                            }
                        }
                    }
                    builder.set_brick(UVec3::new(bx, by, bz), &v).expect("validated values");
                }
            }
        }
        builder.finish().expect("validated values")
    }

    /// The same values placed elsewhere: `origin` its minimum corner, `voxel_size`
    /// per axis.
    pub fn placed(mut self, origin: Vec3, voxel_size: Vec3) -> Result<Self, GridError> {
        Self::check_placement(self.dims, origin, voxel_size)?;
        self.origin = origin;
        self.voxel_size = voxel_size;
        self.inv_voxel_size = voxel_size.recip();
        Ok(self)
    }

    /// Whether the grid stores bricks.
    pub fn is_sparse(&self) -> bool {
        matches!(self.storage, Storage::Sparse(_))
    }

    /// Every voxel value, x fastest (allocates the dense box for a sparse grid).
    pub fn to_dense_vec(&self) -> Vec<f32> {
        match &self.storage {
            Storage::Dense(d) => d.clone(),
            Storage::Sparse(_) => {
                let n = self.dims;
                let mut out = Vec::with_capacity(n.x as usize * n.y as usize * n.z as usize);
                for z in 0..n.z {
                    for y in 0..n.y {
                        for x in 0..n.x {
                            out.push(self.voxel(x, y, z));
                        }
                    }
                }
                out
            }
        }
    }

    /// Bricks per axis ([`BRICK`]^3 voxels each, the last ones cut by the bounds).
    pub fn brick_dims(&self) -> UVec3 {
        (self.dims + BRICK - 1) / BRICK
    }

    /// Whether every voxel of brick `b` is zero (answered from the table for a
    /// sparse grid, by reading the voxels for a dense one).
    pub fn brick_is_zero(&self, b: UVec3) -> bool {
        match &self.storage {
            Storage::Sparse(br) => br.brick_slot(b) == 0,
            Storage::Dense(_) => self.brick_max(b) == 0.0,
        }
    }

    /// The largest voxel value in brick `b`.
    pub fn brick_max(&self, b: UVec3) -> f32 {
        match &self.storage {
            Storage::Sparse(br) => br.slot_range[br.brick_slot(b)][1],
            Storage::Dense(_) => self.max_in_box(b * BRICK, b * BRICK + (BRICK - 1)),
        }
    }

    /// The bounds of the density over cells of `b`^3 voxels covering the grid's support:
    /// the cells' dims, and per cell (x fastest) the largest and the smallest density its
    /// region takes, the one-voxel trilinear footprint included (pbrt-v4
    /// `SampledGrid::MaxValue` widens the same way). The smallest is 0 for a cell whose
    /// footprint reaches past the grid, where the density tapers to zero.
    pub(crate) fn cell_bounds(&self, b: u32) -> (UVec3, Vec<f32>, Vec<f32>) {
        use rayon::prelude::*;
        let n = self.dims;
        // Support spans n + 1 voxels in index space u' in [-0.5, n + 0.5].
        let dims = (n + 1 + UVec3::splat(b - 1)) / b;
        // Cell c spans u' in [-0.5 + c b, -0.5 + (c + 1) b]; the density there depends
        // on voxels floor(u' - 0.5) .. floor(u' - 0.5) + 1, i.e. c b - 1 ..= (c + 1) b:
        // the exact maximum over them, dense or sparse.
        let lo = |c: u32| (c as i64 * b as i64 - 1).max(0) as u32;
        let hi = |c: u32, nn: u32| (((c + 1) * b) as i64).min(nn as i64 - 1) as u32;
        // A footprint that reaches below voxel 0 or above voxel n - 1 interpolates
        // toward the zero outside the grid.
        let within = |c: u32, nn: u32| c * b >= 1 && (c + 1) * b < nn;
        let (max_density, min_density): (Vec<f32>, Vec<f32>) = (0..dims.x * dims.y * dims.z)
            .into_par_iter()
            .map(|i| {
                let (cx, cy, cz) = (i % dims.x, (i / dims.x) % dims.y, i / (dims.x * dims.y));
                let (l, h) = (UVec3::new(lo(cx), lo(cy), lo(cz)), UVec3::new(hi(cx, n.x), hi(cy, n.y), hi(cz, n.z)));
                let inside = within(cx, n.x) && within(cy, n.y) && within(cz, n.z);
                let max = self.max_in_box(l, h);
                (max, if inside && max > 0.0 { self.min_in_box(l, h) } else { 0.0 })
            })
            .unzip();
        (dims, max_density, min_density)
    }

    /// The largest voxel value in the box `lo ..= hi` (grid voxel indices, inside the
    /// grid). A sparse grid answers whole zero, constant and fully covered bricks from
    /// their slots and reads only the voxels of partly covered ones.
    pub fn max_in_box(&self, lo: UVec3, hi: UVec3) -> f32 {
        let hi = hi.min(self.dims - 1);
        if lo.cmpgt(hi).any() {
            return 0.0;
        }
        let Storage::Sparse(br) = &self.storage else {
            return self.fold_voxels(lo, hi, 0.0, f32::max);
        };
        let (b0, b1) = (lo / BRICK, hi / BRICK);
        let mut m = 0.0f32;
        for bz in b0.z..=b1.z {
            for by in b0.y..=b1.y {
                for bx in b0.x..=b1.x {
                    let b = UVec3::new(bx, by, bz);
                    let slot = br.brick_slot(b);
                    let smax = br.slot_range[slot][1];
                    if smax <= m {
                        continue;
                    }
                    let (blo, bhi) = (b * BRICK, b * BRICK + (BRICK - 1));
                    if br.constant[slot] || (lo.cmple(blo).all() && hi.cmpge(bhi).all()) {
                        m = smax;
                        continue;
                    }
                    m = br.fold_slot(slot, lo.max(blo) - blo, hi.min(bhi) - blo, m, f32::max);
                }
            }
        }
        m
    }

    /// The smallest voxel value in the box `lo ..= hi` (grid voxel indices, inside
    /// the grid). A sparse grid answers constant bricks (zero ones among them) from
    /// their slots and reads the voxels of varying ones; it stops at 0.
    pub fn min_in_box(&self, lo: UVec3, hi: UVec3) -> f32 {
        let hi = hi.min(self.dims - 1);
        if lo.cmpgt(hi).any() {
            return 0.0;
        }
        let Storage::Sparse(br) = &self.storage else {
            return self.fold_voxels(lo, hi, f32::INFINITY, f32::min);
        };
        let mut m = f32::INFINITY;
        let (b0, b1) = (lo / BRICK, hi / BRICK);
        for bz in b0.z..=b1.z {
            for by in b0.y..=b1.y {
                for bx in b0.x..=b1.x {
                    if m == 0.0 {
                        return 0.0;
                    }
                    let b = UVec3::new(bx, by, bz);
                    let slot = br.brick_slot(b);
                    if br.constant[slot] {
                        m = m.min(br.slot_range[slot][0]);
                        continue;
                    }
                    let blo = b * BRICK;
                    m = br.fold_slot(slot, lo.max(blo) - blo, hi.min(blo + (BRICK - 1)) - blo, m, f32::min);
                }
            }
        }
        m
    }

    /// `pick` (max or min) folded over the voxels of the box `lo ..= hi` from `init`,
    /// voxel by voxel.
    fn fold_voxels(&self, lo: UVec3, hi: UVec3, init: f32, pick: fn(f32, f32) -> f32) -> f32 {
        let mut m = init;
        for z in lo.z..=hi.z {
            for y in lo.y..=hi.y {
                for x in lo.x..=hi.x {
                    m = pick(m, self.voxel(x, y, z));
                }
            }
        }
        m
    }

    /// Bricks that are not all zero in a sparse grid's table (every brick of a dense
    /// grid).
    pub fn stored_bricks(&self) -> usize {
        match &self.storage {
            Storage::Sparse(br) => br.table.iter().filter(|&&s| s != 0).count(),
            Storage::Dense(_) => {
                let b = self.brick_dims();
                (b.x * b.y * b.z) as usize
            }
        }
    }

    /// Builds a grid whose voxels exactly tile `bounds`.
    pub fn from_bounds(dims: UVec3, data: Vec<f32>, bounds: Bounds3) -> Result<Self, GridError> {
        let voxel_size = Self::check_bounds(dims, bounds)?;
        Self::new(dims, data, bounds.min, voxel_size)
    }

    /// Samples `f(world position of the voxel centre)` on every voxel of `bounds`.
    pub fn from_fn(dims: UVec3, bounds: Bounds3, f: impl Fn(Vec3) -> f32 + Sync) -> Result<Self, GridError> {
        use rayon::prelude::*;
        let vs = bounds.extent() / dims.as_vec3();
        let n = dims.x as usize * dims.y as usize * dims.z as usize;
        let data: Vec<f32> = (0..n)
            .into_par_iter()
            .map(|i| {
                let (x, y, z) = unflatten(i, dims);
                f(bounds.min + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * vs)
            })
            .collect();
        Self::from_bounds(dims, data, bounds)
    }

    pub fn dims(&self) -> UVec3 {
        self.dims
    }
    pub fn origin(&self) -> Vec3 {
        self.origin
    }
    pub fn voxel_size(&self) -> Vec3 {
        self.voxel_size
    }
    /// The largest voxel value.
    pub fn max_value(&self) -> f32 {
        self.max_value
    }

    /// The box tiled by the voxels.
    pub fn bounds(&self) -> Bounds3 {
        Bounds3::new(self.origin, self.origin + self.dims.as_vec3() * self.voxel_size)
    }

    /// Where the interpolated density can be non-zero: bounds grown by half a voxel.
    pub fn support_bounds(&self) -> Bounds3 {
        let b = self.bounds();
        Bounds3::new(b.min - 0.5 * self.voxel_size, b.max + 0.5 * self.voxel_size)
    }

    #[inline]
    pub fn voxel(&self, x: u32, y: u32, z: u32) -> f32 {
        match &self.storage {
            Storage::Dense(d) => {
                d[(x as usize) + self.dims.x as usize * (y as usize + self.dims.y as usize * z as usize)]
            }
            Storage::Sparse(b) => b.voxel(x, y, z),
        }
    }

    /// Voxel value with zero outside the index range.
    #[inline]
    fn voxel_or_zero(&self, x: i32, y: i32, z: i32) -> f32 {
        if x < 0 || y < 0 || z < 0 || x >= self.dims.x as i32 || y >= self.dims.y as i32 || z >= self.dims.z as i32 {
            0.0
        } else {
            self.voxel(x as u32, y as u32, z as u32)
        }
    }

    /// World position to continuous voxel coordinates in which voxel centres sit at
    /// integers.
    #[inline]
    pub fn world_to_index(&self, p: Vec3) -> Vec3 {
        (p - self.origin) * self.inv_voxel_size - 0.5
    }

    /// The lower corner of the trilinear stencil at world position `p` and the
    /// fractional offsets from it; None for far-away points (and NaN), which are
    /// outside anyway, so that the i32 casts stay exact.
    #[inline(always)]
    fn stencil(&self, p: Vec3) -> Option<(i32, i32, i32, Vec3)> {
        let u = self.world_to_index(p);
        if !(u.abs().max_element() < 1.0e9) {
            return None;
        }
        let (x, y, z) = (floor_i32(u.x), floor_i32(u.y), floor_i32(u.z));
        Some((x, y, z, u - Vec3::new(x as f32, y as f32, z as f32)))
    }

    /// Trilinearly interpolated density at world position `p`.
    #[inline]
    pub fn lookup(&self, p: Vec3) -> f32 {
        let Some((x, y, z, f)) = self.stencil(p) else { return 0.0 };
        let (nx, ny, nz) = (self.dims.x as i32, self.dims.y as i32, self.dims.z as i32);
        let (c000, c100, c010, c110, c001, c101, c011, c111);
        let inside = x >= 0 && y >= 0 && z >= 0 && x + 1 < nx && y + 1 < ny && z + 1 < nz;
        // Fast path: all eight corners inside (and, sparse, inside one brick).
        let fast = match &self.storage {
            Storage::Dense(d) if inside => {
                let sy = nx as usize;
                let sz = (nx * ny) as usize;
                Some((d.as_slice(), x as usize + sy * y as usize + sz * z as usize, sy, sz))
            }
            Storage::Sparse(b)
                if inside && {
                    let m = BRICK as i32 - 1;
                    (x & m) < m && (y & m) < m && (z & m) < m
                } =>
            {
                let m = BRICK - 1;
                let (xu, yu, zu) = (x as u32, y as u32, z as u32);
                let local = (xu & m) + BRICK * ((yu & m) + BRICK * (zu & m));
                let slot = b.slot_of(xu, yu, zu);
                if b.constant[slot] {
                    // Eight equal corners: the interpolation returns that value
                    // exactly (c + f (c - c) = c), so it is skipped.
                    return b.slot_range[slot][1];
                }
                Some((
                    b.pool.as_slice(),
                    slot * BRICK_VOXELS + local as usize,
                    BRICK as usize,
                    (BRICK * BRICK) as usize,
                ))
            }
            _ => None,
        };
        if let Some((d, i, sy, sz)) = fast {
            let sx = 1usize;
            c000 = d[i];
            c100 = d[i + sx];
            c010 = d[i + sy];
            c110 = d[i + sy + sx];
            c001 = d[i + sz];
            c101 = d[i + sz + sx];
            c011 = d[i + sz + sy];
            c111 = d[i + sz + sy + sx];
        } else if let (Storage::Sparse(b), true) = (&self.storage, inside) {
            // Inside, across brick faces: the (up to eight) bricks' slots, then the
            // corners within them.
            let m = BRICK - 1;
            let (xu, yu, zu) = (x as u32, y as u32, z as u32);
            let bd = b.bdims;
            let (bx0, bx1) = (xu >> BRICK_LOG2, (xu + 1) >> BRICK_LOG2);
            let (by0, by1) = ((yu >> BRICK_LOG2) * bd.x, ((yu + 1) >> BRICK_LOG2) * bd.x);
            let (bz0, bz1) = ((zu >> BRICK_LOG2) * bd.x * bd.y, ((zu + 1) >> BRICK_LOG2) * bd.x * bd.y);
            let (lx0, lx1) = (xu & m, (xu + 1) & m);
            let (ly0, ly1) = ((yu & m) * BRICK, ((yu + 1) & m) * BRICK);
            let (lz0, lz1) = ((zu & m) * BRICK * BRICK, ((zu + 1) & m) * BRICK * BRICK);
            let at = |bx: u32, by: u32, bz: u32, l: u32| {
                b.pool[b.table[(bx + by + bz) as usize] as usize * BRICK_VOXELS + l as usize]
            };
            c000 = at(bx0, by0, bz0, lx0 + ly0 + lz0);
            c100 = at(bx1, by0, bz0, lx1 + ly0 + lz0);
            c010 = at(bx0, by1, bz0, lx0 + ly1 + lz0);
            c110 = at(bx1, by1, bz0, lx1 + ly1 + lz0);
            c001 = at(bx0, by0, bz1, lx0 + ly0 + lz1);
            c101 = at(bx1, by0, bz1, lx1 + ly0 + lz1);
            c011 = at(bx0, by1, bz1, lx0 + ly1 + lz1);
            c111 = at(bx1, by1, bz1, lx1 + ly1 + lz1);
        } else {
            if x < -1 || y < -1 || z < -1 || x >= nx || y >= ny || z >= nz {
                return 0.0;
            }
            c000 = self.voxel_or_zero(x, y, z);
            c100 = self.voxel_or_zero(x + 1, y, z);
            c010 = self.voxel_or_zero(x, y + 1, z);
            c110 = self.voxel_or_zero(x + 1, y + 1, z);
            c001 = self.voxel_or_zero(x, y, z + 1);
            c101 = self.voxel_or_zero(x + 1, y, z + 1);
            c011 = self.voxel_or_zero(x, y + 1, z + 1);
            c111 = self.voxel_or_zero(x + 1, y + 1, z + 1);
        }
        let c00 = c000 + f.x * (c100 - c000);
        let c10 = c010 + f.x * (c110 - c010);
        let c01 = c001 + f.x * (c101 - c001);
        let c11 = c011 + f.x * (c111 - c011);
        let c0 = c00 + f.y * (c10 - c00);
        let c1 = c01 + f.y * (c11 - c01);
        c0 + f.z * (c1 - c0)
    }

    /// One corner of the trilinear stencil at `p`, drawn with probability equal to its
    /// trilinear weight: `bits` holds three 21-bit uniforms, one per axis, each choosing
    /// the upper corner with probability the fractional coordinate (to 2^-21). The
    /// value's expectation over `bits` is [`DensityGrid::lookup`], at the cost of one
    /// voxel's read in place of eight (stochastic trilinear filtering). Corners outside
    /// the grid read 0, as in `lookup`.
    #[inline]
    pub fn lookup_stochastic(&self, p: Vec3, bits: u64) -> f32 {
        let Some((x, y, z)) = self.drawn_corner(p, bits) else { return 0.0 };
        self.voxel_or_zero(x, y, z)
    }

    /// The corner [`DensityGrid::lookup_stochastic`] reads, in voxel indices that may
    /// lie outside the grid (where it reads 0): `bits` holds three 21-bit uniforms, one
    /// per axis, each choosing the upper corner with probability the fractional
    /// coordinate. None for far-away points.
    #[inline(always)]
    fn drawn_corner(&self, p: Vec3, bits: u64) -> Option<(i32, i32, i32)> {
        let (x, y, z, f) = self.stencil(p)?;
        const SCALE: f32 = 1.0 / (1u32 << 21) as f32;
        let upper = |r: u64, f: f32| ((r & 0x1F_FFFF) as f32 * SCALE < f) as i32;
        Some((x + upper(bits, f.x), y + upper(bits >> 21, f.y), z + upper(bits >> 42, f.z)))
    }

    /// `pred(v)` for the value v that [`DensityGrid::lookup_stochastic`] reads with the
    /// same `p` and `bits`, where `pred` is monotone (false up to some value, true
    /// above it). A sparse grid first asks it of the drawn voxel's brick bounds and
    /// reads the voxel only where they disagree: in a big pool that read is a miss to
    /// memory, and a tracker's acceptance test, which is such a predicate, is mostly
    /// settled by the bounds. The answer is `pred(lookup_stochastic(p, bits))`'s.
    #[inline(always)]
    pub fn stochastic_test(&self, p: Vec3, bits: u64, pred: impl Fn(f32) -> bool) -> bool {
        let Some((x, y, z)) = self.drawn_corner(p, bits) else { return pred(0.0) };
        let Storage::Sparse(b) = &self.storage else { return pred(self.voxel_or_zero(x, y, z)) };
        if x < 0 || y < 0 || z < 0 || x >= self.dims.x as i32 || y >= self.dims.y as i32 || z >= self.dims.z as i32 {
            return pred(0.0);
        }
        let c = UVec3::new(x as u32, y as u32, z as u32);
        let slot = b.slot_of(c.x, c.y, c.z);
        let [lo, hi] = b.slot_range[slot];
        // One branch, taken the same way whenever the bounds agree.
        let (at_lo, at_hi) = (pred(lo), pred(hi));
        if at_lo == at_hi {
            return at_lo;
        }
        let m = BRICK - 1;
        pred(b.pool[slot * BRICK_VOXELS + ((c.x & m) + BRICK * ((c.y & m) + BRICK * (c.z & m))) as usize])
    }

    /// The largest value on the grid's outer layer of voxels: 0 means the cloud does not
    /// touch its box (nothing is cut off at the bounds).
    pub fn max_on_boundary(&self) -> f32 {
        let n = self.dims;
        let mut m = 0.0f32;
        for z in 0..n.z {
            for y in 0..n.y {
                let on_yz = z == 0 || z == n.z - 1 || y == 0 || y == n.y - 1;
                if on_yz {
                    (0..n.x).for_each(|x| m = m.max(self.voxel(x, y, z)));
                } else {
                    m = m.max(self.voxel(0, y, z)).max(self.voxel(n.x - 1, y, z));
                }
            }
        }
        m
    }

    /// Memory held by the voxel values (and a sparse grid's table), in bytes.
    pub fn memory_bytes(&self) -> usize {
        match &self.storage {
            Storage::Dense(d) => d.len() * std::mem::size_of::<f32>(),
            Storage::Sparse(b) => {
                (b.table.len() + b.pool.len() + 2 * b.slot_range.len()) * std::mem::size_of::<f32>() + b.constant.len()
            }
        }
    }
}

/// Fills a sparse grid brick by brick or voxel by voxel, without the dense box: bricks
/// start as zeros, and a brick gets a slot of its own on the first write that makes
/// it vary. Values are checked as they arrive (finite, >= 0).
pub struct SparseBuilder {
    dims: UVec3,
    origin: Vec3,
    voxel_size: Vec3,
    bricks: Bricks,
    /// Slot of each constant value seen so far (by its bits).
    constants: std::collections::HashMap<u32, u32>,
}

impl SparseBuilder {
    pub fn new(dims: UVec3, origin: Vec3, voxel_size: Vec3) -> Result<Self, GridError> {
        DensityGrid::check_placement(dims, origin, voxel_size)?;
        let bdims = (dims + BRICK - 1) / BRICK;
        let bricks = Bricks {
            bdims,
            table: vec![0; bdims.x as usize * bdims.y as usize * bdims.z as usize],
            pool: vec![0.0; BRICK_VOXELS],
            slot_range: vec![[0.0, 0.0]],
            constant: vec![true],
        };
        let mut constants = std::collections::HashMap::new();
        constants.insert(0.0f32.to_bits(), 0);
        Ok(SparseBuilder { dims, origin, voxel_size, bricks, constants })
    }

    pub fn dims(&self) -> UVec3 {
        self.dims
    }

    fn constant_slot(&mut self, v: f32) -> u32 {
        // -0.0 and 0.0 are one value for a density.
        let v = if v == 0.0 { 0.0 } else { v };
        if let Some(&s) = self.constants.get(&v.to_bits()) {
            return s;
        }
        let s = self.bricks.slot_range.len() as u32;
        self.reserve_slot();
        self.bricks.pool.extend(std::iter::repeat_n(v, BRICK_VOXELS));
        self.bricks.slot_range.push([v, v]);
        self.bricks.constant.push(true);
        self.constants.insert(v.to_bits(), s);
        s
    }

    /// Reserves room for `slots` more slots in one allocation advised for huge pages
    /// (address space only: pages are touched as slots are filled). Where the system
    /// refuses that much address space, as much as it grants.
    pub fn reserve_slots(&mut self, slots: usize) {
        let mut want = slots.saturating_mul(BRICK_VOXELS);
        let pool = &mut self.bricks.pool;
        while want > BRICK_VOXELS && pool.try_reserve_exact(want).is_err() {
            want /= 2;
        }
        advise_huge_pages(pool);
    }

    /// Room for one more slot in the pool; when the pool grows, the new allocation is
    /// advised for huge pages before its new pages are touched.
    fn reserve_slot(&mut self) {
        let pool = &mut self.bricks.pool;
        if pool.capacity() - pool.len() < BRICK_VOXELS {
            pool.reserve(BRICK_VOXELS.max(pool.len() / 2));
            advise_huge_pages(pool);
        }
    }

    #[inline]
    fn brick_index(&self, b: UVec3) -> usize {
        let d = self.bricks.bdims;
        (b.x + d.x * (b.y + d.y * b.z)) as usize
    }

    /// Sets brick `b` from its 512 values (x fastest within the brick; values beyond
    /// the grid's bounds are ignored and read as zero).
    pub fn set_brick(&mut self, b: UVec3, values: &[f32]) -> Result<(), GridError> {
        assert_eq!(values.len(), BRICK_VOXELS);
        let lo = b * BRICK;
        let hi = (lo + BRICK).min(self.dims);
        let mut first = None;
        let mut uniform = true;
        let mut m = 0.0f32;
        let mut least = f32::INFINITY;
        let mut clean = [0.0f32; BRICK_VOXELS];
        for z in lo.z..hi.z {
            for y in lo.y..hi.y {
                for x in lo.x..hi.x {
                    let i = ((x - lo.x) + BRICK * ((y - lo.y) + BRICK * (z - lo.z))) as usize;
                    let v = values[i];
                    check_value(x, y, z, v)?;
                    clean[i] = v;
                    m = m.max(v);
                    least = least.min(v);
                    match first {
                        None => first = Some(v),
                        Some(f) => uniform &= f == v,
                    }
                }
            }
        }
        // A brick cut by the bounds is uniform only if it covers no voxel outside.
        let whole = hi - lo == UVec3::splat(BRICK);
        let slot = if uniform && (whole || first == Some(0.0)) {
            self.constant_slot(first.unwrap_or(0.0))
        } else {
            let s = self.bricks.slot_range.len() as u32;
            self.reserve_slot();
            self.bricks.pool.extend_from_slice(&clean);
            self.bricks.slot_range.push([least, m]);
            self.bricks.constant.push(false);
            s
        };
        let i = self.brick_index(b);
        self.bricks.table[i] = slot;
        Ok(())
    }

    /// Sets one voxel.
    pub fn put(&mut self, x: u32, y: u32, z: u32, v: f32) -> Result<(), GridError> {
        check_value(x, y, z, v)?;
        let bi = self.brick_index(UVec3::new(x, y, z) / BRICK);
        let mut slot = self.bricks.table[bi] as usize;
        if self.bricks.constant[slot] {
            let old = self.bricks.pool[slot * BRICK_VOXELS];
            if old.to_bits() == v.to_bits() {
                return Ok(());
            }
            // The brick starts to vary: give it a slot of its own. Its voxels beyond
            // the bounds must stay zero.
            let lo = UVec3::new(x, y, z) / BRICK * BRICK;
            let mut vals = [0.0f32; BRICK_VOXELS];
            for lz in 0..BRICK {
                for ly in 0..BRICK {
                    for lx in 0..BRICK {
                        if (lo + UVec3::new(lx, ly, lz)).cmplt(self.dims).all() {
                            vals[(lx + BRICK * (ly + BRICK * lz)) as usize] = old;
                        }
                    }
                }
            }
            slot = self.bricks.slot_range.len();
            self.reserve_slot();
            self.bricks.pool.extend_from_slice(&vals);
            self.bricks.slot_range.push([old, old]);
            self.bricks.constant.push(false);
            self.bricks.table[bi] = slot as u32;
        }
        let m = BRICK - 1;
        self.bricks.pool[slot * BRICK_VOXELS + ((x & m) + BRICK * ((y & m) + BRICK * (z & m))) as usize] = v;
        // Bounds, not the exact extremes: a value written over another leaves them
        // wider than the brick's values, never narrower.
        let r = &mut self.bricks.slot_range[slot];
        *r = [r[0].min(v), r[1].max(v)];
        Ok(())
    }

    /// Sets every voxel of the box `lo ..= hi` (clipped to the grid) to `v`: whole
    /// bricks share the constant slot, partly covered ones are written voxel by voxel.
    pub fn fill(&mut self, lo: UVec3, hi: UVec3, v: f32) -> Result<(), GridError> {
        let hi = hi.min(self.dims - 1);
        if lo.cmpgt(hi).any() {
            return Ok(());
        }
        check_value(lo.x, lo.y, lo.z, v)?;
        let (b0, b1) = (lo / BRICK, hi / BRICK);
        for bz in b0.z..=b1.z {
            for by in b0.y..=b1.y {
                for bx in b0.x..=b1.x {
                    let b = UVec3::new(bx, by, bz);
                    let (blo, bhi) = (b * BRICK, (b * BRICK + BRICK).min(self.dims) - 1);
                    let whole_brick = bhi - blo == UVec3::splat(BRICK - 1);
                    if whole_brick && lo.cmple(blo).all() && hi.cmpge(bhi).all() {
                        let s = self.constant_slot(v);
                        let i = self.brick_index(b);
                        self.bricks.table[i] = s;
                        continue;
                    }
                    let (a, c) = (blo.max(lo), bhi.min(hi));
                    for z in a.z..=c.z {
                        for y in a.y..=c.y {
                            for x in a.x..=c.x {
                                self.put(x, y, z, v)?;
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }

    pub fn finish(self) -> Result<DensityGrid, GridError> {
        let max_value = self.bricks.table.iter().map(|&s| self.bricks.slot_range[s as usize][1]).fold(0.0f32, f32::max);
        Ok(DensityGrid {
            dims: self.dims,
            storage: Storage::Sparse(self.bricks),
            origin: self.origin,
            voxel_size: self.voxel_size,
            inv_voxel_size: self.voxel_size.recip(),
            max_value,
        })
    }
}

/// A density must be finite and non-negative; the error names the voxel.
fn check_value(x: u32, y: u32, z: u32, v: f32) -> Result<(), GridError> {
    if v >= 0.0 && v.is_finite() {
        Ok(())
    } else if v.is_finite() {
        Err(GridError::Negative { x, y, z, value: v })
    } else {
        Err(GridError::NonFinite { x, y, z, value: v })
    }
}

/// Asks the kernel to back `v`'s allocation with 2 MiB pages (transparent huge pages
/// in `madvise` mode), so the pages touched from now on are huge: a big grid's lookups
/// then miss the TLB far less often. The advice follows the mapping when a growing
/// Vec is moved by `mremap`, so nothing is copied. Harmless where declined.
fn advise_huge_pages(v: &mut Vec<f32>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let base = v.as_mut_ptr() as usize;
        let start = base.next_multiple_of(HUGE);
        let end = (base + v.capacity() * std::mem::size_of::<f32>()) / HUGE * HUGE;
        if end > start {
            // SAFETY: the range lies inside `v`'s allocation; madvise only advises and
            // never changes the memory's contents or validity.
            unsafe {
                libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
            }
        }
    }
    let _ = v;
}

/// floor() as an integer without a libm call (x86-64 without SSE4.1 has no rounding
/// instruction, and `f32::floor` becomes a function call on the hot path). |x| < 2^31.
#[inline(always)]
pub fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    i - ((x < i as f32) as i32)
}

#[inline]
fn unflatten(i: usize, dims: UVec3) -> (u32, u32, u32) {
    let nx = dims.x as usize;
    let ny = dims.y as usize;
    ((i % nx) as u32, ((i / nx) % ny) as u32, (i / (nx * ny)) as u32)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_grid(n: u32, v: f32) -> DensityGrid {
        DensityGrid::from_bounds(
            UVec3::splat(n),
            vec![v; (n * n * n) as usize],
            Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
        )
        .unwrap()
    }

    #[test]
    fn rejects_bad_values_naming_the_voxel() {
        let mut data = vec![0.5f32; 27];
        data[1 + 3 * (2 + 3 * 1)] = f32::NAN;
        let e = DensityGrid::new(UVec3::splat(3), data.clone(), Vec3::ZERO, Vec3::ONE).unwrap_err();
        assert_eq!(e.to_string(), "grid value at voxel (1, 2, 1) is NaN: densities must be finite");
        data[1 + 3 * (2 + 3 * 1)] = -0.25;
        let e = DensityGrid::new(UVec3::splat(3), data.clone(), Vec3::ZERO, Vec3::ONE).unwrap_err();
        assert!(matches!(e, GridError::Negative { x: 1, y: 2, z: 1, .. }));
        data[1 + 3 * (2 + 3 * 1)] = f32::INFINITY;
        assert!(matches!(
            DensityGrid::new(UVec3::splat(3), data, Vec3::ZERO, Vec3::ONE),
            Err(GridError::NonFinite { .. })
        ));
        assert!(DensityGrid::new(UVec3::new(2, 0, 2), vec![], Vec3::ZERO, Vec3::ONE).is_err());
        assert!(DensityGrid::new(UVec3::splat(2), vec![0.0; 7], Vec3::ZERO, Vec3::ONE).is_err());
        assert!(DensityGrid::new(UVec3::splat(2), vec![0.0; 8], Vec3::ZERO, Vec3::new(1.0, 0.0, 1.0)).is_err());
    }

    #[test]
    fn cell_centred_trilinear() {
        // A grid whose values are a linear function of the voxel centre is reproduced
        // exactly by trilinear interpolation between the first and last centres.
        let dims = UVec3::new(5, 6, 7);
        let b = Bounds3::new(Vec3::new(-1.0, 0.0, 2.0), Vec3::new(1.5, 3.0, 2.7));
        let f = |p: Vec3| 3.0 + 0.5 * p.x + 0.25 * p.y - 0.75 * (p.z - 2.0);
        let g = DensityGrid::from_fn(dims, b, f).unwrap();
        let vs = g.voxel_size();
        let lo = b.min + 0.5 * vs;
        let hi = b.max - 0.5 * vs;
        for i in 0..50 {
            let t = Vec3::new((i as f32 * 0.37) % 1.0, (i as f32 * 0.61) % 1.0, (i as f32 * 0.13) % 1.0);
            let p = lo + t * (hi - lo);
            assert!((g.lookup(p) - f(p)).abs() < 1e-4, "{p}");
        }
        // Voxel centres return the voxel value.
        assert!((g.lookup(b.min + 0.5 * vs) - g.voxel(0, 0, 0)).abs() < 1e-5);
    }

    #[test]
    fn boundary_maximum() {
        let mut data = vec![0.0f32; 64];
        data[1 + 4 * (1 + 4 * 1)] = 0.9; // interior
        let g = DensityGrid::new(UVec3::splat(4), data.clone(), Vec3::ZERO, Vec3::ONE).unwrap();
        assert_eq!(g.max_on_boundary(), 0.0);
        data[3 + 4 * (2 + 4 * 1)] = 0.5; // on the x = 3 face
        let g = DensityGrid::new(UVec3::splat(4), data, Vec3::ZERO, Vec3::ONE).unwrap();
        assert_eq!(g.max_on_boundary(), 0.5);
    }

    #[test]
    fn floor_matches_std() {
        for x in [-2.5f32, -2.0, -1e-7, 0.0, 1e-7, 0.5, 1.0, 3.999, -1e6 - 0.5, 1e6 + 0.5] {
            assert_eq!(floor_i32(x), x.floor() as i32, "{x}");
        }
    }

    #[test]
    fn zero_outside_and_tapers_at_faces() {
        let g = unit_grid(4, 1.0);
        assert_eq!(g.lookup(Vec3::new(0.0, 0.0, 0.76)), 0.0);
        assert_eq!(g.lookup(Vec3::splat(10.0)), 0.0);
        assert_eq!(g.lookup(Vec3::splat(-1e30)), 0.0);
        // On a face: halfway between the last voxel centre (1) and the outside (0).
        assert!((g.lookup(Vec3::new(0.0, 0.0, 0.5)) - 0.5).abs() < 1e-6);
        assert!((g.lookup(Vec3::ZERO) - 1.0).abs() < 1e-6);
    }

    /// A grid with empty regions, constant regions and noise, with dims that are not
    /// multiples of the brick edge.
    fn patchy(dims: UVec3, seed: u64) -> DensityGrid {
        let mut rng = crate::Rng::new(seed, 0, 0);
        let n = (dims.x * dims.y * dims.z) as usize;
        let mut data = vec![0.0f32; n];
        for (i, v) in data.iter_mut().enumerate() {
            let (x, y, z) = unflatten(i, dims);
            let r = rng.uniform();
            *v = if z < 9 {
                0.0
            } else if x < 16 && y < 16 && z >= 16 {
                0.75
            } else if r < 0.4 {
                0.0
            } else {
                r
            };
        }
        DensityGrid::new(dims, data, Vec3::new(-1.0, 0.5, 2.0), Vec3::new(0.1, 0.07, 0.05)).unwrap()
    }

    /// `stochastic_test` answers a monotone predicate (a threshold) as the predicate of
    /// the voxel `lookup_stochastic` draws, on dense and sparse storage, whether the
    /// brick bounds settle it or the voxel is read: on a smooth ramp (narrow bounds,
    /// mostly settled), the patchy grid (wide ones) and a built grid whose voxels were
    /// overwritten with lower and higher values (bounds wider than the values). Every
    /// stored voxel lies within its slot's bounds.
    #[test]
    fn stochastic_test_answers_as_the_drawn_voxel() {
        let dims = UVec3::new(29, 21, 35);
        let ramp: Vec<f32> = (0..(dims.x * dims.y * dims.z) as usize)
            .map(|i| {
                let (x, y, _) = unflatten(i, dims);
                0.03 * x as f32 + 0.01 * y as f32
            })
            .collect();
        let ramp = DensityGrid::new(dims, ramp, Vec3::ZERO, Vec3::splat(0.1)).unwrap();
        let mut built = SparseBuilder::new(dims, Vec3::ZERO, Vec3::splat(0.1)).unwrap();
        built.fill(UVec3::new(0, 0, 0), UVec3::new(20, 20, 20), 0.6).unwrap();
        built.fill(UVec3::new(3, 3, 3), UVec3::new(12, 12, 12), 0.2).unwrap();
        for i in 0..400u32 {
            built.put(i % 29, (i * 7) % 21, (i * 13) % 35, (i % 5) as f32 * 0.3).unwrap();
        }
        let built = built.finish().unwrap();
        let patchy = patchy(dims, 5);
        let grids = [ramp.to_sparse(), ramp, patchy.to_sparse(), patchy, built];
        let mut rng = crate::Rng::new(6, 0, 0);
        let (mut settled, mut read) = (0u32, 0u32);
        for (gi, g) in grids.iter().enumerate() {
            if let Storage::Sparse(b) = &g.storage {
                for z in 0..dims.z {
                    for y in 0..dims.y {
                        for x in 0..dims.x {
                            let [lo, hi] = b.slot_range[b.slot_of(x, y, z)];
                            let v = g.voxel(x, y, z);
                            assert!(lo <= v && v <= hi, "grid {gi} ({x}, {y}, {z}): {v} outside [{lo}, {hi}]");
                        }
                    }
                }
            }
            let sb = g.support_bounds();
            for _ in 0..100_000 {
                let t = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1.2 - 0.1;
                let p = sb.min + t * sb.extent();
                let bits = rng.next_u64();
                let v = g.lookup_stochastic(p, bits);
                let threshold = rng.uniform() * 1.3 * g.max_value();
                let reads = std::cell::Cell::new(0u32);
                let strict = g.stochastic_test(p, bits, |x| {
                    reads.set(reads.get() + 1);
                    threshold < x
                });
                assert_eq!(strict, threshold < v, "grid {gi} at {p}: {v} against {threshold}");
                assert_eq!(g.stochastic_test(p, bits, |x| threshold <= x), threshold <= v, "grid {gi} at {p}");
                if gi == 0 {
                    if reads.get() < 3 { settled += 1 } else { read += 1 }
                }
            }
        }
        // A brick of the ramp spans at most 0.28 of values, the thresholds 1.35: about
        // four tests in five end at the bounds.
        assert!(settled > 2 * read, "{settled} settled, {read} read");
    }

    /// Sparse storage answers every voxel and every trilinear lookup (inside bricks,
    /// across brick faces, at the grid's faces and outside) with the dense grid's
    /// values bit for bit, and shares one slot among the constant bricks.
    #[test]
    fn sparse_matches_dense_bit_for_bit() {
        let dense = patchy(UVec3::new(29, 21, 35), 3);
        let sparse = dense.to_sparse();
        assert!(sparse.is_sparse() && !dense.is_sparse());
        assert_eq!(sparse.max_value(), dense.max_value());
        assert_eq!(sparse.max_on_boundary(), dense.max_on_boundary());
        assert_eq!(sparse.to_dense_vec(), dense.to_dense_vec());
        let mut rng = crate::Rng::new(4, 0, 0);
        let sb = dense.support_bounds();
        for _ in 0..200_000 {
            let t = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1.2 - 0.1;
            let p = sb.min + t * sb.extent();
            assert_eq!(sparse.lookup(p).to_bits(), dense.lookup(p).to_bits(), "{p}");
        }
        // Bricks 0 and 1 in z are zero (z < 9 is empty, brick 1 holds z 8..16 with
        // z = 8 empty but not z >= 9), and the constant 0.75 block shares a slot.
        assert!(sparse.brick_is_zero(UVec3::new(0, 0, 0)));
        assert!(!sparse.brick_is_zero(UVec3::new(0, 0, 1)));
        assert_eq!(sparse.brick_max(UVec3::new(1, 1, 2)), 0.75);
        let bd = dense.brick_dims();
        for bz in 0..bd.z {
            for by in 0..bd.y {
                for bx in 0..bd.x {
                    let b = UVec3::new(bx, by, bz);
                    assert_eq!(sparse.brick_max(b), dense.brick_max(b));
                    assert_eq!(sparse.brick_is_zero(b), dense.brick_is_zero(b));
                }
            }
        }
        if let Storage::Sparse(b) = &sparse.storage {
            let distinct: std::collections::HashSet<u32> = b.table.iter().copied().collect();
            // 2 x 2 x 2 bricks of 0.75 (z 16..32) share one slot.
            let shared = b.table.iter().filter(|&&s| b.constant[s as usize] && s != 0).count();
            assert_eq!(shared, 8);
            assert_eq!(distinct.len(), b.slot_range.len());
        }
    }

    /// The stochastic lookup returns each corner of the trilinear stencil with its
    /// weight (chi-square, 10^5 draws per point, alpha 0.01 with Sidak correction over
    /// the points: inside a brick, across brick faces, at the grid's faces with corners
    /// outside), and sparse storage returns the dense grid's corner for the same bits.
    #[test]
    fn stochastic_lookup_draws_corners_by_weight() {
        use crate::stats::{chi2_test, sidak};
        let dims = UVec3::new(13, 11, 10);
        let n = (dims.x * dims.y * dims.z) as usize;
        // Distinct values name the voxel a draw read.
        let data: Vec<f32> = (0..n).map(|i| (i + 1) as f32).collect();
        let dense = DensityGrid::new(dims, data, Vec3::new(0.5, -1.0, 0.25), Vec3::new(0.1, 0.2, 0.05)).unwrap();
        let sparse = dense.to_sparse();
        let index_points = [
            Vec3::new(2.3, 4.6, 5.1),
            Vec3::new(7.25, 7.5, 7.9),
            Vec3::new(6.9, 3.02, 7.5),
            Vec3::new(-0.4, 10.3, 4.5),
            Vec3::new(12.6, 0.5, -0.7),
        ];
        let alpha = sidak(0.01, index_points.len());
        let draws = 100_000usize;
        let mut rng = crate::Rng::new(11, 0, 0);
        for u in index_points {
            let p = dense.origin() + (u + 0.5) * dense.voxel_size();
            let base = u.floor();
            let f = u - base;
            // Expected probability of each value (corners outside pooled under 0).
            let mut expected: std::collections::BTreeMap<u32, f64> = Default::default();
            for c in 0..8u32 {
                let d = UVec3::new(c & 1, (c >> 1) & 1, c >> 2);
                let w = (0..3).map(|a| if d[a] == 1 { f[a] as f64 } else { 1.0 - f[a] as f64 }).product::<f64>();
                let q = base.as_ivec3() + d.as_ivec3();
                let v = dense.voxel_or_zero(q.x, q.y, q.z);
                *expected.entry(v.to_bits()).or_default() += w;
            }
            let mut counts: std::collections::BTreeMap<u32, f64> = Default::default();
            let mut sum = 0.0f64;
            for _ in 0..draws {
                let bits = rng.next_u64();
                let v = dense.lookup_stochastic(p, bits);
                assert_eq!(v.to_bits(), sparse.lookup_stochastic(p, bits).to_bits(), "{u}");
                assert!(expected.contains_key(&v.to_bits()), "{u}: {v} is not a corner");
                *counts.entry(v.to_bits()).or_default() += 1.0;
                sum += v as f64;
            }
            let keys: Vec<u32> = expected.keys().copied().collect();
            let obs: Vec<f64> = keys.iter().map(|k| counts.get(k).copied().unwrap_or(0.0)).collect();
            let exp: Vec<f64> = keys.iter().map(|k| expected[k] * draws as f64).collect();
            let t = chi2_test(&obs, &exp, 5.0);
            assert!(t.p_value > alpha, "{u}: {t:?} observed {obs:?} expected {exp:?}");
            // The draws' mean against the trilinear value, within 5 standard errors.
            let mean = sum / draws as f64;
            let want = dense.lookup(p) as f64;
            let var: f64 = expected.iter().map(|(k, w)| w * (f32::from_bits(*k) as f64 - want).powi(2)).sum();
            assert!((mean - want).abs() <= 5.0 * (var / draws as f64).sqrt() + 1e-6, "{u}: {mean} vs {want}");
        }
    }

    /// Sampling brick by brick gives the dense sampling's values, skips the bricks
    /// the test rejects (and then never calls the function there), and names a bad
    /// voxel.
    #[test]
    fn from_fn_sparse_matches_from_fn() {
        let dims = UVec3::new(40, 33, 17);
        let b = Bounds3::new(Vec3::new(-1.0, -0.5, 0.0), Vec3::new(1.0, 0.5, 0.6));
        let ball = |p: Vec3| (0.2 - (p - Vec3::new(0.0, 0.0, 0.3)).length()).max(0.0) * 3.0;
        let dense = DensityGrid::from_fn(dims, b, ball).unwrap();
        let calls = std::sync::atomic::AtomicUsize::new(0);
        let sparse = DensityGrid::from_fn_sparse(
            dims,
            b,
            |bx| bx.min.max(Vec3::new(-0.2, -0.2, 0.1)).cmple(bx.max.min(Vec3::new(0.2, 0.2, 0.5))).all(),
            |p| {
                calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                ball(p)
            },
        )
        .unwrap();
        assert_eq!(sparse.to_dense_vec(), dense.to_dense_vec());
        let n = calls.into_inner();
        assert!(n < (dims.x * dims.y * dims.z) as usize / 2, "{n} calls: the brick test skipped nothing");
        assert!(sparse.memory_bytes() < dense.memory_bytes());
        let e = DensityGrid::from_fn_sparse(dims, b, |_| true, |p| if p.x > 0.5 { f32::NAN } else { 0.0 }).unwrap_err();
        assert!(matches!(e, GridError::NonFinite { x: 30, .. }), "{e}");
    }

    /// The builder: single voxels, boxes covering whole and partial bricks, a write
    /// into a shared constant brick (which must not leak into its sharers), bad values.
    #[test]
    fn sparse_builder_writes() {
        let dims = UVec3::new(20, 20, 12);
        let mut want = vec![0.0f32; 20 * 20 * 12];
        let mut b = SparseBuilder::new(dims, Vec3::ZERO, Vec3::ONE).unwrap();
        let mut fill = |b: &mut SparseBuilder, lo: UVec3, hi: UVec3, v: f32| {
            b.fill(lo, hi, v).unwrap();
            for z in lo.z..=hi.z.min(11) {
                for y in lo.y..=hi.y.min(19) {
                    for x in lo.x..=hi.x.min(19) {
                        want[(x + 20 * (y + 20 * z)) as usize] = v;
                    }
                }
            }
        };
        fill(&mut b, UVec3::ZERO, UVec3::new(15, 15, 7), 0.5); // four whole bricks
        fill(&mut b, UVec3::new(3, 17, 2), UVec3::new(30, 30, 30), 0.25); // partial, clipped
        b.put(9, 9, 1, 2.0).unwrap(); // into one of the shared 0.5 bricks
        want[9 + 20 * (9 + 20)] = 2.0;
        assert!(matches!(b.put(1, 2, 3, -1.0), Err(GridError::Negative { x: 1, y: 2, z: 3, .. })));
        assert!(b.fill(UVec3::ZERO, UVec3::ONE, f32::INFINITY).is_err());
        let g = b.finish().unwrap();
        assert_eq!(g.to_dense_vec(), want);
        assert_eq!(g.max_value(), 2.0);
        assert_eq!(g.voxel(1, 1, 1), 0.5, "the write leaked into a brick sharing the slot");
    }
}
