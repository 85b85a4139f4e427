//! Images with per-pixel variances and the figures of merit of docs/conventions.md:
//! lit pixels, lit mean, TTUV, bias and relative bias with their noise floor,
//! relative RMSE against a noisy reference, the RMSE floor, time to preview and its
//! projection, and the false-colour ramp of error images. The window's compare view
//! and the evaluations use the same functions.

use engine::{Buffer, Film};

/// Relative RMSE that counts as a preview (docs/conventions.md).
pub const PREVIEW_RMSE: f64 = 0.05;

/// Seconds until the relative RMSE reaches [`PREVIEW_RMSE`] for an estimator whose
/// variance of the mean is `ttuv / t` (mean over the lit pixels) and whose bias part
/// is `floor` (relative), for an image of mean `mean`; None if the floor is too high.
pub fn projected_preview(ttuv: f64, mean: f64, floor: f64) -> Option<f64> {
    let room = PREVIEW_RMSE * PREVIEW_RMSE - floor * floor;
    (room > 0.0 && mean > 0.0).then(|| ttuv / (mean * mean * room))
}

/// An image with the per-pixel variance of its estimate.
pub struct Image {
    pub w: u32,
    pub h: u32,
    pub mean: Vec<[f32; 3]>,
    pub var: Vec<[f32; 3]>,
}

impl Image {
    pub fn from_film(film: &Film, b: Buffer) -> Self {
        Image { w: film.width(), h: film.height(), mean: film.mean(b), var: film.variance_of_mean(b) }
    }
}

/// The mean over the three channels, in f64.
pub fn avg3(v: &[f32; 3]) -> f64 {
    (v[0] as f64 + v[1] as f64 + v[2] as f64) / 3.0
}

/// Pixels whose reference value is > 0.
pub fn nonempty(reference: &[[f32; 3]]) -> Vec<bool> {
    reference.iter().map(|p| avg3(p) > 0.0).collect()
}

/// Mean of the pixels whose value (averaged over channels) is > 0.
pub fn lit_mean(img: &[[f32; 3]]) -> f64 {
    let (s, n) = img.iter().map(avg3).filter(|v| *v > 0.0).fold((0.0f64, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 { 0.0 } else { s / n as f64 }
}

/// Mean over `mask` of the pixels (averaged over channels); 0 for an empty mask.
pub fn masked_mean(img: &[[f32; 3]], mask: &[bool]) -> f64 {
    let (mut s, mut n) = (0.0f64, 0usize);
    for (v, m) in img.iter().zip(mask) {
        if *m {
            s += avg3(v);
            n += 1;
        }
    }
    if n == 0 { 0.0 } else { s / n as f64 }
}

/// TTUV: mean over `mask` of the variance of the pixel estimate, times seconds.
pub fn ttuv(var: &[[f32; 3]], mask: &[bool], seconds: f64) -> f64 {
    masked_mean(var, mask) * seconds
}

/// Box-filters an image down by `f` per axis (partial blocks at the edges averaged over
/// the pixels they hold); per-channel means, and the variance of each block mean.
pub fn downscale(img: &Image, f: u32) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let (bw, bh) = (img.w.div_ceil(f), img.h.div_ceil(f));
    let mut mean = vec![[0.0f64; 3]; (bw * bh) as usize];
    let mut var = vec![[0.0f64; 3]; (bw * bh) as usize];
    let mut count = vec![0u32; (bw * bh) as usize];
    for y in 0..img.h {
        for x in 0..img.w {
            let i = (y * img.w + x) as usize;
            let b = ((y / f) * bw + x / f) as usize;
            for c in 0..3 {
                mean[b][c] += img.mean[i][c] as f64;
                var[b][c] += img.var[i][c] as f64;
            }
            count[b] += 1;
        }
    }
    for b in 0..mean.len() {
        let n = count[b] as f64;
        for c in 0..3 {
            mean[b][c] /= n;
            var[b][c] /= n * n;
        }
    }
    (mean, var)
}

/// (bias, relative bias, relative noise floor) of `pred` against `reference`
/// (docs/conventions.md): 16x box downscale, mean over blocks with a reference value > 0
/// of |reference - prediction| averaged over channels; relative = divided by the mean
/// reference over those blocks. The noise floor is E|N(0, s)| = s sqrt(2 / pi) with
/// s^2 the two block means' variances, averaged the same way.
pub fn bias(reference: &Image, pred: &Image) -> (f64, f64, f64) {
    bias_in(reference, pred, &nonempty(&reference.mean))
}

/// [`bias`] over the blocks that hold at least one pixel of `mask` (with a sky behind
/// the cloud, the pixels the cloud covers; without one, `nonempty` gives [`bias`]).
pub fn bias_in(reference: &Image, pred: &Image, mask: &[bool]) -> (f64, f64, f64) {
    let (rm, rv) = downscale(reference, 16);
    let (pm, pv) = downscale(pred, 16);
    let bw = reference.w.div_ceil(16);
    let mut covered = vec![false; rm.len()];
    for (i, m) in mask.iter().enumerate() {
        if *m {
            let (x, y) = (i as u32 % reference.w, i as u32 / reference.w);
            covered[((y / 16) * bw + x / 16) as usize] = true;
        }
    }
    let (mut err, mut refsum, mut floor, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
    for b in 0..rm.len() {
        let r = (rm[b][0] + rm[b][1] + rm[b][2]) / 3.0;
        if r <= 0.0 || !covered[b] {
            continue;
        }
        n += 1;
        refsum += r;
        for c in 0..3 {
            err += (rm[b][c] - pm[b][c]).abs() / 3.0;
            floor += (rv[b][c] + pv[b][c]).sqrt() * (2.0 / std::f64::consts::PI).sqrt() / 3.0;
        }
    }
    if n == 0 || refsum <= 0.0 {
        return (0.0, 0.0, 0.0);
    }
    let (err, mean, floor) = (err / n as f64, refsum / n as f64, floor / n as f64);
    (err, err / mean, floor / mean)
}

/// Relative RMSE of `img` against the converged image, measured with a reference that
/// is itself noisy: sqrt(mean over `mask` of (img - ref)^2 - var(ref)) divided by the
/// mean reference value. For an image independent of the reference,
/// E[(img - ref)^2] = E[(img - truth)^2] + var(ref), so subtracting the reference's
/// own variance of the mean (unbiased per pixel) leaves an unbiased estimate of the
/// squared error against the truth: a reference about as converged as the preview
/// itself is enough, where comparing against its mean alone needs one far below 5 %.
/// Clamped at 0 (the estimate can dip below zero when both are nearly exact).
pub fn relative_rmse(img: &[[f32; 3]], reference: &Image, mask: &[bool]) -> f64 {
    relative_rmse_less(img, reference, mask, None)
}

/// [`relative_rmse`] with, optionally, the image's own variance of the mean also
/// subtracted: what is left is the error no amount of samples removes, the bias part
/// of the RMSE (the floor a biased estimator converges to).
pub fn relative_rmse_less(img: &[[f32; 3]], reference: &Image, mask: &[bool], img_var: Option<&[[f32; 3]]>) -> f64 {
    relative_rmse_with_error(img, reference, mask, img_var).0
}

/// [`relative_rmse_less`] and its standard error over the pixels: the per-pixel
/// terms' standard deviation over sqrt(n), carried through the square root (where the
/// squared error's estimate is at most its own standard error, the square root of that
/// error, the size of what cannot be told from 0). Against a reference far noisier
/// than the error it measures, the estimate is a small difference of large numbers;
/// this says how small.
pub fn relative_rmse_with_error(
    img: &[[f32; 3]],
    reference: &Image,
    mask: &[bool],
    img_var: Option<&[[f32; 3]]>,
) -> (f64, f64) {
    let (mut sum, mut sum_sq, mut r, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
    for (i, m) in mask.iter().enumerate() {
        if *m {
            let (a, b, v) = (&img[i], &reference.mean[i], &reference.var[i]);
            let mut t = 0.0;
            for c in 0..3 {
                let d = a[c] as f64 - b[c] as f64;
                let own = img_var.map_or(0.0, |iv| iv[i][c] as f64);
                t += (d * d - v[c] as f64 - own) / 3.0;
            }
            (sum, sum_sq) = (sum + t, sum_sq + t * t);
            r += avg3(b);
            n += 1;
        }
    }
    // No lit pixel: no preview can be judged.
    if n == 0 || r <= 0.0 {
        return (f64::INFINITY, f64::INFINITY);
    }
    let nf = n as f64;
    let (mean_sq, ref_mean) = (sum / nf, r / nf);
    let se_sq = if n > 1 { ((sum_sq - sum * sum / nf).max(0.0) / (nf - 1.0) / nf).sqrt() } else { f64::INFINITY };
    let value = mean_sq.max(0.0).sqrt();
    let se = if mean_sq > se_sq { se_sq / (2.0 * value) } else { se_sq.sqrt() };
    (value / ref_mean, se / ref_mean)
}

/// The reference's own relative noise: sqrt(mean over `mask` of its variance of the
/// mean) / its mean; the RMSE a comparison against its mean alone could not go below.
pub fn reference_noise(reference: &Image, mask: &[bool]) -> f64 {
    let mean = lit_mean(&reference.mean);
    if mean > 0.0 { ttuv(&reference.var, mask, 1.0).sqrt() / mean } else { f64::INFINITY }
}

/// The absolute error of `a` against `b` per pixel (mean over the channels) in false
/// colour, yellow at `scale`.
pub fn error_colours(a: &[[f32; 3]], b: &[[f32; 3]], scale: f64) -> Vec<[u8; 3]> {
    a.iter()
        .zip(b)
        .map(|(a, b)| false_colour((avg3(&std::array::from_fn(|c| (a[c] - b[c]).abs())) / scale) as f32))
        .collect()
}

/// False colour for t in [0, 1]: black, purple, orange, yellow (an inferno-like ramp).
pub fn false_colour(t: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] =
        [[0.0, 0.0, 0.02], [0.34, 0.06, 0.43], [0.73, 0.21, 0.33], [0.98, 0.55, 0.04], [0.99, 1.0, 0.64]];
    let x = t.clamp(0.0, 1.0) * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f32;
    std::array::from_fn(|c| ((STOPS[i][c] * (1.0 - f) + STOPS[i + 1][c] * f) * 255.0 + 0.5) as u8)
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::Rng;

    /// A pixel estimate from `m` samples of value * Exp(1) (a skewed, heavy-ish tailed
    /// estimator like a path tracer's): (mean, unbiased variance of the mean), as the
    /// film computes them.
    fn estimate(value: f64, m: u32, rng: &mut Rng) -> (f32, f32) {
        let xs: Vec<f64> = (0..m).map(|_| -value * (1.0 - rng.uniform() as f64).max(1e-12).ln()).collect();
        let mean = xs.iter().sum::<f64>() / m as f64;
        let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (m - 1) as f64;
        (mean as f32, (var / m as f64) as f32)
    }

    /// Mean and standard error of per-pixel terms.
    fn mean_se(t: &[f64]) -> (f64, f64) {
        let n = t.len() as f64;
        let m = t.iter().sum::<f64>() / n;
        (m, (t.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0) / n).sqrt())
    }

    /// A noisy reference of `m_ref` samples per pixel, and an image of `m_img` samples
    /// of truth + a known relative bias up to `amp`, on 20,000 pixels.
    fn setup(seed: u64, m_ref: u32, m_img: u32, amp: f64) -> (Vec<f64>, Vec<f64>, Image, Image) {
        let n = 20_000;
        let mut rng = Rng::new(seed, 0, 0);
        let truth: Vec<f64> = (0..n).map(|_| 0.2 + 0.8 * rng.uniform() as f64).collect();
        let bias: Vec<f64> = truth.iter().enumerate().map(|(i, t)| amp * t * (i as f64 * 0.01).sin()).collect();
        let mk = |vals: Vec<(f32, f32)>| Image {
            w: n as u32,
            h: 1,
            mean: vals.iter().map(|v| [v.0; 3]).collect(),
            var: vals.iter().map(|v| [v.1; 3]).collect(),
        };
        let reference = mk(truth.iter().map(|t| estimate(*t, m_ref, &mut rng)).collect());
        let img = mk(truth.iter().zip(&bias).map(|(t, b)| estimate(t + b, m_img, &mut rng)).collect());
        (truth, bias, reference, img)
    }

    /// Checks that `rel` (a relative RMSE over all pixels) squared, in absolute units,
    /// matches `exact` within 4 standard errors of the per-pixel `terms`, the
    /// differences whose mean is zero; returns (the squared estimate, its standard error).
    fn agrees(rel: f64, reference: &Image, terms: impl Fn(usize) -> f64, exact: f64, what: &str) -> (f64, f64) {
        let est = (rel * lit_mean(&reference.mean)).powi(2);
        let (_, se) = mean_se(&(0..reference.mean.len()).map(terms).collect::<Vec<_>>());
        assert!((est - exact).abs() <= 4.0 * se, "{what}: estimate {est}, exact {exact}, se {se}");
        (est, se)
    }

    /// The noise-corrected squared error against a noisy reference agrees with the
    /// squared error against the truth within 4 standard errors of the difference (the
    /// per-pixel terms -2 (img - t)(ref - t) + (ref - t)^2 - var(ref), mean zero); the
    /// uncorrected one is off by far more: the reference's variance.
    #[test]
    fn noise_corrected_rmse_matches_the_rmse_against_the_truth() {
        for seed in 0..3 {
            let (truth, _, reference, img) = setup(seed, 16, 64, 0.03);
            let n = truth.len() as f64;
            let px = |i: usize| (img.mean[i][0] as f64, reference.mean[i][0] as f64, reference.var[i][0] as f64);
            let exact = truth.iter().zip(&img.mean).map(|(t, a)| (a[0] as f64 - t).powi(2)).sum::<f64>() / n;
            let rel = relative_rmse(&img.mean, &reference, &vec![true; truth.len()]);
            let term = |i: usize| {
                let (a, r, v) = px(i);
                (a - r).powi(2) - v - (a - truth[i]).powi(2)
            };
            let (est, se) = agrees(rel, &reference, term, exact, &format!("seed {seed}"));
            let naive = est + reference.var.iter().map(|v| v[0] as f64).sum::<f64>() / n;
            assert!(naive - exact > 20.0 * se, "seed {seed}: the reference noise should show: {naive} vs {exact}");
        }
    }

    /// With the image's own variance also subtracted, what remains is the squared bias:
    /// within 4 standard errors of its exact mean.
    #[test]
    fn rmse_floor_is_the_bias_part() {
        for seed in 10..13 {
            let (truth, bias, reference, img) = setup(seed, 256, 256, 0.1);
            let exact = bias.iter().map(|b| b * b).sum::<f64>() / bias.len() as f64;
            let rel = relative_rmse_less(&img.mean, &reference, &vec![true; truth.len()], Some(&img.var));
            let term = |i: usize| {
                let (a, r) = (img.mean[i][0] as f64, reference.mean[i][0] as f64);
                (a - r).powi(2) - reference.var[i][0] as f64 - img.var[i][0] as f64 - bias[i].powi(2)
            };
            let (_, se) = agrees(rel, &reference, term, exact, &format!("seed {seed}, floor"));
            assert!(exact > 8.0 * se, "the test's bias must be resolvable: {exact} vs se {se}");
        }
    }

    /// The floor's standard error describes its scatter: over 16 independent
    /// references and images of one truth, the floors' standard deviation and the
    /// reported standard error (their mean) agree within the spread a standard
    /// deviation of 16 draws has (chi-square with 15 degrees of freedom: below half or
    /// above twice the truth with probability 0.002 and 10^-9).
    #[test]
    fn rmse_floor_error_describes_its_scatter() {
        let (mut floors, mut errors) = (vec![], vec![]);
        for seed in 20..36 {
            let (truth, _, reference, img) = setup(seed, 16, 64, 0.05);
            let (f, e) = relative_rmse_with_error(&img.mean, &reference, &vec![true; truth.len()], Some(&img.var));
            assert_eq!(f, relative_rmse_less(&img.mean, &reference, &vec![true; truth.len()], Some(&img.var)));
            floors.push(f);
            errors.push(e);
        }
        let (mean, _) = mean_se(&floors);
        let sd = (floors.iter().map(|f| (f - mean).powi(2)).sum::<f64>() / 15.0).sqrt();
        let reported = errors.iter().sum::<f64>() / 16.0;
        eprintln!("floor {mean}: sd {sd}, reported {reported}");
        assert!(reported > 0.5 * sd && reported < 2.0 * sd, "floors {floors:?}: sd {sd}, reported {reported}");
        // A noisy reference (16 samples) makes the error large beside the floor itself.
        assert!(reported > 0.02 * mean, "floor {mean}, error {reported}");
    }

    /// Projection: an unbiased estimator reaching 5 % needs TTUV / (0.05 mean)^2
    /// seconds; a floor of 3 % leaves 0.05^2 - 0.03^2 of room; 5 % leaves none.
    #[test]
    fn projected_preview_follows_the_variance() {
        let t0 = projected_preview(0.01, 0.2, 0.0).unwrap();
        assert!((t0 - 0.01 / (0.01 * 0.01)).abs() < 1e-9 * t0);
        let t3 = projected_preview(0.01, 0.2, 0.03).unwrap();
        assert!((t3 / t0 - 0.0025 / 0.0016).abs() < 1e-9);
        assert!(projected_preview(0.01, 0.2, 0.05).is_none());
    }
}
