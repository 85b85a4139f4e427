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

/// A validated density grid.
#[derive(Clone, Debug)]
pub struct DensityGrid {
    dims: UVec3,
    data: Vec<f32>,
    origin: Vec3,
    voxel_size: Vec3,
    inv_voxel_size: Vec3,
    max_value: f32,
}

impl DensityGrid {
    /// Builds a grid from values (x fastest), rejecting NaN, infinity and negative
    /// values with the first bad voxel named.
    pub fn new(dims: UVec3, data: Vec<f32>, origin: Vec3, voxel_size: Vec3) -> Result<Self, GridError> {
        if dims.min_element() == 0 {
            return Err(GridError::EmptyDims(dims.x, dims.y, dims.z));
        }
        let expected = dims.x as usize * dims.y as usize * dims.z as usize;
        if data.len() != expected {
            return Err(GridError::LengthMismatch { dims: dims.to_array(), expected, got: data.len() });
        }
        if !voxel_size.is_finite() || voxel_size.min_element() <= 0.0 {
            return Err(GridError::BadVoxelSize(voxel_size.to_array()));
        }
        if !origin.is_finite() {
            return Err(GridError::BadOrigin(origin.to_array()));
        }
        let mut max_value = 0.0f32;
        for (i, &v) in data.iter().enumerate() {
            if !(v >= 0.0 && v.is_finite()) {
                let (x, y, z) = unflatten(i, dims);
                return Err(if v.is_finite() {
                    GridError::Negative { x, y, z, value: v }
                } else {
                    GridError::NonFinite { x, y, z, value: v }
                });
            }
            max_value = max_value.max(v);
        }
        Ok(DensityGrid { dims, data, origin, voxel_size, inv_voxel_size: voxel_size.recip(), max_value })
    }

    /// Builds a grid whose voxels exactly tile `bounds`.
    pub fn from_bounds(dims: UVec3, data: Vec<f32>, bounds: Bounds3) -> Result<Self, GridError> {
        if !(bounds.min.is_finite() && bounds.max.is_finite()) || bounds.extent().min_element() <= 0.0 {
            return Err(GridError::BadBounds { min: bounds.min.to_array(), max: bounds.max.to_array() });
        }
        if dims.min_element() == 0 {
            return Err(GridError::EmptyDims(dims.x, dims.y, dims.z));
        }
        let voxel_size = bounds.extent() / dims.as_vec3();
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
    pub fn data(&self) -> &[f32] {
        &self.data
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
        self.data[(x as usize) + self.dims.x as usize * (y as usize + self.dims.y as usize * z as usize)]
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

    /// Trilinearly interpolated density at world position `p`.
    #[inline]
    pub fn lookup(&self, p: Vec3) -> f32 {
        let u = self.world_to_index(p);
        // Far-away points (and NaN) are outside anyway; this keeps the i32 casts exact.
        if !(u.abs().max_element() < 1.0e9) {
            return 0.0;
        }
        let (x, y, z) = (floor_i32(u.x), floor_i32(u.y), floor_i32(u.z));
        let f = u - Vec3::new(x as f32, y as f32, z as f32);
        let (nx, ny, nz) = (self.dims.x as i32, self.dims.y as i32, self.dims.z as i32);
        let (c000, c100, c010, c110, c001, c101, c011, c111);
        if x >= 0 && y >= 0 && z >= 0 && x + 1 < nx && y + 1 < ny && z + 1 < nz {
            // Fast path: all eight corners inside.
            let sx = 1usize;
            let sy = nx as usize;
            let sz = (nx * ny) as usize;
            let i = x as usize + sy * y as usize + sz * z as usize;
            let d = &self.data;
            c000 = d[i];
            c100 = d[i + sx];
            c010 = d[i + sy];
            c110 = d[i + sy + sx];
            c001 = d[i + sz];
            c101 = d[i + sz + sx];
            c011 = d[i + sz + sy];
            c111 = d[i + sz + sy + sx];
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

    /// Memory held by the voxel values, in bytes.
    pub fn memory_bytes(&self) -> usize {
        self.data.len() * std::mem::size_of::<f32>()
    }
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
}
