//! A multilayer perceptron of [`Dense`] layers (the global and cloud-aware models'
//! network), evaluated in f32 without allocation, with the fastest layer kernel the
//! CPU runs (AVX-512F, AVX2 + FMA, or portable; the same bits from each).

use super::dense::{Activation, Dense, Kernel};

/// The MLP evaluated in f32 without allocation.
#[derive(Clone, Debug)]
pub struct Mlp {
    layers: Vec<Dense>,
    activation: Activation,
    /// Widest padded layer: the scratch size.
    width: usize,
}

/// Per-thread scratch space of the evaluator.
#[derive(Clone, Debug, Default)]
pub struct Scratch {
    a: Vec<f32>,
    b: Vec<f32>,
    /// The caller's input row (the global model standardizes its features here).
    pub(crate) features: Vec<f32>,
    /// [`BATCH_ROWS`] rows of the batched pass, each `width` apart (sized on its
    /// first use).
    rows_a: Vec<f32>,
    rows_b: Vec<f32>,
    /// The caller's input rows for a batch (the models standardize their features here).
    pub(crate) batch: Vec<f32>,
}

/// Rows [`Mlp::forward_batch`] passes through the layers together.
pub const BATCH_ROWS: usize = 16;

/// The forward pass with one layer kernel.
#[inline(always)]
fn forward_with(mlp: &Mlp, x: &[f32], scratch: &mut Scratch, kernel: Kernel) -> f32 {
    let (mut cur, mut next) = (std::mem::take(&mut scratch.a), std::mem::take(&mut scratch.b));
    cur[..x.len()].copy_from_slice(x);
    let last = mlp.layers.len() - 1;
    for (l, layer) in mlp.layers.iter().enumerate() {
        kernel.layer_forward(layer, &cur, &mut next, (l < last).then_some(mlp.activation));
        std::mem::swap(&mut cur, &mut next);
    }
    let out = cur[0];
    scratch.a = cur;
    scratch.b = next;
    out
}

impl Mlp {
    /// Layers as (inputs, outputs, row-major [out][in] weights, bias).
    pub fn new(layers: &[(usize, usize, Vec<f32>, Vec<f32>)], activation: Activation) -> Self {
        let layers: Vec<Dense> = layers.iter().map(|(i, o, w, b)| Dense::new(*i, *o, w, b)).collect();
        let width = layers.iter().map(|l| l.stride.max(l.inputs)).max().unwrap_or(16);
        Mlp { layers, activation, width }
    }

    /// The MLP of a safetensors file with layers `layers.L.weight` ([out, in]) and
    /// `layers.L.bias` for the layer widths `widths` (inputs first, 1 output last);
    /// refuses missing tensors, other shapes and non-finite values, saying which.
    pub fn from_safetensors(bytes: &[u8], widths: &[usize], activation: Activation) -> Result<Self, String> {
        let tensors = candle_core::safetensors::load_buffer(bytes, &candle_core::Device::Cpu)
            .map_err(|e| format!("not a readable safetensors file: {e}"))?;
        let mut layers = vec![];
        for l in 0..widths.len() - 1 {
            let (i, o) = (widths[l], widths[l + 1]);
            let get = |name: String, shape: &[usize]| -> Result<Vec<f32>, String> {
                let t = tensors.get(&name).ok_or_else(|| format!("tensor {name} is missing"))?;
                if t.dims() != shape {
                    return Err(format!("tensor {name} has shape {:?}, expected {shape:?}", t.dims()));
                }
                let v: Vec<f32> = t
                    .to_dtype(candle_core::DType::F32)
                    .and_then(|t| t.flatten_all())
                    .and_then(|t| t.to_vec1())
                    .map_err(|e| format!("tensor {name}: {e}"))?;
                if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                    return Err(format!("tensor {name} holds a non-finite value at {k}"));
                }
                Ok(v)
            };
            layers.push((i, o, get(format!("layers.{l}.weight"), &[o, i])?, get(format!("layers.{l}.bias"), &[o])?));
        }
        Ok(Mlp::new(&layers, activation))
    }

    pub fn n_inputs(&self) -> usize {
        self.layers[0].inputs
    }

    /// Scratch space for this network (allocate once per thread).
    pub fn scratch(&self) -> Scratch {
        Scratch {
            a: vec![0.0; self.width],
            b: vec![0.0; self.width],
            features: vec![0.0; self.n_inputs()],
            ..Default::default()
        }
    }

    /// Sizes `scratch` for this network if it is too small.
    pub(crate) fn ensure(&self, scratch: &mut Scratch) {
        if scratch.a.len() < self.width || scratch.features.len() < self.n_inputs() {
            *scratch = self.scratch();
        }
    }

    /// The network's output for one (standardized) input; allocation free once
    /// `scratch` has been sized by [`Mlp::scratch`].
    #[inline]
    pub fn forward(&self, x: &[f32], scratch: &mut Scratch) -> f32 {
        self.ensure(scratch);
        self.forward_sized(x, scratch)
    }

    /// [`Mlp::forward`] with `scratch` already sized by [`Mlp::ensure`].
    #[inline]
    pub(crate) fn forward_sized(&self, x: &[f32], scratch: &mut Scratch) -> f32 {
        debug_assert_eq!(x.len(), self.n_inputs());
        forward_with(self, x, scratch, Kernel::best())
    }

    /// [`Mlp::forward`] with a chosen layer kernel, for tests and benchmarks; None if
    /// this CPU does not run it.
    pub fn forward_with_kernel(&self, kernel: Kernel, x: &[f32], scratch: &mut Scratch) -> Option<f32> {
        if !kernel.available() {
            return None;
        }
        self.ensure(scratch);
        Some(forward_with(self, x, scratch, kernel))
    }

    /// The portable forward pass (what CPUs without AVX2 + FMA run), for tests.
    pub fn forward_portable(&self, x: &[f32], scratch: &mut Scratch) -> f32 {
        self.ensure(scratch);
        forward_with(self, x, scratch, Kernel::Portable)
    }

    /// The layers as (weights [out][in] row-major, bias): the layout they were made from.
    pub fn layers_out_in(&self) -> Vec<(Vec<f32>, Vec<f32>)> {
        self.layers
            .iter()
            .map(|l| {
                let mut w = vec![0.0f32; l.outputs * l.inputs];
                for o in 0..l.outputs {
                    for i in 0..l.inputs {
                        w[o * l.inputs + i] = l.w[i * l.stride + o];
                    }
                }
                (w, l.b[..l.outputs].to_vec())
            })
            .collect()
    }

    /// [`Mlp::forward_batch`] on raw rows `stride` apart, each row's first n_inputs
    /// values standardized by `standardize(k, v)` (input k's value v) into the scratch's
    /// batch rows first: the models' batched predictions, each standardizing as its
    /// single-row path does.
    pub(crate) fn forward_batch_standardized(
        &self,
        raw: &[f32],
        stride: usize,
        out: &mut [f32],
        scratch: &mut Scratch,
        standardize: impl Fn(usize, f32) -> f32,
    ) {
        let n = self.n_inputs();
        assert!(stride >= n && raw.len() >= out.len().saturating_sub(1) * stride + n, "feature rows");
        let mut x = std::mem::take(&mut scratch.batch);
        x.resize(out.len() * n, 0.0);
        for (r, row) in x.chunks_exact_mut(n).enumerate() {
            for (k, (xk, &v)) in row.iter_mut().zip(&raw[r * stride..r * stride + n]).enumerate() {
                *xk = standardize(k, v);
            }
        }
        self.forward_batch(&x, out, scratch);
        scratch.batch = x;
    }

    /// Batched entry point: `xs` holds rows of n_inputs values, one output per row, the
    /// same bits as [`Mlp::forward`] on each. [`BATCH_ROWS`] rows at a time pass
    /// through each layer together, so a weight is loaded once for several rows (a
    /// single row's pass is bound by streaming the weights). Allocation free once
    /// `scratch` has served a batch of this network.
    pub fn forward_batch(&self, xs: &[f32], out: &mut [f32], scratch: &mut Scratch) {
        let n = self.n_inputs();
        assert_eq!(xs.len(), n * out.len(), "rows and outputs");
        let ws = self.width;
        if scratch.rows_a.len() < BATCH_ROWS * ws {
            scratch.rows_a = vec![0.0; BATCH_ROWS * ws];
            scratch.rows_b = vec![0.0; BATCH_ROWS * ws];
        }
        let kernel = Kernel::best();
        let (mut cur, mut next) = (std::mem::take(&mut scratch.rows_a), std::mem::take(&mut scratch.rows_b));
        let last = self.layers.len() - 1;
        for (xg, og) in xs.chunks(BATCH_ROWS * n).zip(out.chunks_mut(BATCH_ROWS)) {
            let rows = og.len();
            for (r, x) in xg.chunks_exact(n).enumerate() {
                cur[r * ws..r * ws + n].copy_from_slice(x);
            }
            for (l, layer) in self.layers.iter().enumerate() {
                kernel.layer_forward_rows(layer, &cur, &mut next, rows, ws, (l < last).then_some(self.activation));
                std::mem::swap(&mut cur, &mut next);
            }
            for (r, o) in og.iter_mut().enumerate() {
                *o = cur[r * ws];
            }
        }
        (scratch.rows_a, scratch.rows_b) = (cur, next);
    }
}
