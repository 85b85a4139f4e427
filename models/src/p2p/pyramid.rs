//! The density pyramid of the point-to-point model's features (thesis 6.1.1): the
//! cloud's density filtered by Gaussians of growing width, built once per cloud, so
//! that a filtered density is a point lookup. Octave m has grid spacing
//! h_m = h_0 2^m and levels of width 2 h_m and 2 sqrt(2) h_m (the voxel grid also has
//! h_0 and sqrt(2) h_0, and the raw voxels). A lookup of another width blends the two
//! levels around it so that the blend's variance is exactly s^2 (mipmapping in
//! variance rather than in level). The thesis's feature grids put their points two
//! filter widths apart; the pyramid stores its samples half a width apart, so that
//! trilinear interpolation stays close to the Gaussian everywhere, tails included.
//!
//! A level's stored values are Gaussian-filtered voxel samples; a lookup between
//! them is trilinear, and the trilinear tent adds variance h^2 / 6 on average per
//! axis. Each level is therefore stored with Gaussian variance s^2 - h^2 / 6, so
//! that stored filter and interpolation together have the nominal variance s^2.
//! Going from octave m to m + 1 needs an extra Gaussian of variance 3 (4 - 1/6) h_m^2:
//! a separable convolution evaluated at the coarse centres, which fall halfway
//! between fine ones.

use engine::{Cancel, DensityGrid};
use glam::Vec3;
use rayon::prelude::*;

/// Coarse voxels of padding added around each new level: the filtered density spreads
/// beyond the cloud, and lookups there must see it.
const PAD: i64 = 8;

/// A level's samples: 32-bit floats while the pyramid is built, then (for lookups)
/// 16-bit fixed point, value = q * scale with scale = the level's maximum / 65535.
/// Half the bytes keep a 128^3 cloud's pyramid (28 MiB, not 56) within a 32 MiB
/// last-level cache beside the renderer's own grid, and a lookup is mostly waiting
/// for memory. The rounding error, at most scale / 2 = 7.6e-6 of the level's
/// maximum, is far below what the network resolves (its relative error is about
/// 5 %). Trilinear weights sum to one, so interpolating the integers and scaling
/// once gives the scaled interpolation.
#[derive(Clone, Debug)]
enum Texels {
    F32(Vec<f32>),
    U16 { q: Vec<u16>, scale: f32 },
}

impl Texels {
    /// The samples of a level being built.
    fn f32(&self) -> &[f32] {
        match self {
            Texels::F32(d) => d,
            Texels::U16 { .. } => unreachable!("levels are 32-bit until the pyramid is built"),
        }
    }

    fn bytes(&self) -> usize {
        match self {
            Texels::F32(d) => d.len() * 4,
            Texels::U16 { q, .. } => q.len() * 2,
        }
    }

    /// 16-bit fixed point, rounded to nearest (negative values, which filtering
    /// non-negative densities does not make, clamp to 0).
    fn quantized(&self) -> Texels {
        let Texels::F32(d) = self else { return self.clone() };
        // (The largest value, in parallel: a maximum does not depend on the order.)
        let max = d.par_iter().fold(|| 0.0f32, |m, v| m.max(*v)).reduce(|| 0.0f32, f32::max);
        // (65535 / max, not 1 / scale: a subnormal scale would invert to infinity.)
        let inv = if max > 0.0 { 65535.0 / max } else { 0.0 };
        let (scale, inv) = if inv.is_finite() { (max / 65535.0, inv) } else { (0.0, 0.0) };
        Texels::U16 { q: d.par_iter().map(|v| (v * inv).round().clamp(0.0, 65535.0) as u16).collect(), scale }
    }

    #[inline(always)]
    fn get(&self, i: usize) -> f32 {
        match self {
            Texels::F32(d) => d[i],
            Texels::U16 { q, scale } => q[i] as f32 * scale,
        }
    }
}

/// Trilinear interpolation of the cell whose lowest corner is `d[0]` (rows `sy`,
/// slices `sz` apart).
#[inline(always)]
fn trilinear<T: Copy + Into<f32>>(d: &[T], sy: usize, sz: usize, t: Vec3) -> f32 {
    let d = &d[..sz + sy + 2];
    let v = |j: usize| -> f32 { d[j].into() };
    let lerp = |a: f32, b: f32, w: f32| a + (b - a) * w;
    let c00 = lerp(v(0), v(1), t.x);
    let c10 = lerp(v(sy), v(sy + 1), t.x);
    let c01 = lerp(v(sz), v(sz + 1), t.x);
    let c11 = lerp(v(sz + sy), v(sz + sy + 1), t.x);
    lerp(lerp(c00, c10, t.y), lerp(c01, c11, t.y), t.z)
}

/// One level: values at `origin + (ijk + 0.5) * h`, zero outside.
#[derive(Clone, Debug)]
struct Level {
    origin: Vec3,
    h: Vec3,
    /// 1 / h (a lookup multiplies).
    inv_h: Vec3,
    dims: [usize; 3],
    data: Texels,
}

impl Level {
    /// A level with samples `data` (1 / h derived here, so it always matches h).
    fn new(origin: Vec3, h: Vec3, dims: [usize; 3], data: Texels) -> Self {
        Level { origin, h, inv_h: 1.0 / h, dims, data }
    }

    /// The same grid with other samples.
    fn with_data(&self, dims: [usize; 3], data: Texels) -> Self {
        Level::new(self.origin, self.h, dims, data)
    }

    #[inline]
    fn at(&self, x: i64, y: i64, z: i64) -> f32 {
        let [nx, ny, nz] = self.dims;
        if x < 0 || y < 0 || z < 0 || x >= nx as i64 || y >= ny as i64 || z >= nz as i64 {
            return 0.0;
        }
        self.data.get(x as usize + nx * (y as usize + ny * z as usize))
    }

    /// The interior cell holding `p` (the index of its lowest corner) and the
    /// weights inside it, or None where the cell touches the border or lies outside
    /// (then [`Level::lookup`] handles it).
    #[inline(always)]
    fn cell(&self, p: Vec3) -> Option<(usize, Vec3)> {
        let u = (p - self.origin) * self.inv_h - 0.5;
        // NaN, infinite or so far out that index arithmetic could overflow: not here.
        if !(u.is_finite() && u.abs().max_element() < 1e9) {
            return None;
        }
        // floor by truncation (a libm call on baseline x86-64 otherwise): exact for
        // |u| < 1e9.
        let floor = |v: f32| {
            let t = v as i64;
            t - (v < t as f32) as i64
        };
        let (x, y, z) = (floor(u.x), floor(u.y), floor(u.z));
        let f = Vec3::new(x as f32, y as f32, z as f32);
        let [nx, ny, nz] = self.dims;
        (x >= 0 && y >= 0 && z >= 0 && x + 1 < nx as i64 && y + 1 < ny as i64 && z + 1 < nz as i64)
            .then(|| (x as usize + nx * (y as usize + ny * z as usize), u - f))
    }

    /// Asks the cache for the four lines of the cell at `i` (a hint, no effect on
    /// results), so that many lookups wait for memory together rather than in turn.
    #[inline(always)]
    fn prefetch(&self, i: usize) {
        #[cfg(target_arch = "x86_64")]
        {
            let (sy, sz) = (self.dims[0], self.dims[0] * self.dims[1]);
            for j in [i, i + sy, i + sz, i + sz + sy] {
                let p = match &self.data {
                    Texels::F32(d) => d.get(j).map(|v| v as *const f32 as *const i8),
                    Texels::U16 { q, .. } => q.get(j).map(|v| v as *const u16 as *const i8),
                };
                if let Some(p) = p {
                    // SAFETY: a prefetch of a valid address has no observable effect.
                    unsafe { std::arch::x86_64::_mm_prefetch(p, std::arch::x86_64::_MM_HINT_T0) };
                }
            }
        }
    }

    /// Trilinear interpolation in the interior cell at `i` with weights `t`.
    #[inline(always)]
    fn interpolate(&self, i: usize, t: Vec3) -> f32 {
        let (sy, sz) = (self.dims[0], self.dims[0] * self.dims[1]);
        match &self.data {
            Texels::F32(d) => trilinear(&d[i..], sy, sz, t),
            Texels::U16 { q, scale } => trilinear(&q[i..], sy, sz, t) * scale,
        }
    }

    /// Whether [`Level::interpolate8`] serves this level: 16-bit samples, and every
    /// index (and its +x neighbour) within the gathers' signed 32-bit offsets.
    #[cfg(target_arch = "x86_64")]
    fn simd_ready(&self) -> bool {
        matches!(self.data, Texels::U16 { .. }) && self.dims.iter().product::<usize>() < i32::MAX as usize / 2
    }

    /// Eight lookups at once (AVX2): writes `out[j]` for every lane j whose cell is
    /// interior (interpolated) or has no corner inside (0) and returns those lanes as
    /// a bit mask; the cells that straddle the border are left to [`Level::lookup`]. Bit for bit what [`Level::cell`] and
    /// [`Level::interpolate`] give: the same operations in the same order.
    ///
    /// # Safety
    /// The CPU must have AVX2, and the level must pass [`Level::simd_ready`].
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn interpolate8(&self, p: &[Vec3; 8], out: &mut [f32; 8]) -> u32 {
        use std::arch::x86_64::*;
        let Texels::U16 { q, scale } = &self.data else { return 0 };
        let (nx, ny, nz) = (self.dims[0] as i32, self.dims[1] as i32, self.dims[2] as i32);
        let (sy, sz) = (nx, nx * ny);
        let half = _mm256_set1_ps(0.5);
        let abs_bits = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
        let far = _mm256_set1_ps(1e9);
        let mut ok = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
        let mut interior_all = _mm256_set1_epi32(-1);
        let mut outside_any = _mm256_setzero_si256();
        let mut cell = [_mm256_setzero_si256(); 3];
        let mut t = [_mm256_setzero_ps(); 3];
        for axis in 0..3 {
            let c: [f32; 8] = std::array::from_fn(|j| p[j][axis]);
            // SAFETY: c holds eight floats.
            let v = unsafe { _mm256_loadu_ps(c.as_ptr()) };
            // u = (p - origin) / h - 0.5, as Level::cell computes it.
            let u = _mm256_sub_ps(
                _mm256_mul_ps(_mm256_sub_ps(v, _mm256_set1_ps(self.origin[axis])), _mm256_set1_ps(self.inv_h[axis])),
                half,
            );
            // Finite and |u| < 1e9 (an ordered compare is false for NaN).
            ok = _mm256_and_ps(ok, _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(u, abs_bits), far));
            let i = _mm256_cvtps_epi32(_mm256_floor_ps(u));
            // The corner as the portable path makes it (an integer converted back:
            // +0.0, never -0.0), and the weight u - corner.
            t[axis] = _mm256_sub_ps(u, _mm256_cvtepi32_ps(i));
            let n = [nx, ny, nz][axis];
            let interior = _mm256_and_si256(
                _mm256_cmpgt_epi32(i, _mm256_set1_epi32(-1)),
                _mm256_cmpgt_epi32(_mm256_set1_epi32(n - 1), i),
            );
            interior_all = _mm256_and_si256(interior_all, interior);
            // No corner of the cell inside: the portable lookup's sum of zeros.
            let outside = _mm256_or_si256(
                _mm256_cmpgt_epi32(_mm256_set1_epi32(-1), i),
                _mm256_cmpgt_epi32(i, _mm256_set1_epi32(n - 1)),
            );
            outside_any = _mm256_or_si256(outside_any, outside);
            cell[axis] = i;
        }
        // Zero: not finite, far, or entirely outside (+0.0, as the portable path).
        let zero = _mm256_or_si256(_mm256_xor_si256(_mm256_castps_si256(ok), _mm256_set1_epi32(-1)), outside_any);
        let mask = _mm256_and_si256(_mm256_castps_si256(ok), interior_all);
        let idx = _mm256_add_epi32(
            cell[0],
            _mm256_mullo_epi32(
                _mm256_set1_epi32(nx),
                _mm256_add_epi32(cell[1], _mm256_mullo_epi32(_mm256_set1_epi32(ny), cell[2])),
            ),
        );
        let idx = _mm256_and_si256(idx, mask);
        let base = q.as_ptr() as *const i32;
        // The corners (x, x + 1) of one row in one 32-bit read (little-endian: the
        // lower address in the low half); lanes outside the mask read nothing.
        let row = |off: i32| -> (__m256, __m256) {
            // SAFETY: for a masked-in lane the cell is interior, so both samples of
            // the read lie inside `q`; masked-out lanes are not read.
            let v = unsafe {
                _mm256_mask_i32gather_epi32::<2>(
                    _mm256_setzero_si256(),
                    base,
                    _mm256_add_epi32(idx, _mm256_set1_epi32(off)),
                    mask,
                )
            };
            let lo = _mm256_cvtepi32_ps(_mm256_and_si256(v, _mm256_set1_epi32(0xffff)));
            let hi = _mm256_cvtepi32_ps(_mm256_srli_epi32::<16>(v));
            (lo, hi)
        };
        let lerp = |a: __m256, b: __m256, w: __m256| _mm256_add_ps(a, _mm256_mul_ps(_mm256_sub_ps(b, a), w));
        let (a, b) = row(0);
        let c00 = lerp(a, b, t[0]);
        let (a, b) = row(sy);
        let c10 = lerp(a, b, t[0]);
        let (a, b) = row(sz);
        let c01 = lerp(a, b, t[0]);
        let (a, b) = row(sz + sy);
        let c11 = lerp(a, b, t[0]);
        let v = lerp(lerp(c00, c10, t[1]), lerp(c01, c11, t[1]), t[2]);
        let v = _mm256_and_ps(_mm256_mul_ps(v, _mm256_set1_ps(*scale)), _mm256_castsi256_ps(mask));
        // SAFETY: out holds eight floats.
        unsafe { _mm256_storeu_ps(out.as_mut_ptr(), v) };
        _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_or_si256(mask, zero))) as u32
    }

    /// Trilinear interpolation of the voxel centres, zero outside.
    #[inline]
    fn lookup(&self, p: Vec3) -> f32 {
        if let Some((i, t)) = self.cell(p) {
            return self.interpolate(i, t);
        }
        // The border and outside: per-voxel checks.
        let u = (p - self.origin) * self.inv_h - 0.5;
        // Not finite, or so far out that the index arithmetic could overflow: outside.
        if !(u.is_finite() && u.abs().max_element() < 1e9) {
            return 0.0;
        }
        let f = u.floor();
        let t = u - f;
        let (x, y, z) = (f.x as i64, f.y as i64, f.z as i64);
        let mut v = 0.0;
        for dz in 0..2 {
            let wz = if dz == 0 { 1.0 - t.z } else { t.z };
            for dy in 0..2 {
                let wy = if dy == 0 { 1.0 - t.y } else { t.y };
                for dx in 0..2 {
                    let wx = if dx == 0 { 1.0 - t.x } else { t.x };
                    v += wx * wy * wz * self.at(x + dx, y + dy, z + dz);
                }
            }
        }
        v
    }
}

/// For each of `n_out` output positions j (at input index position `start + step *
/// j`): the first input index and the normalized weights of a Gaussian of variance
/// `var` (input voxels^2) over the indices within 4 standard deviations plus one.
fn gaussian_taps(var: f64, start: f64, step: f64, n_out: usize) -> Vec<(i64, Vec<f32>)> {
    let radius = (4.0 * var.sqrt()).ceil().max(1.0) + 1.0;
    (0..n_out)
        .map(|j| {
            let c = start + step * j as f64;
            let lo = (c - radius).ceil() as i64;
            let hi = (c + radius).floor() as i64;
            let mut w: Vec<f64> = (lo..=hi).map(|i| (-(i as f64 - c).powi(2) / (2.0 * var)).exp()).collect();
            let s: f64 = w.iter().sum();
            w.iter_mut().for_each(|x| *x /= s);
            (lo, w.into_iter().map(|x| x as f32).collect())
        })
        .collect()
}

/// The first input index and the integer step between outputs when every output of
/// `taps` has the same weights and its first tap lies `step` inputs after the
/// previous output's (what [`gaussian_taps`] makes for an integer step), else None.
fn uniform_taps(taps: &[(i64, Vec<f32>)]) -> Option<(i64, usize)> {
    let (lo0, w0) = taps.first()?;
    let step = taps.get(1).map_or(1, |(lo1, _)| lo1 - lo0);
    let same = taps.iter().enumerate().all(|(j, (lo, w))| {
        *lo == lo0 + step * j as i64 && w.iter().map(|v| v.to_bits()).eq(w0.iter().map(|v| v.to_bits()))
    });
    (step >= 1 && same).then_some((*lo0, step as usize))
}

/// Convolves `data` along `axis` with a normalized Gaussian of variance `var` (in
/// input voxels) and resamples: output voxel j sits at input index position
/// `start + step * j`, and `n_out` of them are made.
fn resample_axis(
    data: &[f32],
    dims: [usize; 3],
    axis: usize,
    var: f64,
    start: f64,
    step: f64,
    n_out: usize,
) -> (Vec<f32>, [usize; 3]) {
    let mut out_dims = dims;
    out_dims[axis] = n_out;
    let n_in = dims[axis] as i64;
    // Weights per output position along the axis (the same for every line).
    let taps = gaussian_taps(var, start, step, n_out);
    let total: usize = out_dims.iter().product();
    let mut out = vec![0.0f32; total];
    // Each output value is the same sum in the same order as a line-by-line pass,
    // computed in parallel over output slices (z), so the result is bit for bit the
    // same on any thread count.
    let slice_len = out_dims[0] * out_dims[1];
    if axis == 2 {
        // Along z: output slice j is a weighted sum of whole input slices.
        let plane = dims[0] * dims[1];
        out.par_chunks_mut(slice_len).zip(taps.par_iter()).for_each(|(slice, (lo, w))| {
            for (k, wk) in w.iter().enumerate() {
                let i = lo + k as i64;
                if i >= 0 && i < n_in {
                    let src = &data[i as usize * plane..(i as usize + 1) * plane];
                    for (o, v) in slice.iter_mut().zip(src) {
                        *o += wk * v;
                    }
                }
            }
        });
    } else if axis == 1 {
        // Along y: output row j of a z slice is a weighted sum of whole input rows
        // (the taps in the same order as along a line, so the same sums).
        let (row, in_slice) = (dims[0], dims[0] * dims[1]);
        out.par_chunks_mut(slice_len).enumerate().for_each(|(z, slice)| {
            let src = &data[z * in_slice..(z + 1) * in_slice];
            for (dst, (lo, w)) in slice.chunks_mut(row).zip(&taps) {
                for (k, wk) in w.iter().enumerate() {
                    let i = lo + k as i64;
                    if i >= 0 && i < n_in {
                        let src = &src[i as usize * row..(i as usize + 1) * row];
                        for (o, v) in dst.iter_mut().zip(src) {
                            *o += wk * v;
                        }
                    }
                }
            }
        });
    } else if let Some((lo0, step)) = uniform_taps(&taps) {
        // Along x with one weight vector for every output (a Gaussian centred at the
        // same fraction of a voxel for each): outputs eight at a time over a copy of
        // the line padded with zeros, each summing its taps in order from the first,
        // as a line-by-line pass does. A tap outside the input adds +0, which leaves
        // the sum as it was (x + 0 = x for every x but -0, and a sum begun at +0 never
        // becomes -0), so the bits are those of skipping it. The eight sums are
        // independent and do not wait on each other's additions, where one line's
        // sums, output by output, wait on every addition in turn.
        let w = &taps[0].1;
        let (row_out, len) = (out_dims[0], dims[0] as i64);
        // Output o reads input lo0 + step o + k, held at padded[step o + k]; the line
        // is padded to whole blocks of eight outputs, the last block's spare ones
        // computed and not stored.
        let blocks = row_out.div_ceil(8);
        let plen = step * (8 * blocks - 1) + w.len();
        let (i0, i1) = (lo0.max(0), (lo0 + plen as i64).min(len));
        out.par_chunks_mut(slice_len).enumerate().for_each(|(z, slice)| {
            // The positions outside the input stay 0 for every line.
            let mut padded = vec![0.0f32; plen];
            for (l, dst) in slice.chunks_mut(row_out).enumerate() {
                let line = z * dims[1] + l;
                let src = &data[line * dims[0]..(line + 1) * dims[0]];
                if i0 < i1 {
                    padded[(i0 - lo0) as usize..(i1 - lo0) as usize].copy_from_slice(&src[i0 as usize..i1 as usize]);
                }
                match step {
                    1 => blocks_of_eight(&padded, w, 1, dst),
                    2 => blocks_of_eight(&padded, w, 2, dst),
                    _ => blocks_of_eight(&padded, w, step, dst),
                }
            }
        });
    } else {
        // Along x: each line is contiguous; the taps inside the input, in order.
        let row_out = out_dims[0];
        out.par_chunks_mut(slice_len).enumerate().for_each(|(z, slice)| {
            for (l, dst) in slice.chunks_mut(row_out).enumerate() {
                let line = z * dims[1] + l;
                let src = &data[line * dims[0]..(line + 1) * dims[0]];
                for (o, (lo, w)) in dst.iter_mut().zip(&taps) {
                    let k0 = (-lo).clamp(0, w.len() as i64) as usize;
                    let k1 = (n_in - lo).clamp(0, w.len() as i64) as usize;
                    let mut v = 0.0f32;
                    if k0 < k1 {
                        let first = (lo + k0 as i64) as usize;
                        for (wk, x) in w[k0..k1].iter().zip(&src[first..first + (k1 - k0)]) {
                            v += wk * x;
                        }
                    }
                    *o = v;
                }
            }
        });
    }
    (out, out_dims)
}

/// Outputs of one line along x, eight at a time: output o sums `w[k] *
/// padded[step o + k]` over k in order, from +0. Always inlined, so that a call with
/// a literal step (the blurs' 1, the octaves' 2) is compiled for that step: the eight
/// products of a tap become one vector load (or two and a shuffle) and one multiply
/// and add, where a step known only at run time reads its inputs one by one.
#[inline(always)]
fn blocks_of_eight(padded: &[f32], w: &[f32], step: usize, dst: &mut [f32]) {
    for (b, block) in dst.chunks_mut(8).enumerate() {
        let o = step * 8 * b;
        let mut acc = [0.0f32; 8];
        for (k, wk) in w.iter().enumerate() {
            let src = &padded[o + k..o + k + 7 * step + 1];
            for (j, a) in acc.iter_mut().enumerate() {
                *a += wk * src[step * j];
            }
        }
        block.copy_from_slice(&acc[..block.len()]);
    }
}

/// [`resample_axis`] line by line, as the definition of its sums (tests compare the
/// two bit for bit).
#[cfg(test)]
fn resample_axis_by_lines(data: &[f32], dims: [usize; 3], axis: usize, taps: &[(i64, Vec<f32>)]) -> Vec<f32> {
    let mut out_dims = dims;
    out_dims[axis] = taps.len();
    let stride = |d: [usize; 3], a: usize| [1, d[0], d[0] * d[1]][a];
    let mut out = vec![0.0f32; out_dims.iter().product()];
    let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
    for ia in 0..dims[a] {
        for ib in 0..dims[b] {
            let base_in = ia * stride(dims, a) + ib * stride(dims, b);
            let base_out = ia * stride(out_dims, a) + ib * stride(out_dims, b);
            for (j, (lo, w)) in taps.iter().enumerate() {
                let mut v = 0.0f32;
                for (k, wk) in w.iter().enumerate() {
                    let i = lo + k as i64;
                    if i >= 0 && i < dims[axis] as i64 {
                        v += wk * data[base_in + i as usize * stride(dims, axis)];
                    }
                }
                out[base_out + j * stride(out_dims, axis)] = v;
            }
        }
    }
    out
}

/// Which pyramid levels a filter width reads, and how they blend.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LevelBlend {
    lo: usize,
    hi: usize,
    f: f32,
}

/// The two levels of the pyramid with level widths `stds` (increasing) and the blend
/// weight of filter width `std` ([`DensityPyramid::select`]).
fn select_in(stds: &[f32], std: f32) -> LevelBlend {
    let i = stds.partition_point(|s| *s <= std);
    if i == 0 {
        return LevelBlend { lo: 0, hi: 0, f: 0.0 };
    }
    let last = stds.len() - 1;
    if i > last {
        return LevelBlend { lo: last, hi: last, f: 0.0 };
    }
    let (a, b) = (stds[i - 1], stds[i]);
    // Variance-matched blend: (1 - f) a^2 + f b^2 = std^2. A width that is a
    // level's own reads that level alone (the same value, half the lookups).
    let f = ((std * std - a * a) / (b * b - a * a)).clamp(0.0, 1.0);
    if f == 0.0 {
        return LevelBlend { lo: i - 1, hi: i - 1, f: 0.0 };
    }
    LevelBlend { lo: i - 1, hi: i, f }
}

/// The Gaussian pyramid of a density grid (values in density units, before rho).
#[derive(Clone, Debug)]
pub struct DensityPyramid {
    levels: Vec<Level>,
    /// Nominal filter width of each level (increasing).
    stds: Vec<f32>,
}

/// Means of `f`^3 blocks of voxels (the last blocks cut by the bounds count the
/// voxels outside as zero), x fastest, in parallel over the output.
fn block_average(grid: &DensityGrid, f: u32) -> Vec<f32> {
    let n = grid.dims();
    let d = (n + (f - 1)) / f;
    let inv = 1.0 / (f as f64).powi(3);
    (0..d.x as usize * d.y as usize * d.z as usize)
        .into_par_iter()
        .map(|i| {
            let (x, y, z) = (
                (i % d.x as usize) as u32,
                ((i / d.x as usize) % d.y as usize) as u32,
                (i / (d.x as usize * d.y as usize)) as u32,
            );
            let lo = glam::UVec3::new(x, y, z) * f;
            let hi = (lo + f).min(n);
            let mut sum = 0.0f64;
            for vz in lo.z..hi.z {
                for vy in lo.y..hi.y {
                    for vx in lo.x..hi.x {
                        sum += grid.voxel(vx, vy, vz) as f64;
                    }
                }
            }
            (sum * inv) as f32
        })
        .collect()
}

impl DensityPyramid {
    /// Builds levels until one's filter is wider than `max_std` (world units).
    pub fn new(grid: &DensityGrid, max_std: f32) -> Self {
        Self::build(grid, max_std, None, u32::MAX, Cancel::NEVER).expect("never cancelled")
    }

    /// [`DensityPyramid::new`] for lookups at the filter widths `widths` alone (up to
    /// the largest): the levels that their [`DensityPyramid::select`] blends read are
    /// made as `new` makes them, bit for bit; the others are left empty (no samples:
    /// a lookup through one reads 0), which skips their filtering and their memory.
    pub fn for_widths(grid: &DensityGrid, widths: &[f32]) -> Self {
        Self::for_widths_until(grid, widths, u32::MAX, Cancel::NEVER).expect("never cancelled")
    }

    /// [`DensityPyramid::for_widths`] on block averages of `grid` with at most
    /// `max_axis` samples per axis ([`DensityPyramid::block_factor`]), or None when
    /// `cancel` asks to stop (it is checked between the passes of the filters, a few
    /// milliseconds apart at 128^3). A coarse binding of a cloud (the window's first
    /// look) then filters an eighth of the voxels or fewer: its finest features see
    /// the block averages, the wider ones are unchanged.
    pub fn for_widths_until(grid: &DensityGrid, widths: &[f32], max_axis: u32, cancel: Cancel) -> Option<Self> {
        let max_std = widths.iter().fold(0.0f32, |m, w| m.max(*w));
        Self::build(grid, max_std, Some(widths), max_axis, cancel)
    }

    /// The block size (voxels per axis, a power of two) the pyramid of a grid of
    /// `dims` voxels starts from: the least that leaves at most `max_axis` blocks per
    /// axis and at most 256^3 blocks in all (so that the finest level stays within
    /// 64 MiB).
    pub fn block_factor(dims: glam::UVec3, max_axis: u32) -> u32 {
        let mut f = 1u32;
        let blocks = |f: u32| (dims + (f - 1)) / f;
        let fits = |f: u32| {
            let c = blocks(f);
            c.max_element() <= max_axis.max(1) && c.x as u64 * c.y as u64 * c.z as u64 <= 1 << 24
        };
        while !fits(f) && f < 1 << 16 {
            f *= 2;
        }
        f
    }

    fn build(grid: &DensityGrid, max_std: f32, widths: Option<&[f32]>, max_axis: u32, cancel: Cancel) -> Option<Self> {
        let f = Self::block_factor(grid.dims(), max_axis);
        let (d, h0, values) = if f == 1 {
            (grid.dims(), grid.voxel_size(), grid.to_dense_vec())
        } else {
            ((grid.dims() + (f - 1)) / f, grid.voxel_size() * f as f32, block_average(grid, f))
        };
        let hmax = h0.max_element();
        let tent = 1.0 / 6.0;
        let raw = Level::new(grid.origin(), h0, [d.x as usize, d.y as usize, d.z as usize], Texels::F32(values));
        // Filters `level` (stored variance `from` in its voxels^2) to stored variance
        // `to` on the same grid.
        let stop = || cancel.requested();
        let blur = |level: &Level, from: f64, to: f64| {
            let (mut data, mut dims) = (level.data.f32().to_vec(), level.dims);
            for axis in 0..3 {
                if stop() {
                    return None;
                }
                (data, dims) = resample_axis(&data, dims, axis, to - from, 0.0, 1.0, dims[axis]);
            }
            Some(level.with_data(dims, Texels::F32(data)))
        };
        // Octave 0: the voxel grid, padded, stored with the variance of its base
        // width 2h.
        let base = 4.0 - tent;
        let (mut data, mut dims) = (raw.data.f32().to_vec(), raw.dims);
        for axis in 0..3 {
            if stop() {
                return None;
            }
            let n_out = dims[axis] + 2 * PAD as usize;
            (data, dims) = resample_axis(&data, dims, axis, base, -(PAD as f64), 1.0, n_out);
        }
        let mut octaves = vec![Level::new(grid.origin() - h0 * PAD as f32, h0, dims, Texels::F32(data))];
        let mut s = 2.0 * hmax;
        while s < max_std.max(hmax) && octaves.len() < 40 {
            let prev = octaves.last().unwrap();
            let (mut data, mut dims) = (prev.data.f32().to_vec(), prev.dims);
            for axis in 0..3 {
                if stop() {
                    return None;
                }
                // Coarse centre J sits at fine index position 2 (J - PAD) + 0.5; the
                // stored variance grows from `base` h^2 to `base` (2h)^2.
                let n_out = prev.dims[axis].div_ceil(2) + 2 * PAD as usize;
                (data, dims) = resample_axis(&data, dims, axis, 3.0 * base, 0.5 - 2.0 * PAD as f64, 2.0, n_out);
            }
            let h = prev.h * 2.0;
            octaves.push(Level::new(prev.origin - h * PAD as f32, h, dims, Texels::F32(data)));
            s *= 2.0;
        }
        // The raw voxels (the tent alone: width h / sqrt(6)); on the voxel grid the
        // widths h and sqrt(2) h; then each octave's base width 2 h_m and, toward
        // the next octave, 2 sqrt(2) h_m on the same grid.
        let sqrt2 = std::f32::consts::SQRT_2;
        let n_oct = octaves.len();
        let mut stds = vec![hmax * tent.sqrt() as f32, hmax, sqrt2 * hmax];
        for (m, level) in octaves.iter().enumerate() {
            let h = level.h.max_element();
            stds.push(2.0 * h);
            if m + 1 < n_oct {
                stds.push(2.0 * sqrt2 * h);
            }
        }
        // Which levels the asked widths read (all of them without a list).
        let mut needed = vec![widths.is_none(); stds.len()];
        for w in widths.unwrap_or(&[]) {
            let s = select_in(&stds, *w);
            (needed[s.lo], needed[s.hi]) = (true, true);
        }
        let empty = |level: &Level| level.with_data([0; 3], Texels::F32(Vec::new()));
        let made = |i: usize, make: &dyn Fn() -> Option<Level>, like: &Level| {
            if needed[i] { make() } else { Some(empty(like)) }
        };
        let mut levels = vec![
            made(0, &|| Some(raw.clone()), &raw)?,
            made(1, &|| blur(&raw, 0.0, 1.0 - tent), &raw)?,
            made(2, &|| blur(&raw, 0.0, 2.0 - tent), &raw)?,
        ];
        for (m, level) in octaves.into_iter().enumerate() {
            let half = if m + 1 < n_oct {
                Some(made(levels.len() + 1, &|| blur(&level, base, 8.0 - tent), &level)?)
            } else {
                None
            };
            levels.push(if needed[levels.len()] { level } else { empty(&level) });
            levels.extend(half);
        }
        Some(DensityPyramid { levels, stds })
    }

    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// Bytes held by the levels.
    pub fn bytes(&self) -> usize {
        self.levels.iter().map(|l| l.data.bytes()).sum()
    }

    /// The same pyramid with 16-bit samples (see [`Texels`]): what features are
    /// computed from, for data sets and rendering alike.
    pub fn quantized(&self) -> Self {
        let levels = self.levels.iter().map(|l| l.with_data(l.dims, l.data.quantized())).collect();
        DensityPyramid { levels, stds: self.stds.clone() }
    }

    /// Whether the samples are 16-bit.
    pub fn is_quantized(&self) -> bool {
        self.levels.iter().all(|l| matches!(l.data, Texels::U16 { .. }))
    }

    /// The density at `p` filtered by a Gaussian of standard deviation `std` (world
    /// units). Widths below the raw voxels' read them; widths beyond the coarsest
    /// level read that level.
    #[inline]
    pub fn lookup(&self, p: Vec3, std: f32) -> f32 {
        self.lookup_in(self.select(std), p)
    }

    /// The two levels and the blend weight of filter width `std` (computed once for
    /// many lookups of one width).
    #[inline]
    pub fn select(&self, std: f32) -> LevelBlend {
        select_in(&self.stds, std)
    }

    /// [`DensityPyramid::lookup_in`] for many points: `out[i]` for `points[i]`. All
    /// cells are located and prefetched first, then interpolated, so that the cache
    /// misses of a level's points overlap (a lookup in a large pyramid is mostly
    /// waiting for memory).
    pub fn lookup_many(&self, sel: LevelBlend, points: &[Vec3], out: &mut [f32]) {
        assert_eq!(points.len(), out.len(), "one output per point");
        #[cfg(target_arch = "x86_64")]
        if self.levels[sel.lo].simd_ready()
            && self.levels[sel.hi].simd_ready()
            && std::arch::is_x86_feature_detected!("avx2")
        {
            // SAFETY: AVX2 is present (checked just now), and both levels are 16-bit
            // with indices that fit the gathers' 32-bit offsets.
            return unsafe { self.lookup_many_avx2(sel, points, out) };
        }
        self.lookup_many_portable(sel, points, out)
    }

    /// [`DensityPyramid::lookup_many`] eight points at a time with AVX2: each lane
    /// locates its cell, and four 32-bit gathers fetch the cell's eight 16-bit
    /// corners (a 32-bit read at a corner takes its +x neighbour with it). The
    /// arithmetic is the portable path's, operation for operation and without fused
    /// multiply-adds, so the results are the same to the bit (tested); lanes whose
    /// cell touches the border or lies outside take the portable lookup.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn lookup_many_avx2(&self, sel: LevelBlend, points: &[Vec3], out: &mut [f32]) {
        let levels = if sel.lo == sel.hi { 1 } else { 2 };
        let pick = [sel.lo, sel.hi];
        let weight = if levels == 1 { [1.0, 0.0] } else { [1.0 - sel.f, sel.f] };
        for (pc, oc) in points.chunks(8).zip(out.chunks_mut(8)) {
            // A short last chunk repeats its last point in the spare lanes.
            let lanes: [Vec3; 8] = std::array::from_fn(|j| pc[j.min(pc.len() - 1)]);
            let mut x = [[0.0f32; 8]; 2];
            for l in 0..levels {
                let level = &self.levels[pick[l]];
                // SAFETY: AVX2 is enabled in this function; the level is 16-bit.
                let inside = unsafe { level.interpolate8(&lanes, &mut x[l]) };
                for (j, p) in pc.iter().enumerate() {
                    if inside & (1 << j) == 0 {
                        x[l][j] = level.lookup(*p);
                    }
                }
            }
            for (j, o) in oc.iter_mut().enumerate() {
                let mut v = 0.0;
                for l in 0..levels {
                    v += weight[l] * x[l][j];
                }
                *o = v;
            }
        }
    }

    /// The portable [`DensityPyramid::lookup_many`]: all cells of a chunk are located
    /// and prefetched first, then interpolated.
    fn lookup_many_portable(&self, sel: LevelBlend, points: &[Vec3], out: &mut [f32]) {
        const CHUNK: usize = 32;
        assert_eq!(points.len(), out.len(), "one output per point");
        let levels = if sel.lo == sel.hi { 1 } else { 2 };
        let pick = [sel.lo, sel.hi];
        let weight = if levels == 1 { [1.0, 0.0] } else { [1.0 - sel.f, sel.f] };
        for (pc, oc) in points.chunks(CHUNK).zip(out.chunks_mut(CHUNK)) {
            let mut cells = [[None; CHUNK]; 2];
            for l in 0..levels {
                let level = &self.levels[pick[l]];
                for (c, p) in cells[l].iter_mut().zip(pc) {
                    *c = level.cell(*p);
                    if let Some((i, _)) = *c {
                        level.prefetch(i);
                    }
                }
            }
            for (j, (o, p)) in oc.iter_mut().zip(pc).enumerate() {
                let mut v = 0.0;
                for l in 0..levels {
                    let level = &self.levels[pick[l]];
                    let x = match cells[l][j] {
                        Some((i, t)) => level.interpolate(i, t),
                        None => level.lookup(*p),
                    };
                    v += weight[l] * x;
                }
                *o = v;
            }
        }
    }

    /// The filtered density at `p` for a width chosen by [`DensityPyramid::select`].
    #[inline]
    pub fn lookup_in(&self, sel: LevelBlend, p: Vec3) -> f32 {
        if sel.lo == sel.hi {
            return self.levels[sel.lo].lookup(p);
        }
        (1.0 - sel.f) * self.levels[sel.lo].lookup(p) + sel.f * self.levels[sel.hi].lookup(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The interior fast path of the trilinear lookup and the checked one give the
    /// same values, inside, on the border cells and outside the level.
    #[test]
    fn fast_trilinear_matches_the_checked_one() {
        let dims = [5usize, 4, 6];
        let data: Vec<f32> = (0..dims[0] * dims[1] * dims[2]).map(|i| ((i * 37) % 11) as f32 + 0.25).collect();
        let level = Level::new(Vec3::new(-0.3, 0.1, 0.2), Vec3::new(0.5, 0.25, 0.4), dims, Texels::F32(data));
        let quantized = level.with_data(dims, level.data.quantized());
        for level in [level, quantized] {
            trilinear_matches_checked(&level);
        }
    }

    fn trilinear_matches_checked(level: &Level) {
        let checked = |p: Vec3| {
            let u = (p - level.origin) / level.h - 0.5;
            let f = u.floor();
            let t = u - f;
            let (x, y, z) = (f.x as i64, f.y as i64, f.z as i64);
            let mut v = 0.0;
            for (dz, wz) in [(0, 1.0 - t.z), (1, t.z)] {
                for (dy, wy) in [(0, 1.0 - t.y), (1, t.y)] {
                    for (dx, wx) in [(0, 1.0 - t.x), (1, t.x)] {
                        v += wx * wy * wz * level.at(x + dx, y + dy, z + dz);
                    }
                }
            }
            v
        };
        let mut rng = engine::Rng::new(3, 0, 0);
        let (mut inside, mut border) = (0, 0);
        for _ in 0..20_000 {
            let u = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1.4 - 0.2;
            let p = level.origin + u * level.h * Vec3::new(5.0, 4.0, 6.0);
            let (a, b) = (level.lookup(p), checked(p));
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{p}: {a} vs {b}");
            let q = (p - level.origin) / level.h - 0.5;
            if q.cmpge(Vec3::ZERO).all() && (q + 1.0).cmplt(Vec3::new(5.0, 4.0, 6.0)).all() {
                inside += 1
            } else {
                border += 1
            }
        }
        assert!(inside > 1000 && border > 1000, "{inside} {border}");
    }

    /// The many-point lookup (AVX2 for 16-bit samples where the CPU has it, else the
    /// prefetching portable one) gives exactly the single lookups, for one level and
    /// for blends, with points inside, on the border, outside, infinite and NaN, in
    /// full chunks of eight and a short last one, with 32-bit and 16-bit samples; the
    /// 16-bit lookups are within half a step of the largest level (max / 65535 / 2,
    /// plus float rounding) of the 32-bit ones.
    #[test]
    fn many_point_lookups_match_single_ones() {
        #[cfg(target_arch = "x86_64")]
        println!("AVX2 lookups: {}", std::arch::is_x86_feature_detected!("avx2"));
        let grid = DensityGrid::from_fn(
            glam::UVec3::splat(20),
            engine::Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
            |p| (1.0 - 2.2 * p.length()).max(0.0) * (1.0 + (9.0 * p.x).sin()),
        )
        .unwrap();
        let full = DensityPyramid::new(&grid, 2.0);
        let half = full.quantized();
        assert!(half.is_quantized() && !full.is_quantized());
        assert!(half.bytes() * 2 == full.bytes(), "{} vs {}", half.bytes(), full.bytes());
        let mut rng = engine::Rng::new(4, 0, 0);
        let mut points: Vec<Vec3> =
            (0..75).map(|_| (Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5) * 1.3).collect();
        points[7] = Vec3::NAN;
        // Far enough out that index arithmetic on it would overflow: outside, 0.
        points[8] = Vec3::splat(1e30);
        points[9] = Vec3::splat(-1e30);
        points[10] = Vec3::new(f32::NEG_INFINITY, 0.0, 0.0);
        points[11] = Vec3::new(0.0, 0.0, f32::INFINITY);
        // The largest step of any level.
        let step = half
            .levels
            .iter()
            .map(|l| match l.data {
                Texels::U16 { scale, .. } => scale,
                Texels::F32(_) => unreachable!(),
            })
            .fold(0.0f32, f32::max);
        assert!(step > 0.0);
        let mut worst = 0.0f32;
        for std in [0.001, 0.05, 0.07, 0.3, 5.0] {
            let mut looked = vec![];
            for pyramid in [&full, &half] {
                let sel = pyramid.select(std);
                let mut many = vec![f32::NAN; points.len()];
                pyramid.lookup_many(sel, &points, &mut many);
                // The portable path, whatever the dispatch picked (AVX2 for the 16-bit
                // pyramid where the CPU has it).
                let mut portable = vec![f32::NAN; points.len()];
                pyramid.lookup_many_portable(sel, &points, &mut portable);
                for ((p, m), q) in points.iter().zip(&many).zip(&portable) {
                    assert_eq!(m.to_bits(), pyramid.lookup_in(sel, *p).to_bits(), "std {std} at {p}");
                    assert_eq!(m.to_bits(), q.to_bits(), "std {std} at {p}: dispatched vs portable");
                }
                assert!(many.iter().filter(|v| **v > 0.0).count() > 10, "std {std}: {many:?}");
                looked.push(many);
            }
            for (i, (a, b)) in looked[0].iter().zip(&looked[1]).enumerate() {
                if a.is_finite() {
                    let d = (a - b).abs();
                    worst = worst.max(d);
                    assert!(d <= 0.5 * step + 1e-6 * a.abs(), "std {std}, point {i}: {a} vs 16-bit {b} (step {step})");
                } else {
                    assert_eq!(a.to_bits(), b.to_bits());
                }
            }
        }
        // Rounding really happened (the test sees the 16-bit samples).
        assert!(worst > 0.01 * step, "worst difference {worst}, step {step}");
    }

    /// A pyramid made for some filter widths reads, at those widths, exactly what the
    /// whole pyramid reads (quantized too, as the cloud-aware model's features use
    /// it), holds fewer samples, and leaves out the levels no width reads.
    #[test]
    fn pyramid_for_some_widths_reads_the_same_at_them() {
        let grid = DensityGrid::from_fn(
            glam::UVec3::splat(24),
            engine::Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
            |p| (1.0 - 2.2 * p.length()).max(0.0) * (1.0 + (9.0 * p.x).sin()),
        )
        .unwrap();
        let h = 1.0 / 24.0;
        // A level's own width, between levels, below the raw voxels and beyond the top.
        let widths = [0.5 * h, h, 2.7 * h, 4.0 * h, 11.0 * h, 0.2 * h, 40.0 * h];
        let full = DensityPyramid::new(&grid, 40.0 * h).quantized();
        let some = DensityPyramid::for_widths(&grid, &widths).quantized();
        assert_eq!(full.levels(), some.levels());
        assert!(some.bytes() < full.bytes(), "{} vs {}", some.bytes(), full.bytes());
        let mut rng = engine::Rng::new(5, 0, 0);
        let points: Vec<Vec3> =
            (0..203).map(|_| (Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5) * 1.2).collect();
        let mut read = vec![false; full.levels()];
        for w in widths {
            let (a, b) = (full.select(w), some.select(w));
            assert_eq!((a.lo, a.hi, a.f.to_bits()), (b.lo, b.hi, b.f.to_bits()), "width {w}");
            (read[a.lo], read[a.hi]) = (true, true);
            let (mut x, mut y) = (vec![0.0; points.len()], vec![0.0; points.len()]);
            full.lookup_many(a, &points, &mut x);
            some.lookup_many(b, &points, &mut y);
            assert!(x.iter().zip(&y).all(|(x, y)| x.to_bits() == y.to_bits()), "width {w}");
            assert!(x.iter().any(|v| *v > 0.0), "width {w} reads the cloud");
        }
        for (i, r) in read.iter().enumerate() {
            assert_eq!(some.levels[i].data.bytes() > 0, *r, "level {i}: kept only if read");
        }
    }

    /// The block size the pyramid starts from: the least power of two within the
    /// samples per axis asked for and within 256^3 samples in all.
    #[test]
    fn block_factor_keeps_within_both_limits() {
        let f = |d: [u32; 3], max_axis| DensityPyramid::block_factor(glam::UVec3::from_array(d), max_axis);
        assert_eq!(f([96; 3], u32::MAX), 1);
        assert_eq!(f([96; 3], 96), 1);
        assert_eq!(f([96; 3], 64), 2);
        assert_eq!(f([96, 40, 20], 48), 2);
        assert_eq!(f([97; 3], 48), 4);
        assert_eq!(f([256; 3], u32::MAX), 1);
        assert_eq!(f([257, 256, 256], u32::MAX), 2);
        assert_eq!(f([1024; 3], 512), 4);
        assert_eq!(f([5; 3], 0), 8);
    }

    /// A pyramid limited to fewer samples per axis than the grid's voxels is the
    /// pyramid of the grid's block averages, bit for bit (the blocks placed where the
    /// voxels they average are); a cancelled build gives nothing.
    #[test]
    fn a_coarse_pyramid_is_that_of_the_block_averages() {
        let bounds = engine::Bounds3::new(Vec3::new(-0.5, -0.3, -0.4), Vec3::new(0.5, 0.3, 0.4));
        let cloud = |p: Vec3| (1.0 - 2.2 * p.length()).max(0.0) * (1.0 + (9.0 * p.x).sin());
        let grid = DensityGrid::from_fn(glam::UVec3::new(30, 18, 24), bounds, cloud).unwrap();
        let h = 1.0 / 30.0;
        let widths = [0.5 * h, 1.5 * h, 3.0 * h, 7.0 * h];
        let coarse = DensityPyramid::for_widths_until(&grid, &widths, 16, Cancel::NEVER).unwrap();
        let averages = DensityGrid::new(
            glam::UVec3::new(15, 9, 12),
            block_average(&grid, 2),
            grid.origin(),
            grid.voxel_size() * 2.0,
        )
        .unwrap();
        let direct = DensityPyramid::for_widths(&averages, &widths);
        assert_eq!(coarse.levels(), direct.levels());
        let mut rng = engine::Rng::new(8, 0, 0);
        let points: Vec<Vec3> =
            (0..101).map(|_| (Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5) * 1.1).collect();
        for w in widths {
            let (a, b) = (coarse.select(w), direct.select(w));
            let (mut x, mut y) = (vec![0.0; points.len()], vec![0.0; points.len()]);
            coarse.lookup_many(a, &points, &mut x);
            direct.lookup_many(b, &points, &mut y);
            assert!(x.iter().zip(&y).all(|(x, y)| x.to_bits() == y.to_bits()), "width {w}");
            assert!(x.iter().any(|v| *v > 0.0), "width {w} reads the cloud");
        }
        // Fewer samples than the full-resolution pyramid (padding included).
        let full = DensityPyramid::for_widths(&grid, &widths).bytes();
        assert!(coarse.bytes() * 2 < full, "{} / {full}", coarse.bytes());
        let control = engine::RenderControl::new();
        let stale = control.generation();
        control.bump();
        assert!(DensityPyramid::for_widths_until(&grid, &widths, 64, Cancel::on(&control, stale)).is_none());
        assert!(DensityPyramid::for_widths_until(&grid, &widths, 64, Cancel::on(&control, stale + 1)).is_some());
    }

    /// The separable filter, vectorized along rows and slices, makes exactly the sums
    /// of its line-by-line definition, along each axis, for a filter and resampling
    /// like an octave's (halving, padded) and a blur's (same grid), for a step of 3,
    /// and for taps that differ from output to output.
    #[test]
    fn resampling_matches_the_line_by_line_sums() {
        let dims = [13usize, 9, 11];
        let mut rng = engine::Rng::new(6, 0, 0);
        let data: Vec<f32> = (0..dims.iter().product::<usize>()).map(|_| rng.uniform()).collect();
        for axis in 0..3 {
            for (var, start, step, n_out) in
                // (A step of 1.5 gives taps that differ from output to output: the
                // general path along x.)
                [
                    (3.8, -8.0, 1.0, dims[axis] + 16),
                    (11.5, 0.5 - 16.0, 2.0, 23),
                    (0.8, 0.0, 1.0, dims[axis]),
                    (2.0, 0.25, 1.5, 8),
                    // An integer step other than the blurs' 1 and the octaves' 2.
                    (4.0, -2.0, 3.0, 7),
                ]
            {
                let (fast, out_dims) = resample_axis(&data, dims, axis, var, start, step, n_out);
                let taps = gaussian_taps(var, start, step, n_out);
                assert_eq!(uniform_taps(&taps).is_some(), step != 1.5, "step {step}");
                let slow = resample_axis_by_lines(&data, dims, axis, &taps);
                assert_eq!(out_dims[axis], n_out);
                assert!(fast.iter().zip(&slow).all(|(a, b)| a.to_bits() == b.to_bits()), "axis {axis}, var {var}");
                assert!(fast.iter().any(|v| *v > 0.0));
            }
        }
    }
}
