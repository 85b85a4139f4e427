#!/usr/bin/python3
"""Writes the VDB import test fixtures with OpenVDB itself, and their JSON truth.

Run from anywhere (Debian: apt-get install python3-openvdb, which brings numpy):

    /usr/bin/python3 modeler/tests/data/vdb/make_fixtures.py            # into this directory
    /usr/bin/python3 modeler/tests/data/vdb/make_fixtures.py --out DIR  # elsewhere

A plain `python3` works too when it is the interpreter that has pyopenvdb; if it
cannot import pyopenvdb, the script re-runs itself under /usr/bin/python3.

Seven files, each with a `<name>.json` sidecar of its true contents:

- sphere_dense.vdb: smooth dense sphere (1 - (r/R)^2)^2, R = 30 voxels, centred on
  voxel (0, 0, 0); voxel 1/64, no translation (UniformScaleMap); blosc.
- cloud_sparse.vdb: sparse noisy cumulus (union of 8 spheres, fBm falloff, flat
  base); its saturated core of exactly 1.0 is stored as active 8^3 tiles, not voxels;
  voxel 1/128; blosc.
- transformed_zip.vdb: noisy torus evaluated on the index box (10, 5, -20) to
  (78, 33, 48), so its active box starts far from 0; voxel 0.05
  and translation (1.25, -0.5, 2.0) (UniformScaleTranslateMap); zip compression;
  grid class unknown.
- multi_grid.vdb: two grids, `temperature` first (voxel 0.04, a dense 24 x 20 x 20
  block of about 265-302 K) then `density` (voxel 0.02, two merged blobs, max 0.8); both
  translated by (0, 0.1, 0); blosc.
- half_float.vdb: wispy flattened ellipsoid saved as 16-bit half floats
  (grid.saveFloatAsHalf = True: tree type Tree_float_5_4_3_HalfFloat, metadata
  is_saved_as_half_float); voxel 0.02, translation (0, 0.3, 0); blosc.
- half_zip.vdb: the values of half_float.vdb, saved as half floats, as a grid of
  class unknown with zip compression (transcoded like transformed_zip.vdb).
- half_sparse.vdb: half floats, blosc, voxel 0.01, translation (0.5, 0, -0.25): a
  128^3 active tile (in an internal node of 32^3 entries), 8^3 active tiles and
  partial leaves of a box, a noisy blob, three isolated voxels far apart (the active
  box is 232 x 170 x 198), an inactive 8^3 tile and inactive voxels whose values are
  not the background (node compression codes 2, 4 and 5: the inactive values are
  stored as 32-bit floats inside the half-float arrays).

What pyopenvdb can and cannot choose. pyopenvdb.write() has no compression argument
(OpenVDB's io::File::setCompression is not exposed): it always writes blosc + active
mask, the library default. OpenVDB also never zips fog volumes (Archive::
setGridCompression drops zip for them). So transformed_zip.vdb and half_zip.vdb are
written by pyopenvdb with blosc, as grids of class unknown, and then transcoded here:
every value chunk
is unpacked with the system's libblosc (the one OpenVDB links) and packed again as
OpenVDB's zipToStream does (zlib at the default level, stored raw with a negative
size when zlib does not shrink it; half floats as 16-bit values, and an empty
half-float array, for which io::HalfWriter writes nothing, stays empty), the grid's compression flags become zip + active
mask, its file_compression metadata and the per-leaf chunk sizes in its delayed-load
metadata (file_delayed_load) follow, and the grid offsets are rewritten. The
result is then read back by OpenVDB and checked value by value against the blosc file.

Determinism. Everything is generated from fixed seeds with a hash-based value noise
using only +, -, *, / and floor (no libm calls), so the values are the same on every
machine. OpenVDB writes a random UUID into each file header (std::random_device);
the script overwrites it with a UUID derived from the file name (uuid5), so the files
are the same bytes on every run with the same OpenVDB, blosc and zlib.

The sidecars are computed from OpenVDB's own reading of each finished file
(pyopenvdb.readAll), in float64, iterating the active values with iterOnValues()
(a tile counts as the voxels it covers); the grid descriptors, UUID and the map's
stored scale and translation come from the file itself. Grids are listed in file
order (readAll sorts them by name). Fields (per grid):
active_voxel_count (activeVoxelCount()), active_voxel_count_iter (the same counted
by iteration), active_tile_count, leaf_count, index_bbox_active (inclusive),
index_bbox_dim, world_bbox_voxel_centres, world_bbox_cells (centres +- half a voxel),
sum_active, sum_sq_active, mean_active, min_active, max_active, centroid_index and
centroid_world (value-weighted), transform (map_type, is_linear, voxel_size,
translation, index_to_world: row-major 4x4, world = M @ [i, j, k, 1], checked against
OpenVDB's indexToWorld), values_at (value and active state at probe coordinates,
chosen from the data: the first active value equal to the maximum, the active voxel
nearest 0.3, the rounded centroid, the point halfway from the centroid to the box's
maximum corner, the box's minimum corner, a point outside the box, a point inside
the first tile where there are tiles, and points a fixture names: isolated voxels,
inactive voxels with values) and metadata (the grid's metadata as stored).
"""

import argparse
import ctypes
import ctypes.util
import json
import os
import struct
import sys
import uuid
import zlib

try:
    import numpy as np
    import pyopenvdb as vdb
except ImportError:
    debian = "/usr/bin/python3"
    if os.path.realpath(sys.executable) != os.path.realpath(debian) and os.path.exists(debian):
        os.execv(debian, [debian] + sys.argv)
    raise

HERE = os.path.dirname(os.path.abspath(__file__))
LIB = "%d.%d.%d" % tuple(vdb.LIBRARY_VERSION)
GENERATOR = "Nimbus modeler/tests/data/vdb/make_fixtures.py, pyopenvdb " + LIB

# OpenVDB io::Compression flags.
COMPRESS_ZIP, COMPRESS_ACTIVE_MASK, COMPRESS_BLOSC = 0x1, 0x2, 0x4
# io::writeCompressedValues: NO_MASK_AND_ALL_VALS (no active-mask compression).
NO_MASK_AND_ALL_VALS = 6


# ---------------------------------------------------------------- deterministic noise

M32 = np.uint64(0xFFFFFFFF)


def hash3(ix, iy, iz, seed):
    """32-bit integer hash of lattice points (int64 arrays) -> uint64 in [0, 2^32)."""
    u = lambda a: (a.astype(np.int64) & 0xFFFFFFFF).astype(np.uint64)
    h = (u(ix) * np.uint64(0x8DA6B343)) & M32
    h ^= (u(iy) * np.uint64(0xD8163841)) & M32
    h ^= (u(iz) * np.uint64(0xCB1AB31F)) & M32
    h ^= np.uint64((seed * 0x9E3779B9) & 0xFFFFFFFF)
    h ^= h >> np.uint64(16)
    h = (h * np.uint64(0x7FEB352D)) & M32
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x846CA68B)) & M32
    h ^= h >> np.uint64(16)
    return h


def value_noise(x, y, z, seed):
    """Trilinear value noise in [0, 1) with smoothstep fades; float64 arrays."""
    fx, fy, fz = np.floor(x), np.floor(y), np.floor(z)
    ix, iy, iz = fx.astype(np.int64), fy.astype(np.int64), fz.astype(np.int64)
    tx, ty, tz = x - fx, y - fy, z - fz
    tx, ty, tz = tx * tx * (3 - 2 * tx), ty * ty * (3 - 2 * ty), tz * tz * (3 - 2 * tz)
    out = np.zeros_like(x)
    for dz in (0, 1):
        wz = tz if dz else 1 - tz
        for dy in (0, 1):
            wy = ty if dy else 1 - ty
            for dx in (0, 1):
                wx = tx if dx else 1 - tx
                h = hash3(ix + dx, iy + dy, iz + dz, seed)
                out += wx * wy * wz * ((h >> np.uint64(8)).astype(np.float64) / 16777216.0)
    return out


def fbm(x, y, z, seed, octaves=4):
    """Fractal sum of value noise, normalised to [0, 1)."""
    total, amp, norm, f = np.zeros_like(x), 1.0, 0.0, 1.0
    for o in range(octaves):
        total += amp * value_noise(x * f, y * f, z * f, seed + 101 * o)
        norm += amp
        amp *= 0.5
        f *= 2.0
    return total / norm


def lattice(lo, hi):
    """Index coordinates (float64, 'ij' order) of the inclusive box lo..hi."""
    axes = [np.arange(a, b + 1, dtype=np.float64) for a, b in zip(lo, hi)]
    return np.meshgrid(*axes, indexing="ij")


def grid_from(values, lo, name, voxel, translation=None, grid_class=vdb.GridClass.FOG_VOLUME):
    """A FloatGrid holding values (float64, indexed [i][j][k] from lo); zeros are
    inactive background. copyFromArray stores a leaf whose 512 voxels are equal and
    active as a tile."""
    g = vdb.FloatGrid()
    g.name = name
    g.gridClass = grid_class
    g.copyFromArray(values.astype(np.float32), ijk=tuple(lo), tolerance=0)
    t = vdb.createLinearTransform(voxel)
    if translation is not None:
        t.translate(translation)
    g.transform = t
    return g


def clip01(a):
    return np.minimum(np.maximum(a, 0.0), 1.0)


# ------------------------------------------------------------------------- the five files

def sphere_dense():
    r_vox = 30.0
    lo, hi = (-30, -30, -30), (30, 30, 30)
    i, j, k = lattice(lo, hi)
    q = (i * i + j * j + k * k) / (r_vox * r_vox)
    v = np.where(q < 1.0, (1.0 - q) * (1.0 - q), 0.0)
    return [grid_from(v, lo, "density", 1.0 / 64.0)], {"generator": GENERATOR}


CLOUD_SPHERES = [  # centre (voxels), radius (voxels)
    ((0, 0, 0), 26), ((-24, -6, 4), 20), ((24, -4, -3), 21), ((-8, 14, -2), 18),
    ((10, 12, 6), 17), ((-38, -14, 2), 13), ((38, -12, 0), 14), ((2, -10, 16), 15),
]


def cloud_sparse():
    lo, hi = (-56, -28, -32), (56, 40, 32)
    i, j, k = lattice(lo, hi)
    s = np.full_like(i, -1.0)
    for (cx, cy, cz), r in CLOUD_SPHERES:
        d = np.sqrt((i - cx) ** 2 + (j - cy) ** 2 + (k - cz) ** 2)
        s = np.maximum(s, 1.0 - d / r)
    n = fbm(i / 9.0, j / 9.0, k / 9.0, seed=7)
    f = s + 0.5 * (n - 0.5)
    base = clip01((j + 26.0) / 3.0)  # flat bottom at j = -26
    v = clip01(2.4 * f) * base  # exactly 1.0 where 2.4 f >= 1: the core
    v = np.where(v >= 0.02, v, 0.0)
    return [grid_from(v, lo, "density", 1.0 / 128.0)], {"generator": GENERATOR}


def transformed_zip():
    lo = (10, 5, -20)
    major, minor = 24.0, 9.0
    c = (lo[0] + 34, lo[1] + 14, lo[2] + 34)
    hi = (lo[0] + 68, lo[1] + 28, lo[2] + 68)
    i, j, k = lattice(lo, hi)
    q = np.sqrt((i - c[0]) ** 2 + (k - c[2]) ** 2) - major
    d = np.sqrt(q * q + (j - c[1]) ** 2)
    n = fbm(i / 6.0, j / 6.0, k / 6.0, seed=23)
    v = clip01(1.8 * ((1.0 - d / minor) + 0.4 * (n - 0.5)))
    v = np.where(v >= 0.01, v, 0.0)
    g = grid_from(v, lo, "density", 0.05, (1.25, -0.5, 2.0), grid_class=vdb.GridClass.UNKNOWN)
    return [g], {"generator": GENERATOR}


def multi_grid():
    lo_t, hi_t = (-12, -10, -10), (11, 9, 9)
    i, j, k = lattice(lo_t, hi_t)
    n = fbm(i / 5.0, j / 5.0, k / 5.0, seed=41)
    temp = 283.0 - 1.25 * j + 24.0 * (n - 0.5)
    t = grid_from(temp, lo_t, "temperature", 0.04, (0.0, 0.1, 0.0), grid_class=vdb.GridClass.UNKNOWN)
    lo_d, hi_d = (-24, -16, -16), (22, 16, 16)
    i, j, k = lattice(lo_d, hi_d)
    s = np.maximum(
        1.0 - np.sqrt((i + 10) ** 2 + (j + 2) ** 2 + k ** 2) / 12.0,
        1.0 - np.sqrt((i - 9) ** 2 + (j - 3) ** 2 + (k - 2) ** 2) / 10.0,
    )
    n = fbm(i / 5.0, j / 5.0, k / 5.0, seed=43)
    v = 0.8 * clip01(1.6 * (s + 0.4 * (n - 0.5)))
    v = np.where(v >= 0.01, v, 0.0)
    d = grid_from(v, lo_d, "density", 0.02, (0.0, 0.1, 0.0))
    meta = {"generator": GENERATOR, "note": "temperature first; density second", "units_temperature": "kelvin"}
    return [t, d], meta


def half_float(grid_class=vdb.GridClass.FOG_VOLUME):
    lo, hi = (-34, -12, -24), (34, 12, 24)
    i, j, k = lattice(lo, hi)
    e = np.sqrt((i / 32.0) ** 2 + (j / 11.0) ** 2 + (k / 23.0) ** 2)
    n = fbm(i / 6.0, j / 4.0, k / 6.0, seed=59, octaves=5)
    v = 0.9 * clip01(1.5 * ((1.0 - e) + 0.7 * (n - 0.5)))
    v = np.where(v >= 0.01, v, 0.0)
    g = grid_from(v, lo, "density", 0.02, (0.0, 0.3, 0.0), grid_class=grid_class)
    g.saveFloatAsHalf = True
    return [g], {"generator": GENERATOR}


def half_zip():
    return half_float(grid_class=vdb.GridClass.UNKNOWN)


# Points of half_sparse.vdb the sidecar probes besides the data-chosen ones.
HALF_SPARSE_ISOLATED = [((-100, -40, -70), 0.3), ((131, 129, -2), 0.05), ((60, -20, 127), 0.8)]
HALF_SPARSE_PROBES = [
    [-100, -40, -70], [131, 129, -2], [60, -20, 127],  # isolated active voxels
    [0, 0, 0], [127, 127, 127], [64, 100, 3],  # inside the 128^3 tile
    [-66, 7, 9], [-60, 4, 20],  # a partial leaf of the box, an 8^3 tile of it
    [-125, -3, -5],  # the inactive 8^3 tile (value 0.25)
    [-101, 18, -4], [-100, 20, -2],  # leaf with inactive voxels all 0.5 (code 2); its active voxel
    [-93, 19, -7], [-92, 19, -7],  # leaf with inactive 0.5 and 0.25 (code 5)
    [-30, -20, -40],  # inside the blob
]


def half_sparse():
    g = vdb.FloatGrid()
    g.name = "density"
    g.gridClass = vdb.GridClass.FOG_VOLUME
    # A noisy blob from an array: leaves of voxels.
    lo, hi = (-40, -30, -60), (-1, -7, -21)
    i, j, k = lattice(lo, hi)
    c = [(a + b) / 2.0 for a, b in zip(lo, hi)]
    d = np.sqrt(((i - c[0]) / 20.0) ** 2 + ((j - c[1]) / 12.0) ** 2 + ((k - c[2]) / 20.0) ** 2)
    n = fbm(i / 5.0, j / 5.0, k / 5.0, seed=71)
    v = 0.85 * clip01(1.6 * ((1.0 - d) + 0.5 * (n - 0.5)))
    g.copyFromArray(np.where(v >= 0.01, v, 0.0).astype(np.float32), ijk=lo, tolerance=0)
    # sparseFill makes tiles at the largest level that fits: one 128^3 tile (an entry of
    # an internal node of 32^3 entries), and 8^3 tiles plus partial leaves for the box.
    g.fill((0, 0, 0), (127, 127, 127), 0.375, active=True)
    g.fill((-66, 0, 8), (-41, 15, 31), 0.6, active=True)
    acc = g.getAccessor()
    for ijk, value in HALF_SPARSE_ISOLATED:
        acc.setValueOn(ijk, value)
    # Inactive values other than the background: an inactive tile, a leaf whose
    # inactive voxels are all 0.5 (one active voxel), one with inactive 0.5 and 0.25,
    # and blob voxels switched off with value 0.5 (inactive values 0 and 0.5).
    g.fill((-128, -8, -8), (-121, -1, -1), 0.25, active=False)
    g.fill((-104, 16, -8), (-97, 23, -1), 0.5, active=False)
    acc.setValueOn((-100, 20, -2), 0.7)
    g.fill((-96, 16, -8), (-89, 23, -1), 0.5, active=False)
    acc.setValueOn((-90, 22, -3), 0.45)
    acc.setValueOff((-93, 19, -7), 0.25)
    for ijk in ((-30, -20, -40), (-25, -18, -35), (-12, -10, -30)):
        acc.setValueOff(ijk, 0.5)
    t = vdb.createLinearTransform(0.01)
    t.translate((0.5, 0.0, -0.25))
    g.transform = t
    g.saveFloatAsHalf = True
    return [g], {"generator": GENERATOR}


# Voxels thousands of voxels apart: an active box of 3601 x 1101 x 1301 voxels (5.2e9,
# 19 GiB as dense f32), which the importer must hold sparsely.
SPARSE_FAR_ISOLATED = [((-1800, -300, 500), 0.3), ((1800, 800, -800), 0.9), ((7, -5, 3), 0.125)]
SPARSE_FAR_PROBES = [
    [-1800, -300, 500], [1800, 800, -800], [7, -5, 3],  # isolated active voxels
    [-1800, -300, 501], [1799, 800, -800],  # their neighbours (background)
    [128, 0, 0], [255, 127, 127], [200, 64, 3],  # inside the 128^3 tile
    [-40, 0, 0], [-33, 7, 7], [-20, 3, 5],  # the 8^3 tiles and a partial leaf
    [0, 0, 0], [10, 20, 30],  # inside the noisy blob
]


def sparse_far():
    g = vdb.FloatGrid()
    g.name = "density"
    g.gridClass = vdb.GridClass.FOG_VOLUME
    lo, hi = (-8, -8, -8), (40, 40, 40)
    i, j, k = lattice(lo, hi)
    d = np.sqrt(((i - 16) / 24.0) ** 2 + ((j - 16) / 24.0) ** 2 + ((k - 16) / 24.0) ** 2)
    n = fbm(i / 6.0, j / 6.0, k / 6.0, seed=91)
    v = clip01(1.5 * ((1.0 - d) + 0.4 * (n - 0.5)))
    g.copyFromArray(np.where(v >= 0.01, v, 0.0).astype(np.float32), ijk=lo, tolerance=0)
    g.fill((128, 0, 0), (255, 127, 127), 0.5, active=True)
    g.fill((-40, 0, 0), (-17, 7, 7), 0.7, active=True)
    acc = g.getAccessor()
    for ijk, value in SPARSE_FAR_ISOLATED:
        acc.setValueOn(ijk, value)
    g.transform = vdb.createLinearTransform(0.001)
    return [g], {"generator": GENERATOR}


FIXTURES = [
    ("sphere_dense", sphere_dense,
     "Dense smooth sphere (1-(r/R)^2)^2, R = 30 voxels, centred on voxel (0,0,0); "
     "voxel size 1/64, no translation (UniformScaleMap); blosc (the library default)."),
    ("cloud_sparse", cloud_sparse,
     "Cumulus-like union of 8 spheres with fBm noise falloff and a flat base; the saturated "
     "core (exactly 1.0) is stored as active 8^3 tiles; voxel size 1/128; blosc."),
    ("transformed_zip", transformed_zip,
     "Noisy torus in the xz plane (major 24, minor 9 voxels), evaluated on the index box (10,5,-20)..(78,33,48); "
     "voxel 0.05, translation (1.25,-0.5,2.0) = UniformScaleTranslateMap; grid class unknown; "
     "ZIP + active-mask compression (written by pyopenvdb with blosc, value chunks re-packed "
     "with zlib as OpenVDB's zipToStream does)."),
    ("multi_grid", multi_grid,
     "Two grids: 'temperature' (first; voxel 0.04; dense 24x20x20 block, about 265-302 K) and "
     "'density' (second; voxel 0.02; two merged blobs, max 0.8); both translated by (0,0.1,0); "
     "blosc."),
    ("half_float", half_float,
     "Wispy flattened ellipsoid with strong fBm; saved as 16-bit half floats (grid metadata "
     "is_saved_as_half_float = true; values in the sidecar are the half-rounded ones read back); "
     "voxel 0.02, translation (0,0.3,0); blosc."),
    ("half_zip", half_zip,
     "The values of half_float.vdb saved as 16-bit half floats, grid class unknown, ZIP + "
     "active-mask compression (written by pyopenvdb with blosc, value chunks re-packed with "
     "zlib as OpenVDB's zipToStream does); voxel 0.02, translation (0,0.3,0)."),
    ("half_sparse", half_sparse,
     "Saved as 16-bit half floats; blosc; voxel 0.01, translation (0.5,0,-0.25): a 128^3 active "
     "tile, a box of 8^3 active tiles and partial leaves, a noisy blob, three isolated voxels far "
     "apart, an inactive 8^3 tile and inactive voxels with non-background values (node "
     "compression codes 2, 4 and 5)."),
    ("sparse_far", sparse_far,
     "Float32, blosc, voxel 0.001: a 128^3 active tile, 8^3 active tiles and a partial leaf, a "
     "noisy blob, and isolated voxels thousands of voxels apart: an active box of "
     "3601 x 1101 x 1301 voxels (19 GiB as dense f32), imported sparsely."),
]

# Files transcoded from blosc to zip, files saved as half floats, and extra probes.
ZIPPED = ("transformed_zip", "half_zip")
HALF = ("half_float", "half_zip", "half_sparse")
EXTRA_PROBES = {"half_sparse": HALF_SPARSE_PROBES, "sparse_far": SPARSE_FAR_PROBES}


# ------------------------------------------------------------------ reading the file header

class Reader:
    def __init__(self, data, pos=0):
        self.data, self.pos = data, pos

    def take(self, n):
        if self.pos + n > len(self.data):
            raise ValueError("truncated at %d" % self.pos)
        b = self.data[self.pos:self.pos + n]
        self.pos += n
        return b

    def u8(self):
        return self.take(1)[0]

    def u32(self):
        return struct.unpack("<I", self.take(4))[0]

    def i32(self):
        return struct.unpack("<i", self.take(4))[0]

    def i64(self):
        return struct.unpack("<q", self.take(8))[0]

    def string(self):
        return self.take(self.u32()).decode("utf-8")

    def metadata(self):
        """MetaMap as [(name, type, value bytes)]."""
        return [(self.string(), self.string(), self.take(self.u32())) for _ in range(self.u32())]


def write_string(out, s):
    b = s.encode("utf-8")
    out += struct.pack("<I", len(b)) + b


def write_metadata(out, entries):
    out += struct.pack("<I", len(entries))
    for name, ty, value in entries:
        write_string(out, name)
        write_string(out, ty)
        out += struct.pack("<I", len(value)) + value


UUID_AT = 8 + 4 + 4 + 4 + 1  # magic, file version, library major/minor, has-offsets flag


def header(data):
    """File version, library version, UUID, and the grid descriptors (with each grid's
    compression flags); the position after the header's file metadata."""
    r = Reader(data)
    magic = r.take(8)
    file_version, major, minor = r.u32(), r.u32(), r.u32()
    has_offsets = r.u8()
    tag = r.take(36).decode("ascii")
    r.metadata()
    descriptors_at = r.pos
    descriptors = []
    for _ in range(r.i32()):
        d = {"name": r.string(), "type": r.string(), "instance_parent": r.string()}
        d["grid_pos"], d["block_pos"], d["end_pos"] = r.i64(), r.i64(), r.i64()
        g = Reader(data, d["grid_pos"])
        d["compression_flags"] = g.u32()
        g.metadata()
        # The map as stored: (Uniform)ScaleMap writes its scale first, the
        # translate maps their translation and then the scale.
        d["map_type"] = g.string()
        if d["map_type"] in ("UniformScaleTranslateMap", "ScaleTranslateMap"):
            d["translation"] = list(struct.unpack("<3d", g.take(24)))
        elif d["map_type"] in ("UniformScaleMap", "ScaleMap"):
            d["translation"] = [0.0, 0.0, 0.0]
        d["scale"] = list(struct.unpack("<3d", g.take(24))) if "translation" in d else None
        descriptors.append(d)
        r.pos = d["end_pos"]
    return {
        "magic_ok": magic == struct.pack("<q", 0x56444220) and has_offsets == 1,
        "file_version": file_version,
        "library_version": [major, minor],
        "uuid": tag,
        "descriptors_at": descriptors_at,
        "grid_descriptors": descriptors,
    }


def fix_uuid(path, name):
    """Replaces OpenVDB's random header UUID with one derived from the file name."""
    tag = str(uuid.uuid5(uuid.NAMESPACE_URL, "nimbus/modeler/tests/data/vdb/" + name + ".vdb"))
    with open(path, "r+b") as f:
        f.seek(UUID_AT)
        f.write(tag.encode("ascii"))


# ------------------------------------------------------------------- blosc -> zip transcode

def load_blosc():
    for name in ("libblosc.so.1", ctypes.util.find_library("blosc")):
        if name:
            try:
                lib = ctypes.CDLL(name)
            except OSError:
                continue
            lib.blosc_decompress_ctx.restype = ctypes.c_int
            lib.blosc_decompress_ctx.argtypes = [ctypes.c_char_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
            lib.blosc_compress_ctx.restype = ctypes.c_int
            lib.blosc_compress_ctx.argtypes = [
                ctypes.c_int, ctypes.c_int, ctypes.c_size_t, ctypes.c_size_t, ctypes.c_char_p,
                ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_int]
            return lib
    sys.exit("make_fixtures.py: cannot load libblosc (libopenvdb depends on it)")


BLOSC = None


def blosc():
    global BLOSC
    if BLOSC is None:
        BLOSC = load_blosc()
    return BLOSC


def unblosc(chunk, nbytes):
    buf = ctypes.create_string_buffer(max(nbytes, 1))
    got = blosc().blosc_decompress_ctx(chunk, buf, nbytes, 1) if nbytes else 0
    assert got == nbytes, "blosc gave %d bytes where %d are due" % (got, nbytes)
    return buf.raw[:nbytes]


def rebosc(raw):
    """compression::bloscCompress (points/StreamCompression.cc) for buffers of at least
    128 bytes: lz4, level 9, byte shuffle, typesize 4, one block, one thread. None where
    blosc does not make the buffer smaller (OpenVDB then stores it raw)."""
    assert len(raw) >= 128
    dest = ctypes.create_string_buffer(len(raw) + 16)
    n = blosc().blosc_compress_ctx(9, 1, 4, len(raw), raw, dest, len(dest), b"lz4", len(raw), 1)
    return dest.raw[:n] if 0 < n < len(raw) else None


def popcount(mask):
    return sum(bin(b).count("1") for b in mask)


class ZipTranscoder:
    """Copies one grid's tree (Tree_float_5_4_3, file version 224, as io::File writes
    it) with each compressed value array re-packed from blosc to zip; records each
    leaf buffer's chunk size (8-byte size field + payload, nothing for an empty
    half-float array) for the delayed-load metadata. With `half`, the value arrays
    hold 16-bit halves (inactive values, background and root tiles stay 32-bit)."""

    def __init__(self, r, flags, half):
        self.r, self.flags, self.half, self.out = r, flags, half, bytearray()
        self.leaves, self.old_chunks, self.new_chunks = [], [], []

    def copy(self, n):
        self.out += self.r.take(n)

    def values(self, n, active):
        """One io::writeCompressedValues array of n values, `active` of them active;
        returns (old, new) chunk sizes."""
        meta = self.r.u8()
        self.out.append(meta)
        if meta in (2, 4, 5):
            self.copy(4)  # one inactive value
        if meta == 5:
            self.copy(4)  # a second one
        if meta in (3, 4, 5):
            self.copy(n // 8)  # selection mask
        count = active if (self.flags & COMPRESS_ACTIVE_MASK and meta != NO_MASK_AND_ALL_VALS) else n
        if self.half and count == 0:
            return 0, 0  # io::HalfWriter writes nothing, not even a chunk size
        nbytes = (2 if self.half else 4) * count
        size = self.r.i64()
        if size <= 0:
            assert -size == nbytes, "raw chunk of %d bytes where %d are due" % (-size, nbytes)
            raw = self.r.take(nbytes)
        else:
            raw = unblosc(self.r.take(size), nbytes)
        # io::zipToStream: zlib at Z_DEFAULT_COMPRESSION; raw with a negative size
        # when zlib does not make it smaller.
        z = zlib.compress(raw, zlib.Z_DEFAULT_COMPRESSION)
        if len(z) < len(raw):
            self.out += struct.pack("<q", len(z)) + z
        else:
            self.out += struct.pack("<q", -len(raw)) + raw
            z = raw
        return 8 + abs(size), 8 + len(z)

    def internal(self, log2dim):
        n = 1 << (3 * log2dim)
        child_mask = self.r.take(n // 8)
        value_mask = self.r.take(n // 8)
        self.out += child_mask + value_mask
        self.values(n, popcount(value_mask))
        for _ in range(popcount(child_mask)):
            if log2dim == 5:
                self.internal(4)
            else:
                mask = self.r.take(64)  # leaf topology: its value mask
                self.out += mask
                self.leaves.append(popcount(mask))

    def topology(self):
        assert self.r.u32() == 1, "one buffer per node expected"
        self.out += struct.pack("<I", 1)
        self.copy(4)  # background
        tiles, children = self.r.u32(), self.r.u32()
        self.out += struct.pack("<II", tiles, children)
        self.copy(tiles * (12 + 4 + 1))  # origin, value, active
        for _ in range(children):
            self.copy(12)  # origin
            self.internal(5)

    def buffers(self):
        for active in self.leaves:
            mask = self.r.take(64)
            assert popcount(mask) == active
            self.out += mask
            old, new = self.values(512, active)
            self.old_chunks.append(old)
            self.new_chunks.append(new)


def delayed_load(value, old_chunks, new_chunks):
    """io::DelayedLoadMetadata (per-leaf mask codes and chunk sizes) with the chunk
    sizes replaced; checks that the stored sizes are the old ones and that blosc here
    packs them into the very bytes OpenVDB wrote."""
    r = Reader(value)
    count = r.u32()
    assert count == len(old_chunks), "delayed-load metadata for %d leaves, the tree has %d" % (count, len(old_chunks))
    mask_bytes = r.u32()
    mask = struct.pack("<I", mask_bytes) + r.take(mask_bytes if mask_bytes else count)
    size_bytes = r.u32()
    assert size_bytes != 0xFFFFFFFF, "blosc-compressed grids store chunk sizes"
    stored = r.take(size_bytes if size_bytes else 8 * count)
    old = struct.pack("<%dq" % count, *old_chunks)
    assert (unblosc(stored, 8 * count) if size_bytes else stored) == old, "chunk sizes differ from the tree's"
    assert r.pos == len(value)
    if size_bytes:
        assert rebosc(old) == stored, "libblosc here does not reproduce OpenVDB's packing"
    new = struct.pack("<%dq" % count, *new_chunks)
    packed = rebosc(new)
    sizes = struct.pack("<I", len(packed)) + packed if packed else struct.pack("<I", 0) + new
    return struct.pack("<I", count) + mask + sizes


MAP_BYTES = {"UniformScaleMap": 15 * 8, "ScaleMap": 15 * 8,
             "UniformScaleTranslateMap": 18 * 8, "ScaleTranslateMap": 18 * 8}


def compression_string(flags):
    """io::compressionToString."""
    if flags == 0:
        return "none"
    parts = [s for bit, s in ((COMPRESS_ZIP, "zip"), (COMPRESS_BLOSC, "blosc"),
                              (COMPRESS_ACTIVE_MASK, "active values")) if flags & bit]
    return " + ".join(parts)


def transcode_to_zip(src, dst):
    """Writes dst: src with every grid's value chunks zip-compressed instead of blosc,
    as io::File would have written it with setCompression(COMPRESS_ZIP |
    COMPRESS_ACTIVE_MASK)."""
    data = open(src, "rb").read()
    h = header(data)
    out = bytearray(data[:h["descriptors_at"]])
    out += struct.pack("<i", len(h["grid_descriptors"]))
    for d in h["grid_descriptors"]:
        assert d["type"] in ("Tree_float_5_4_3", "Tree_float_5_4_3_HalfFloat") and not d["instance_parent"], d
        write_string(out, d["name"])
        write_string(out, d["type"])
        write_string(out, d["instance_parent"])
        offsets_at = len(out)
        out += struct.pack("<qqq", 0, 0, 0)
        grid_pos = len(out)
        r = Reader(data, d["grid_pos"])
        old_flags = r.u32()
        assert old_flags & COMPRESS_BLOSC, "expected a blosc grid"
        flags = (old_flags & ~COMPRESS_BLOSC) | COMPRESS_ZIP
        meta = r.metadata()
        map_type = r.string()
        transform = r.take(MAP_BYTES[map_type])
        t = ZipTranscoder(r, old_flags, d["type"].endswith("_HalfFloat"))
        t.topology()
        assert r.pos == d["block_pos"], "topology ends at %d, buffers start at %d" % (r.pos, d["block_pos"])
        topology_len = len(t.out)
        t.buffers()
        assert r.pos == d["end_pos"], "buffers end at %d, the grid at %d" % (r.pos, d["end_pos"])
        new_meta = []
        for name, ty, value in meta:
            if name == "file_compression":
                value = compression_string(flags).encode()
            elif ty == "__delayedload":
                value = delayed_load(value, t.old_chunks, t.new_chunks)
            new_meta.append((name, ty, value))
        out += struct.pack("<I", flags)
        write_metadata(out, new_meta)
        write_string(out, map_type)
        out += transform
        block_pos = len(out) + topology_len
        out += t.out
        struct.pack_into("<qqq", out, offsets_at, grid_pos, block_pos, len(out))
    with open(dst, "wb") as f:
        f.write(out)


def all_values(grid):
    return [(it.min, it.max, it.value, it.active) for it in grid.citerAllValues()]


# --------------------------------------------------------------------------- the sidecar

def plain(v):
    """Metadata values as JSON values (tuples become lists)."""
    if isinstance(v, (tuple, list)):
        return [plain(x) for x in v]
    return v


def transform_json(t, d):
    """The transform: matrix entries as the file stores them (descriptor d), checked
    against OpenVDB's own indexToWorld."""
    assert t.typeName == d["map_type"] and d["scale"] is not None, "axis-aligned maps only"
    sc, tr = d["scale"], d["translation"]
    m = [[sc[r] if c == r else 0.0 for c in range(3)] + [tr[r]] for r in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
    for ijk in ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (-7, 13, 29)):
        w = t.indexToWorld(ijk)
        for r in range(3):
            want = sum(m[r][c] * ijk[c] for c in range(3)) + m[r][3]
            assert abs(w[r] - want) <= 1e-12 * max(1.0, abs(want)), (ijk, w, want)
    return {
        "map_type": t.typeName,
        "is_linear": t.isLinear,
        "voxel_size": list(t.voxelSize()),
        "translation": list(t.indexToWorld((0, 0, 0))),
        "index_to_world": m,
    }


def grid_json(g, d, extra_probes=()):
    count = tiles = 0
    total = total_sq = 0.0
    ci = [0.0, 0.0, 0.0]
    vmin, vmax = float("inf"), float("-inf")
    lo, hi = [None] * 3, [None] * 3
    first_max = nearest = first_tile = None
    for it in g.iterOnValues():
        v, n = float(it.value), it.count
        a, b = it.min, it.max
        count += n
        if n > 1:
            tiles += 1
            if first_tile is None:
                first_tile = a
        total += v * n
        total_sq += v * v * n
        for ax in range(3):
            ci[ax] += v * n * (a[ax] + b[ax]) / 2.0
            lo[ax] = a[ax] if lo[ax] is None else min(lo[ax], a[ax])
            hi[ax] = b[ax] if hi[ax] is None else max(hi[ax], b[ax])
        vmin, vmax = min(vmin, v), max(vmax, v)
        if n == 1 and (nearest is None or abs(v - 0.3) < abs(nearest[1] - 0.3)):
            nearest = (a, v)
    for it in g.iterOnValues():
        if float(it.value) == vmax:
            first_max = it.min
            break
    # OpenVDB's own answers must agree with the iteration.
    assert count == g.activeVoxelCount()
    assert [list(c) for c in g.evalActiveVoxelBoundingBox()] == [lo, hi]
    assert tuple(float(x) for x in g.evalMinMax()) == (vmin, vmax)
    ci = [c / total for c in ci]
    t = g.transform
    bbox = [lo, hi]
    centre_probe = [int(np.floor(c + 0.5)) for c in ci]
    off_axis = [int(np.floor((c + h) / 2.0 + 0.5)) for c, h in zip(ci, hi)]
    outside = [hi[0] + 37, hi[1] + 5, lo[2] - 11]
    candidates = [list(first_max), list(nearest[0]), centre_probe, off_axis, lo, outside]
    if first_tile is not None:
        candidates.append([first_tile[0] + 3, first_tile[1] + 5, first_tile[2] + 2])
    candidates += [list(p) for p in extra_probes]
    probes = []
    for p in candidates:
        if p not in probes:
            probes.append(p)
    acc = g.getConstAccessor()
    meta = {k: plain(v) for k, v in sorted(g.metadata.items())}
    return {
        "name": g.name,
        "value_type": g.valueTypeName,
        "grid_class": g.gridClass,
        "background": float(g.background),
        "vector_note": None,
        "saved_as_half": bool(g.saveFloatAsHalf),
        "compression": meta.get("file_compression"),
        "transform": transform_json(t, d),
        "active_voxel_count": g.activeVoxelCount(),
        "active_voxel_count_iter": count,
        "active_tile_count": tiles,
        "leaf_count": g.leafCount(),
        "index_bbox_active": bbox,
        "index_bbox_dim": list(g.evalActiveVoxelDim()),
        "world_bbox_voxel_centres": [list(t.indexToWorld(tuple(lo))), list(t.indexToWorld(tuple(hi)))],
        "world_bbox_cells": [list(t.indexToWorld(tuple(c - 0.5 for c in lo))),
                             list(t.indexToWorld(tuple(c + 0.5 for c in hi)))],
        "sum_active": total,
        "sum_sq_active": total_sq,
        "mean_active": total / count,
        "min_active": vmin,
        "max_active": vmax,
        "centroid_index": ci,
        "centroid_world": list(t.indexToWorld(tuple(ci))),
        "values_at": [{"ijk": p, "value": float(acc.getValue(tuple(p))), "active": bool(acc.isValueOn(tuple(p)))}
                      for p in probes],
        "metadata": meta,
    }


def sidecar(path, name, description):
    data = open(path, "rb").read()
    h = header(data)
    grids, file_meta = vdb.readAll(path)
    # readAll lists grids by name; the sidecar keeps the file's order.
    order = [d["name"] for d in h["grid_descriptors"]]
    grids.sort(key=lambda g: order.index(g.name))
    return {
        "magic_ok": h["magic_ok"],
        "file_version": h["file_version"],
        "library_version": h["library_version"],
        "uuid": h["uuid"],
        "grid_descriptors": [{k: d[k] for k in ("name", "type", "instance_parent", "grid_pos", "block_pos", "end_pos")}
                             for d in h["grid_descriptors"]],
        "file_metadata": {k: plain(v) for k, v in sorted(file_meta.items())},
        "grid_names": [g.name for g in grids],
        "grids": [grid_json(g, d, EXTRA_PROBES.get(name, ())) for g, d in zip(grids, h["grid_descriptors"])],
        "file": name + ".vdb",
        "description": description,
        "written_by": "OpenVDB %s (pyopenvdb, Debian python3-openvdb)" % LIB,
        "file_size_bytes": len(data),
    }


def main():
    ap = argparse.ArgumentParser(description="Write the VDB test fixtures and their JSON truth.")
    ap.add_argument("--out", default=HERE, help="output directory (default: this script's directory)")
    ap.add_argument("--only", nargs="*", help="write only these fixtures (default: all)")
    args = ap.parse_args()
    out_dir = args.out
    os.makedirs(out_dir, exist_ok=True)
    for name, make, description in FIXTURES:
        if args.only and name not in args.only:
            continue
        grids, file_meta = make()
        path = os.path.join(out_dir, name + ".vdb")
        if name in ZIPPED:
            tmp = path + ".blosc.tmp"
            vdb.write(tmp, grids, metadata=file_meta)
            transcode_to_zip(tmp, path)
            blosc_grid, zip_grid = vdb.read(tmp, "density"), vdb.read(path, "density")
            assert all_values(blosc_grid) == all_values(zip_grid), "zip transcode changed the values"
            os.remove(tmp)
        else:
            vdb.write(path, grids, metadata=file_meta)
        fix_uuid(path, name)
        truth = sidecar(path, name, description)
        for d, g in zip(header(open(path, "rb").read())["grid_descriptors"], truth["grids"]):
            want = COMPRESS_ZIP if name in ZIPPED else COMPRESS_BLOSC
            assert d["compression_flags"] & (COMPRESS_ZIP | COMPRESS_BLOSC) == want, (name, d)
            assert g["saved_as_half"] == (name in HALF), (name, g["name"])
            assert d["type"].endswith("_HalfFloat") == (name in HALF), (name, d)
        if name == "cloud_sparse":
            assert truth["grids"][0]["active_tile_count"] > 0, "the cloud's core must be stored as tiles"
        with open(os.path.join(out_dir, name + ".json"), "w") as f:
            f.write(json.dumps(truth, indent=1) + "\n")
        print("%s: %d bytes, %d active voxels" % (
            path, truth["file_size_bytes"], sum(g["active_voxel_count"] for g in truth["grids"])))


if __name__ == "__main__":
    main()
