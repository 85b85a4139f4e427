//! Dense layers evaluated in f32 without allocation, shared by the models'
//! networks: weights stored input-major with the outputs padded to a multiple of 16,
//! a portable kernel, AVX2 + FMA kernels (one row, or several rows per loaded weight
//! vector) and an AVX-512 kernel (one row). Every kernel computes each output as the
//! same chain of fused multiply-adds over the inputs in order, so they give the same
//! bits.

use serde::{Deserialize, Serialize};

/// The activation of the hidden layers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Activation {
    Relu,
    Tanh,
    /// x * sigmoid(x)
    Silu,
}

impl Activation {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "relu" => Some(Activation::Relu),
            "tanh" => Some(Activation::Tanh),
            "silu" => Some(Activation::Silu),
            _ => None,
        }
    }

    #[inline(always)]
    pub(crate) fn apply(self, x: f32) -> f32 {
        match self {
            Activation::Relu => x.max(0.0),
            Activation::Tanh => x.tanh(),
            Activation::Silu => x / (1.0 + (-x).exp()),
        }
    }
}

/// One dense layer, weights stored input-major ([in][out_padded]) so that a forward
/// pass is a sequence of axpy's over contiguous output rows, which the compiler turns
/// into full-width vector FMAs.
#[derive(Clone, Debug)]
pub(crate) struct Dense {
    pub(crate) inputs: usize,
    pub(crate) outputs: usize,
    /// Outputs rounded up to a multiple of 16 (padding weights are zero).
    pub(crate) stride: usize,
    pub(crate) w: Vec<f32>,
    pub(crate) b: Vec<f32>,
}

impl Dense {
    /// From a row-major [out][in] weight matrix (candle's / PyTorch's layout).
    pub(crate) fn new(inputs: usize, outputs: usize, w_out_in: &[f32], b: &[f32]) -> Self {
        let stride = outputs.div_ceil(16) * 16;
        let mut w = vec![0.0; inputs * stride];
        for o in 0..outputs {
            for i in 0..inputs {
                w[i * stride + o] = w_out_in[o * inputs + i];
            }
        }
        let mut bb = vec![0.0; stride];
        bb[..outputs].copy_from_slice(b);
        Dense { inputs, outputs, stride, w, b: bb }
    }
}

/// The portable layer kernel: y[..stride] = act(W x + b), padding outputs included.
#[inline(always)]
pub(crate) fn layer_forward(layer: &Dense, x: &[f32], y: &mut [f32], act: Option<Activation>) {
    let s = layer.stride;
    let y = &mut y[..s];
    y.copy_from_slice(&layer.b);
    for (i, &xi) in x[..layer.inputs].iter().enumerate() {
        let row = &layer.w[i * s..(i + 1) * s];
        for (yo, wo) in y.chunks_exact_mut(16).zip(row.chunks_exact(16)) {
            for k in 0..16 {
                yo[k] = wo[k].mul_add(xi, yo[k]);
            }
        }
    }
    if let Some(a) = act {
        for v in y[..layer.outputs].iter_mut() {
            *v = a.apply(*v);
        }
    }
}

/// AVX2 + FMA kernel: outputs in register blocks of 64 (eight 8-wide accumulators,
/// then blocks of 16 for the rest of the padded row), inputs streamed through them, so
/// each weight is loaded once and the outputs stay in registers for the whole layer.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::{Activation, Dense};
    use std::arch::x86_64::*;

    /// Outputs b .. b + 8 NV of one layer.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA, b + 8 NV <= layer.stride, x.len() >= layer.inputs,
    /// y.len() >= layer.stride (and the layer was made by `Dense::new`, so w holds
    /// inputs * stride values and b holds stride values).
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn block<const NV: usize>(layer: &Dense, b: usize, x: &[f32], y: &mut [f32]) {
        let s = layer.stride;
        debug_assert!(b + 8 * NV <= s && x.len() >= layer.inputs && layer.w.len() >= layer.inputs * s && y.len() >= s);
        // SAFETY: every load reads w[i * s + b .. i * s + b + 8 NV] with i < inputs and
        // b + 8 NV <= s (so within w, which holds inputs * s values), the bias block
        // b .. b + 8 NV < s, and the store writes y[b .. b + 8 NV] within y[..s].
        unsafe {
            let mut acc = [_mm256_setzero_ps(); NV];
            for (j, a) in acc.iter_mut().enumerate() {
                *a = _mm256_loadu_ps(layer.b.as_ptr().add(b + 8 * j));
            }
            let w = layer.w.as_ptr();
            for (i, &xi) in x[..layer.inputs].iter().enumerate() {
                let xv = _mm256_set1_ps(xi);
                let row = w.add(i * s + b);
                for (j, a) in acc.iter_mut().enumerate() {
                    *a = _mm256_fmadd_ps(_mm256_loadu_ps(row.add(8 * j)), xv, *a);
                }
            }
            for (j, a) in acc.iter().enumerate() {
                _mm256_storeu_ps(y.as_mut_ptr().add(b + 8 * j), *a);
            }
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn layer_forward(layer: &Dense, x: &[f32], y: &mut [f32], act: Option<Activation>) {
        let s = layer.stride;
        assert!(x.len() >= layer.inputs && y.len() >= s);
        let mut b = 0;
        // SAFETY: this function runs only with AVX2 + FMA (its target features), the
        // assert above bounds x and y, and every block ends at or before s (a multiple
        // of 16).
        while b + 64 <= s {
            unsafe { block::<8>(layer, b, x, y) };
            b += 64;
        }
        while b < s {
            unsafe { block::<2>(layer, b, x, y) };
            b += 16;
        }
        if let Some(a) = act {
            for v in y[..layer.outputs].iter_mut() {
                *v = a.apply(*v);
            }
        }
    }

    /// Outputs b .. b + 16 of one layer for R rows at once: rows r's input is
    /// xs[r * ws ..], its output ys[r * ws ..]. Each weight vector is loaded once and
    /// used for all R rows (2 R accumulators), which is what makes a batch cheaper
    /// per row than single passes: a single pass is bound by streaming the weights.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA, b + 16 <= layer.stride, and for r < R,
    /// xs.len() >= r * ws + layer.inputs and ys.len() >= r * ws + layer.stride.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn block_rows<const R: usize>(layer: &Dense, b: usize, xs: &[f32], ws: usize, ys: &mut [f32]) {
        let s = layer.stride;
        debug_assert!(b + 16 <= s && xs.len() >= (R - 1) * ws + layer.inputs && ys.len() >= (R - 1) * ws + s);
        // SAFETY: the weight loads read w[i * s + b .. + 16] with i < inputs and
        // b + 16 <= s; the input reads xs[r * ws + i] with i < inputs; the stores write
        // ys[r * ws + b .. + 16] within r * ws + s; all bounded by the caller's contract.
        unsafe {
            let bias = [_mm256_loadu_ps(layer.b.as_ptr().add(b)), _mm256_loadu_ps(layer.b.as_ptr().add(b + 8))];
            let mut acc = [[bias[0], bias[1]]; R];
            let w = layer.w.as_ptr();
            let x = xs.as_ptr();
            for i in 0..layer.inputs {
                let row = w.add(i * s + b);
                let (w0, w1) = (_mm256_loadu_ps(row), _mm256_loadu_ps(row.add(8)));
                for (r, a) in acc.iter_mut().enumerate() {
                    let xv = _mm256_set1_ps(*x.add(r * ws + i));
                    a[0] = _mm256_fmadd_ps(w0, xv, a[0]);
                    a[1] = _mm256_fmadd_ps(w1, xv, a[1]);
                }
            }
            for (r, a) in acc.iter().enumerate() {
                _mm256_storeu_ps(ys.as_mut_ptr().add(r * ws + b), a[0]);
                _mm256_storeu_ps(ys.as_mut_ptr().add(r * ws + b + 8), a[1]);
            }
        }
    }

    /// [`layer_forward`] for `rows` rows at once (row r at xs[r * ws ..], its output
    /// at ys[r * ws ..]), four rows per weight pass.
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn layer_forward_rows(
        layer: &Dense,
        xs: &[f32],
        ys: &mut [f32],
        rows: usize,
        ws: usize,
        act: Option<Activation>,
    ) {
        let s = layer.stride;
        assert!(rows > 0 && ws >= s && ws >= layer.inputs);
        assert!(xs.len() >= (rows - 1) * ws + layer.inputs && ys.len() >= (rows - 1) * ws + s);
        let mut b = 0;
        while b < s {
            let mut r = 0;
            // SAFETY: AVX2 + FMA are this function's target features; b + 16 <= s (s
            // is a multiple of 16); the asserts above bound every row r < rows.
            while r + 4 <= rows {
                unsafe { block_rows::<4>(layer, b, &xs[r * ws..], ws, &mut ys[r * ws..]) };
                r += 4;
            }
            while r < rows {
                unsafe { block_rows::<1>(layer, b, &xs[r * ws..], ws, &mut ys[r * ws..]) };
                r += 1;
            }
            b += 16;
        }
        if let Some(a) = act {
            for r in 0..rows {
                for v in ys[r * ws..r * ws + layer.outputs].iter_mut() {
                    *v = a.apply(*v);
                }
            }
        }
    }
}

/// The layer kernels a CPU can run, fastest last.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    Portable,
    /// 8-wide FMAs (x86-64 with AVX2 and FMA).
    Avx2,
    /// 16-wide FMAs (x86-64 with AVX-512F).
    Avx512,
}

impl Kernel {
    /// Whether this CPU runs the kernel.
    pub fn available(self) -> bool {
        match self {
            Kernel::Portable => true,
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma"),
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx512 => std::arch::is_x86_feature_detected!("avx512f"),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The kernel the networks run: the fastest this CPU runs, or the one the
    /// environment variable `NIMBUS_NN_KERNEL` names (portable, avx2 or avx512) where
    /// the CPU runs it, so that builds can be compared on one machine (the outputs are
    /// the same bits, only the time differs). Decided once per process.
    pub fn best() -> Kernel {
        static BEST: std::sync::OnceLock<Kernel> = std::sync::OnceLock::new();
        *BEST.get_or_init(|| {
            let fastest =
                [Kernel::Avx512, Kernel::Avx2].into_iter().find(|k| k.available()).unwrap_or(Kernel::Portable);
            match std::env::var("NIMBUS_NN_KERNEL").ok().as_deref().and_then(Kernel::parse) {
                Some(k) if k.available() => k,
                _ => fastest,
            }
        })
    }

    pub fn parse(s: &str) -> Option<Kernel> {
        [Kernel::Portable, Kernel::Avx2, Kernel::Avx512].into_iter().find(|k| k.name() == s)
    }

    pub fn name(self) -> &'static str {
        match self {
            Kernel::Portable => "portable",
            Kernel::Avx2 => "avx2",
            Kernel::Avx512 => "avx512",
        }
    }

    /// One layer with this kernel: y[..stride] = act(W x + b), padding outputs
    /// included. A kernel this CPU does not run falls back to the portable one, which
    /// gives the same bits; the check is a cached feature test per layer.
    #[inline]
    pub(crate) fn layer_forward(self, layer: &Dense, x: &[f32], y: &mut [f32], act: Option<Activation>) {
        match self {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: the CPU has AVX-512F (checked by `available`).
            Kernel::Avx512 if self.available() => unsafe { avx512::layer_forward(layer, x, y, act) },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: the CPU has AVX2 and FMA (checked by `available`).
            Kernel::Avx2 if self.available() => unsafe { avx2::layer_forward(layer, x, y, act) },
            _ => layer_forward(layer, x, y, act),
        }
    }

    /// `rows` rows through one layer (row r's input at xs[r * ws ..], its output at
    /// ys[r * ws ..], ws at least the layer's stride and inputs): several rows per
    /// loaded weight vector where the CPU has AVX2 + FMA, else row by row; the same
    /// bits as [`Kernel::layer_forward`] on each row either way.
    #[inline]
    pub(crate) fn layer_forward_rows(
        self,
        layer: &Dense,
        xs: &[f32],
        ys: &mut [f32],
        rows: usize,
        ws: usize,
        act: Option<Activation>,
    ) {
        #[cfg(target_arch = "x86_64")]
        if self != Kernel::Portable && Kernel::Avx2.available() {
            // SAFETY: the CPU has AVX2 and FMA (checked above).
            unsafe { avx2::layer_forward_rows(layer, xs, ys, rows, ws, act) };
            return;
        }
        for r in 0..rows {
            self.layer_forward(layer, &xs[r * ws..], &mut ys[r * ws..], act);
        }
    }
}

/// AVX-512F kernel for one row: the outputs in register blocks of up to 256 (sixteen
/// 16-wide accumulators, so layers up to 256 wide take one pass over the inputs),
/// each weight loaded once. On cores whose 512-bit units run at full width (AMD Zen 5,
/// recent Intel server cores) this halves the instructions of the AVX2 kernel; the
/// loads of a single row's pass are what bind it (every weight once), 64 bytes each.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512 {
    use super::{Activation, Dense};
    use std::arch::x86_64::*;

    /// Outputs b .. b + 16 NV of one layer.
    ///
    /// # Safety
    /// The CPU has AVX-512F, b + 16 NV <= layer.stride, x.len() >= layer.inputs,
    /// y.len() >= layer.stride (and the layer was made by `Dense::new`, so w holds
    /// inputs * stride values and b holds stride values).
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn block<const NV: usize>(layer: &Dense, b: usize, x: &[f32], y: &mut [f32]) {
        let s = layer.stride;
        debug_assert!(b + 16 * NV <= s && x.len() >= layer.inputs && layer.w.len() >= layer.inputs * s && y.len() >= s);
        // SAFETY: every load reads w[i * s + b .. i * s + b + 16 NV] with i < inputs and
        // b + 16 NV <= s (so within w, which holds inputs * s values), the bias block
        // b .. b + 16 NV <= s, and the store writes y[b .. b + 16 NV] within y[..s].
        unsafe {
            let mut acc = [_mm512_setzero_ps(); NV];
            for (j, a) in acc.iter_mut().enumerate() {
                *a = _mm512_loadu_ps(layer.b.as_ptr().add(b + 16 * j));
            }
            let w = layer.w.as_ptr();
            for (i, &xi) in x[..layer.inputs].iter().enumerate() {
                let xv = _mm512_set1_ps(xi);
                let row = w.add(i * s + b);
                for (j, a) in acc.iter_mut().enumerate() {
                    *a = _mm512_fmadd_ps(_mm512_loadu_ps(row.add(16 * j)), xv, *a);
                }
            }
            for (j, a) in acc.iter().enumerate() {
                _mm512_storeu_ps(y.as_mut_ptr().add(b + 16 * j), *a);
            }
        }
    }

    #[target_feature(enable = "avx512f")]
    pub(crate) fn layer_forward(layer: &Dense, x: &[f32], y: &mut [f32], act: Option<Activation>) {
        let s = layer.stride;
        assert!(x.len() >= layer.inputs && y.len() >= s);
        let mut b = 0;
        // SAFETY: this function runs only with AVX-512F (its target feature), the
        // assert above bounds x and y, and every block ends at or before s (a multiple
        // of 16): the first loop's at b + 256 <= s, the last one's at b + 16 (s - b) / 16.
        unsafe {
            while b + 256 <= s {
                block::<16>(layer, b, x, y);
                b += 256;
            }
            match (s - b) / 16 {
                0 => {}
                1 => block::<1>(layer, b, x, y),
                2 => block::<2>(layer, b, x, y),
                3 => block::<3>(layer, b, x, y),
                4 => block::<4>(layer, b, x, y),
                5 => block::<5>(layer, b, x, y),
                6 => block::<6>(layer, b, x, y),
                7 => block::<7>(layer, b, x, y),
                8 => block::<8>(layer, b, x, y),
                9 => block::<9>(layer, b, x, y),
                10 => block::<10>(layer, b, x, y),
                11 => block::<11>(layer, b, x, y),
                12 => block::<12>(layer, b, x, y),
                13 => block::<13>(layer, b, x, y),
                14 => block::<14>(layer, b, x, y),
                _ => block::<15>(layer, b, x, y),
            }
        }
        if let Some(a) = act {
            for v in y[..layer.outputs].iter_mut() {
                *v = a.apply(*v);
            }
        }
    }
}
