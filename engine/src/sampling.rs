//! Sampling routines as pure functions of uniform numbers, with sample, pdf and
//! inverse side by side (the pbrt-v4 `util/sampling.h` layout).

use glam::{Vec2, Vec3};
use std::f32::consts::PI;

pub const INV_4PI: f32 = 1.0 / (4.0 * PI);

/// Exponential distance with rate `sigma`: pdf(t) = sigma exp(-sigma t).
#[inline]
pub fn sample_exponential(u: f32, sigma: f32) -> f32 {
    // 1 - u is in (0, 1], so the log is finite.
    -(1.0 - u).ln() / sigma
}

#[inline]
pub fn exponential_pdf(t: f32, sigma: f32) -> f32 {
    sigma * (-sigma * t).exp()
}

#[inline]
pub fn invert_exponential_sample(t: f32, sigma: f32) -> f32 {
    1.0 - (-sigma * t).exp()
}

/// Uniform direction on the unit sphere.
#[inline]
pub fn sample_uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

#[inline]
pub fn uniform_sphere_pdf() -> f32 {
    INV_4PI
}

/// Uniform direction in the cone of half-angle `acos(cos_max)` around +z.
#[inline]
pub fn sample_uniform_cone(u: Vec2, cos_max: f32) -> Vec3 {
    let cos_t = 1.0 - u.x * (1.0 - cos_max);
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t)
}

#[inline]
pub fn uniform_cone_pdf(cos_max: f32) -> f32 {
    1.0 / (2.0 * PI * (1.0 - cos_max))
}

/// Uniform point on the unit disk (polar mapping: r = sqrt(u.x), phi = 2 pi u.y).
#[inline]
pub fn sample_uniform_disk(u: Vec2) -> Vec2 {
    let r = u.x.sqrt();
    let phi = 2.0 * PI * u.y;
    Vec2::new(r * phi.cos(), r * phi.sin())
}

#[inline]
pub fn uniform_disk_pdf() -> f32 {
    1.0 / PI
}

/// An orthonormal basis (t, b, n) around unit `n` (Duff et al. 2017, branchless).
#[inline]
pub fn coordinate_system(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x), Vec3::new(b, sign + n.y * n.y * a, -n.y))
}

/// Maps a direction given in the local frame around `n` (local +z = n) to world space.
#[inline]
pub fn local_to_world(local: Vec3, n: Vec3) -> Vec3 {
    let (t, b) = coordinate_system(n);
    t * local.x + b * local.y + n * local.z
}

/// A direction with the given cosine to `axis` and azimuth `phi` about it.
#[inline]
pub fn spherical_direction(cos_t: f32, phi: f32, axis: Vec3) -> Vec3 {
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    local_to_world(Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t), axis)
}

/// The radical inverse of `i` in base `b`: its base-b digits mirrored about the
/// point (van der Corput), in [0, 1).
#[inline]
pub fn radical_inverse(mut i: u32, b: u32) -> f64 {
    let (inv, mut f, mut r) = (1.0 / b as f64, 1.0 / b as f64, 0.0f64);
    while i > 0 {
        r += (i % b) as f64 * f;
        i /= b;
        f *= inv;
    }
    r
}

/// Point `index` of the Halton sequence in bases 2, 3 and 5, rotated by `shift` in
/// [0, 1)^3 (a Cranley-Patterson rotation: a uniformly random shift makes each point
/// uniform over [0, 1)^3, while the first N points keep their even spread: along each
/// axis the first b^k lie one in each interval of length b^-k, and the first 6^k one
/// in each 2^-k x 3^-k box of the first two axes, all shifted alike). In f32, below 1.
#[inline]
pub fn halton_point(index: u32, shift: [f64; 3]) -> [f32; 3] {
    const BASES: [u32; 3] = [2, 3, 5];
    std::array::from_fn(|k| ((radical_inverse(index, BASES[k]) + shift[k]).fract() as f32).min(ONE_BELOW))
}

/// The largest f32 below 1.
const ONE_BELOW: f32 = 1.0 - f32::EPSILON / 2.0;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exponential_inverse_roundtrip() {
        for &u in &[0.0f32, 0.1, 0.5, 0.9, 0.999] {
            let t = sample_exponential(u, 3.0);
            assert!((invert_exponential_sample(t, 3.0) - u).abs() < 1e-5);
        }
        assert!(sample_exponential(1.0 - f32::EPSILON, 1.0).is_finite());
    }

    #[test]
    fn frames_are_orthonormal() {
        for n in [Vec3::Z, -Vec3::Z, Vec3::X, Vec3::new(0.3, -0.5, 0.8).normalize()] {
            let (t, b) = coordinate_system(n);
            assert!(t.dot(b).abs() < 1e-6 && t.dot(n).abs() < 1e-6 && b.dot(n).abs() < 1e-6);
            assert!((t.length() - 1.0).abs() < 1e-6 && (b.length() - 1.0).abs() < 1e-6);
            assert!((t.cross(b) - n).length() < 1e-5, "right-handed frame");
        }
    }
}

#[cfg(test)]
mod chi2_tests {
    use super::*;
    use crate::rng::Rng;
    use crate::stats::{chi2_test, sidak};

    /// Uniform cone and sphere sampling against their pdfs (10^6 samples, binned in
    /// cos theta and phi about the axis; alpha 0.01, Sidak over the cases).
    #[test]
    fn cone_and_sphere_chi_square() {
        let cases = [1.0f32 - 1e-3, 0.9, 0.2, -1.0];
        let alpha = sidak(0.01, cases.len());
        for (ci, &cos_max) in cases.iter().enumerate() {
            let (nc, np) = (40usize, 16usize);
            let mut obs = vec![0.0; nc * np];
            let mut rng = Rng::new(77, ci as u64, 0);
            let n = 1_000_000;
            for _ in 0..n {
                let d = if cos_max == -1.0 {
                    sample_uniform_sphere(rng.uniform2())
                } else {
                    sample_uniform_cone(rng.uniform2(), cos_max)
                };
                assert!(d.z >= cos_max - 1e-6);
                let t = ((d.z - cos_max) / (1.0 - cos_max)).clamp(0.0, 1.0 - 1e-7);
                let phi = d.y.atan2(d.x).rem_euclid(2.0 * PI);
                let ip = ((phi / (2.0 * PI)) * np as f32) as usize;
                obs[(t * nc as f32) as usize * np + ip.min(np - 1)] += 1.0;
            }
            // Uniform in cos theta over [cos_max, 1] and in phi: equal expected counts.
            let exp = vec![n as f64 / (nc * np) as f64; nc * np];
            let r = chi2_test(&obs, &exp, 5.0);
            assert!(r.p_value > alpha, "cos_max {cos_max}: {r:?}");
            let pdf = if cos_max == -1.0 { uniform_sphere_pdf() } else { uniform_cone_pdf(cos_max) };
            assert!((pdf * 2.0 * PI * (1.0 - cos_max) - 1.0).abs() < 1e-3);
        }
    }

    /// Uniform disk sampling: 10^6 points binned in 20 rings of equal area by 16
    /// sectors; every cell expects the same count.
    #[test]
    fn disk_chi_square() {
        let (nr, np) = (20usize, 16usize);
        let mut obs = vec![0.0; nr * np];
        let mut rng = Rng::new(78, 0, 0);
        let n = 1_000_000;
        for _ in 0..n {
            let p = sample_uniform_disk(rng.uniform2());
            let r2 = p.length_squared();
            assert!(r2 <= 1.0 + 1e-6);
            let ir = ((r2 * nr as f32) as usize).min(nr - 1);
            let phi = p.y.atan2(p.x).rem_euclid(2.0 * PI);
            let ip = ((phi / (2.0 * PI) * np as f32) as usize).min(np - 1);
            obs[ir * np + ip] += 1.0;
        }
        let exp = vec![n as f64 / (nr * np) as f64; nr * np];
        let r = chi2_test(&obs, &exp, 5.0);
        assert!(r.p_value > 0.01, "{r:?}");
        assert!((uniform_disk_pdf() * PI - 1.0).abs() < 1e-6);
    }

    /// Halton points under random rotations are uniform over [0, 1)^3 (any one
    /// point: chi-square over 8^3 cells, 400,000 rotations), and prefixes keep their
    /// strata: the first b^k points of axis b (2, 3, 5) leave no circular gap of
    /// 2 b^-k or more, and the first 36 points of the first two axes, unrotated, lie
    /// one in each 1/4 x 1/9 box.
    #[test]
    fn halton_points_are_uniform_and_stratified() {
        let mut rng = Rng::new(79, 0, 0);
        let (nb, n) = (8usize, 400_000);
        let mut obs = vec![0.0; nb * nb * nb];
        for i in 0..n {
            let shift = [rng.uniform_f64(), rng.uniform_f64(), rng.uniform_f64()];
            let p = halton_point(i as u32 % 97, shift);
            assert!(p.iter().all(|v| (0.0..1.0).contains(v)), "{p:?}");
            let c = p.map(|v| (v * nb as f32) as usize);
            obs[(c[2] * nb + c[1]) * nb + c[0]] += 1.0;
        }
        let exp = vec![n as f64 / obs.len() as f64; obs.len()];
        let r = chi2_test(&obs, &exp, 5.0);
        assert!(r.p_value > 0.01, "{r:?}");
        for (axis, b) in [2u32, 3, 5].into_iter().enumerate() {
            for k in 1..=4 {
                let count = b.pow(k);
                let shift = [rng.uniform_f64(), rng.uniform_f64(), rng.uniform_f64()];
                let mut v: Vec<f32> = (0..count).map(|i| halton_point(i, shift)[axis]).collect();
                v.sort_by(f32::total_cmp);
                let wrap = v[0] + 1.0 - v[v.len() - 1];
                let gap = v.windows(2).map(|w| w[1] - w[0]).fold(wrap, f32::max);
                assert!(gap < 2.0 / count as f32, "base {b}, {count} points: a gap of {gap}");
            }
        }
        let mut boxes = [0u32; 36];
        for i in 0..36 {
            let p = halton_point(i, [0.0; 3]);
            boxes[(p[1] * 9.0) as usize * 4 + (p[0] * 4.0) as usize] += 1;
        }
        assert!(boxes.iter().all(|c| *c == 1), "{boxes:?}");
    }
}
