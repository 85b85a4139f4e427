//! Statistics for testing Monte Carlo code: chi-square goodness of fit and normal
//! quantiles for z-tests with Sidak-corrected significance levels. Public so that the
//! cross-crate tests and the model crates use the same routines.

/// ln Gamma(x) for x > 0 (Lanczos, g = 7, n = 9; ~1e-15 relative).
pub fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, &c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularized upper incomplete gamma Q(a, x) (Numerical Recipes' split between the
/// series and the continued fraction).
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let gln = ln_gamma(a);
    if x < a + 1.0 {
        // Series for P.
        let mut ap = a;
        let mut sum = 1.0 / a;
        let mut del = sum;
        for _ in 0..10_000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        1.0 - sum * (-x + a * x.ln() - gln).exp()
    } else {
        // Lentz continued fraction for Q.
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..10_000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        (-x + a * x.ln() - gln).exp() * h
    }
}

/// Survival function of the chi-square distribution: P(X >= stat) for `dof` degrees.
pub fn chi2_sf(stat: f64, dof: f64) -> f64 {
    gamma_q(0.5 * dof, 0.5 * stat)
}

/// Result of a chi-square goodness-of-fit test.
#[derive(Clone, Copy, Debug)]
pub struct Chi2 {
    pub statistic: f64,
    pub dof: usize,
    pub p_value: f64,
}

/// Pearson's chi-square test of observed counts against expected counts. Cells with
/// an expected count below `min_expected` are pooled (in order) until they reach it,
/// as pbrt-v4's and Mitsuba's chi-square tests do.
pub fn chi2_test(observed: &[f64], expected: &[f64], min_expected: f64) -> Chi2 {
    assert_eq!(observed.len(), expected.len());
    let mut idx: Vec<usize> = (0..expected.len()).collect();
    idx.sort_by(|&a, &b| expected[a].total_cmp(&expected[b]));
    let (mut stat, mut cells) = (0.0, 0usize);
    let (mut pool_o, mut pool_e) = (0.0, 0.0);
    for &i in &idx {
        if expected[i] < min_expected {
            pool_o += observed[i];
            pool_e += expected[i];
            if pool_e >= min_expected {
                stat += (pool_o - pool_e) * (pool_o - pool_e) / pool_e;
                cells += 1;
                pool_o = 0.0;
                pool_e = 0.0;
            }
        } else {
            if observed[i] > 0.0 && expected[i] == 0.0 {
                return Chi2 { statistic: f64::INFINITY, dof: 1, p_value: 0.0 };
            }
            stat += (observed[i] - expected[i]) * (observed[i] - expected[i]) / expected[i];
            cells += 1;
        }
    }
    if pool_e > 0.0 {
        stat += (pool_o - pool_e) * (pool_o - pool_e) / pool_e;
        cells += 1;
    } else if pool_o > 0.0 {
        return Chi2 { statistic: f64::INFINITY, dof: 1, p_value: 0.0 };
    }
    let dof = cells.saturating_sub(1).max(1);
    Chi2 { statistic: stat, dof, p_value: chi2_sf(stat, dof as f64) }
}

/// Per-test significance so that `m` independent tests have family-wise level `alpha`.
pub fn sidak(alpha: f64, m: usize) -> f64 {
    1.0 - (1.0 - alpha).powf(1.0 / m as f64)
}

/// Standard normal quantile (Acklam's rational approximation, refined by one Halley
/// step; ~1e-7 relative, limited by `erfc`).
pub fn normal_quantile(p: f64) -> f64 {
    assert!(p > 0.0 && p < 1.0);
    const A: [f64; 6] = [
        -3.969683028665376e1,
        2.209460984245205e2,
        -2.759285104469687e2,
        1.383577518672690e2,
        -3.066479806614716e1,
        2.506628277459239,
    ];
    const B: [f64; 5] =
        [-5.447609879822406e1, 1.615858368580409e2, -1.556989798598866e2, 6.680131188771972e1, -1.328068155288572e1];
    const C: [f64; 6] = [
        -7.784894002430293e-3,
        -3.223964580411365e-1,
        -2.400758277161838,
        -2.549732539343734,
        4.374664141464968,
        2.938163982698783,
    ];
    const D: [f64; 4] = [7.784695709041462e-3, 3.224671290700398e-1, 2.445134137142996, 3.754408661907416];
    let pl = 0.02425;
    let x = if p < pl {
        let q = (-2.0 * p.ln()).sqrt();
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    } else if p <= 1.0 - pl {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    } else {
        let q = (-2.0 * (1.0 - p).ln()).sqrt();
        -(((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    // Halley refinement with erfc-based CDF.
    let e = 0.5 * erfc(-x / std::f64::consts::SQRT_2) - p;
    let u = e * (2.0 * std::f64::consts::PI).sqrt() * (0.5 * x * x).exp();
    x - u / (1.0 + 0.5 * x * u)
}

/// Complementary error function (W. J. Cody-style rational fit via Numerical
/// Recipes' erfcc, ~1.2e-7 relative; enough for one Halley step).
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let r = t
        * (-z * z - 1.26551223
            + t * (1.00002368
                + t * (0.37409196
                    + t * (0.09678418
                        + t * (-0.18628806
                            + t * (0.27886807
                                + t * (-1.13520398 + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277)))))))))
            .exp();
    if x >= 0.0 { r } else { 2.0 - r }
}

/// Two-sided z bound for `m` simultaneous tests at family-wise level `alpha`.
pub fn z_bound(alpha: f64, m: usize) -> f64 {
    normal_quantile(1.0 - 0.5 * sidak(alpha, m))
}

/// Welford running mean and variance, mergeable (pbrt-v4 `VarianceEstimator`).
#[derive(Clone, Copy, Debug, Default)]
pub struct Welford {
    pub n: u64,
    pub mean: f64,
    m2: f64,
}

impl Welford {
    pub fn add(&mut self, x: f64) {
        self.n += 1;
        let d = x - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (x - self.mean);
    }
    pub fn merge(&mut self, o: &Welford) {
        if o.n == 0 {
            return;
        }
        let n = self.n + o.n;
        let d = o.mean - self.mean;
        self.mean += d * o.n as f64 / n as f64;
        self.m2 += o.m2 + d * d * self.n as f64 * o.n as f64 / n as f64;
        self.n = n;
    }
    pub fn variance(&self) -> f64 {
        if self.n < 2 { 0.0 } else { self.m2 / (self.n - 1) as f64 }
    }
    /// Standard error of the mean.
    pub fn std_error(&self) -> f64 {
        (self.variance() / self.n.max(1) as f64).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        // chi2 with 1 dof: P(X >= 3.841459) = 0.05; 10 dof: P(X >= 18.307) = 0.05.
        assert!((chi2_sf(3.841_458_820_694_124, 1.0) - 0.05).abs() < 1e-9);
        assert!((chi2_sf(18.307_038_053_275_146, 10.0) - 0.05).abs() < 1e-9);
        assert!((chi2_sf(100.0, 100.0) - 0.481_192_2).abs() < 1e-6);
        assert!((ln_gamma(5.0) - 24f64.ln()).abs() < 1e-12);
        assert!((normal_quantile(0.975) - 1.959_963_984_540_054).abs() < 1e-6);
        assert!((normal_quantile(1e-6) + 4.753_424_308_822_899).abs() < 1e-5);
    }

    #[test]
    fn welford_merge_matches_direct() {
        let xs: Vec<f64> = (0..100).map(|i| ((i * 37) % 11) as f64 * 0.5).collect();
        let mut a = Welford::default();
        let mut b = Welford::default();
        let mut all = Welford::default();
        for (i, &x) in xs.iter().enumerate() {
            all.add(x);
            if i < 40 { a.add(x) } else { b.add(x) }
        }
        a.merge(&b);
        assert!((a.mean - all.mean).abs() < 1e-12 && (a.variance() - all.variance()).abs() < 1e-10);
    }

    #[test]
    fn chi2_detects_wrong_distribution() {
        let expected = vec![1000.0; 10];
        let fair: Vec<f64> = vec![1010.0, 990.0, 1005.0, 995.0, 1000.0, 1020.0, 980.0, 1000.0, 1003.0, 997.0];
        assert!(chi2_test(&fair, &expected, 5.0).p_value > 0.5);
        let skewed: Vec<f64> = (0..10).map(|i| 800.0 + 40.0 * i as f64).collect();
        assert!(chi2_test(&skewed, &expected, 5.0).p_value < 1e-6);
    }
}
