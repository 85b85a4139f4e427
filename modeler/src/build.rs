//! Growing the sphere hierarchy and evaluating the density field.

use crate::params::{CloudParams, ParamError};
use engine::{Bounds3, DensityGrid, Rng};
use glam::{UVec3, Vec3};
use noise::{Fbm, MultiFractal, NoiseFn, Perlin};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sphere {
    pub center: Vec3,
    pub radius: f32,
}

/// Bins of sphere indices over the cloud box, so a density lookup only visits the
/// spheres that can influence it.
const BINS: usize = 32;

/// The bin index along one axis of a box coordinate (clamped to the bins).
fn bin_coord(x: f32) -> usize {
    (((x + 0.5) * BINS as f32).floor() as i64).clamp(0, BINS as i64 - 1) as usize
}

/// Smooth union of sphere distances, independent of which far spheres are listed:
/// start from the nearest sphere (distance m), blend in, in list order, the others
/// within `k` of it, and never go below m - k / 4 (a chain of polynomial smooth
/// minima would otherwise keep sinking as more lobes overlap). The running value only
/// decreases, so a sphere more than `k` beyond the nearest never changes the result,
/// and binning spheres by reach is exact.
#[inline]
fn union_distance(spheres: impl Iterator<Item = Sphere>, p: Vec3, k: f32) -> f32 {
    // Distances are computed once; bins rarely hold more than a few dozen spheres.
    let mut buf = [0.0f32; 128];
    let mut spill = Vec::new();
    let mut n = 0;
    let (mut m, mut arg) = (f32::INFINITY, usize::MAX);
    for s in spheres {
        let di = (p - s.center).length() - s.radius;
        if n < buf.len() {
            buf[n] = di;
        } else {
            spill.push(di);
        }
        if di < m {
            m = di;
            arg = n;
        }
        n += 1;
    }
    let mut d = m;
    for (j, &di) in buf[..n.min(buf.len())].iter().chain(spill.iter()).enumerate() {
        if j != arg && di < m + k {
            d = smooth_min(d, di, k);
        }
    }
    d.max(m - 0.25 * k)
}

/// Worley (cellular) noise: distance to the nearest of one jittered feature point per
/// integer cell, mapped to [-1, 1] (-1 at a feature point). Billowy when subtracted.
/// Written here because `noise::Worley` holds an `Rc` and cannot be shared between
/// the threads that voxelize.
pub struct Cellular {
    seed: u64,
    frequency: f32,
}

impl Cellular {
    /// Squared distance from `p` (in cells) to the feature point of cell `cell`.
    #[inline]
    fn feature_distance2(&self, cell: Vec3, p: Vec3) -> f32 {
        let h = engine::rng::mix64(
            self.seed
                ^ (cell.x as i64 as u64).wrapping_mul(0x9E37_79B9)
                ^ (cell.y as i64 as u64).wrapping_mul(0x85EB_CA6B_0000)
                ^ (cell.z as i64 as u64).wrapping_mul(0xC2B2_AE35_0000_0000),
        );
        let jitter = Vec3::new((h & 0xFFFF) as f32, ((h >> 16) & 0xFFFF) as f32, ((h >> 32) & 0xFFFF) as f32) / 65536.0;
        (cell + jitter - p).length_squared()
    }

    #[inline]
    fn get(&self, p: Vec3) -> f32 {
        let p = p * self.frequency;
        let base = p.floor();
        let f = p - base;
        let feature = |o: Vec3| self.feature_distance2(base + o, p);
        // The own cell first; a neighbour can only win if its box is nearer than the
        // best point so far, which skips most of the 26 hashes.
        let mut best = feature(Vec3::ZERO);
        for dz in -1i32..=1 {
            for dy in -1i32..=1 {
                for dx in -1i32..=1 {
                    if dx == 0 && dy == 0 && dz == 0 {
                        continue;
                    }
                    let gap = |o: i32, fa: f32| match o {
                        -1 => fa,
                        1 => 1.0 - fa,
                        _ => 0.0,
                    };
                    let box_d2 = gap(dx, f.x).powi(2) + gap(dy, f.y).powi(2) + gap(dz, f.z).powi(2);
                    if box_d2 < best {
                        best = best.min(feature(Vec3::new(dx as f32, dy as f32, dz as f32)));
                    }
                }
            }
        }
        // Nearest-point distances rarely exceed ~1 cell; map [0, 1] to [-1, 1].
        (2.0 * best.sqrt() - 1.0).clamp(-1.0, 1.0)
    }
}

/// A cloud ready to be sampled: the fitted hierarchy plus its noises.
pub struct CloudModel {
    params: CloudParams,
    spheres: Vec<Sphere>,
    base_y: Option<f32>,
    bins: Vec<Vec<u32>>,
    /// How far from a sphere's surface a listed sphere can still make density
    /// (displacement + advection + the union's blend allowance).
    reach: f32,
    /// Bins that lie, warp and displacement included, at least `falloff` inside one
    /// sphere (and above the base): their density is 1 before interior noise, and no
    /// sphere needs to be visited. Most of a cloud's interior.
    solid: Vec<bool>,
    displacement: Fbm<Perlin>,
    worley: Cellular,
    warp: [Fbm<Perlin>; 3],
    interior: Fbm<Perlin>,
}

/// Smooth minimum (polynomial, width k): exactly min(a, b) once |a - b| >= k.
#[inline]
fn smooth_min(a: f32, b: f32, k: f32) -> f32 {
    if k <= 0.0 {
        return a.min(b);
    }
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b + (a - b) * h - k * h * (1.0 - h)
}

#[inline]
fn smoothstep(x: f32) -> f32 {
    let t = x.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn grow(params: &CloudParams) -> (Vec<Sphere>, Option<f32>) {
    let mut rng = Rng::new(params.seed, 0x5EED_C10D, 0);
    let mut spheres: Vec<Sphere> = Vec::new();
    // Roots form a chain on the ground plane: each grows from a random earlier root at
    // a distance below the sum of their radii, so the lobes always overlap (one
    // connected cloud, however concave).
    for i in 0..params.roots {
        let radius = params.root_radius * (0.85 + 0.3 * rng.uniform()) * if i == 0 { 1.0 } else { 0.8 };
        let center = if i == 0 {
            Vec3::ZERO
        } else {
            let from = spheres[((rng.uniform() * i as f32) as usize).min(i as usize - 1)];
            let a = std::f32::consts::TAU * rng.uniform();
            let dist = (0.5 + 0.9 * params.root_spread) * params.root_radius;
            from.center + Vec3::new(a.cos(), 0.0, a.sin()) * dist
        };
        spheres.push(Sphere { center, radius });
    }
    let centroid = spheres.iter().map(|s| s.center).sum::<Vec3>() / spheres.len() as f32;
    let root_bottom = spheres.iter().map(|s| s.center.y).fold(f32::INFINITY, f32::min);
    let mut level_start = 0;
    for _ in 0..params.levels {
        let level_end = spheres.len();
        for pi in level_start..level_end {
            let parent = spheres[pi];
            for _ in 0..params.children {
                let random = engine::sampling::sample_uniform_sphere(rng.uniform2());
                let outward =
                    Vec3::new(parent.center.x - centroid.x, 0.0, parent.center.z - centroid.z).normalize_or_zero();
                let mut dir =
                    (random + params.upward_bias * Vec3::Y + params.outward_bias * outward).normalize_or(Vec3::Y);
                if params.flatten_base > 0.0 && dir.y < -0.2 {
                    dir.y = -dir.y * 0.5;
                    dir = dir.normalize();
                }
                let radius = parent.radius * params.radius_ratio * (0.8 + 0.4 * rng.uniform());
                let center = parent.center + dir * parent.radius * (0.7 + 0.25 * rng.uniform());
                spheres.push(Sphere { center, radius });
            }
        }
        level_start = level_end;
    }
    // flatten_base = 1 cuts at the roots' centres; smaller values lower the cut.
    let base_y = (params.flatten_base > 0.0).then(|| root_bottom - params.root_radius * (1.0 - params.flatten_base));
    (spheres, base_y)
}

impl CloudModel {
    pub fn new(params: &CloudParams) -> Result<Self, ParamError> {
        Self::with_resolution(params, None)
    }

    /// A model for voxelizing at `resolution`: noise octaves above the grid's Nyquist
    /// frequency (half a cycle per voxel) are dropped, since they would only alias.
    pub fn with_resolution(params: &CloudParams, resolution: Option<u32>) -> Result<Self, ParamError> {
        params.validate()?;
        let octaves = |base_freq: f32, octaves: u32| match resolution {
            None => octaves,
            Some(res) => {
                let nyquist = 0.5 * res as f32;
                let mut n = 1;
                while n < octaves && base_freq * params.lacunarity.powi(n as i32) <= nyquist {
                    n += 1;
                }
                n
            }
        };
        let (mut spheres, mut base_y) = grow(params);
        // Fit the hierarchy into the box, keeping room for displacement and warp.
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for s in &spheres {
            lo = lo.min(s.center - s.radius);
            hi = hi.max(s.center + s.radius);
        }
        if let Some(b) = base_y {
            lo.y = lo.y.max(b);
        }
        let pad = params.displacement + params.advection;
        let avail = 1.0 - 2.0 * (params.margin + pad);
        let scale = avail.max(0.05) / (hi - lo).max_element().max(1e-6);
        let mid = 0.5 * (lo + hi);
        for s in &mut spheres {
            s.center = (s.center - mid) * scale;
            s.radius *= scale;
        }
        base_y = base_y.map(|b| (b - mid.y) * scale);

        // Bin spheres by their zone of influence. Density is non-zero only where the
        // union distance is below T = displacement + advection; there the nearest
        // sphere is within T + blend / 4 (the union's bound), and only spheres within
        // blend of that one take part.
        let reach = params.displacement + params.advection + 1.25 * params.blend + 1e-3;
        let mut bins = vec![Vec::new(); BINS * BINS * BINS];
        let inset = params.displacement + params.falloff + params.advection + 1e-4;
        let bin_size = 1.0 / BINS as f32;
        let solid: Vec<bool> = {
            use rayon::prelude::*;
            (0..BINS * BINS * BINS)
                .into_par_iter()
                .map(|i| {
                    let (x, y, z) = (i % BINS, (i / BINS) % BINS, i / (BINS * BINS));
                    let lo = Vec3::new(x as f32, y as f32, z as f32) * bin_size - 0.5;
                    let hi = lo + bin_size;
                    let above_base = base_y.is_none_or(|b| lo.y - b >= inset);
                    above_base
                        && spheres.iter().any(|s| {
                            let far = (lo - s.center).abs().max((hi - s.center).abs());
                            far.length() <= s.radius - inset
                        })
                })
                .collect()
        };
        for (i, s) in spheres.iter().enumerate() {
            let (a, b) = (s.center - (s.radius + reach), s.center + (s.radius + reach));
            for z in bin_coord(a.z)..=bin_coord(b.z) {
                for y in bin_coord(a.y)..=bin_coord(b.y) {
                    for x in bin_coord(a.x)..=bin_coord(b.x) {
                        // Only if some point of the bin is within reach of the surface.
                        let lo = Vec3::new(x as f32, y as f32, z as f32) * bin_size - 0.5;
                        let nearest = s.center.clamp(lo, lo + bin_size);
                        if (nearest - s.center).length() <= s.radius + reach {
                            bins[x + BINS * (y + BINS * z)].push(i as u32);
                        }
                    }
                }
            }
        }
        let seed = |k: u64| engine::rng::mix64(params.seed ^ k) as u32;
        let fbm = |k: u64, freq: f32, octaves: u32| {
            Fbm::<Perlin>::new(seed(k))
                .set_octaves(octaves as usize)
                .set_frequency(freq as f64)
                .set_lacunarity(params.lacunarity as f64)
                .set_persistence(params.gain as f64)
        };
        Ok(CloudModel {
            params: params.clone(),
            spheres,
            base_y,
            bins,
            reach,
            solid,
            displacement: fbm(1, params.frequency, octaves(params.frequency, params.octaves)),
            worley: Cellular { seed: seed(2) as u64, frequency: params.frequency * 0.5 },
            warp: [
                fbm(3, params.advection_frequency, 2),
                fbm(4, params.advection_frequency, 2),
                fbm(5, params.advection_frequency, 2),
            ],
            interior: fbm(6, params.interior_frequency, octaves(params.interior_frequency, 3)),
        })
    }

    pub fn spheres(&self) -> &[Sphere] {
        &self.spheres
    }

    /// Signed distance to the (undisplaced) hierarchy, exact where it is below the
    /// influence reach; +inf far away.
    #[inline]
    fn bin_index(p: Vec3) -> usize {
        let b = |x: f32| (((x + 0.5) * BINS as f32) as i64).clamp(0, BINS as i64 - 1) as usize;
        b(p.x) + BINS * (b(p.y) + BINS * b(p.z))
    }

    #[inline]
    fn hierarchy_distance(&self, p: Vec3) -> f32 {
        let bin = &self.bins[Self::bin_index(p)];
        let d = union_distance(bin.iter().map(|&i| self.spheres[i as usize]), p, self.params.blend);
        match self.base_y {
            Some(base) => d.max(base - p.y),
            None => d,
        }
    }

    #[inline]
    fn noise3(n: &impl NoiseFn<f64, 3>, p: Vec3) -> f32 {
        (n.get([p.x as f64, p.y as f64, p.z as f64]) as f32).clamp(-1.0, 1.0)
    }

    /// Density in [0, 1] at `p` (box units, cloud box [-0.5, 0.5]^3).
    pub fn density(&self, p: Vec3) -> f32 {
        let pr = &self.params;
        // The interior multiplier is sampled at the unwarped point, so solid bins need
        // neither the warp nor the hierarchy.
        if self.solid[Self::bin_index(p)] {
            return self.interior_factor(p);
        }
        // The warp moves points by at most `advection`, the displacement the surface
        // by at most `displacement`: far outside, skip the noise altogether.
        if pr.advection > 0.0 && self.hierarchy_distance(p) > pr.advection + pr.displacement {
            return 0.0;
        }
        // Domain warp: move the lookup point along a smooth noise vector field.
        let q = if pr.advection > 0.0 {
            p + pr.advection
                * Vec3::new(
                    Self::noise3(&self.warp[0], p),
                    Self::noise3(&self.warp[1], p),
                    Self::noise3(&self.warp[2], p),
                )
        } else {
            p
        };
        let sd = self.hierarchy_distance(q);
        let a = pr.displacement;
        if sd - a >= 0.0 {
            return 0.0;
        }
        let sd = if sd + a > -pr.falloff && a > 0.0 {
            // In the boundary band: displace by fBm mixed with Worley.
            let perlin = Self::noise3(&self.displacement, q);
            let cells = if pr.worley > 0.0 { self.worley.get(q) } else { 0.0 };
            sd - a * ((1.0 - pr.worley) * perlin - pr.worley * cells)
        } else {
            sd
        };
        let d = smoothstep(-sd / pr.falloff);
        if d > 0.0 { d * self.interior_factor(p) } else { 0.0 }
    }

    /// Whether the density can be non-zero anywhere in box `b` (a conservative test:
    /// false only where no sphere's reach comes near). Density at p needs a sphere
    /// within `reach` of p's surface distance, and the bin holding p lists every such
    /// sphere, so the bins overlapping `b` hold all the candidates.
    pub fn may_be_nonzero(&self, b: Bounds3) -> bool {
        let (lo, hi) = (b.min, b.max);
        if hi.cmplt(Vec3::splat(-0.5 - self.reach)).any() || lo.cmpgt(Vec3::splat(0.5 + self.reach)).any() {
            return false;
        }
        for z in bin_coord(lo.z)..=bin_coord(hi.z) {
            for y in bin_coord(lo.y)..=bin_coord(hi.y) {
                for x in bin_coord(lo.x)..=bin_coord(hi.x) {
                    for &i in &self.bins[x + BINS * (y + BINS * z)] {
                        let s = self.spheres[i as usize];
                        let nearest = s.center.clamp(lo, hi);
                        if (nearest - s.center).length() <= s.radius + self.reach {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }

    /// Interior noise multiplier in [1 - interior, 1].
    #[inline]
    fn interior_factor(&self, p: Vec3) -> f32 {
        let amount = self.params.interior;
        if amount == 0.0 {
            return 1.0;
        }
        let n = 0.5 + 0.75 * Self::noise3(&self.interior, p);
        1.0 - amount + amount * n.clamp(0.0, 1.0)
    }
}

/// The cloud voxelized at `resolution`^3 over the box [-0.5, 0.5]^3 (2 ..= 2048), in
/// sparse bricks: the bricks no sphere reaches are skipped, and sparse storage renders
/// the same image as dense bit for bit, faster (the constant core's bricks share one
/// slot that stays in cache, and a lookup inside a constant brick skips the
/// interpolation).
pub fn build_grid(params: &CloudParams, resolution: u32) -> Result<DensityGrid, ParamError> {
    if !(2..=2048).contains(&resolution) {
        return Err(ParamError { name: "resolution", value: resolution.to_string(), range: "2 ..= 2048" });
    }
    let model = CloudModel::with_resolution(params, Some(resolution))?;
    let (dims, bounds) = (UVec3::splat(resolution), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)));
    Ok(DensityGrid::from_fn_sparse(dims, bounds, |b| model.may_be_nonzero(b), |p| model.density(p))
        .expect("modeler densities are finite and in [0, 1]"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn density_in_unit_range_and_fits_the_box() {
        let p = CloudParams { advection: 0.05, interior: 0.7, ..Default::default() };
        let g = build_grid(&p, 32).unwrap();
        assert!(g.max_value() <= 1.0 && g.max_value() > 0.9);
        assert_eq!(g.max_on_boundary(), 0.0, "cloud touches the box");
    }

    #[test]
    fn same_seed_same_cloud_other_seed_other_cloud() {
        let a = build_grid(&CloudParams::default(), 24).unwrap();
        let b = build_grid(&CloudParams::default(), 24).unwrap();
        let c = build_grid(&CloudParams { seed: 2, ..Default::default() }, 24).unwrap();
        let lin = |g: &DensityGrid| {
            let n = g.dims();
            (0..n.x * n.y * n.z).map(|i| g.voxel(i % n.x, (i / n.x) % n.y, i / (n.x * n.y))).collect::<Vec<f32>>()
        };
        assert_eq!(lin(&a), lin(&b));
        assert_ne!(lin(&a), lin(&c));
    }

    #[test]
    fn out_of_range_parameters_are_named() {
        let e = build_grid(&CloudParams { falloff: 0.0, ..Default::default() }, 16).unwrap_err();
        assert_eq!(e.to_string(), "falloff = 0 is out of range: 0.002 ..= 0.3");
        let e = build_grid(&CloudParams { octaves: 12, ..Default::default() }, 16).unwrap_err();
        assert_eq!(e.to_string(), "octaves = 12 is out of range: 1 ..= 8");
        let e = build_grid(&CloudParams { gain: f32::NAN, ..Default::default() }, 16).unwrap_err();
        assert!(e.to_string().starts_with("gain = NaN"));
    }

    /// The pruned Worley search finds the same nearest feature point as all 27 cells.
    #[test]
    fn cellular_pruning_is_exact() {
        let c = Cellular { seed: 7, frequency: 3.0 };
        let mut rng = Rng::new(4, 0, 0);
        for _ in 0..5000 {
            let p = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 4.0 - 2.0;
            let q = p * c.frequency;
            let base = q.floor();
            let mut best = f32::INFINITY;
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        best = best.min(c.feature_distance2(base + Vec3::new(dx as f32, dy as f32, dz as f32), q));
                    }
                }
            }
            assert_eq!(c.get(p), (2.0 * best.sqrt() - 1.0).clamp(-1.0, 1.0), "{p}");
        }
    }

    /// Solid bins only skip work: every point in them really is at full density.
    #[test]
    fn solid_bins_are_inside() {
        for name in ["scene-a", "scene-b", "scene-c"] {
            let p = crate::preset(name).unwrap();
            let m = CloudModel::new(&p).unwrap();
            assert!(m.solid.iter().filter(|s| **s).count() > 10, "{name}: no solid bins");
            let mut rng = Rng::new(8, 0, 0);
            for _ in 0..20_000 {
                let x = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5;
                if m.solid[CloudModel::bin_index(x)] {
                    assert!(m.hierarchy_distance(x) <= -(p.displacement + p.falloff + p.advection), "{name} {x}");
                }
            }
        }
    }

    #[test]
    fn binning_matches_brute_force() {
        let p = CloudParams { levels: 3, children: 5, ..Default::default() };
        let m = CloudModel::new(&p).unwrap();
        let mut rng = Rng::new(3, 0, 0);
        let reach = p.displacement + p.advection;
        for _ in 0..5000 {
            let x = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5;
            let mut brute = union_distance(m.spheres().iter().copied(), x, p.blend);
            if let Some(b) = m.base_y {
                brute = brute.max(b - x.y);
            }
            let fast = m.hierarchy_distance(x);
            // Exact wherever the density can be non-zero; elsewhere it only has to
            // stay out of that range.
            if brute < reach {
                assert!((fast - brute).abs() < 1e-5, "{x}: {fast} vs {brute}");
            } else {
                assert!(fast >= reach - 1e-5, "{x}: {fast} vs {brute}");
            }
        }
    }

    /// The brick test never rejects a brick that holds density: every voxel of a
    /// dense build lies in a brick the test accepts, for clouds with displacement,
    /// advection and a flattened base; and it does reject most of the empty box.
    #[test]
    fn brick_test_is_conservative() {
        for (name, res) in [("scene-a", 96u32), ("scene-b", 80), ("set-03", 64), ("set-07", 64)] {
            let params = crate::preset(name).unwrap();
            let model = CloudModel::with_resolution(&params, Some(res)).unwrap();
            // The dense reference, sampled without the brick test.
            let g = DensityGrid::from_fn(UVec3::splat(res), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
                model.density(p)
            })
            .unwrap();
            let vs = 1.0 / res as f32;
            let bd = g.brick_dims();
            let mut rejected = 0;
            for bz in 0..bd.z {
                for by in 0..bd.y {
                    for bx in 0..bd.x {
                        let b = UVec3::new(bx, by, bz);
                        let lo = Vec3::splat(-0.5) + (b * engine::grid::BRICK).as_vec3() * vs;
                        let hi = Vec3::splat(-0.5) + ((b + 1) * engine::grid::BRICK).min(g.dims()).as_vec3() * vs;
                        if !model.may_be_nonzero(Bounds3::new(lo, hi)) {
                            rejected += 1;
                            assert_eq!(g.brick_max(b), 0.0, "{name}: brick {b} holds density but was rejected");
                        }
                    }
                }
            }
            assert!(rejected > 0, "{name}: the test rejected nothing");
            let sparse = build_grid(&params, res).unwrap();
            assert!(sparse.is_sparse());
            assert!(sparse.to_dense_vec() == g.to_dense_vec(), "{name}: sparse build differs from dense");
        }
    }
}
