//! Reading OpenVDB files with `vdb-rs` 0.6, behind a check of our own.
//!
//! vdb-rs 0.6.0 has measured defects that would crash Nimbus on some inputs, so the
//! file's header, grid descriptors, grid metadata, transform type and root node are
//! first parsed here, bounds-checked, and refused with a clear message where vdb-rs
//! would fail:
//! - non-VDB files (its magic check is inverted, it never rejects them);
//! - file versions below 218 (`todo!()`), missing grid offsets (`assert!`);
//! - half-float grids with blosc or zip compression (it loses sync on empty value
//!   arrays and aborts on a huge allocation);
//! - transforms other than (uniform) scale + translation (`panic!`);
//! - tiles at the root level (it drops them silently: the cloud would lose density).
//!
//! The call into vdb-rs then runs under `catch_unwind`, so any panic left becomes an
//! import error too. Sparse data (voxels and tiles of 8^3 and 128^3) is resampled into
//! a dense grid covering the active bounding box.

use engine::DensityGrid;
use glam::{DVec3, IVec3, UVec3};
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
    #[error("{path}: grid '{name}' spans {dims:?} voxels, more than Nimbus holds densely ({max} voxels)")]
    TooLarge { path: String, name: String, dims: [i64; 3], max: u64 },
    #[error("{path}: the VDB reader failed on grid '{name}': {what}")]
    Reader { path: String, name: String, what: String },
}

/// Most voxels an imported dense grid may have (2 GiB of f32).
pub const MAX_DENSE_VOXELS: u64 = 1 << 29;

/// What the importer found, besides the dense grid.
#[derive(Debug)]
pub struct VdbImport {
    pub grid: DensityGrid,
    pub name: String,
    /// Index of the dense grid's voxel (0, 0, 0) in the file's index space.
    pub index_min: IVec3,
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

/// A grid descriptor as the preflight saw it.
#[derive(Debug, Clone)]
struct Descriptor {
    name: String,
    grid_type: String,
    compression: u32,
    half: bool,
    map_type: String,
    root_tiles: u32,
}

struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
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
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn i64(&mut self) -> Result<i64, String> {
        Ok(i64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn string(&mut self) -> Result<String, String> {
        let n = self.u32()? as usize;
        if n > 1 << 20 {
            return Err(format!("string of {n} bytes at offset {}", self.pos));
        }
        Ok(String::from_utf8_lossy(self.take(n)?).into_owned())
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
                // vdb-rs reads these types at their fixed size whatever the stored
                // size says, and would lose its place in the file.
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

fn preflight(data: &[u8]) -> Result<Vec<Descriptor>, (bool, String)> {
    // (is_format_problem, message): format problems are "not a VDB"/"corrupt".
    let corrupt = |e: String| (false, e);
    let mut c = Cursor { data, pos: 0 };
    let magic = c.i64().map_err(|_| (true, String::new()))?;
    if magic != 0x5644_4220 {
        return Err((true, String::new()));
    }
    let version = c.u32().map_err(corrupt)?;
    if !(222..=224).contains(&version) {
        return Err((
            false,
            format!(
                "unsupported: OpenVDB file format version {version}; Nimbus reads versions 222 to 224 (OpenVDB 2 and later)"
            ),
        ));
    }
    let _lib = (c.u32().map_err(corrupt)?, c.u32().map_err(corrupt)?);
    if c.u8().map_err(corrupt)? != 1 {
        return Err((false, "unsupported: file written without grid offsets".into()));
    }
    c.take(36).map_err(corrupt)?; // UUID
    c.metadata().map_err(corrupt)?;
    let count = c.u32().map_err(corrupt)?;
    if count > 10_000 {
        return Err(corrupt(format!("{count} grids")));
    }
    let mut out = Vec::new();
    for _ in 0..count {
        let name = c.string().map_err(corrupt)?;
        let grid_type = c.string().map_err(corrupt)?;
        let _parent = c.string().map_err(corrupt)?;
        let (gp, bp, ep) = (c.i64().map_err(corrupt)?, c.i64().map_err(corrupt)?, c.i64().map_err(corrupt)?);
        let len = data.len() as i64;
        if !(gp > 0 && gp <= bp && bp <= ep && ep <= len) {
            return Err(corrupt(format!("grid '{name}' offsets {gp}/{bp}/{ep} outside the file of {len} bytes")));
        }
        if out.iter().any(|d: &Descriptor| d.name == name) {
            return Err(corrupt(format!("two grids named '{name}'")));
        }
        let mut g = Cursor { data: &data[..bp as usize], pos: gp as usize };
        let compression = g.u32().map_err(corrupt)?;
        let meta = g.metadata().map_err(corrupt)?;
        let half_meta =
            meta.iter().any(|(n, t, v)| n == "is_saved_as_half_float" && t == "bool" && v.first() == Some(&1));
        let half = half_meta || grid_type.ends_with("_HalfFloat");
        let map_type = g.string().map_err(corrupt)?;
        let map_bytes = match map_type.as_str() {
            "UniformScaleMap" | "ScaleMap" => 15 * 8,
            "UniformScaleTranslateMap" | "ScaleTranslateMap" => 18 * 8,
            _ => 0,
        };
        let mut root_tiles = 0;
        if map_bytes > 0 && grid_type.starts_with("Tree_float_5_4_3") {
            g.take(map_bytes).map_err(corrupt)?;
            if half {
                // Half-float trees store 16-bit values only inside compressed value
                // arrays; compressed ones are refused below, raw ones carry no sizes
                // to trust. Only the root tile count matters here.
                g.take(8).map_err(corrupt)?; // buffer count, background (f32)
                root_tiles = g.u32().map_err(corrupt)?;
                out.push(Descriptor { name, grid_type, compression, half, map_type, root_tiles });
                c.pos = ep as usize;
                continue;
            }
            // Walk the whole tree: every mask, value block and compressed chunk must
            // fit where the descriptor says, before vdb-rs allocates from these sizes.
            let mut t = TreeScan {
                c: Cursor { data: &data[..ep as usize], pos: g.pos },
                compression,
                value_size: 4,
                leaves: Vec::new(),
            };
            root_tiles = t.topology().map_err(|e| corrupt(format!("grid '{name}': {e}")))?;
            if t.c.pos != bp as usize {
                return Err(corrupt(format!(
                    "grid '{name}': tree topology ends at {} but its buffers start at {bp}",
                    t.c.pos
                )));
            }
            t.buffers().map_err(|e| corrupt(format!("grid '{name}': {e}")))?;
            if t.c.pos != ep as usize {
                return Err(corrupt(format!("grid '{name}': tree data ends at {} but the grid at {ep}", t.c.pos)));
            }
        }
        out.push(Descriptor { name, grid_type, compression, half, map_type, root_tiles });
        c.pos = ep as usize;
    }
    Ok(out)
}

/// A structural walk of a `Tree_float_5_4_3` as OpenVDB writes it (file versions
/// 222+): root, internal nodes (child mask, value mask, compressed values, children),
/// leaf value masks, then every leaf's buffer. Nothing is decompressed; each size read
/// from the file is checked against the bytes that remain.
struct TreeScan<'a> {
    c: Cursor<'a>,
    compression: u32,
    value_size: usize,
    /// Number of active values of each leaf, in topology order (their buffers follow
    /// in this order).
    leaves: Vec<usize>,
}

fn popcount(mask: &[u8]) -> usize {
    mask.iter().map(|b| b.count_ones() as usize).sum()
}

impl TreeScan<'_> {
    /// Returns the number of root tiles.
    fn topology(&mut self) -> Result<u32, String> {
        let buffers = self.c.u32()?;
        if buffers != 1 {
            return Err(format!("{buffers} buffers per node"));
        }
        self.c.take(self.value_size)?; // background
        let tiles = self.c.u32()?;
        let children = self.c.u32()?;
        if tiles as usize > self.c.data.len() || children as usize > self.c.data.len() {
            return Err(format!("{tiles} root tiles and {children} root children"));
        }
        for _ in 0..tiles {
            self.c.take(12 + self.value_size + 1)?; // origin, value, active
        }
        for _ in 0..children {
            self.c.take(12)?; // origin
            self.internal(5)?;
        }
        Ok(tiles)
    }

    /// An internal node with 2^(3 log2dim) entries; its children are internal nodes of
    /// log2dim 4 (below a 5) or leaves (below a 4).
    fn internal(&mut self, log2dim: u32) -> Result<(), String> {
        let n = 1usize << (3 * log2dim);
        let child_mask = self.c.take(n / 8)?;
        let value_mask = self.c.take(n / 8)?;
        self.values(n, popcount(value_mask))?;
        for _ in 0..popcount(child_mask) {
            if log2dim == 5 {
                self.internal(4)?;
            } else {
                let mask = self.c.take(64)?; // leaf topology: its value mask
                self.leaves.push(popcount(mask));
            }
        }
        Ok(())
    }

    fn buffers(&mut self) -> Result<(), String> {
        for i in 0..self.leaves.len() {
            let active = popcount(self.c.take(64)?);
            if active != self.leaves[i] {
                return Err(format!("leaf {i}: buffer mask differs from the topology's"));
            }
            self.values(512, active)?;
        }
        Ok(())
    }

    /// One compressed value array of `n` values, `active` of them active
    /// (OpenVDB's io::readCompressedValues).
    fn values(&mut self, n: usize, active: usize) -> Result<(), String> {
        let meta = self.c.u8()?;
        if meta > 6 {
            return Err(format!("node compression code {meta}"));
        }
        if matches!(meta, 2 | 4 | 5) {
            self.c.take(self.value_size)?; // one inactive value
        }
        if meta == 5 {
            self.c.take(self.value_size)?; // a second one
        }
        if matches!(meta, 3..=5) {
            self.c.take(n / 8)?; // selection mask
        }
        let count = if self.compression & 0x2 != 0 && meta != 6 { active } else { n };
        let bytes = count * self.value_size;
        if self.compression & 0x5 != 0 {
            // Blosc or zip: an i64 byte count, negative for data stored raw.
            let size = self.c.i64()?;
            let remaining = (self.c.data.len() - self.c.pos) as u64;
            if size.unsigned_abs() > remaining {
                return Err(format!("compressed block of {size} bytes at offset {} with {remaining} left", self.c.pos));
            }
            if size <= 0 {
                if size.unsigned_abs() as usize != bytes {
                    return Err(format!("raw block of {} bytes where {bytes} are due", -size));
                }
                self.c.take(bytes)?;
            } else {
                let chunk = self.c.take(size as usize)?;
                if self.compression & 0x4 != 0 && count > 0 {
                    // Blosc header: the uncompressed size sits at bytes 4..8.
                    let nbytes = chunk.get(4..8).map(|b| u32::from_le_bytes(b.try_into().unwrap()) as usize);
                    if nbytes != Some(bytes) {
                        return Err(format!("blosc block unpacks to {nbytes:?} bytes where {bytes} are due"));
                    }
                }
            }
        } else {
            self.c.take(bytes)?;
        }
        Ok(())
    }
}

/// Routes panics inside vdb-rs to an error instead of the terminal.
fn quiet_panics<T>(f: impl FnOnce() -> T) -> std::thread::Result<T> {
    thread_local!(static QUIET: std::cell::Cell<bool> = const { std::cell::Cell::new(false) });
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(|q| q.get()) {
                previous(info);
            }
        }));
    });
    QUIET.with(|q| q.set(true));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET.with(|q| q.set(false));
    r
}

fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".into())
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
    let descriptors = preflight(data).map_err(|(not_vdb, what)| {
        if not_vdb {
            VdbReadError::NotVdb { path: p.clone() }
        } else if let Some(w) = what.strip_prefix("unsupported: ") {
            VdbReadError::Unsupported { path: p.clone(), what: w.to_string() }
        } else {
            VdbReadError::Corrupt { path: p.clone(), what }
        }
    })?;
    let grids: Vec<(String, String)> = descriptors.iter().map(|d| (d.name.clone(), d.grid_type.clone())).collect();
    let is_float = |d: &Descriptor| d.grid_type == "Tree_float_5_4_3" || d.grid_type == "Tree_float_5_4_3_HalfFloat";
    let chosen = match name {
        Some(n) => descriptors.iter().find(|d| d.name == n),
        None => descriptors
            .iter()
            .find(|d| d.name == "density" && is_float(d))
            .or_else(|| descriptors.iter().find(|d| is_float(d))),
    };
    let available = grids.iter().map(|(n, t)| format!("'{n}' ({t})")).collect::<Vec<_>>().join(", ");
    let Some(d) = chosen else {
        return Err(VdbReadError::NoSuchGrid { path: p, name: name.unwrap_or("density").into(), available });
    };
    let unsupported = |what: String| VdbReadError::Unsupported { path: p.clone(), what };
    if !is_float(d) {
        return Err(unsupported(format!(
            "grid '{}' holds {} values; Nimbus imports float grids (Tree_float_5_4_3)",
            d.name, d.grid_type
        )));
    }
    if d.half && d.compression & 0x5 != 0 {
        return Err(unsupported(format!(
            "grid '{}' is saved as 16-bit half floats with {} compression, which the VDB reader (vdb-rs 0.6) cannot decode; \
             re-save it as 32-bit floats (e.g. pyopenvdb: grid.saveFloatAsHalf = False)",
            d.name,
            if d.compression & 0x4 != 0 { "blosc" } else { "zip" }
        )));
    }
    if !matches!(d.map_type.as_str(), "UniformScaleMap" | "UniformScaleTranslateMap" | "ScaleTranslateMap") {
        return Err(unsupported(format!(
            "grid '{}' has a {} transform; Nimbus imports axis-aligned grids (scale and translation only)",
            d.name, d.map_type
        )));
    }
    if d.root_tiles > 0 {
        return Err(unsupported(format!(
            "grid '{}' has {} tiles at the root level (4096^3 blocks), which the VDB reader would drop",
            d.name, d.root_tiles
        )));
    }
    let reader_err = |what: String| VdbReadError::Reader { path: p.clone(), name: d.name.clone(), what };
    // Collect the active values under catch_unwind.
    let collected = quiet_panics(|| -> Result<_, String> {
        let mut r = vdb_rs::VdbReader::new(std::io::Cursor::new(data)).map_err(|e| e.to_string())?;
        let g = r.read_grid::<f32>(&d.name).map_err(|e| e.to_string())?;
        let (scale, translation) = match &g.transform {
            vdb_rs::Map::UniformScaleMap { scale_values: s, .. } => (DVec3::new(s.x, s.y, s.z), DVec3::ZERO),
            vdb_rs::Map::ScaleTranslateMap { scale_values: s, translation: t, .. } => {
                (DVec3::new(s.x, s.y, s.z), DVec3::new(t.x, t.y, t.z))
            }
        };
        let items: Vec<(IVec3, i32, f32)> = g
            .iter()
            .map(|(pos, v, level)| (IVec3::new(pos.x as i32, pos.y as i32, pos.z as i32), level.scale() as i32, v))
            .collect();
        Ok((scale, translation, items))
    });
    let (scale, translation, items) = match collected {
        Ok(Ok(x)) => x,
        Ok(Err(e)) => return Err(reader_err(e)),
        Err(panic) => {
            return Err(reader_err(format!(
                "the reader crashed ({}); the file is probably corrupt",
                panic_message(&*panic)
            )));
        }
    };
    if items.is_empty() {
        return Err(VdbReadError::Empty { path: p, name: d.name.clone() });
    }
    // Active bounding box (tiles cover edge^3 voxels from their minimum corner).
    let (mut lo, mut hi) = (IVec3::MAX, IVec3::MIN);
    let (mut active, mut tiles, mut sum) = (0u64, 0u64, 0.0f64);
    for &(c, edge, v) in &items {
        if !(v.is_finite() && v >= 0.0) {
            return Err(VdbReadError::BadValue { path: p, name: d.name.clone(), i: c.x, j: c.y, k: c.z, value: v });
        }
        lo = lo.min(c);
        hi = hi.max(c + edge - 1);
        let n = (edge as u64).pow(3);
        active += n;
        tiles += (edge > 1) as u64;
        sum += v as f64 * n as f64;
    }
    let dims64 = (hi - lo).as_i64vec3() + 1;
    if dims64.x as u64 * dims64.y as u64 * dims64.z as u64 > MAX_DENSE_VOXELS {
        return Err(VdbReadError::TooLarge {
            path: p,
            name: d.name.clone(),
            dims: dims64.to_array(),
            max: MAX_DENSE_VOXELS,
        });
    }
    let dims = UVec3::new(dims64.x as u32, dims64.y as u32, dims64.z as u32);
    let mut values = vec![0.0f32; dims.x as usize * dims.y as usize * dims.z as usize];
    let index = |c: IVec3| {
        let r = (c - lo).as_uvec3();
        r.x as usize + dims.x as usize * (r.y as usize + dims.y as usize * r.z as usize)
    };
    for &(c, edge, v) in &items {
        if edge == 1 {
            values[index(c)] = v;
        } else {
            for z in 0..edge {
                for y in 0..edge {
                    for x in 0..edge {
                        values[index(c + IVec3::new(x, y, z))] = v;
                    }
                }
            }
        }
    }
    // OpenVDB voxel (i, j, k) is a point sample at translation + scale * (i, j, k): our
    // grid's origin (minimum corner) is half a voxel before the first centre.
    let origin = translation + scale * (lo.as_dvec3() - 0.5);
    let grid = DensityGrid::new(dims, values, origin.as_vec3(), scale.as_vec3())
        .map_err(|e| VdbReadError::Unsupported { path: p.clone(), what: format!("grid '{}': {e}", d.name) })?;
    Ok(VdbImport {
        grid,
        name: d.name.clone(),
        index_min: lo,
        active_voxels: active,
        active_tiles: tiles,
        sum,
        voxel_size: scale,
        translation,
        grids,
    })
}
