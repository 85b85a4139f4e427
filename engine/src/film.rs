//! Accumulation buffers: per pixel sums and sums of squares for each buffer of
//! docs/conventions.md, so means, per-pixel variances and TTUV come from one place.
//! Sums are f64: 10^5 samples per pixel lose nothing.

use crate::integrator::base::PathSample;
use rayon::prelude::*;

/// The buffers a render accumulates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Buffer {
    /// Order 0: the sky seen through the medium (black environment: empty).
    Direct,
    /// Orders 1 .. k-1.
    Low,
    /// Orders >= k (path traced, or predicted).
    High,
    /// Everything: direct + low + high.
    Full,
}

impl Buffer {
    pub const ALL: [Buffer; 4] = [Buffer::Direct, Buffer::Low, Buffer::High, Buffer::Full];

    pub fn name(&self) -> &'static str {
        match self {
            Buffer::Direct => "direct",
            Buffer::Low => "low",
            Buffer::High => "high",
            Buffer::Full => "full",
        }
    }

    fn index(&self) -> usize {
        *self as usize
    }
}

#[derive(Clone, Debug)]
struct Layer {
    sum: Vec<[f64; 3]>,
    sum_sq: Vec<[f64; 3]>,
}

impl Layer {
    fn new(n: usize) -> Self {
        Layer { sum: vec![[0.0; 3]; n], sum_sq: vec![[0.0; 3]; n] }
    }

    #[inline]
    fn add(&mut self, i: usize, v: [f64; 3]) {
        let (s, q) = (&mut self.sum[i], &mut self.sum_sq[i]);
        for c in 0..3 {
            s[c] += v[c];
            q[c] += v[c] * v[c];
        }
    }
}

/// A progressive image: every pixel has received `spp` samples.
#[derive(Clone, Debug)]
pub struct Film {
    width: u32,
    height: u32,
    spp: u32,
    layers: [Layer; 4],
    /// Samples dropped because they were not finite (a bug if ever non-zero).
    rejected: u64,
}

impl Film {
    pub fn new(width: u32, height: u32) -> Self {
        let n = width as usize * height as usize;
        Film { width, height, spp: 0, layers: std::array::from_fn(|_| Layer::new(n)), rejected: 0 }
    }

    /// Makes this film a copy of `other`, in the memory it already holds where the
    /// sizes agree (a render worker that publishes a copy per pass reuses the copies
    /// the viewer has let go of, rather than allocating the buffers anew).
    pub fn copy_from(&mut self, other: &Film) {
        self.width = other.width;
        self.height = other.height;
        self.spp = other.spp;
        self.rejected = other.rejected;
        for (a, b) in self.layers.iter_mut().zip(&other.layers) {
            a.sum.clone_from(&b.sum);
            a.sum_sq.clone_from(&b.sum_sq);
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn spp(&self) -> u32 {
        self.spp
    }
    pub fn rejected_samples(&self) -> u64 {
        self.rejected
    }
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Adds one pass: exactly one sample for every pixel, in pixel order. A sample
    /// that is not finite never enters a buffer: it counts as zero and is recorded.
    pub fn add_pass(&mut self, samples: &[PathSample]) {
        self.add_passes(&[samples]);
    }

    /// Adds several passes, in order: the same sums bit for bit as [`Film::add_pass`]
    /// once per pass (every pixel still receives its passes in order), with the four
    /// buffers accumulated on parallel threads, so the accumulation does not hold one
    /// core idle between batches of passes.
    pub fn add_passes<P: AsRef<[PathSample]> + Sync>(&mut self, passes: &[P]) {
        let n = self.pixel_count();
        for samples in passes {
            assert_eq!(samples.as_ref().len(), n, "a pass covers every pixel once");
        }
        let rejected: usize =
            passes.par_iter().map(|samples| samples.as_ref().iter().filter(|s| !s.is_finite()).count()).sum();
        self.layers.par_iter_mut().enumerate().for_each(|(k, layer)| {
            for samples in passes {
                for (i, s) in samples.as_ref().iter().enumerate() {
                    // A non-finite sample counts as zero.
                    let s = if s.is_finite() { *s } else { PathSample::default() };
                    let (d, l, h) = (s.direct.as_dvec3(), s.low.as_dvec3(), s.high.as_dvec3());
                    // Summed in f64, so full = direct + low + high to f64 rounding.
                    let v = match k {
                        0 => d,
                        1 => l,
                        2 => h,
                        _ => d + l + h,
                    };
                    layer.add(i, v.to_array());
                }
            }
        });
        self.rejected += rejected as u64;
        self.spp += passes.len() as u32;
    }

    /// Per-pixel mean (the image) of a buffer.
    pub fn mean(&self, buffer: Buffer) -> Vec<[f32; 3]> {
        let inv = if self.spp > 0 { 1.0 / self.spp as f64 } else { 0.0 };
        self.layers[buffer.index()].sum.iter().map(|s| s.map(|x| (x * inv) as f32)).collect()
    }

    /// Raw per-pixel sums (for exact comparisons in tests).
    pub fn sums(&self, buffer: Buffer) -> &[[f64; 3]] {
        &self.layers[buffer.index()].sum
    }

    /// Relative standard error of the image in `b`: sqrt(sum of the per-pixel
    /// variances of the mean / sum of the squared means), over pixels with light
    /// (luminance as the mean of the channels). Zero before any light arrives.
    pub fn relative_noise(&self, b: Buffer) -> f64 {
        self.relative_noise_over(b, |_| true)
    }

    /// [`Film::relative_noise`] over the cloud's pixels only: those that received
    /// scattered light (orders >= 1). The background, the sky seen unobstructed, has
    /// no variance and would dilute the figure (with a bright sky an image whose cloud
    /// is grainy reads as a few percent). Zero before any light is scattered.
    pub fn cloud_noise(&self, b: Buffer) -> f64 {
        let (low, high) = (&self.layers[Buffer::Low.index()].sum, &self.layers[Buffer::High.index()].sum);
        self.relative_noise_over(b, |i| (0..3).map(|c| low[i][c] + high[i][c]).sum::<f64>() > 0.0)
    }

    /// The relative noise of `b` over the lit pixels `i` with `include(i)`.
    fn relative_noise_over(&self, b: Buffer, include: impl Fn(usize) -> bool) -> f64 {
        let (mean, var) = (self.mean(b), self.variance_of_mean(b));
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for (i, (m, v)) in mean.iter().zip(&var).enumerate() {
            let l = (m[0] + m[1] + m[2]) as f64 / 3.0;
            if l > 0.0 && include(i) {
                num += (v[0] + v[1] + v[2]) as f64 / 3.0;
                den += l * l;
            }
        }
        if den > 0.0 { (num / den).sqrt() } else { 0.0 }
    }

    /// Per-pixel, per-channel variance of the pixel ESTIMATE (the sample variance
    /// divided by spp): the "variance" of docs/conventions.md's TTUV.
    pub fn variance_of_mean(&self, buffer: Buffer) -> Vec<[f32; 3]> {
        let n = self.spp as f64;
        let layer = &self.layers[buffer.index()];
        layer
            .sum
            .iter()
            .zip(&layer.sum_sq)
            .map(|(s, q)| {
                if self.spp < 2 {
                    return [0.0; 3];
                }
                std::array::from_fn(|c| {
                    let mean = s[c] / n;
                    let var = ((q[c] / n - mean * mean) * n / (n - 1.0)).max(0.0);
                    (var / n) as f32
                })
            })
            .collect()
    }

    /// Mean over all pixels and channels of a buffer's image.
    pub fn average(&self, buffer: Buffer) -> f64 {
        let sum: f64 = self.layers[buffer.index()].sum.iter().map(|s| s[0] + s[1] + s[2]).sum();
        sum / (3.0 * self.spp.max(1) as f64 * self.pixel_count().max(1) as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn rejects_non_finite_and_tracks_variance() {
        let mut f = Film::new(2, 1);
        let good = PathSample { direct: Vec3::ZERO, low: Vec3::ONE, high: Vec3::splat(2.0) };
        let bad = PathSample { direct: Vec3::ZERO, low: Vec3::NAN, high: Vec3::ONE };
        f.add_pass(&[good, bad]);
        f.add_pass(&[PathSample::default(), PathSample { high: Vec3::splat(f32::INFINITY), ..good }]);
        assert_eq!(f.rejected_samples(), 2);
        let m = f.mean(Buffer::Full);
        assert_eq!(m[0], [1.5; 3]);
        assert_eq!(m[1], [0.0; 3]);
        // Samples 3 and 0: sample variance 4.5, variance of the mean 2.25.
        assert!((f.variance_of_mean(Buffer::Full)[0][0] - 2.25).abs() < 1e-6);
        assert!(m.iter().flatten().all(|x| x.is_finite()));
        assert!((f.average(Buffer::Full) - 0.75).abs() < 1e-12);
    }

    /// Passes added as one batch give the sums of passes added one at a time, bit for
    /// bit, and reject the same non-finite samples.
    #[test]
    fn batched_passes_add_up_like_single_ones() {
        let mut rng = crate::Rng::new(5, 0, 0);
        let n = 37;
        let passes: Vec<Vec<PathSample>> = (0..5)
            .map(|p| {
                (0..n)
                    .map(|i| {
                        let mut v = || Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1e3;
                        let mut s = PathSample { direct: v(), low: v(), high: v() };
                        if (i + p) % 11 == 0 {
                            s.low.y = f32::NAN;
                        }
                        s
                    })
                    .collect()
            })
            .collect();
        let (mut one, mut batch) = (Film::new(n as u32, 1), Film::new(n as u32, 1));
        one.add_pass(&passes[0]);
        batch.add_pass(&passes[0]);
        for p in &passes[1..] {
            one.add_pass(p);
        }
        batch.add_passes(&passes[1..]);
        assert_eq!(batch.spp(), 5);
        assert_eq!(batch.rejected_samples(), one.rejected_samples());
        assert!(one.rejected_samples() > 0);
        for b in Buffer::ALL {
            assert!(one.sums(b) == batch.sums(b), "{b:?}");
            assert!(one.layers[b.index()].sum_sq == batch.layers[b.index()].sum_sq, "{b:?}");
        }
    }

    /// A copy into a film of another size, or of the same size (its memory reused),
    /// equals the source in every sum, count and dimension.
    #[test]
    fn copy_from_equals_the_source() {
        let mut src = Film::new(3, 2);
        let s = PathSample { direct: Vec3::splat(0.5), low: Vec3::new(1.0, 2.0, 3.0), high: Vec3::NAN };
        src.add_pass(&[s; 6]);
        src.add_pass(&[PathSample { high: Vec3::ONE, ..s }; 6]);
        for mut dst in [Film::new(1, 1), Film::new(3, 2), Film::new(8, 8)] {
            dst.add_pass(&vec![PathSample { low: Vec3::splat(9.0), ..Default::default() }; dst.pixel_count()]);
            let before = dst.layers[0].sum.as_ptr();
            let same_size = dst.pixel_count() == src.pixel_count();
            dst.copy_from(&src);
            assert_eq!((dst.width(), dst.height(), dst.spp(), dst.rejected_samples()), (3, 2, 2, 6));
            for b in Buffer::ALL {
                assert!(dst.sums(b) == src.sums(b), "{b:?}");
                assert!(dst.layers[b.index()].sum_sq == src.layers[b.index()].sum_sq, "{b:?}");
            }
            if same_size {
                assert_eq!(dst.layers[0].sum.as_ptr(), before, "the same size reuses the memory");
            }
        }
    }

    /// A bright, noiseless background pixel counts in the image's noise but not in the
    /// cloud's: the cloud's is that of the scattering pixel alone.
    #[test]
    fn cloud_noise_leaves_the_background_out() {
        let mut f = Film::new(2, 1);
        let sky = PathSample { direct: Vec3::splat(4.0), ..Default::default() };
        for v in [1.0f32, 3.0, 1.0, 3.0] {
            f.add_pass(&[sky, PathSample { direct: Vec3::ZERO, low: Vec3::splat(v), high: Vec3::ZERO }]);
        }
        // Cloud pixel: mean 2, sample variance 4/3, variance of the mean 1/3.
        let cloud = ((1.0f64 / 3.0) / 4.0).sqrt();
        assert!((f.cloud_noise(Buffer::Full) - cloud).abs() < 1e-6, "{}", f.cloud_noise(Buffer::Full));
        let all = ((1.0f64 / 3.0) / (4.0 + 16.0)).sqrt();
        assert!((f.relative_noise(Buffer::Full) - all).abs() < 1e-6);
        assert_eq!(Film::new(1, 1).cloud_noise(Buffer::Full), 0.0);
    }
}
