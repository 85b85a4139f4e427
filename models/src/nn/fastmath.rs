//! ln(1 + x) for the learned models' inputs, eight at a time.
//!
//! A point-to-point prediction takes the logarithm of its 351 densities (and phi_D)
//! before standardizing them; through libm's `log1pf` that was 6.5 % of a frontlit
//! render's time (perf; docs/point-to-point.md). The cloud-aware model's stencil takes
//! 324 (its cells' optical thicknesses and the sun's tau_hat). Here the same polynomial runs as portable scalar code and
//! as AVX2, operation for operation and without fused multiply-adds, so both give the
//! same bits and a render does not depend on the CPU it ran on. Against the exact
//! value the error is within 2 units in the last place (tested; 1.0 measured), far
//! below what the network resolves. Training uses it too; the shipped models were
//! trained with libm's ln_1p, which differs from it by as little.
//!
//! Method: u = 1 + x rounded, ln(1 + x) = ln(u) + (x - (u - 1)) / u (the second term
//! undoes the rounding of u); u = m 2^e with m in [sqrt(1/2), sqrt(2)), ln(m) =
//! 2 atanh(s) with s = (m - 1) / (m + 1), |s| < 0.172, by its series to s^9.

/// Bits of sqrt(1/2): mantissas are reduced into [sqrt(1/2), sqrt(2)).
const SQRT_HALF_BITS: i32 = 0x3f35_04f3;
/// ln 2 split (fdlibm's) so that e ln2_hi is exact for the exponents of a float.
const LN2_HI: f32 = f32::from_bits(0x3f31_7180); // 6.9313812256e-1
const LN2_LO: f32 = f32::from_bits(0x3717_f7d1); // 9.0580006145e-6
const C3: f32 = 2.0 / 3.0;
const C5: f32 = 2.0 / 5.0;
const C7: f32 = 2.0 / 7.0;
const C9: f32 = 2.0 / 9.0;

/// ln(1 + max(x, 0)); +infinity for +infinity, 0 for NaN (as `x.max(0.0).ln_1p()`
/// gives for NaN).
#[inline]
pub fn ln_1p(x: f32) -> f32 {
    // max(x, 0) as the AVX2 path's maxps makes it: NaN and -0 become +0.
    let x = if x > 0.0 { x } else { 0.0 };
    if x == f32::INFINITY {
        return x;
    }
    let u = 1.0 + x;
    let ix = u.to_bits() as i32 - SQRT_HALF_BITS;
    let e = (ix >> 23) as f32;
    let m = f32::from_bits(((ix & 0x007f_ffff) + SQRT_HALF_BITS) as u32);
    let f = m - 1.0;
    let s = f / (2.0 + f);
    let z = s * s;
    let poly = z * (C3 + z * (C5 + z * (C7 + z * C9)));
    let c = (x - (u - 1.0)) / u;
    e * LN2_HI + ((f - s * (f - poly)) + (e * LN2_LO + c))
}

/// `out[i] = (ln_1p(raw[i]) - mean[i]) / std[i]`: the network's standardized input.
pub fn standardize(raw: &[f32], mean: &[f32], std: &[f32], out: &mut [f32]) {
    assert!(raw.len() == out.len() && mean.len() >= out.len() && std.len() >= out.len(), "lengths");
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked just now).
        return unsafe { standardize_avx2(raw, mean, std, out) };
    }
    standardize_portable(raw, mean, std, out)
}

/// [`standardize`] without SIMD.
pub fn standardize_portable(raw: &[f32], mean: &[f32], std: &[f32], out: &mut [f32]) {
    for (i, (o, v)) in out.iter_mut().zip(raw).enumerate() {
        *o = (ln_1p(*v) - mean[i]) / std[i];
    }
}

/// [`standardize`] eight at a time: [`ln_1p`]'s operations in the same order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn standardize_avx2(raw: &[f32], mean: &[f32], std: &[f32], out: &mut [f32]) {
    use std::arch::x86_64::*;
    let n = out.len();
    let full = n / 8 * 8;
    let mut i = 0;
    while i < full {
        // SAFETY: i + 8 <= n, and every slice holds at least n floats.
        let (v, mu, sd) = unsafe {
            (
                _mm256_loadu_ps(raw.as_ptr().add(i)),
                _mm256_loadu_ps(mean.as_ptr().add(i)),
                _mm256_loadu_ps(std.as_ptr().add(i)),
            )
        };
        let r = _mm256_div_ps(_mm256_sub_ps(ln_1p_avx2(v), mu), sd);
        // SAFETY: i + 8 <= n = out.len().
        unsafe { _mm256_storeu_ps(out.as_mut_ptr().add(i), r) };
        i += 8;
    }
    standardize_portable(&raw[full..], &mean[full..], &std[full..], &mut out[full..]);
}

/// `x[i] = ln_1p(x[i])` for every element, eight at a time where the CPU has AVX2
/// (the same bits as [`ln_1p`] either way).
pub fn ln_1p_many(x: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked just now).
        return unsafe { ln_1p_many_avx2(x) };
    }
    ln_1p_many_portable(x)
}

/// [`ln_1p_many`] without SIMD.
pub fn ln_1p_many_portable(x: &mut [f32]) {
    for v in x {
        *v = ln_1p(*v);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn ln_1p_many_avx2(x: &mut [f32]) {
    use std::arch::x86_64::*;
    let n = x.len();
    let full = n / 8 * 8;
    let mut i = 0;
    while i < full {
        // SAFETY: i + 8 <= n = x.len().
        unsafe {
            let p = x.as_mut_ptr().add(i);
            _mm256_storeu_ps(p, ln_1p_avx2(_mm256_loadu_ps(p)));
        }
        i += 8;
    }
    ln_1p_many_portable(&mut x[full..]);
}

/// [`ln_1p`] of eight lanes, operation for operation (no fused multiply-adds).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn ln_1p_avx2(v: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    let one = _mm256_set1_ps(1.0);
    let two = _mm256_set1_ps(2.0);
    let inf = _mm256_set1_ps(f32::INFINITY);
    let sqrt_half = _mm256_set1_epi32(SQRT_HALF_BITS);
    let mantissa = _mm256_set1_epi32(0x007f_ffff);
    // max(v, 0) with f32::max's NaN rule: a NaN lane becomes 0 (maxps returns its
    // second operand when either is NaN).
    let x = _mm256_max_ps(v, _mm256_setzero_ps());
    let u = _mm256_add_ps(one, x);
    let ix = _mm256_sub_epi32(_mm256_castps_si256(u), sqrt_half);
    let e = _mm256_cvtepi32_ps(_mm256_srai_epi32::<23>(ix));
    let m = _mm256_castsi256_ps(_mm256_add_epi32(_mm256_and_si256(ix, mantissa), sqrt_half));
    let f = _mm256_sub_ps(m, one);
    let s = _mm256_div_ps(f, _mm256_add_ps(two, f));
    let z = _mm256_mul_ps(s, s);
    let p = _mm256_add_ps(_mm256_set1_ps(C7), _mm256_mul_ps(z, _mm256_set1_ps(C9)));
    let p = _mm256_add_ps(_mm256_set1_ps(C5), _mm256_mul_ps(z, p));
    let p = _mm256_add_ps(_mm256_set1_ps(C3), _mm256_mul_ps(z, p));
    let poly = _mm256_mul_ps(z, p);
    let c = _mm256_div_ps(_mm256_sub_ps(x, _mm256_sub_ps(u, one)), u);
    let head = _mm256_sub_ps(f, _mm256_mul_ps(s, _mm256_sub_ps(f, poly)));
    let tail = _mm256_add_ps(_mm256_mul_ps(e, _mm256_set1_ps(LN2_LO)), c);
    let l = _mm256_add_ps(_mm256_mul_ps(e, _mm256_set1_ps(LN2_HI)), _mm256_add_ps(head, tail));
    // +infinity stays +infinity.
    _mm256_blendv_ps(l, inf, _mm256_cmp_ps::<_CMP_EQ_OQ>(x, inf))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Within 2 units in the last place of the exact ln(1 + x) (in f64) over eleven
    /// decades and at the edges; 0 at 0, NaN to 0, infinity kept.
    #[test]
    fn ln_1p_is_accurate() {
        let mut rng = engine::Rng::new(5, 0, 0);
        let mut xs: Vec<f32> = (0..200_000).map(|_| 10f32.powf(-5.0 + 11.0 * rng.uniform())).collect();
        xs.extend([0.0, f32::MIN_POSITIVE, 1e-30, 0.4142135, 0.4142136, 1.0, 2.0, 1e30, f32::MAX]);
        let mut worst = 0.0f64;
        for &x in &xs {
            let (got, want) = (ln_1p(x) as f64, (x as f64).ln_1p());
            let ulp = (want as f32).abs().max(f32::MIN_POSITIVE) as f64 * f32::EPSILON as f64;
            worst = worst.max((got - want).abs() / ulp);
        }
        println!("worst error {worst:.2} ulp");
        assert!(worst <= 2.0, "worst error {worst} ulp");
        assert_eq!(ln_1p(0.0).to_bits(), 0.0f32.to_bits());
        assert_eq!(ln_1p(-3.0), 0.0);
        assert_eq!(ln_1p(f32::NAN), 0.0);
        assert_eq!(ln_1p(f32::INFINITY), f32::INFINITY);
    }

    /// The AVX2 path (where the CPU has it) gives the portable path's bits, for full
    /// groups of eight and a short tail, with NaN, negative and infinite inputs.
    #[test]
    fn standardize_paths_agree_bit_for_bit() {
        #[cfg(target_arch = "x86_64")]
        println!("AVX2: {}", std::arch::is_x86_feature_detected!("avx2"));
        let mut rng = engine::Rng::new(6, 0, 0);
        // 352 = 44 full groups; 355 and 5 end in a short tail (5: nothing but one).
        for n in [352usize, 355, 5] {
            let mut raw: Vec<f32> = (0..n).map(|_| 10f32.powf(-4.0 + 9.0 * rng.uniform())).collect();
            raw[1] = f32::NAN;
            raw[2] = -2.0;
            raw[3] = f32::INFINITY;
            raw[4] = -0.0;
            raw[n - 2] = 0.0;
            let mean: Vec<f32> = (0..n).map(|_| 3.0 * rng.uniform()).collect();
            let std: Vec<f32> = (0..n).map(|_| 0.1 + rng.uniform()).collect();
            standardize_matches(&raw, &mean, &std);
        }
    }

    /// ln_1p_many gives ln_1p's bits on either path, full groups and tails.
    #[test]
    fn ln_1p_many_paths_agree_bit_for_bit() {
        let mut rng = engine::Rng::new(7, 0, 0);
        for n in [324usize, 13, 3] {
            let mut x: Vec<f32> = (0..n).map(|_| 10f32.powf(-6.0 + 12.0 * rng.uniform())).collect();
            x[0] = f32::NAN;
            x[1] = -1.5;
            x[2] = f32::INFINITY;
            let (mut a, mut b) = (x.clone(), x.clone());
            ln_1p_many(&mut a);
            ln_1p_many_portable(&mut b);
            for i in 0..n {
                assert_eq!(a[i].to_bits(), b[i].to_bits(), "{i}");
                assert_eq!(a[i].to_bits(), ln_1p(x[i]).to_bits(), "{i}");
            }
        }
    }

    fn standardize_matches(raw: &[f32], mean: &[f32], std: &[f32]) {
        let n = raw.len();
        let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
        standardize(raw, mean, std, &mut a);
        standardize_portable(raw, mean, std, &mut b);
        for i in 0..n {
            assert_eq!(a[i].to_bits(), b[i].to_bits(), "{i}: {} vs {}", a[i], b[i]);
            let want = ((raw[i].max(0.0) as f64).ln_1p() - mean[i] as f64) / std[i] as f64;
            if want.is_finite() {
                assert!((a[i] as f64 - want).abs() <= 1e-5 * (1.0 + want.abs()), "{i}: {} vs {want}", a[i]);
            } else {
                assert_eq!(a[i] as f64, want, "{i}");
            }
        }
    }
}
