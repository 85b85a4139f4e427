//! Seeded random streams.
//!
//! Every stream is a PCG32 generator whose state and stream selector are derived from
//! (scene seed, pass index, pixel or sample index) by a 64-bit mixing function, so a
//! single path can be replayed alone and an image does not depend on the thread count
//! (docs/conventions.md, Reproducibility).

/// SplitMix64 finalizer: a bijective 64-bit mixer with good avalanche.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// PCG32 (XSH-RR 64/32) random number generator.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
    inc: u64,
}

impl Rng {
    const MULT: u64 = 6_364_136_223_846_793_005;

    /// A stream identified by three integers, e.g. (seed, pass, pixel).
    pub fn new(seed: u64, a: u64, b: u64) -> Self {
        let s = mix64(seed ^ mix64(a.wrapping_mul(0xD1B5_4A32_D192_ED03) ^ mix64(b)));
        let inc = (mix64(s ^ 0x5851_F42D_4C95_7F2D) << 1) | 1;
        let mut rng = Rng { state: 0, inc };
        rng.next_u32();
        rng.state = rng.state.wrapping_add(s);
        rng.next_u32();
        rng
    }

    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(Self::MULT).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// 64 random bits: the next two 32-bit outputs, the first in the high half.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        let hi = self.next_u32() as u64;
        (hi << 32) | self.next_u32() as u64
    }

    /// Uniform in [0, 1), with 24 bits of resolution (never returns 1.0).
    #[inline]
    pub fn uniform(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    #[inline]
    pub fn uniform2(&mut self) -> glam::Vec2 {
        let x = self.uniform();
        glam::Vec2::new(x, self.uniform())
    }

    /// Uniform in [0, 1) as f64 with 53 bits, for tests and data generation.
    #[inline]
    pub fn uniform_f64(&mut self) -> f64 {
        let hi = (self.next_u32() as u64) << 21;
        let lo = (self.next_u32() >> 11) as u64;
        (hi | lo) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_differ_and_repeat() {
        let mut a = Rng::new(1, 2, 3);
        let mut b = Rng::new(1, 2, 3);
        let mut c = Rng::new(1, 2, 4);
        let va: Vec<u32> = (0..8).map(|_| a.next_u32()).collect();
        let vb: Vec<u32> = (0..8).map(|_| b.next_u32()).collect();
        let vc: Vec<u32> = (0..8).map(|_| c.next_u32()).collect();
        assert_eq!(va, vb);
        assert_ne!(va, vc);
    }

    #[test]
    fn uniform_mean_and_range() {
        // Mean of U(0,1) is 1/2 with standard error sqrt(1/12 / n).
        let mut r = Rng::new(7, 0, 0);
        let n = 1_000_000;
        let mut sum = 0.0f64;
        for _ in 0..n {
            let u = r.uniform();
            assert!((0.0..1.0).contains(&u));
            sum += u as f64;
        }
        let se = (1.0 / 12.0 / n as f64).sqrt();
        assert!((sum / n as f64 - 0.5).abs() < 5.0 * se);
    }
}
