//! Writing OpenVDB files. No crate writes VDB, so Nimbus does it itself: one float grid
//! (tree `Tree_float_5_4_3`), file format version 224 as OpenVDB 10 writes it, a
//! `UniformScaleTranslateMap` transform, background 0 and only non-zero voxels active,
//! compression "active mask" (only active values are stored; no zip/blosc).
//!
//! Layout (checked byte for byte against files written by libopenvdb 10.0.1): header,
//! grid descriptor with its three file offsets, grid compression flags, grid
//! metadata, transform, then the tree topology (root, internal nodes with their masks
//! and tile values, leaf value masks) followed by every leaf's buffer (value mask,
//! a per-node compression byte, the active values) in the same order.
//!
//! Index space: our voxel (i, j, k) becomes OpenVDB voxel (i, j, k), whose value is a
//! point sample at world `translation + voxel_size * (i, j, k)` (the voxel centre), so
//! `translation = origin + voxel_size / 2`.

use engine::DensityGrid;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VdbWriteError {
    #[error("VDB export needs cubic voxels (OpenVDB's uniform scale map); this grid's voxel size is {0:?}")]
    NonUniformVoxels([f32; 3]),
    #[error("VDB grid name must be 1 to 255 printable characters, got {0:?}")]
    BadName(String),
}

const LEAF_DIM: u32 = 8; // 2^3
const NODE4_DIM: u32 = 128; // 2^(4+3)
const NODE5_CHILDREN: usize = 32 * 32 * 32;
const NODE4_CHILDREN: usize = 16 * 16 * 16;

/// OpenVDB per-node value compression codes (io/Compression.h).
const NO_MASK_OR_INACTIVE_VALS: u8 = 0;
/// Grid compression flag: store active values only (COMPRESS_ACTIVE_MASK).
const COMPRESS_ACTIVE_MASK: u32 = 0x2;

struct Writer {
    buf: Vec<u8>,
}

impl Writer {
    fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    fn i32(&mut self, v: i32) {
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    fn i64(&mut self, v: i64) {
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    fn string(&mut self, s: &str) {
        self.u32(s.len() as u32);
        self.buf.extend_from_slice(s.as_bytes());
    }
    fn mask(&mut self, bits: &[u64]) {
        for w in bits {
            self.buf.extend_from_slice(&w.to_le_bytes());
        }
    }
    fn meta(&mut self, name: &str, type_name: &str, value: &[u8]) {
        self.string(name);
        self.string(type_name);
        self.u32(value.len() as u32);
        self.buf.extend_from_slice(value);
    }
}

struct Leaf {
    /// Index of the leaf inside its Node4.
    index: usize,
    mask: [u64; 8],
    /// Active values in bit order (OpenVDB leaf offset: z fastest).
    values: Vec<f32>,
}

struct Node4 {
    index: usize,
    leaves: Vec<Leaf>,
}

/// A canonical version-4 UUID string (OpenVDB silently reads no grids from a file
/// whose UUID is not in canonical form).
fn uuid_v4(seed: u64) -> String {
    let a = engine::rng::mix64(seed);
    let b = engine::rng::mix64(a ^ 0x5851_F42D_4C95_7F2D);
    let a = (a & 0xFFFF_FFFF_FFFF_0FFF) | 0x0000_0000_0000_4000;
    let b = (b & 0x3FFF_FFFF_FFFF_FFFF) | 0x8000_0000_0000_0000;
    format!(
        "{:08x}-{:04x}-{:04x}-{:04x}-{:012x}",
        a >> 32,
        (a >> 16) & 0xFFFF,
        a & 0xFFFF,
        b >> 48,
        b & 0xFFFF_FFFF_FFFF
    )
}

/// The bytes of a .vdb file holding `grid` as a float grid named `name`.
pub fn vdb_bytes(grid: &DensityGrid, name: &str) -> Result<Vec<u8>, VdbWriteError> {
    let vs = grid.voxel_size();
    if (vs.x - vs.y).abs() > 1e-6 * vs.x || (vs.x - vs.z).abs() > 1e-6 * vs.x {
        return Err(VdbWriteError::NonUniformVoxels(vs.to_array()));
    }
    if name.is_empty() || name.len() > 255 || name.chars().any(|c| c.is_control()) {
        return Err(VdbWriteError::BadName(name.to_string()));
    }
    let dims = grid.dims();
    // Group non-zero voxels into leaves and Node4s (all indices are in [0, 1024), so
    // one Node5 at the origin holds everything).
    let mut node4s: Vec<Node4> = Vec::new();
    let (mut bbox_min, mut bbox_max) = ([i32::MAX; 3], [i32::MIN; 3]);
    let mut active_count: i64 = 0;
    let n4 = |d: u32| d.div_ceil(NODE4_DIM);
    let nl = |d: u32| d.div_ceil(LEAF_DIM);
    // Node4s in child-mask bit order: index = (x4 << 10) | (y4 << 5) | z4.
    for x4 in 0..n4(dims.x) {
        for y4 in 0..n4(dims.y) {
            for z4 in 0..n4(dims.z) {
                let mut leaves = Vec::new();
                // Leaves in bit order: index = (xl << 8) | (yl << 4) | zl within the Node4.
                for xl in 0..16u32 {
                    for yl in 0..16u32 {
                        for zl in 0..16u32 {
                            let (lx, ly, lz) = (x4 * 16 + xl, y4 * 16 + yl, z4 * 16 + zl);
                            if lx >= nl(dims.x) || ly >= nl(dims.y) || lz >= nl(dims.z) {
                                continue;
                            }
                            // Leaves and the grid's bricks share their 8^3 footprint.
                            if grid.brick_is_zero(glam::UVec3::new(lx, ly, lz)) {
                                continue;
                            }
                            let mut mask = [0u64; 8];
                            let mut values = Vec::new();
                            for x in 0..LEAF_DIM {
                                for y in 0..LEAF_DIM {
                                    for z in 0..LEAF_DIM {
                                        let (gx, gy, gz) = (lx * 8 + x, ly * 8 + y, lz * 8 + z);
                                        if gx >= dims.x || gy >= dims.y || gz >= dims.z {
                                            continue;
                                        }
                                        let v = grid.voxel(gx, gy, gz);
                                        if v != 0.0 {
                                            let bit = ((x << 6) | (y << 3) | z) as usize;
                                            mask[bit >> 6] |= 1 << (bit & 63);
                                            values.push(v);
                                            let g = [gx as i32, gy as i32, gz as i32];
                                            for a in 0..3 {
                                                bbox_min[a] = bbox_min[a].min(g[a]);
                                                bbox_max[a] = bbox_max[a].max(g[a]);
                                            }
                                        }
                                    }
                                }
                            }
                            if !values.is_empty() {
                                active_count += values.len() as i64;
                                leaves.push(Leaf { index: ((xl << 8) | (yl << 4) | zl) as usize, mask, values });
                            }
                        }
                    }
                }
                if !leaves.is_empty() {
                    node4s.push(Node4 { index: ((x4 << 10) | (y4 << 5) | z4) as usize, leaves });
                }
            }
        }
    }

    let mut w = Writer { buf: Vec::new() };
    // Header.
    w.i64(0x5644_4220);
    w.u32(224); // file format version
    w.u32(10); // library major
    w.u32(0); // library minor
    w.u8(1); // has grid offsets
    let seed = [dims.x, dims.y, dims.z, grid.max_value().to_bits(), active_count as u32]
        .iter()
        .fold(grid.memory_bytes() as u64, |h, &v| engine::rng::mix64(h ^ v as u64))
        ^ std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0);
    w.buf.extend_from_slice(uuid_v4(seed).as_bytes());
    w.u32(0); // file metadata count
    w.i32(1); // grid count
    w.string(name);
    w.string("Tree_float_5_4_3");
    w.string(""); // instance parent
    let offsets_at = w.buf.len();
    w.i64(0); // grid pos, block pos, end pos: patched below
    w.i64(0);
    w.i64(0);
    let grid_pos = w.buf.len() as i64;
    w.u32(COMPRESS_ACTIVE_MASK);

    // Grid metadata.
    let has_bbox = active_count > 0;
    w.u32(if has_bbox { 6 } else { 4 });
    w.meta("class", "string", b"fog volume");
    if has_bbox {
        let v = |b: [i32; 3]| b.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        w.meta("file_bbox_max", "vec3i", &v(bbox_max));
        w.meta("file_bbox_min", "vec3i", &v(bbox_min));
    }
    w.meta("file_compression", "string", b"active values");
    w.meta("file_voxel_count", "int64", &active_count.to_le_bytes());
    w.meta("name", "string", name.as_bytes());

    // Transform: UniformScaleTranslateMap (translation, scale, voxel size, 1/scale,
    // 1/scale^2, 1/(2 scale)), doubles.
    let s = vs.x as f64;
    let t = grid.origin().as_dvec3() + 0.5 * vs.as_dvec3();
    w.string("UniformScaleTranslateMap");
    for v in [t.x, t.y, t.z, s, s, s, s.abs(), s.abs(), s.abs(), 1.0 / s, 1.0 / s, 1.0 / s] {
        w.f64(v);
    }
    let (inv_sq, inv_twice) = (1.0 / s / s, 0.5 / s);
    for v in [inv_sq, inv_sq, inv_sq, inv_twice, inv_twice, inv_twice] {
        w.f64(v);
    }

    // Tree topology.
    w.i32(1); // buffer count
    w.f32(0.0); // background
    w.u32(0); // root tiles
    w.u32(if node4s.is_empty() { 0 } else { 1 }); // root children
    if !node4s.is_empty() {
        w.i32(0);
        w.i32(0);
        w.i32(0); // the Node5 at the origin
        let mut child5 = vec![0u64; NODE5_CHILDREN / 64];
        for n in &node4s {
            child5[n.index >> 6] |= 1 << (n.index & 63);
        }
        w.mask(&child5);
        w.mask(&vec![0u64; NODE5_CHILDREN / 64]); // no active tiles
        w.u8(NO_MASK_OR_INACTIVE_VALS); // and so no values
        for n in &node4s {
            let mut child4 = vec![0u64; NODE4_CHILDREN / 64];
            for l in &n.leaves {
                child4[l.index >> 6] |= 1 << (l.index & 63);
            }
            w.mask(&child4);
            w.mask(&vec![0u64; NODE4_CHILDREN / 64]);
            w.u8(NO_MASK_OR_INACTIVE_VALS);
            for l in &n.leaves {
                w.mask(&l.mask); // leaf topology: its value mask
            }
        }
    }
    // Leaf buffers, in topology order.
    let block_pos = w.buf.len() as i64;
    for n in &node4s {
        for l in &n.leaves {
            w.mask(&l.mask);
            w.u8(NO_MASK_OR_INACTIVE_VALS);
            for &v in &l.values {
                w.f32(v);
            }
        }
    }
    let end_pos = w.buf.len() as i64;
    w.buf[offsets_at..offsets_at + 8].copy_from_slice(&grid_pos.to_le_bytes());
    w.buf[offsets_at + 8..offsets_at + 16].copy_from_slice(&block_pos.to_le_bytes());
    w.buf[offsets_at + 16..offsets_at + 24].copy_from_slice(&end_pos.to_le_bytes());
    Ok(w.buf)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{UVec3, Vec3};

    #[test]
    fn uuid_is_canonical() {
        let u = uuid_v4(42);
        assert_eq!(u.len(), 36);
        let parts: Vec<&str> = u.split('-').collect();
        assert_eq!(parts.iter().map(|p| p.len()).collect::<Vec<_>>(), [8, 4, 4, 4, 12]);
        assert!(parts[2].starts_with('4'));
        assert!(u.chars().all(|c| c == '-' || c.is_ascii_hexdigit()));
    }

    #[test]
    fn rejects_non_cubic_voxels() {
        let g = DensityGrid::new(UVec3::splat(2), vec![1.0; 8], Vec3::ZERO, Vec3::new(1.0, 2.0, 1.0)).unwrap();
        assert!(matches!(vdb_bytes(&g, "density"), Err(VdbWriteError::NonUniformVoxels(_))));
    }
}
