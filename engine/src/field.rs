//! Precomputed fields over a medium: optical depth toward a fixed direction on a
//! lattice of nodes, and the sun's transmittance built from it.
//!
//! A field is computed once per cloud and direction and read by trilinear
//! interpolation, so that what would cost a ray march per query (the optical depth
//! toward the sun) costs eight loads. The instant preview reads the sun's
//! transmittance at every march point; the learned models read optical depths as
//! features.
//!
//! Construction ([`optical_depth_sweep`]): the lattice is swept slice by slice along
//! the direction's dominant axis a, starting from the slice where rays along d leave
//! the support. A node x of slice s sees the next slice at y = x + h d,
//! h = spacing_a / |d_a|; tau(x) = the integral of sigma_t over [x, y] (midpoint rule,
//! steps of at most one grid voxel) + tau(y), with tau(y) interpolated bilinearly in
//! the slice already done, and 0 where y has left the support (the density is zero
//! outside). O(nodes x few lookups); the bilinear reads add a little numerical
//! diffusion across d, which the tests bound against ray marching.
//!
//! The sun's transmittance ([`SunTransmittance`]) uses a lattice aligned with the
//! light instead, whose columns follow rays to the sun, so it needs no interpolation
//! while it is built. Parameters: `max_nodes` per axis, >= 2. Memory: 4 bytes per
//! node.

use crate::control::Cancel;
use crate::grid::Bounds3;
use crate::light::Sun;
use crate::medium::Medium;
use glam::{UVec3, Vec3};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, OnceLock};

/// The nodes of a lattice over a medium's support: at most `max_nodes` per axis and
/// at most one per grid voxel plus one; returns (nodes per axis, spacing).
pub fn lattice_over(medium: &Medium, max_nodes: u32) -> (UVec3, Vec3) {
    lattice_over_per_voxel(medium, max_nodes, 1)
}

/// [`lattice_over`] with at most `per_voxel` (>= 1) node spacings per grid voxel.
pub fn lattice_over_per_voxel(medium: &Medium, max_nodes: u32, per_voxel: u32) -> (UVec3, Vec3) {
    let grid = medium.grid();
    let n = (grid.dims() * per_voxel.max(1) + UVec3::ONE).min(UVec3::splat(max_nodes.max(2)));
    let spacing = grid.support_bounds().extent() / (n - UVec3::ONE).as_vec3();
    (n, spacing)
}

/// Optical depth from every node of the lattice (`n` nodes per axis from
/// `support.min`, `spacing` apart) along the unit direction `d` to where the ray
/// leaves the support; node index x + n.x (y + n.y z). The nodes of one slice are
/// computed in parallel; the result does not depend on the thread count. None when
/// `cancel` asks to stop (checked before every slice).
pub fn optical_depth_sweep(
    medium: &Medium,
    support: Bounds3,
    n: UVec3,
    spacing: Vec3,
    d: Vec3,
    cancel: Cancel,
) -> Option<Vec<f32>> {
    let nodes = (n.x * n.y * n.z) as usize;
    let mut tau = vec![0.0f32; nodes];
    let a = d.abs().max_position();
    // The two lateral axes.
    let (b, c) = ((a + 1) % 3, (a + 2) % 3);
    let h = spacing[a] / d[a].abs();
    let voxel = medium.grid().voxel_size().min_element();
    let steps = (h / voxel).ceil().max(1.0) as u32;
    let dt = h / steps as f32;
    let rho = medium.rho();
    let cap = medium.density_cap();
    let idx = |p: [u32; 3]| (p[0] + n.x * (p[1] + n.y * p[2])) as usize;
    // Lateral shift of the upstream point, in nodes of axes b and c.
    let shift_b = h * d[b] / spacing[b];
    let shift_c = h * d[c] / spacing[c];
    let na = n[a];
    let (mb, mc) = ((n[b] - 1) as f32, (n[c] - 1) as f32);
    let mut slice = vec![0.0f32; (n[b] * n[c]) as usize];
    // Slices from the exit side inward; the exit slice itself keeps tau = 0 (rays from
    // it leave the support at once).
    for step in 1..na {
        if cancel.requested() {
            return None;
        }
        let s = if d[a] > 0.0 { na - 1 - step } else { step };
        let s_up = if d[a] > 0.0 { s + 1 } else { s - 1 };
        let done = &tau;
        slice.par_chunks_mut(n[b] as usize).enumerate().for_each(|(j, row)| {
            let j = j as u32;
            for (i, out) in row.iter_mut().enumerate() {
                let i = i as u32;
                let mut p = [0u32; 3];
                p[a] = s;
                p[b] = i;
                p[c] = j;
                let x = support.min + Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32) * spacing;
                let mut sum = 0.0f32;
                for k in 0..steps {
                    sum += medium.grid().lookup(x + d * ((k as f32 + 0.5) * dt)).min(cap);
                }
                let mut t = sum * dt * rho;
                // Upstream value: bilinear in slice s_up at (i + shift_b, j + shift_c).
                let (ub, uc) = (i as f32 + shift_b, j as f32 + shift_c);
                if ub >= 0.0 && uc >= 0.0 && ub <= mb && uc <= mc {
                    let (ib, ic) = ((ub as u32).min(n[b] - 2), (uc as u32).min(n[c] - 2));
                    let (fb, fc) = (ub - ib as f32, uc - ic as f32);
                    let at = |db: u32, dc: u32| {
                        let mut q = [0u32; 3];
                        q[a] = s_up;
                        q[b] = ib + db;
                        q[c] = ic + dc;
                        done[idx(q)]
                    };
                    t += (1.0 - fb) * (1.0 - fc) * at(0, 0)
                        + fb * (1.0 - fc) * at(1, 0)
                        + (1.0 - fb) * fc * at(0, 1)
                        + fb * fc * at(1, 1);
                }
                *out = t;
            }
        });
        for j in 0..n[c] {
            for i in 0..n[b] {
                let mut p = [0u32; 3];
                p[a] = s;
                p[b] = i;
                p[c] = j;
                tau[idx(p)] = slice[(i + n[b] * j) as usize];
            }
        }
    }
    Some(tau)
}

/// A lazily filled lattice's source: the values of the nodes at `positions` into
/// `values` (the same length), each a function of its position alone. It is called
/// with the nodes of one block of 2^3 (a lazy lattice) or one brick of 4^3 (a lattice
/// filled up front) at a time, so that a source that evaluates several points faster
/// together (a network, several rows per pass over its weights) gets them together,
/// and neighbouring nodes' feature lookups meet in the cache.
pub type NodeSource = Arc<dyn Fn(&[Vec3], &mut [f32]) + Send + Sync>;

/// Bits of a node not evaluated yet (a NaN no source returns: sources' values are
/// stored as they come, and a NaN from one is stored as 0).
const UNSET: u32 = u32::MAX;

/// Edge of a lattice brick, in nodes (4^3 nodes, 256 bytes, to a brick).
const LATTICE_BRICK_LOG2: u32 = 2;
const LATTICE_BRICK_NODES: usize = 1 << (3 * LATTICE_BRICK_LOG2);

/// Edge of the block of nodes a lazy lattice evaluates at once, in nodes (2^3 nodes,
/// the corners of a cell's worth): large enough for the source to evaluate its
/// points together (a network several rows per pass over its weights, neighbouring
/// feature lookups in the cache), small enough to waste few nodes where the lookups
/// read a thin shell (the preview's camera-facing skin).
const LAZY_FILL_LOG2: u32 = 1;

/// A brick of nodes: f32 bits each, UNSET until evaluated.
type LatticeBrick = Box<[AtomicU32; LATTICE_BRICK_NODES]>;

/// One value per node of a lattice over a box, read by trilinear interpolation.
///
/// A lattice is either filled up front ([`ScalarLattice::new`]) or lazily
/// ([`ScalarLattice::lazy`]): the nodes are stored in bricks of 4^3, each allocated
/// when a lookup first reads one of its nodes, and the first lookup that reads a node
/// has the source evaluate the block of 2^3 nodes around it at once, which are kept.
/// Where the lookups concentrate (the camera-facing shell of a dense cloud, for the
/// preview) a fine lattice then costs about the nodes that are read, not all of them,
/// in time and in memory. Two threads reading a new node at once may both evaluate
/// it; the source is a function of the position, so they store the same bits, and
/// the values read do not depend on the thread count or the order of the lookups.
pub struct ScalarLattice {
    n: UVec3,
    origin: Vec3,
    spacing: Vec3,
    inv_spacing: Vec3,
    /// Bricks per axis.
    bricks_n: UVec3,
    /// The bricks, x fastest; within one, node x + 4 (y + 4 z).
    bricks: Vec<OnceLock<LatticeBrick>>,
    source: Option<NodeSource>,
    /// A lazy lattice evaluates the blocks of 2^fill_log2 nodes per axis that hold a
    /// node read, in one call of the source each.
    fill_log2: u32,
}

impl ScalarLattice {
    /// `n` nodes per axis (each >= 2) from `origin`, `spacing` apart, with `data` in
    /// node order (x fastest).
    pub fn new(n: UVec3, origin: Vec3, spacing: Vec3, data: Vec<f32>) -> Self {
        assert!(n.min_element() >= 2 && data.len() == (n.x * n.y * n.z) as usize, "a lattice of {n} nodes");
        let l = Self::empty(n, origin, spacing, None);
        for z in 0..n.z {
            for y in 0..n.y {
                for x in 0..n.x {
                    let (brick, i) = l.brick_of(x, y, z);
                    l.bricks[brick].get_or_init(new_brick)[i]
                        .store(data[(x + n.x * (y + n.y * z)) as usize].to_bits(), Ordering::Relaxed);
                }
            }
        }
        l
    }

    /// `n` nodes per axis (each >= 2) from `origin`, `spacing` apart, each evaluated by
    /// `source` at its position when a lookup first reads it or a node of its block.
    pub fn lazy(n: UVec3, origin: Vec3, spacing: Vec3, source: NodeSource) -> Self {
        assert!(n.min_element() >= 2, "a lattice of {n} nodes");
        Self::empty(n, origin, spacing, Some(source))
    }

    fn empty(n: UVec3, origin: Vec3, spacing: Vec3, source: Option<NodeSource>) -> Self {
        let bricks_n = (n + (1 << LATTICE_BRICK_LOG2) - 1) >> LATTICE_BRICK_LOG2;
        let bricks =
            (0..bricks_n.x as usize * bricks_n.y as usize * bricks_n.z as usize).map(|_| OnceLock::new()).collect();
        ScalarLattice {
            n,
            origin,
            spacing,
            inv_spacing: spacing.recip(),
            bricks_n,
            bricks,
            source,
            fill_log2: LAZY_FILL_LOG2,
        }
    }

    /// Nodes per axis.
    pub fn nodes(&self) -> UVec3 {
        self.n
    }

    /// Nodes evaluated so far (all of them for a lattice filled up front).
    pub fn evaluated(&self) -> usize {
        self.bricks
            .iter()
            .filter_map(|b| b.get())
            .map(|b| b.iter().filter(|v| v.load(Ordering::Relaxed) != UNSET).count())
            .sum()
    }

    /// Bytes held: the brick index and the bricks allocated so far (all of them for a
    /// lattice filled up front, those its lookups have read for a lazy one).
    pub fn memory_bytes(&self) -> usize {
        let allocated = self.bricks.iter().filter(|b| b.get().is_some()).count();
        self.bricks.len() * std::mem::size_of::<OnceLock<LatticeBrick>>()
            + allocated * std::mem::size_of::<[AtomicU32; LATTICE_BRICK_NODES]>()
    }

    /// `n` nodes per axis (each >= 2) from `origin`, `spacing` apart, every node
    /// evaluated by `source` now, in parallel (the result does not depend on the
    /// thread count).
    pub fn filled(n: UVec3, origin: Vec3, spacing: Vec3, source: NodeSource) -> Self {
        // Every node is needed: a brick per call of the source.
        let l = ScalarLattice { fill_log2: LATTICE_BRICK_LOG2, ..Self::lazy(n, origin, spacing, source) };
        let bn = l.bricks_n;
        (0..bn.x * bn.y * bn.z).into_par_iter().for_each(|b| {
            let m = (1 << LATTICE_BRICK_LOG2) as u32;
            // Its first node: evaluates the whole brick.
            l.node((b % bn.x) * m, (b / bn.x) % bn.y * m, b / (bn.x * bn.y) * m);
        });
        ScalarLattice { source: None, ..l }
    }

    /// The brick of node (x, y, z) and the node's index within it.
    #[inline(always)]
    fn brick_of(&self, x: u32, y: u32, z: u32) -> (usize, usize) {
        let m = (1 << LATTICE_BRICK_LOG2) - 1;
        let (s, b) = (LATTICE_BRICK_LOG2, self.bricks_n);
        (
            ((x >> s) + b.x * ((y >> s) + b.y * (z >> s))) as usize,
            ((x & m) | (y & m) << s | (z & m) << (2 * s)) as usize,
        )
    }

    /// The value of node (x, y, z), its fill block evaluated now if it was not.
    #[inline]
    fn node(&self, x: u32, y: u32, z: u32) -> f32 {
        let (b, i) = self.brick_of(x, y, z);
        let brick = match self.bricks[b].get() {
            Some(brick) => brick,
            // A lattice filled up front has every brick; a lazy one makes it now.
            None if self.source.is_some() => self.bricks[b].get_or_init(new_brick),
            None => return 0.0,
        };
        let bits = brick[i].load(Ordering::Relaxed);
        if bits != UNSET {
            return f32::from_bits(bits);
        }
        let Some(source) = &self.source else { return 0.0 };
        self.fill_block((x, y, z), self.fill_log2, brick, source);
        f32::from_bits(brick[i].load(Ordering::Relaxed))
    }

    /// Evaluates the nodes of the block of 2^`log2` nodes per axis (within one brick)
    /// around node (x, y, z) that lie in the lattice and are not set yet, in one call
    /// of the source (a NaN stored as 0).
    #[cold]
    fn fill_block(&self, (x, y, z): (u32, u32, u32), log2: u32, brick: &LatticeBrick, source: &NodeSource) {
        debug_assert!(log2 <= LATTICE_BRICK_LOG2);
        let m = (1u32 << log2) - 1;
        let corner = UVec3::new(x & !m, y & !m, z & !m);
        let mut positions = [Vec3::ZERO; LATTICE_BRICK_NODES];
        let mut slots = [0usize; LATTICE_BRICK_NODES];
        let mut count = 0;
        for j in 0..1u32 << (3 * log2) {
            let g = corner + UVec3::new(j & m, (j >> log2) & m, j >> (2 * log2));
            let (_, i) = self.brick_of(g.x, g.y, g.z);
            if g.cmplt(self.n).all() && brick[i].load(Ordering::Relaxed) == UNSET {
                positions[count] = self.origin + g.as_vec3() * self.spacing;
                slots[count] = i;
                count += 1;
            }
        }
        let mut values = [0.0f32; LATTICE_BRICK_NODES];
        source(&positions[..count], &mut values[..count]);
        for (&i, &v) in slots[..count].iter().zip(&values[..count]) {
            let v = if v.is_nan() { 0.0 } else { v };
            brick[i].store(v.to_bits(), Ordering::Relaxed);
        }
    }

    /// Trilinear value at `x` (positions outside the lattice are clamped to it); the
    /// same arithmetic as [`trilinear`].
    #[inline]
    pub fn lookup(&self, x: Vec3) -> f32 {
        let n = self.n;
        let q = ((x - self.origin) * self.inv_spacing).clamp(Vec3::ZERO, (n - UVec3::ONE).as_vec3());
        // q is clamped to >= 0, so truncation is floor.
        let i0 = q.as_uvec3().min(n - UVec3::splat(2));
        let f = q - i0.as_vec3();
        let (x0, y0, z0) = (i0.x, i0.y, i0.z);
        let m = (1 << LATTICE_BRICK_LOG2) - 1;
        if (x0 & m) < m && (y0 & m) < m && (z0 & m) < m {
            // The eight corners in one brick, all evaluated: read them from it.
            let (b, i) = self.brick_of(x0, y0, z0);
            if let Some(brick) = self.bricks[b].get() {
                let (sy, sz) = (1 << LATTICE_BRICK_LOG2, 1 << (2 * LATTICE_BRICK_LOG2));
                let c = [i, i + 1, i + sy, i + sy + 1, i + sz, i + sz + 1, i + sz + sy, i + sz + sy + 1]
                    .map(|j| brick[j].load(Ordering::Relaxed));
                if c.iter().all(|&bits| bits != UNSET) {
                    return lerp_corners(c.map(f32::from_bits), f);
                }
            }
        }
        let (x1, y1, z1) = (x0 + 1, y0 + 1, z0 + 1);
        let c = [
            self.node(x0, y0, z0),
            self.node(x1, y0, z0),
            self.node(x0, y1, z0),
            self.node(x1, y1, z0),
            self.node(x0, y0, z1),
            self.node(x1, y0, z1),
            self.node(x0, y1, z1),
            self.node(x1, y1, z1),
        ];
        lerp_corners(c, f)
    }
}

/// A brick of nodes not evaluated yet.
fn new_brick() -> LatticeBrick {
    Box::new(std::array::from_fn(|_| AtomicU32::new(UNSET)))
}

/// The sun's transmittance over the medium, for one cloud, density scale and sun
/// direction, on a lattice aligned with the light: its axes are two directions
/// across the sunlight and w, the direction toward the sun, so every column of nodes
/// along w follows one ray to the sun and its optical depth is a running integral
/// down the column (midpoint rule, steps of at most one grid voxel), with no
/// interpolation between rays. A lookup interpolates the optical depth trilinearly in
/// the light frame and exponentiates it (interpolating exp(-tau) itself would
/// overestimate between nodes, exp being convex). The lattice covers the support's
/// projection onto the light frame with one node per voxel edge, capped at
/// `max_nodes` per axis (a 128^3 grid under an oblique sun takes about 11 M nodes,
/// 44 MiB).
#[derive(Clone)]
pub struct SunTransmittance {
    /// The light frame: u, v across the light, w toward the sun.
    u: Vec3,
    v: Vec3,
    w: Vec3,
    /// Light-frame coordinates of node (0, 0, 0) and the node spacing per axis.
    min: Vec3,
    inv_spacing: Vec3,
    /// Nodes per axis (u, v, w).
    n: UVec3,
    /// Optical depth toward the sun, index w + n.z (u + n.x v): columns along w
    /// are contiguous.
    tau: Vec<f32>,
}

impl SunTransmittance {
    /// Default nodes per axis (the cap of an oblique sun over a 256^3 grid).
    pub const DEFAULT_MAX_NODES: u32 = 256;

    /// Builds the field for `medium` and `sun` with at most `max_nodes` (>= 2) per
    /// axis; the columns are integrated in parallel and the result does not depend
    /// on the thread count.
    pub fn build(medium: &Medium, sun: &Sun, max_nodes: u32) -> Self {
        Self::build_until(medium, sun, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`SunTransmittance::build`], or None when `cancel` asks to stop (checked before
    /// every column).
    pub fn build_until(medium: &Medium, sun: &Sun, max_nodes: u32, cancel: Cancel) -> Option<Self> {
        let w = -sun.direction();
        let (u, v) = crate::sampling::coordinate_system(w);
        let support = medium.grid().support_bounds();
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for c in 0..8 {
            let p = Vec3::new(
                if c & 1 == 0 { support.min.x } else { support.max.x },
                if c & 2 == 0 { support.min.y } else { support.max.y },
                if c & 4 == 0 { support.min.z } else { support.max.z },
            );
            let q = Vec3::new(p.dot(u), p.dot(v), p.dot(w));
            (lo, hi) = (lo.min(q), hi.max(q));
        }
        let voxel = medium.grid().voxel_size().min_element();
        let extent = (hi - lo).max(Vec3::splat(voxel));
        let n =
            ((extent / voxel).ceil().as_uvec3() + UVec3::ONE).clamp(UVec3::splat(2), UVec3::splat(max_nodes.max(2)));
        let spacing = extent / (n - UVec3::ONE).as_vec3();
        let steps = (spacing.z / voxel).ceil().max(1.0) as u32;
        let dt = spacing.z / steps as f32;
        let mut tau = vec![0.0f32; (n.x * n.y * n.z) as usize];
        // Set when a column was skipped: the field is then incomplete whatever `cancel`
        // says afterwards (a stop request can be cleared).
        let gave_up = AtomicBool::new(false);
        tau.par_chunks_mut(n.z as usize).enumerate().for_each(|(col, column)| {
            if gave_up.load(Ordering::Relaxed) || cancel.requested() {
                gave_up.store(true, Ordering::Relaxed);
                return;
            }
            let (iu, iv) = (col as u32 % n.x, col as u32 / n.x);
            let base = u * (lo.x + iu as f32 * spacing.x) + v * (lo.y + iv as f32 * spacing.y);
            // From the node nearest the sun (w = hi, outside the support) down.
            let mut t = 0.0f32;
            for k in (0..n.z).rev() {
                if k + 1 < n.z {
                    let w_top = lo.z + (k + 1) as f32 * spacing.z;
                    let mut sum = 0.0f32;
                    for s in 0..steps {
                        sum += medium.sigma_t(base + w * (w_top - (s as f32 + 0.5) * dt));
                    }
                    t += sum * dt;
                }
                column[k as usize] = t;
            }
        });
        if gave_up.into_inner() {
            return None;
        }
        Some(SunTransmittance { u, v, w, min: lo, inv_spacing: spacing.recip(), n, tau })
    }

    /// Optical depth toward the sun at `x` (trilinear in the light frame; positions
    /// outside the lattice are clamped to it).
    #[inline]
    pub fn optical_depth(&self, x: Vec3) -> f32 {
        let q = (Vec3::new(x.dot(self.u), x.dot(self.v), x.dot(self.w)) - self.min) * self.inv_spacing;
        // Stored w fastest, then u, then v.
        trilinear(&self.tau, UVec3::new(self.n.z, self.n.x, self.n.y), Vec3::new(q.z, q.x, q.y))
    }

    /// [`SunTransmittance::optical_depth`] at every point of `pts` into `out`, eight
    /// at a time where the CPU has AVX2 (the same bits either way: the same operations
    /// in the same order, no fused multiply-adds).
    pub fn optical_depth_many(&self, pts: &[Vec3], out: &mut [f32]) {
        assert_eq!(pts.len(), out.len(), "one output per point");
        #[cfg(target_arch = "x86_64")]
        if self.tau.len() < i32::MAX as usize && std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is present (checked just now); node indices fit 32 bits.
            return unsafe { self.optical_depth_many_avx2(pts, out) };
        }
        for (o, p) in out.iter_mut().zip(pts) {
            *o = self.optical_depth(*p);
        }
    }

    /// [`SunTransmittance::optical_depth_many`] with AVX2: each lane transforms its
    /// point into the light frame, locates its cell as [`trilinear`] does and gathers
    /// the eight corners.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn optical_depth_many_avx2(&self, pts: &[Vec3], out: &mut [f32]) {
        use std::arch::x86_64::*;
        let full = pts.len() / 8 * 8;
        // The lattice as trilinear sees it: axes (w, u, v), w fastest.
        let n = UVec3::new(self.n.z, self.n.x, self.n.y);
        let (sy, sz) = (n.x as i32, (n.x * n.y) as i32);
        let top = (n - UVec3::ONE).as_vec3();
        let cap = (n - UVec3::splat(2)).as_ivec3();
        let s = |v: f32| _mm256_set1_ps(v);
        let frame = [self.u, self.v, self.w];
        let (zero, tau) = (_mm256_setzero_ps(), self.tau.as_ptr());
        let mut i = 0;
        while i < full {
            let lane = |k: usize| -> [f32; 8] { std::array::from_fn(|j| pts[i + j][k]) };
            // SAFETY: plain loads of stack arrays.
            let (x, y, z) = unsafe {
                let (a, b, c) = (lane(0), lane(1), lane(2));
                (_mm256_loadu_ps(a.as_ptr()), _mm256_loadu_ps(b.as_ptr()), _mm256_loadu_ps(c.as_ptr()))
            };
            // x.dot(u) etc. as glam adds them: (x ux + y uy) + z uz.
            let dot = |a: Vec3| {
                _mm256_add_ps(
                    _mm256_add_ps(_mm256_mul_ps(x, s(a.x)), _mm256_mul_ps(y, s(a.y))),
                    _mm256_mul_ps(z, s(a.z)),
                )
            };
            let q =
                [0, 1, 2].map(|k| _mm256_mul_ps(_mm256_sub_ps(dot(frame[k]), s(self.min[k])), s(self.inv_spacing[k])));
            // Reordered to (w, u, v), clamped to the lattice (glam's max then min).
            let q = [q[2], q[0], q[1]];
            let q = [0, 1, 2].map(|k| _mm256_min_ps(_mm256_max_ps(q[k], zero), s(top[k])));
            let i0 = [0, 1, 2].map(|k| _mm256_min_epi32(_mm256_cvttps_epi32(q[k]), _mm256_set1_epi32(cap[k])));
            let f = [0, 1, 2].map(|k| _mm256_sub_ps(q[k], _mm256_cvtepi32_ps(i0[k])));
            let base = _mm256_add_epi32(
                _mm256_add_epi32(i0[0], _mm256_mullo_epi32(i0[1], _mm256_set1_epi32(sy))),
                _mm256_mullo_epi32(i0[2], _mm256_set1_epi32(sz)),
            );
            // SAFETY: every index is a corner of a cell inside the lattice (< tau.len()).
            let at =
                |off: i32| unsafe { _mm256_i32gather_ps::<4>(tau, _mm256_add_epi32(base, _mm256_set1_epi32(off))) };
            let lerp = |a: __m256, b: __m256, t: __m256| _mm256_add_ps(a, _mm256_mul_ps(_mm256_sub_ps(b, a), t));
            let c00 = lerp(at(0), at(1), f[0]);
            let c10 = lerp(at(sy), at(sy + 1), f[0]);
            let c01 = lerp(at(sz), at(sz + 1), f[0]);
            let c11 = lerp(at(sz + sy), at(sz + sy + 1), f[0]);
            let r = lerp(lerp(c00, c10, f[1]), lerp(c01, c11, f[1]), f[2]);
            // SAFETY: i + 8 <= full <= out.len().
            unsafe { _mm256_storeu_ps(out.as_mut_ptr().add(i), r) };
            i += 8;
        }
        for (o, p) in out[full..].iter_mut().zip(&pts[full..]) {
            *o = self.optical_depth(*p);
        }
    }

    /// Transmittance toward the sun at `x`.
    #[inline]
    pub fn at(&self, x: Vec3) -> f32 {
        (-self.optical_depth(x)).exp()
    }

    /// The direction toward the sun the field was built for.
    pub fn to_sun(&self) -> Vec3 {
        self.w
    }

    /// Nodes per axis (across, across, toward the sun).
    pub fn nodes(&self) -> UVec3 {
        self.n
    }

    pub fn memory_bytes(&self) -> usize {
        self.tau.len() * 4
    }
}

/// Lattices print their size, not their values.
impl std::fmt::Debug for ScalarLattice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let lazy = if self.source.is_some() { ", lazy" } else { "" };
        write!(f, "ScalarLattice({} nodes, {} bytes{lazy})", self.n, self.memory_bytes())
    }
}

impl std::fmt::Debug for SunTransmittance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "SunTransmittance({} nodes toward {}, {} bytes)", self.n, self.w, self.memory_bytes())
    }
}

/// Trilinear interpolation in a lattice of `n` nodes stored x fastest, at lattice
/// coordinates `q` (clamped to the lattice; every axis needs two nodes or more).
#[inline]
fn trilinear(d: &[f32], n: UVec3, q: Vec3) -> f32 {
    trilinear_with(n, q, |i| d[i])
}

/// [`trilinear`] over nodes read by `d` (node index x + n.x (y + n.y z)).
#[inline(always)]
fn trilinear_with(n: UVec3, q: Vec3, d: impl Fn(usize) -> f32) -> f32 {
    let q = q.clamp(Vec3::ZERO, (n - UVec3::ONE).as_vec3());
    // q is clamped to >= 0, so truncation is floor (and no libm call per lookup).
    let i0 = q.as_uvec3().min(n - UVec3::splat(2));
    let f = q - i0.as_vec3();
    let (sx, sy) = (1usize, n.x as usize);
    let sz = sy * n.y as usize;
    let base = i0.x as usize + sy * i0.y as usize + sz * i0.z as usize;
    let c = [
        d(base),
        d(base + sx),
        d(base + sy),
        d(base + sy + sx),
        d(base + sz),
        d(base + sz + sx),
        d(base + sz + sy),
        d(base + sz + sy + sx),
    ];
    lerp_corners(c, f)
}

/// Trilinear interpolation of a cell's corners (x fastest: c[x + 2 y + 4 z]) at the
/// fractional offsets `f`: along x, then y, then z. The one definition every lattice's
/// lookup uses, so their results agree bit for bit.
#[inline(always)]
fn lerp_corners(c: [f32; 8], f: Vec3) -> f32 {
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let c00 = lerp(c[0], c[1], f.x);
    let c10 = lerp(c[2], c[3], f.x);
    let c01 = lerp(c[4], c[5], f.x);
    let c11 = lerp(c[6], c[7], f.x);
    lerp(lerp(c00, c10, f.y), lerp(c01, c11, f.y), f.z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::DensityGrid;
    use crate::phase::PhaseFunction;
    use std::sync::Arc;

    fn blob() -> Medium {
        let grid = DensityGrid::from_fn(UVec3::splat(40), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
            (1.0 - 2.2 * p.length()).clamp(0.0, 1.0) * (1.2 + (9.0 * p.x).sin() * (7.0 * p.z).cos())
        })
        .unwrap();
        Medium::new(Arc::new(grid), 8.0, 1.0, PhaseFunction::Isotropic).unwrap()
    }

    /// The swept transmittance agrees with ray marching toward the sun at random
    /// points of a heterogeneous blob, for an axis-aligned and an oblique sun: mean
    /// absolute difference below 0.01 (a 1 % share of the preview's 5 % error budget
    /// for single scattering) at one node per voxel, and larger with half the nodes
    /// (the error is the lattice's, and shrinks with it); the same bits come out
    /// whatever the thread count.
    #[test]
    fn sweep_matches_ray_marching() {
        let m = blob();
        for dir in [Vec3::new(0.0, -1.0, 0.0), Vec3::new(0.4, -0.8, 0.3)] {
            let sun = Sun::new(dir, Vec3::ONE, 0.0).unwrap();
            let mean_error = |field: &SunTransmittance| {
                let mut rng = crate::rng::Rng::new(2, 0, 0);
                let n = 4000;
                let mut sum = 0.0f64;
                for _ in 0..n {
                    let x = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5;
                    let exact = (-m.optical_depth(x, field.to_sun(), f32::INFINITY, 0.002, f32::INFINITY)).exp();
                    sum += (field.at(x) - exact).abs() as f64;
                }
                sum / n as f64
            };
            let field = SunTransmittance::build(&m, &sun, 64);
            let (fine, coarse) = (mean_error(&field), mean_error(&SunTransmittance::build(&m, &sun, 21)));
            assert!(fine < 0.01, "sun {dir}: mean |dT| {fine:.4}");
            assert!(coarse > fine, "sun {dir}: coarser lattice {coarse:.4} not worse than {fine:.4}");
            let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
            let again = one.install(|| SunTransmittance::build(&m, &sun, 64));
            assert!(field.tau.iter().zip(&again.tau).all(|(a, b)| a.to_bits() == b.to_bits()));
        }
    }

    /// A sun field for a superseded generation, or with a stop requested, is not
    /// built; for the current generation it is the uncancellable build's, bit for bit;
    /// the slice sweep likewise.
    #[test]
    fn a_cancelled_sun_field_is_not_built() {
        use crate::control::RenderControl;
        let m = blob();
        let sun = Sun::new(Vec3::new(0.3, -1.0, 0.2), Vec3::ONE, 0.0).unwrap();
        let control = RenderControl::new();
        let g = control.bump();
        let field = SunTransmittance::build(&m, &sun, 48);
        let current = SunTransmittance::build_until(&m, &sun, 48, Cancel::on(&control, g)).unwrap();
        assert!(field.tau.iter().zip(&current.tau).all(|(a, b)| a.to_bits() == b.to_bits()));
        control.request_stop();
        assert!(SunTransmittance::build_until(&m, &sun, 48, Cancel::on(&control, g)).is_none());
        control.clear_stop();
        control.bump();
        assert!(SunTransmittance::build_until(&m, &sun, 48, Cancel::on(&control, g)).is_none());
        let (nodes, spacing) = lattice_over(&m, 32);
        let sweep = |c| optical_depth_sweep(&m, m.grid().support_bounds(), nodes, spacing, Vec3::Y, c);
        assert!(sweep(Cancel::on(&control, g)).is_none());
        assert!(sweep(Cancel::NEVER).is_some());
    }

    /// The many-point lookup gives the single lookup's bits (AVX2 or not), inside the
    /// lattice, outside it (clamped) and for NaN, for chunks of eight and a tail.
    #[test]
    fn many_sun_lookups_match_single_ones() {
        let m = blob();
        let sun = Sun::new(Vec3::new(0.4, -0.8, 0.3), Vec3::ONE, 0.0).unwrap();
        let field = SunTransmittance::build(&m, &sun, 48);
        let mut rng = crate::rng::Rng::new(3, 0, 0);
        let mut pts: Vec<Vec3> =
            (0..203).map(|_| (Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5) * 1.6).collect();
        pts[5] = Vec3::splat(f32::NAN);
        pts[6] = Vec3::new(9.0, -9.0, 0.0);
        let mut out = vec![0.0f32; pts.len()];
        field.optical_depth_many(&pts, &mut out);
        for (o, p) in out.iter().zip(&pts) {
            assert_eq!(o.to_bits(), field.optical_depth(*p).to_bits(), "at {p}");
        }
    }

    /// Voxels of the largest float are capped in the slice sweep as in sigma_t: its
    /// optical depths stay finite and large behind them (uncapped, the sums overflow
    /// to infinity and the upstream interpolation spreads NaN).
    #[test]
    fn a_huge_density_keeps_the_sweep_finite() {
        let n = 16u32;
        let mut data = vec![0.5f32; (n * n * n) as usize];
        // A block of 4^3 voxels at the largest float around the centre.
        for z in 6..10 {
            for y in 6..10 {
                for x in 6..10 {
                    data[(x + n * (y + n * z)) as usize] = f32::MAX;
                }
            }
        }
        let grid =
            DensityGrid::from_bounds(UVec3::splat(n), data, Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5))).unwrap();
        let m = Medium::new(Arc::new(grid), 40.0, 1.0, PhaseFunction::Isotropic).unwrap();
        let (nodes, spacing) = lattice_over(&m, 64);
        for dir in [Vec3::Y, Vec3::new(0.4, 0.8, 0.3).normalize()] {
            let tau = optical_depth_sweep(&m, m.grid().support_bounds(), nodes, spacing, dir, Cancel::NEVER).unwrap();
            assert!(tau.iter().all(|t| t.is_finite() && *t >= 0.0), "toward {dir}");
            assert!(tau.iter().cloned().fold(0.0f32, f32::max) > 30.0, "toward {dir}: the block is opaque");
        }
    }

    /// Trilinear interpolation reproduces a linear function exactly and clamps
    /// outside the lattice.
    #[test]
    fn lattice_interpolates_linear_functions() {
        let n = UVec3::new(4, 5, 3);
        let (origin, spacing) = (Vec3::new(-1.0, 0.5, 2.0), Vec3::new(0.5, 0.25, 1.0));
        let f = |p: Vec3| 2.0 * p.x - p.y + 0.5 * p.z;
        let mut data = vec![];
        for k in 0..n.z {
            for j in 0..n.y {
                for i in 0..n.x {
                    data.push(f(origin + UVec3::new(i, j, k).as_vec3() * spacing));
                }
            }
        }
        let l = ScalarLattice::new(n, origin, spacing, data);
        let mut rng = crate::rng::Rng::new(4, 0, 0);
        for _ in 0..1000 {
            let p = origin + Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * (n - 1).as_vec3() * spacing;
            assert!((l.lookup(p) - f(p)).abs() < 1e-4, "{p}");
        }
        let far = origin + Vec3::splat(100.0);
        assert!((l.lookup(far) - f(origin + (n - 1).as_vec3() * spacing)).abs() < 1e-4);
    }

    /// A lattice's lookup is the dense trilinear interpolation of its nodes bit for bit,
    /// inside the lattice and clamped outside it, for node counts that fill their
    /// bricks and counts that do not.
    #[test]
    fn lattice_lookup_is_the_dense_interpolation_bit_for_bit() {
        let mut rng = crate::rng::Rng::new(6, 0, 0);
        for n in [UVec3::new(9, 7, 8), UVec3::new(2, 5, 13), UVec3::splat(4)] {
            let (origin, spacing) = (Vec3::new(-1.0, 0.5, 2.0), Vec3::new(0.5, 0.25, 1.0));
            let data: Vec<f32> = (0..n.x * n.y * n.z).map(|_| rng.uniform() * 3.0 - 1.0).collect();
            let l = ScalarLattice::new(n, origin, spacing, data.clone());
            let inv = spacing.recip();
            for _ in 0..5000 {
                // Points across the lattice and up to half its size beyond every face.
                let u = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 2.0 - 0.5;
                let p = origin + u * (n - 1).as_vec3() * spacing;
                assert_eq!(l.lookup(p).to_bits(), trilinear(&data, n, (p - origin) * inv).to_bits(), "{n} {p}");
            }
        }
    }

    /// A lazy lattice reads the same values as one filled up front, bit for bit, with
    /// lookups from any number of threads in any order; it evaluates only the blocks of
    /// 2^3 nodes its lookups read (those holding the 8 corners of each cell touched),
    /// each in one call of the source when read from one thread, and stores a source's
    /// NaN as 0. A lattice filled up front calls its source once per brick.
    #[test]
    fn lazy_lattice_equals_the_filled_one_and_evaluates_what_it_reads() {
        let n = UVec3::new(9, 7, 8);
        let (origin, spacing) = (Vec3::new(-1.0, 0.5, 2.0), Vec3::new(0.5, 0.25, 1.0));
        let f = |p: Vec3| (3.0 * p.x).sin() * p.y + (p.z * p.x).cos();
        let node = |i: u32| origin + UVec3::new(i % n.x, (i / n.x) % n.y, i / (n.x * n.y)).as_vec3() * spacing;
        let filled = ScalarLattice::new(n, origin, spacing, (0..n.x * n.y * n.z).map(|i| f(node(i))).collect());
        // (source calls, nodes evaluated)
        type Counts = Arc<[std::sync::atomic::AtomicUsize; 2]>;
        let lazy = |counts: Counts| {
            ScalarLattice::lazy(
                n,
                origin,
                spacing,
                Arc::new(move |ps: &[Vec3], out: &mut [f32]| {
                    counts[0].fetch_add(1, Ordering::Relaxed);
                    counts[1].fetch_add(ps.len(), Ordering::Relaxed);
                    for (o, p) in out.iter_mut().zip(ps) {
                        *o = f(*p);
                    }
                }),
            )
        };
        let counts = || Counts::new(Default::default());
        let mut rng = crate::rng::Rng::new(5, 0, 0);
        // Points in the lower half of the box along x only.
        let points: Vec<Vec3> = (0..2000)
            .map(|_| {
                let u = Vec3::new(0.45 * rng.uniform(), rng.uniform(), rng.uniform());
                origin + u * (n - 1).as_vec3() * spacing
            })
            .collect();
        let calls = counts();
        let one = lazy(calls.clone());
        assert_eq!(one.evaluated(), 0);
        for p in &points {
            assert_eq!(one.lookup(*p).to_bits(), filled.lookup(*p).to_bits(), "{p}");
        }
        // Cells with x index 0 .. 3 are read: nodes with x index 0 .. 4, in the fill
        // blocks of 2^3 nodes of x index 0 .. 5, whose nodes inside the lattice are
        // 6 x 7 x 8, 3 x 4 x 4 blocks, each in one call.
        let read = 6 * n.y as usize * n.z as usize;
        assert_eq!(one.evaluated(), read);
        assert_eq!(calls[0].load(Ordering::Relaxed), 3 * 4 * 4, "a block evaluated in more than one call");
        assert_eq!(calls[1].load(Ordering::Relaxed), read, "a node evaluated twice from one thread");
        // Only the bricks read are held: of 3 x 2 x 2 bricks of 4^3 nodes, the 2 x 2 x 2
        // that hold nodes 0 .. 4 along x; the index counts all 12.
        let index = 12 * std::mem::size_of::<OnceLock<LatticeBrick>>();
        assert_eq!(one.memory_bytes(), index + 8 * 4 * LATTICE_BRICK_NODES);
        assert_eq!(filled.memory_bytes(), index + 12 * 4 * LATTICE_BRICK_NODES);
        assert_eq!(ScalarLattice::lazy(n, origin, spacing, Arc::new(|_, out| out.fill(1.0))).memory_bytes(), index);
        // From 3 threads, in reverse order: the same values.
        let three = lazy(counts());
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let got: Vec<u32> = pool.install(|| points.par_iter().rev().map(|p| three.lookup(*p).to_bits()).collect());
        let want: Vec<u32> = points.iter().rev().map(|p| filled.lookup(*p).to_bits()).collect();
        assert_eq!(got, want);
        // Filled up front: the same values, one call per brick.
        let calls = counts();
        let eager = ScalarLattice::filled(n, origin, spacing, lazy(calls.clone()).source.clone().unwrap());
        assert_eq!(calls[0].load(Ordering::Relaxed), 12);
        assert_eq!(calls[1].load(Ordering::Relaxed), (n.x * n.y * n.z) as usize);
        for p in &points {
            assert_eq!(eager.lookup(*p).to_bits(), filled.lookup(*p).to_bits(), "{p}");
        }
        // A NaN from the source is stored as 0.
        let nan = ScalarLattice::lazy(UVec3::splat(2), Vec3::ZERO, Vec3::ONE, Arc::new(|_, out| out.fill(f32::NAN)));
        assert_eq!(nan.lookup(Vec3::splat(0.5)), 0.0);
    }
}
