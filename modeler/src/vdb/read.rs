//! Reading OpenVDB files into a density grid, with a reader of our own.
//!
//! Nimbus imports float grids (`Tree_float_5_4_3`) whose values are stored as 32-bit
//! floats or as 16-bit half floats (`Tree_float_5_4_3_HalfFloat`, what Houdini and
//! EmberGen write by default), uncompressed or zip- or blosc-compressed, from files of
//! format version 222 to 224, with an axis-aligned transform (scale and translation).
//!
//! The file is damaged or hostile input, so it is read in two walks over its bytes:
//! 1. The preflight parses the header, the grid descriptors and metadata, and the
//!    whole tree of every float grid: each mask, value array and compressed chunk size
//!    is checked against the bytes that remain before it is used, and each grid's
//!    active voxels are counted and bounded from the masks alone. Nothing is
//!    decompressed.
//! 2. Once the active bounding box is known, the chosen grid's tree is walked again:
//!    each value array is decompressed into a buffer of the size the masks give (at
//!    most 32^3 values), and the active voxels and tiles (8^3 and 128^3) are written
//!    into a grid covering the active bounding box: dense up to [`MAX_DENSE_VOXELS`],
//!    above that sparse bricks of 8^3 aligned with the file's leaves, so a tile becomes
//!    shared constant bricks and memory follows the active voxels; the dense box of a
//!    big grid is never allocated.
//!
//! Still refused, with a message naming the file and the reason: other value types,
//! maps other than UniformScaleMap, UniformScaleTranslateMap and ScaleTranslateMap,
//! tiles at the root level, NaN or negative values, and active bounding boxes above
//! [`MAX_SPARSE_VOXELS`].

use engine::DensityGrid;
use glam::{DVec3, IVec3, UVec3, Vec3};
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum VdbReadError {
    #[error("{path}: cannot read: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: not an OpenVDB file (bad magic number)")]
    NotVdb { path: String },
    #[error("{path}: truncated or corrupt VDB file ({what})")]
    Corrupt { path: String, what: String },
    #[error("{path}: {what}")]
    Unsupported { path: String, what: String },
    #[error("{path}: no grid named '{name}'; the file has: {available}")]
    NoSuchGrid { path: String, name: String, available: String },
    #[error("{path}: grid '{name}' has no active voxels")]
    Empty { path: String, name: String },
    #[error("{path}: grid '{name}': voxel ({i}, {j}, {k}) is {value}; densities must be finite and >= 0")]
    BadValue { path: String, name: String, i: i32, j: i32, k: i32, value: f32 },
    #[error(
        "{path}: grid '{name}' spans {dims:?} voxels, more than Nimbus holds ({max} voxels in the active bounding box)"
    )]
    TooLarge { path: String, name: String, dims: [i64; 3], max: u64 },
}

/// Most voxels of an active bounding box imported densely (64 MiB of f32, 256^3);
/// bigger boxes import into sparse bricks.
pub const MAX_DENSE_VOXELS: u64 = 1 << 24;
/// Most voxels of the active bounding box of a sparse import (4096^3: a brick table of
/// 512 MiB).
pub const MAX_SPARSE_VOXELS: u64 = 1 << 36;

/// What the importer found, besides the grid.
#[derive(Debug)]
pub struct VdbImport {
    pub grid: DensityGrid,
    pub name: String,
    /// Index of the grid's voxel (0, 0, 0) in the file's index space.
    pub index_min: IVec3,
    /// Inclusive index bounds of the active voxels (the grid's box equals them for a
    /// dense import; a sparse import's box is grown to whole 8^3 leaves).
    pub active_min: IVec3,
    pub active_max: IVec3,
    /// Active voxels, tiles counted as the voxels they cover.
    pub active_voxels: u64,
    pub active_tiles: u64,
    /// Sum of the active values.
    pub sum: f64,
    pub voxel_size: DVec3,
    /// World position of index (0, 0, 0).
    pub translation: DVec3,
    /// All grids in the file, in file order, with their tree types.
    pub grids: Vec<(String, String)>,
}

/// OpenVDB io::Compression flags, stored per grid.
const COMPRESS_ZIP: u32 = 0x1;
const COMPRESS_ACTIVE_MASK: u32 = 0x2;
const COMPRESS_BLOSC: u32 = 0x4;

const FLOAT_TREE: &str = "Tree_float_5_4_3";
/// OpenVDB appends this suffix to the tree type of a grid saved as half floats; it is
/// what OpenVDB's reader keys on (the `is_saved_as_half_float` metadata only mirrors it).
const HALF_FLOAT_TREE: &str = "Tree_float_5_4_3_HalfFloat";

/// A grid descriptor as the preflight saw it.
struct Descriptor {
    name: String,
    grid_type: String,
    map_type: String,
    /// The tree of a float grid with a scale (+ translation) map, checked whole.
    tree: Option<TreeInfo>,
}

struct TreeInfo {
    format: ValueFormat,
    scale: DVec3,
    translation: DVec3,
    /// File offsets: the tree topology starts at `topology`, the leaf buffers at
    /// `buffers`, and the grid ends at `end`.
    topology: usize,
    buffers: usize,
    end: usize,
    shape: Shape,
}

/// How a grid stores its value arrays.
#[derive(Clone, Copy)]
struct ValueFormat {
    compression: u32,
    /// 16-bit half floats in the value arrays (inactive values, the background and
    /// root tiles stay 32-bit floats).
    half: bool,
}

/// A tree's active values as the masks give them.
#[derive(Default)]
struct Shape {
    root_tiles: u32,
    /// Active voxels, tiles counted as the voxels they cover.
    active_voxels: u64,
    active_tiles: u64,
    /// Inclusive index bounds of the active voxels (when there are any).
    lo: IVec3,
    hi: IVec3,
}

impl Shape {
    fn add(&mut self, lo: IVec3, hi: IVec3, voxels: u64) {
        if self.active_voxels == 0 {
            (self.lo, self.hi) = (lo, hi);
        } else {
            (self.lo, self.hi) = (self.lo.min(lo), self.hi.max(hi));
        }
        self.active_voxels += voxels;
    }
}

struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.data.len())
            .ok_or_else(|| format!("needs {n} bytes at offset {}", self.pos))?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], String> {
        let mut a = [0; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    fn i32(&mut self) -> Result<i32, String> {
        Ok(i32::from_le_bytes(self.array()?))
    }
    fn i64(&mut self) -> Result<i64, String> {
        Ok(i64::from_le_bytes(self.array()?))
    }
    fn dvec3(&mut self) -> Result<DVec3, String> {
        let mut v = [0.0; 3];
        for x in &mut v {
            *x = f64::from_le_bytes(self.array()?);
        }
        Ok(DVec3::from_array(v))
    }
    fn string(&mut self) -> Result<String, String> {
        let n = self.u32()? as usize;
        if n > 1 << 20 {
            return Err(format!("string of {n} bytes at offset {}", self.pos));
        }
        // Names and types reach messages: invalid UTF-8 and control characters are
        // shown escaped, never printed raw to a terminal.
        let text = String::from_utf8_lossy(self.take(n)?);
        Ok(text.chars().flat_map(|c| if c.is_control() { c.escape_default().collect() } else { vec![c] }).collect())
    }
    /// Metadata map: (name, type, value bytes).
    fn metadata(&mut self) -> Result<Vec<(String, String, Vec<u8>)>, String> {
        let count = self.u32()?;
        if count > 10_000 {
            return Err(format!("{count} metadata entries"));
        }
        (0..count)
            .map(|_| {
                let name = self.string()?;
                let ty = self.string()?;
                let n = self.u32()? as usize;
                // OpenVDB reads these types at their fixed size whatever the stored
                // size says; a disagreement means the file is damaged.
                let fixed = match ty.as_str() {
                    "bool" => Some(1),
                    "int32" | "float" => Some(4),
                    "int64" => Some(8),
                    "vec3i" => Some(12),
                    _ => None,
                };
                if fixed.is_some_and(|f| f != n) {
                    return Err(format!("metadata '{name}' of type {ty} stored in {n} bytes"));
                }
                Ok((name, ty, self.take(n)?.to_vec()))
            })
            .collect()
    }
}

/// Parses and checks the whole file (see the module docs); trees are walked without
/// decompressing anything.
fn preflight(data: &[u8], path: &str) -> Result<Vec<Descriptor>, VdbReadError> {
    let corrupt = |what: String| VdbReadError::Corrupt { path: path.to_string(), what };
    let unsupported = |what: String| VdbReadError::Unsupported { path: path.to_string(), what };
    let mut c = Cursor { data, pos: 0 };
    if c.i64().ok() != Some(0x5644_4220) {
        return Err(VdbReadError::NotVdb { path: path.to_string() });
    }
    let version = c.u32().map_err(corrupt)?;
    if !(222..=224).contains(&version) {
        return Err(unsupported(format!(
            "OpenVDB file format version {version}; Nimbus reads versions 222 to 224 (OpenVDB 2 and later)"
        )));
    }
    let _library_version = (c.u32().map_err(corrupt)?, c.u32().map_err(corrupt)?);
    if c.u8().map_err(corrupt)? != 1 {
        return Err(unsupported("file written without grid offsets".into()));
    }
    c.take(36).map_err(corrupt)?; // UUID
    c.metadata().map_err(corrupt)?;
    let count = c.u32().map_err(corrupt)?;
    if count > 10_000 {
        return Err(corrupt(format!("{count} grids")));
    }
    let mut out: Vec<Descriptor> = Vec::new();
    for _ in 0..count {
        let name = c.string().map_err(corrupt)?;
        let grid_type = c.string().map_err(corrupt)?;
        let _instance_parent = c.string().map_err(corrupt)?;
        let (gp, bp, ep) = (c.i64().map_err(corrupt)?, c.i64().map_err(corrupt)?, c.i64().map_err(corrupt)?);
        // A grid follows its descriptor and the next descriptor follows the grid, so
        // the grids are disjoint and each byte is walked once.
        let len = data.len() as i64;
        if !(gp >= c.pos as i64 && gp <= bp && bp <= ep && ep <= len) {
            return Err(corrupt(format!(
                "grid '{name}' offsets {gp}/{bp}/{ep} outside {}..{len} (after its descriptor, in the file)",
                c.pos
            )));
        }
        if out.iter().any(|d| d.name == name) {
            return Err(corrupt(format!("two grids named '{name}'")));
        }
        let (buffers, end) = (bp as usize, ep as usize);
        let mut g = Cursor { data: &data[..buffers], pos: gp as usize };
        let compression = g.u32().map_err(corrupt)?;
        g.metadata().map_err(corrupt)?;
        let map_type = g.string().map_err(corrupt)?;
        // The maps Nimbus imports, the one place they are listed: a uniform scale
        // map stores five vectors (scale first), a scale-translate map six
        // (translation first, then scale). Any other map leaves `tree` empty.
        let transform = match map_type.as_str() {
            "UniformScaleMap" => {
                let scale = g.dvec3().map_err(corrupt)?;
                g.take(4 * 24).map_err(corrupt)?;
                Some((scale, DVec3::ZERO))
            }
            "UniformScaleTranslateMap" | "ScaleTranslateMap" => {
                let translation = g.dvec3().map_err(corrupt)?;
                let scale = g.dvec3().map_err(corrupt)?;
                g.take(4 * 24).map_err(corrupt)?;
                Some((scale, translation))
            }
            _ => None,
        };
        let half = grid_type == HALF_FLOAT_TREE;
        let tree = match transform {
            Some((scale, translation)) if half || grid_type == FLOAT_TREE => {
                let format = ValueFormat { compression, half };
                let mut walk = TreeWalk::new(&data[..end], g.pos, format, None);
                walk.run(buffers).map_err(|e| corrupt(format!("grid '{name}': {}", e.message())))?;
                Some(TreeInfo { format, scale, translation, topology: g.pos, buffers, end, shape: walk.shape })
            }
            _ => None,
        };
        out.push(Descriptor { name, grid_type, map_type, tree });
        c.pos = end;
    }
    Ok(out)
}

/// Why a tree walk stopped.
enum Fail {
    Corrupt(String),
    /// A NaN, infinite or negative active value, at this index.
    BadValue(IVec3, f32),
}

impl From<String> for Fail {
    fn from(s: String) -> Self {
        Fail::Corrupt(s)
    }
}

impl Fail {
    fn message(&self) -> String {
        match self {
            Fail::Corrupt(s) => s.clone(),
            Fail::BadValue(c, v) => format!("value {v} at {c}"),
        }
    }
}

/// An active block of a tree, in the order the decoding walk writes them.
enum Block {
    /// A leaf (8^3 voxels): its origin and value mask (from the topology).
    Leaf { origin: IVec3, mask: [u8; 64] },
    /// An active tile of an internal node: an `edge`^3 block of one value.
    Tile { origin: IVec3, edge: i32, value: f32 },
}

/// One walk of a `Tree_float_5_4_3` as OpenVDB writes it (file versions 222+): the
/// topology (root, internal nodes with their child mask, value mask and value array,
/// the leaves' value masks), then every leaf's buffer (value mask and value array) in
/// topology order. With a `target` it decodes the values into it; without it, it only
/// checks the structure and bounds the active voxels.
struct TreeWalk<'a, 'd> {
    c: Cursor<'a>,
    format: ValueFormat,
    target: Option<&'d mut Target>,
    shape: Shape,
    /// The leaves, and when decoding the tiles, depth first, each internal node's
    /// tiles after its children. This is the order in which the sum is accumulated;
    /// the tests check it against vdb-rs 0.6, which iterates in this order.
    blocks: Vec<Block>,
    inflate: flate2::Decompress,
    scratch: Vec<u8>,
}

/// The value array of a node, as stored.
struct Stored {
    /// Decoded values (empty when only checking the structure).
    values: Vec<f32>,
    /// Only the active values are stored, in mask order.
    compact: bool,
}

impl Stored {
    /// The value of entry `i`, the `rank`-th active entry.
    fn get(&self, rank: usize, i: usize) -> f32 {
        self.values[if self.compact { rank } else { i }]
    }
}

/// Indices of the set bits of an OpenVDB node mask (64-bit little-endian words, bit i
/// of the mask is bit i % 8 of byte i / 8), ascending.
fn ones(mask: &[u8]) -> impl Iterator<Item = usize> + '_ {
    mask.iter().enumerate().flat_map(|(i, &b)| {
        let mut bits = b;
        std::iter::from_fn(move || {
            (bits != 0).then(|| {
                let j = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                8 * i + j
            })
        })
    })
}

fn popcount(mask: &[u8]) -> usize {
    mask.iter().map(|b| b.count_ones() as usize).sum()
}

/// Local coordinates of entry `i` of a node with 2^log2dim entries a side (OpenVDB
/// orders them x slowest, z fastest).
fn local(i: usize, log2dim: u32) -> IVec3 {
    let m = (1 << log2dim) - 1;
    IVec3::new((i >> (2 * log2dim)) as i32, ((i >> log2dim) & m) as i32, (i & m) as i32)
}

/// Inclusive local bounds of a leaf's set bits (none for an empty mask). Byte 8x + y
/// of the mask holds the z row of voxels (x, y, 0..8).
fn leaf_bounds(mask: &[u8; 64]) -> Option<(IVec3, IVec3)> {
    let (mut xs, mut ys, mut zs) = (0u8, 0u8, 0u8);
    for (i, &b) in mask.iter().enumerate() {
        if b != 0 {
            xs |= 1 << (i / 8);
            ys |= 1 << (i % 8);
            zs |= b;
        }
    }
    let lo = |m: u8| m.trailing_zeros() as i32;
    let hi = |m: u8| 7 - m.leading_zeros() as i32;
    (xs != 0).then(|| (IVec3::new(lo(xs), lo(ys), lo(zs)), IVec3::new(hi(xs), hi(ys), hi(zs))))
}

impl<'a, 'd> TreeWalk<'a, 'd> {
    fn new(data: &'a [u8], pos: usize, format: ValueFormat, target: Option<&'d mut Target>) -> Self {
        TreeWalk {
            c: Cursor { data, pos },
            format,
            target,
            shape: Shape::default(),
            blocks: Vec::new(),
            inflate: flate2::Decompress::new(true),
            scratch: Vec::new(),
        }
    }

    /// Walks the tree: the topology must end where the buffers start (`buffers`), and
    /// the buffers where the grid ends (the end of the data).
    fn run(&mut self, buffers: usize) -> Result<(), Fail> {
        self.topology()?;
        if self.c.pos != buffers {
            return Err(format!("tree topology ends at {} but its buffers start at {buffers}", self.c.pos).into());
        }
        self.buffers()?;
        if self.c.pos != self.c.data.len() {
            return Err(format!("tree data ends at {} but the grid at {}", self.c.pos, self.c.data.len()).into());
        }
        Ok(())
    }

    fn topology(&mut self) -> Result<(), String> {
        let buffers = self.c.u32()?;
        if buffers != 1 {
            return Err(format!("{buffers} buffers per node"));
        }
        self.c.take(4)?; // background
        let tiles = self.c.u32()?;
        let children = self.c.u32()?;
        // A root tile takes 17 bytes (origin, value, active flag), a child at least
        // 12 + 2 * 4096 (origin, masks).
        if tiles as u64 * 17 + children as u64 * (12 + 2 * 4096) > self.c.remaining() as u64 {
            return Err(format!("{tiles} root tiles and {children} root children in {} bytes", self.c.remaining()));
        }
        self.c.take(tiles as usize * 17)?;
        self.shape.root_tiles = tiles;
        let mut origins = Vec::with_capacity(children as usize);
        for _ in 0..children {
            let origin = IVec3::new(self.c.i32()?, self.c.i32()?, self.c.i32()?);
            if origin & 4095 != IVec3::ZERO {
                return Err(format!("root child origin {origin} is not a multiple of 4096"));
            }
            origins.push(origin.to_array());
            self.internal(origin, 5)?;
        }
        // Distinct children (and disjoint masks below) make the active blocks
        // disjoint, so the active voxels fit their bounding box.
        origins.sort_unstable();
        if let Some(w) = origins.windows(2).find(|w| w[0] == w[1]) {
            return Err(format!("two root children at {:?}", w[0]));
        }
        Ok(())
    }

    /// An internal node with 2^(3 log2dim) entries at `origin`: its children are
    /// internal nodes of log2dim 4 (below a 5) or leaves (below a 4).
    fn internal(&mut self, origin: IVec3, log2dim: u32) -> Result<(), String> {
        let n = 1usize << (3 * log2dim);
        let child_mask = self.c.take(n / 8)?;
        let value_mask = self.c.take(n / 8)?;
        if child_mask.iter().zip(value_mask).any(|(a, b)| a & b != 0) {
            return Err(format!("node at {origin}: an entry is both a child and an active tile"));
        }
        let stored = self.values(n, value_mask)?;
        // Each entry covers 2^shift voxels a side: 128 below the root, 8 below that.
        let shift = if log2dim == 5 { 7 } else { 3 };
        let edge = 1i32 << shift;
        let mut tiles = Vec::new();
        for (rank, i) in ones(value_mask).enumerate() {
            let o = origin + (local(i, log2dim) << shift);
            self.shape.add(o, o + (edge - 1), (edge as u64).pow(3));
            self.shape.active_tiles += 1;
            if self.target.is_some() {
                tiles.push(Block::Tile { origin: o, edge, value: stored.get(rank, i) });
            }
        }
        for i in ones(child_mask) {
            let o = origin + (local(i, log2dim) << shift);
            if log2dim == 5 {
                self.internal(o, 4)?;
            } else {
                let mask: [u8; 64] = self.c.array()?; // a leaf's topology: its value mask
                if let Some((lo, hi)) = leaf_bounds(&mask) {
                    self.shape.add(o + lo, o + hi, popcount(&mask) as u64);
                }
                self.blocks.push(Block::Leaf { origin: o, mask });
            }
        }
        self.blocks.append(&mut tiles);
        Ok(())
    }

    fn buffers(&mut self) -> Result<(), Fail> {
        let blocks = std::mem::take(&mut self.blocks);
        for block in &blocks {
            match *block {
                Block::Leaf { origin, ref mask } => {
                    if self.c.take(64)? != mask {
                        return Err(
                            format!("leaf at {origin}: its buffer's value mask differs from the topology's").into()
                        );
                    }
                    let stored = self.values(512, mask)?;
                    if let Some(target) = self.target.as_deref_mut() {
                        for (rank, i) in ones(mask).enumerate() {
                            target.put(origin + local(i, 3), 1, stored.get(rank, i))?;
                        }
                    }
                }
                Block::Tile { origin, edge, value } => {
                    if let Some(target) = self.target.as_deref_mut() {
                        target.put(origin, edge, value)?;
                    }
                }
            }
        }
        Ok(())
    }

    /// One value array of `n` values as io::writeCompressedValues writes it; `mask` is
    /// the node's value mask. Decodes it when the walk has a target grid.
    fn values(&mut self, n: usize, mask: &[u8]) -> Result<Stored, String> {
        let meta = self.c.u8()?;
        if meta > 6 {
            return Err(format!("node compression code {meta}"));
        }
        // Inactive values (full floats even in half-float grids) and the mask that
        // selects between them: the importer keeps only active values.
        if matches!(meta, 2 | 4 | 5) {
            self.c.take(4)?;
        }
        if meta == 5 {
            self.c.take(4)?;
        }
        if matches!(meta, 3..=5) {
            self.c.take(n / 8)?;
        }
        let compression = self.format.compression;
        // With active-mask compression only the active values are stored, unless the
        // code is 6 (NO_MASK_AND_ALL_VALS).
        let compact = compression & COMPRESS_ACTIVE_MASK != 0 && meta != 6;
        let count = if compact { popcount(mask) } else { n };
        let width = if self.format.half { 2 } else { 4 };
        let bytes = count * width;
        let decode = self.target.is_some();
        let mut raw: &[u8] = &[];
        if self.format.half && count == 0 {
            // io::HalfWriter writes nothing for an empty array, not even a chunk size.
        } else if compression & (COMPRESS_BLOSC | COMPRESS_ZIP) != 0 {
            // A chunk: an i64 byte count, negative for data stored raw.
            let size = self.c.i64()?;
            let remaining = self.c.remaining() as u64;
            if size.unsigned_abs() > remaining {
                return Err(format!("chunk of {size} bytes at offset {} with {remaining} left", self.c.pos));
            }
            if size <= 0 {
                if size.unsigned_abs() != bytes as u64 {
                    return Err(format!("raw chunk of {} bytes where {bytes} are due", -size));
                }
                raw = self.c.take(bytes)?;
            } else {
                let at = self.c.pos;
                let chunk = self.c.take(size as usize)?;
                // A chunk of no values holds nothing to decode (OpenVDB writes an empty
                // blosc header for one).
                if count > 0 {
                    if compression & COMPRESS_BLOSC != 0 {
                        check_blosc_header(chunk, bytes).map_err(|e| format!("blosc chunk at offset {at}: {e}"))?;
                    }
                    if decode {
                        if compression & COMPRESS_BLOSC != 0 {
                            self.scratch.resize(bytes, 0);
                            unblosc(chunk, &mut self.scratch)
                        } else {
                            unzip(&mut self.inflate, chunk, bytes, &mut self.scratch)
                        }
                        .map_err(|e| format!("chunk at offset {at}: {e}"))?;
                        raw = &self.scratch;
                    }
                }
            }
        } else {
            raw = self.c.take(bytes)?;
        }
        let values = if !decode {
            Vec::new()
        } else if self.format.half {
            raw.chunks_exact(2).map(|b| half::f16::from_bits(u16::from_le_bytes([b[0], b[1]])).to_f32()).collect()
        } else {
            raw.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
        };
        Ok(Stored { values, compact })
    }
}

/// A blosc chunk's header (c-blosc 1.x, 16 bytes) must give the chunk's own length as
/// its compressed size, so that c-blosc, which checks every offset inside against that
/// size, reads nothing past the chunk; and `bytes` as its uncompressed size.
fn check_blosc_header(chunk: &[u8], bytes: usize) -> Result<(), String> {
    let field = |at: usize| chunk.get(at..at + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
    let (Some(nbytes), Some(cbytes)) = (field(4), field(12)) else {
        return Err(format!("{} bytes, shorter than its header", chunk.len()));
    };
    if cbytes != chunk.len() {
        return Err(format!("header says {cbytes} bytes, the chunk has {}", chunk.len()));
    }
    if nbytes != bytes {
        return Err(format!("unpacks to {nbytes} bytes where {bytes} are due"));
    }
    Ok(())
}

/// Unpacks a blosc chunk whose header [`check_blosc_header`] accepted into `out`.
fn unblosc(chunk: &[u8], out: &mut [u8]) -> Result<(), String> {
    // SAFETY: c-blosc reads at most the header's compressed size from `chunk`, which
    // is `chunk.len()` (checked), and writes at most `out.len()` bytes to `out`.
    let got = unsafe { blosc_src::blosc_decompress_ctx(chunk.as_ptr().cast(), out.as_mut_ptr().cast(), out.len(), 1) };
    if got < 0 || got as usize != out.len() {
        return Err(format!("blosc gave {got} of {} bytes", out.len()));
    }
    Ok(())
}

/// Inflates a zlib chunk, which must hold exactly `bytes` bytes and end with its
/// checksum, into `out`.
fn unzip(inflate: &mut flate2::Decompress, chunk: &[u8], bytes: usize, out: &mut Vec<u8>) -> Result<(), String> {
    inflate.reset(true);
    // One byte of room more than due, so that a longer stream shows.
    out.resize(bytes + 1, 0);
    let (mut read, mut written) = (0usize, 0usize);
    loop {
        let (in0, out0) = (inflate.total_in(), inflate.total_out());
        let status = inflate
            .decompress(&chunk[read..], &mut out[written..], flate2::FlushDecompress::Finish)
            .map_err(|e| format!("zlib: {e}"))?;
        read += (inflate.total_in() - in0) as usize;
        written += (inflate.total_out() - out0) as usize;
        if status == flate2::Status::StreamEnd {
            break;
        }
        if inflate.total_in() == in0 && inflate.total_out() == out0 {
            return Err(format!("zlib stream does not end within {bytes} bytes"));
        }
    }
    if written != bytes {
        return Err(format!("zlib gave {written} of {bytes} bytes"));
    }
    out.truncate(bytes);
    Ok(())
}

/// The grid being filled over the active bounding box: a dense array, or sparse
/// bricks for a box above [`MAX_DENSE_VOXELS`].
struct Target {
    lo: IVec3,
    dims: UVec3,
    values: Vec<f32>,
    sparse: Option<engine::SparseBuilder>,
    sum: f64,
}

impl Target {
    /// Writes an active `edge`^3 block of one value at `c` (inside the bounding box:
    /// the blocks are the ones the preflight bounded).
    fn put(&mut self, c: IVec3, edge: i32, v: f32) -> Result<(), Fail> {
        if !(v.is_finite() && v >= 0.0) {
            return Err(Fail::BadValue(c, v));
        }
        self.sum += v as f64 * (edge as u64).pow(3) as f64;
        let r = (c - self.lo).as_uvec3();
        if let Some(b) = self.sparse.as_mut() {
            let e = edge as u32 - 1;
            let res = if e == 0 { b.put(r.x, r.y, r.z, v) } else { b.fill(r, r + e, v) };
            return res.map_err(|e| Fail::Corrupt(e.to_string()));
        }
        let (nx, ny) = (self.dims.x as usize, self.dims.y as usize);
        let e = edge as usize;
        for z in 0..e {
            for y in 0..e {
                let start = r.x as usize + nx * (r.y as usize + y + ny * (r.z as usize + z));
                self.values[start..start + e].fill(v);
            }
        }
        Ok(())
    }
}

/// Imports grid `name` (default: "density", else the first float grid).
pub fn read_vdb(path: &Path, name: Option<&str>) -> Result<VdbImport, VdbReadError> {
    let p = path.display().to_string();
    let data = std::fs::read(path).map_err(|source| VdbReadError::Io { path: p.clone(), source })?;
    read_vdb_bytes(&data, &p, name)
}

/// As [`read_vdb`], from bytes in memory; `path` names them in messages.
pub fn read_vdb_bytes(data: &[u8], path: &str, name: Option<&str>) -> Result<VdbImport, VdbReadError> {
    let p = path.to_string();
    let descriptors = preflight(data, path)?;
    let grids: Vec<(String, String)> = descriptors.iter().map(|d| (d.name.clone(), d.grid_type.clone())).collect();
    let is_float = |d: &Descriptor| d.grid_type == FLOAT_TREE || d.grid_type == HALF_FLOAT_TREE;
    let chosen = match name {
        Some(n) => descriptors.iter().find(|d| d.name == n),
        // "density" if it is a float grid, else the first float grid; a "density"
        // grid of another type is chosen only to say why it cannot be read.
        None => descriptors
            .iter()
            .find(|d| d.name == "density" && is_float(d))
            .or_else(|| descriptors.iter().find(|d| is_float(d)))
            .or_else(|| descriptors.iter().find(|d| d.name == "density")),
    };
    let available = grids.iter().map(|(n, t)| format!("'{n}' ({t})")).collect::<Vec<_>>().join(", ");
    let Some(d) = chosen else {
        return Err(VdbReadError::NoSuchGrid { path: p, name: name.unwrap_or("density").into(), available });
    };
    let unsupported = |what: String| VdbReadError::Unsupported { path: p.clone(), what };
    if !is_float(d) {
        return Err(unsupported(format!(
            "grid '{}' holds {} values{}; Nimbus imports float grids (Tree_float_5_4_3)",
            d.name,
            d.grid_type,
            if d.grid_type.contains("vec3") { " (a vector per voxel, such as a velocity)" } else { "" }
        )));
    }
    let Some(tree) = d.tree.as_ref() else {
        return Err(unsupported(format!(
            "grid '{}' has a {} transform; Nimbus imports axis-aligned grids (scale and translation only)",
            d.name, d.map_type
        )));
    };
    let shape = &tree.shape;
    if shape.root_tiles > 0 {
        return Err(unsupported(format!(
            "grid '{}' has {} tiles at the root level (4096^3 blocks), which Nimbus does not import",
            d.name, shape.root_tiles
        )));
    }
    if shape.active_voxels == 0 {
        return Err(VdbReadError::Empty { path: p, name: d.name.clone() });
    }
    let (lo, hi) = (shape.lo, shape.hi);
    let (active_min, active_max) = (lo, hi);
    let dims64 = (hi - lo).as_i64vec3() + 1;
    let box_voxels = dims64.x as u64 * dims64.y as u64 * dims64.z as u64;
    // Big boxes are held sparsely, with the box aligned to OpenVDB's 8^3 leaves so
    // that every leaf fills exactly one brick.
    let sparse = box_voxels > MAX_DENSE_VOXELS;
    let (lo, hi) = if sparse {
        (lo.div_euclid(IVec3::splat(8)) * 8, (hi.div_euclid(IVec3::splat(8)) + 1) * 8 - 1)
    } else {
        (lo, hi)
    };
    let dims64 = (hi - lo).as_i64vec3() + 1;
    if sparse && dims64.x as u64 * dims64.y as u64 * dims64.z as u64 > MAX_SPARSE_VOXELS {
        return Err(VdbReadError::TooLarge {
            path: p,
            name: d.name.clone(),
            dims: dims64.to_array(),
            max: MAX_SPARSE_VOXELS,
        });
    }
    let dims = UVec3::new(dims64.x as u32, dims64.y as u32, dims64.z as u32);
    let mut target = if sparse {
        let builder = engine::SparseBuilder::new(dims, Vec3::ZERO, Vec3::ONE)
            .map_err(|e| VdbReadError::Unsupported { path: p.clone(), what: format!("grid '{}': {e}", d.name) })?;
        Target { lo, dims, values: Vec::new(), sparse: Some(builder), sum: 0.0 }
    } else {
        let n = dims.x as usize * dims.y as usize * dims.z as usize;
        Target { lo, dims, values: vec![0.0; n], sparse: None, sum: 0.0 }
    };
    match TreeWalk::new(&data[..tree.end], tree.topology, tree.format, Some(&mut target)).run(tree.buffers) {
        Ok(()) => {}
        Err(Fail::BadValue(c, value)) => {
            return Err(VdbReadError::BadValue { path: p, name: d.name.clone(), i: c.x, j: c.y, k: c.z, value });
        }
        Err(Fail::Corrupt(what)) => {
            return Err(VdbReadError::Corrupt { path: p, what: format!("grid '{}': {what}", d.name) });
        }
    }
    let (scale, translation) = (tree.scale, tree.translation);
    // OpenVDB voxel (i, j, k) is a point sample at translation + scale * (i, j, k): our
    // grid's origin (minimum corner) is half a voxel before the first centre.
    let origin = translation + scale * (lo.as_dvec3() - 0.5);
    let bad =
        |e: engine::GridError| VdbReadError::Unsupported { path: p.clone(), what: format!("grid '{}': {e}", d.name) };
    let grid = match target.sparse {
        Some(b) => b.finish().map_err(bad)?.placed(origin.as_vec3(), scale.as_vec3()).map_err(bad)?,
        None => DensityGrid::new(dims, target.values, origin.as_vec3(), scale.as_vec3()).map_err(bad)?,
    };
    Ok(VdbImport {
        grid,
        name: d.name.clone(),
        index_min: lo,
        active_min,
        active_max,
        active_voxels: shape.active_voxels,
        active_tiles: shape.active_tiles,
        sum: target.sum,
        voxel_size: scale,
        translation,
        grids,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// IEEE 754 binary16 by its definition: sign, 5 exponent bits (bias 15), 10
    /// fraction bits; exponent 0 is subnormal, 31 is infinity or NaN.
    fn half_reference(bits: u16) -> f64 {
        let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
        let e = ((bits >> 10) & 0x1f) as i32;
        let m = (bits & 0x3ff) as f64;
        match e {
            0 => sign * m * 2f64.powi(-24),
            31 if m == 0.0 => sign * f64::INFINITY,
            31 => f64::NAN,
            _ => sign * (1.0 + m / 1024.0) * 2f64.powi(e - 15),
        }
    }

    #[test]
    fn half_to_float_is_exact_for_every_bit_pattern() {
        for bits in 0..=u16::MAX {
            let got = half::f16::from_bits(bits).to_f32();
            let want = half_reference(bits);
            if want.is_nan() {
                assert!(got.is_nan(), "{bits:#06x}: {got}");
                assert_eq!(got.is_sign_negative(), bits & 0x8000 != 0, "{bits:#06x}");
            } else {
                // Every half is a float: the conversion is exact, signed zeros included.
                assert_eq!(got as f64, want, "{bits:#06x}");
                assert_eq!(got.is_sign_negative(), bits & 0x8000 != 0, "{bits:#06x}");
            }
        }
    }

    #[test]
    fn mask_helpers() {
        let mut mask = [0u8; 64];
        assert_eq!(leaf_bounds(&mask), None);
        // Voxel (x, y, z) is bit 64x + 8y + z.
        for (x, y, z) in [(1, 6, 2), (5, 3, 7)] {
            let i = 64 * x + 8 * y + z;
            mask[i / 8] |= 1 << (i % 8);
            assert_eq!(local(i, 3), IVec3::new(x as i32, y as i32, z as i32));
        }
        assert_eq!(leaf_bounds(&mask), Some((IVec3::new(1, 3, 2), IVec3::new(5, 6, 7))));
        assert_eq!(ones(&mask).collect::<Vec<_>>(), vec![64 + 48 + 2, 320 + 24 + 7]);
        assert_eq!(local(4095, 4), IVec3::splat(15));
        assert_eq!(local(32 * 32 + 2, 5), IVec3::new(1, 0, 2));
    }
}
