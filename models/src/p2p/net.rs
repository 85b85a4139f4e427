//! The point-to-point model's networks (thesis 6.2.1, figure 6.4), in candle for
//! training and as an allocation-free evaluator for rendering.
//!
//! The deep residual network takes the density features one level at a time: block b
//! (a few fully connected ReLU layers of equal width) sees the previous block's
//! output next to level b's densities, its output is added to the previous block's
//! (a residual connection), the local levels come first from the smallest
//! neighbourhood out, then the global levels from the smallest out, and the last block
//! also gets the diffusion feature phi_D. A linear layer gives the output. The
//! thesis's MLP baselines (all features into the first layer) are the other
//! architecture.

use super::features::{LevelSlice, P2pFeatures};
#[cfg(target_arch = "x86_64")]
use crate::nn::dense::avx2;
use crate::nn::dense::{Activation, Dense, Kernel, layer_forward};
use crate::nn::optim::{OptState, Optimizer};
use candle_core::{DType, Device, Tensor, Var};
use engine::Rng;

#[derive(Clone, Debug, PartialEq)]
pub enum P2pArch {
    /// Thesis figure 6.4: `layers` ReLU layers of `width` units per block.
    Residual { width: usize, layers: usize },
    /// A plain MLP with these hidden widths (the thesis's baselines).
    Mlp { hidden: Vec<usize> },
}

impl Default for P2pArch {
    /// The thesis's choice: 3 layers of 200 units per block.
    fn default() -> Self {
        P2pArch::Residual { width: 200, layers: 3 }
    }
}

/// The network's parameters as candle variables.
pub struct P2pNetwork {
    pub arch: P2pArch,
    /// Feature slices per block (residual) in input order; the last entry of the
    /// input row is phi_D.
    slices: Vec<LevelSlice>,
    n_inputs: usize,
    /// Per block (one block for the MLP), its layers.
    blocks: Vec<Vec<(Var, Var)>>,
    out: (Var, Var),
}

fn glorot(rng: &mut Rng, i: usize, o: usize, dev: &Device) -> candle_core::Result<(Var, Var)> {
    let limit = (6.0 / (i + o) as f64).sqrt() as f32;
    let w: Vec<f32> = (0..i * o).map(|_| (2.0 * rng.uniform() - 1.0) * limit).collect();
    Ok((Var::from_tensor(&Tensor::from_vec(w, (o, i), dev)?)?, Var::from_tensor(&Tensor::zeros(o, DType::F32, dev)?)?))
}

impl P2pNetwork {
    /// Glorot-uniform weights, zero biases, from a seeded generator.
    pub fn new(features: &P2pFeatures, arch: P2pArch, seed: u64, dev: &Device) -> candle_core::Result<Self> {
        let mut rng = Rng::new(seed, 0x7032_706e, 0); // "p2pn"
        let slices = features.slices();
        let n_inputs = features.len();
        let mut blocks = vec![];
        let last_width = match &arch {
            P2pArch::Residual { width, layers } => {
                for (b, s) in slices.iter().enumerate() {
                    let mut input = s.len + if b > 0 { *width } else { 0 };
                    if b + 1 == slices.len() {
                        input += 1; // phi_D
                    }
                    let mut block = vec![];
                    for l in 0..*layers {
                        block.push(glorot(&mut rng, if l == 0 { input } else { *width }, *width, dev)?);
                    }
                    blocks.push(block);
                }
                *width
            }
            P2pArch::Mlp { hidden } => {
                let mut block = vec![];
                let mut input = n_inputs;
                for &h in hidden {
                    block.push(glorot(&mut rng, input, h, dev)?);
                    input = h;
                }
                blocks.push(block);
                input
            }
        };
        let out = glorot(&mut rng, last_width, 1, dev)?;
        Ok(P2pNetwork { arch, slices, n_inputs, blocks, out })
    }

    pub fn n_inputs(&self) -> usize {
        self.n_inputs
    }

    pub fn vars(&self) -> Vec<&Var> {
        let mut v: Vec<&Var> = self.blocks.iter().flatten().flat_map(|(w, b)| [w, b]).collect();
        v.extend([&self.out.0, &self.out.1]);
        v
    }

    /// Named tensors: blocks.B.L.weight / .bias and out.weight / out.bias.
    pub fn named(&self) -> std::collections::HashMap<String, Tensor> {
        let mut m = std::collections::HashMap::new();
        for (b, block) in self.blocks.iter().enumerate() {
            for (l, (w, bias)) in block.iter().enumerate() {
                m.insert(format!("blocks.{b}.{l}.weight"), w.as_tensor().clone());
                m.insert(format!("blocks.{b}.{l}.bias"), bias.as_tensor().clone());
            }
        }
        m.insert("out.weight".into(), self.out.0.as_tensor().clone());
        m.insert("out.bias".into(), self.out.1.as_tensor().clone());
        m
    }

    /// Sets every parameter from `named` (as [`P2pNetwork::named`] writes them),
    /// checking names and shapes.
    pub fn load_named(&self, named: &std::collections::HashMap<String, Tensor>) -> Result<(), String> {
        let mine = self.named();
        if named.len() != mine.len() {
            return Err(format!("{} tensors, the architecture has {}", named.len(), mine.len()));
        }
        let set = |name: &str, var: &Var| -> Result<(), String> {
            let t = named.get(name).ok_or_else(|| format!("tensor {name} is missing"))?;
            if t.dims() != var.as_tensor().dims() {
                return Err(format!("{name} has shape {:?}, the architecture {:?}", t.dims(), var.as_tensor().dims()));
            }
            let t = t.to_dtype(DType::F32).map_err(|e| e.to_string())?;
            if t.flatten_all()
                .and_then(|f| f.to_vec1::<f32>())
                .map_err(|e| e.to_string())?
                .iter()
                .any(|v| !v.is_finite())
            {
                return Err(format!("{name} holds a NaN or infinity"));
            }
            var.set(&t).map_err(|e| e.to_string())
        };
        for (b, block) in self.blocks.iter().enumerate() {
            for (l, (w, bias)) in block.iter().enumerate() {
                set(&format!("blocks.{b}.{l}.weight"), w)?;
                set(&format!("blocks.{b}.{l}.bias"), bias)?;
            }
        }
        set("out.weight", &self.out.0)?;
        set("out.bias", &self.out.1)
    }

    pub fn parameters(&self) -> usize {
        self.vars().iter().map(|v| v.as_tensor().elem_count()).sum()
    }

    /// Rows of `n_inputs` features in, one value per row out.
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let dense = |h: &Tensor, (w, b): &(Var, Var)| h.matmul(&w.as_tensor().t()?)?.broadcast_add(b.as_tensor());
        let h = match &self.arch {
            P2pArch::Residual { .. } => {
                let mut prev: Option<Tensor> = None;
                for (b, (s, block)) in self.slices.iter().zip(&self.blocks).enumerate() {
                    let mut parts = vec![];
                    if let Some(p) = &prev {
                        parts.push(p.clone());
                    }
                    parts.push(x.narrow(1, s.start, s.len)?);
                    if b + 1 == self.slices.len() {
                        parts.push(x.narrow(1, self.n_inputs - 1, 1)?);
                    }
                    let mut h = Tensor::cat(&parts, 1)?;
                    for layer in block {
                        h = dense(&h, layer)?.relu()?;
                    }
                    prev = Some(match prev {
                        Some(p) => (h + p)?,
                        None => h,
                    });
                }
                prev.expect("at least one block")
            }
            P2pArch::Mlp { .. } => {
                let mut h = x.clone();
                for layer in &self.blocks[0] {
                    h = dense(&h, layer)?.relu()?;
                }
                h
            }
        };
        dense(&h, &self.out)?.squeeze(1)
    }

    /// The allocation-free evaluator of the same weights.
    pub fn evaluator(&self) -> candle_core::Result<P2pEvaluator> {
        let conv = |(w, b): &(Var, Var)| -> candle_core::Result<Dense> {
            let (o, i) = w.as_tensor().dims2()?;
            let w: Vec<f32> = w.as_tensor().flatten_all()?.to_vec1()?;
            Ok(Dense::new(i, o, &w, &b.as_tensor().to_vec1::<f32>()?))
        };
        let blocks: Vec<Vec<Dense>> =
            self.blocks.iter().map(|b| b.iter().map(conv).collect()).collect::<candle_core::Result<_>>()?;
        let out_w: Vec<f32> = self.out.0.as_tensor().flatten_all()?.to_vec1()?;
        let out_b = self.out.1.as_tensor().to_vec1::<f32>()?[0];
        Ok(P2pEvaluator::new(
            matches!(self.arch, P2pArch::Residual { .. }),
            self.slices.clone(),
            self.n_inputs,
            blocks,
            (out_w, out_b),
        ))
    }

    /// Trains on rows `x` (n x n_inputs) and targets `y` with Adam and mean squared
    /// error for `epochs` passes in shuffled batches; returns the loss per epoch.
    pub fn fit(
        &self,
        x: &[f32],
        y: &[f32],
        epochs: usize,
        batch: usize,
        lr: f64,
        seed: u64,
    ) -> candle_core::Result<Vec<f64>> {
        let mut opt = OptState::new(&self.vars())?;
        (0..epochs).map(|e| self.fit_epoch(x, y, batch, lr, seed.wrapping_add(e as u64), &mut opt)).collect()
    }

    /// One epoch of [`P2pNetwork::fit`] with the optimizer state kept by the caller
    /// (checkpoints); the shuffle is a pure function of `seed`. Returns the mean loss.
    pub(crate) fn fit_epoch(
        &self,
        x: &[f32],
        y: &[f32],
        batch: usize,
        lr: f64,
        seed: u64,
        opt: &mut OptState,
    ) -> candle_core::Result<f64> {
        let dev = Device::Cpu;
        let n = y.len();
        let vars = self.vars();
        let mut order: Vec<usize> = (0..n).collect();
        let mut rng = Rng::new(seed, 0x666974, 0);
        for i in (1..n).rev() {
            order.swap(i, ((rng.uniform_f64() * (i + 1) as f64) as usize).min(i));
        }
        let (mut sum, mut count) = (0.0, 0);
        for chunk in order.chunks(batch.max(1)) {
            let xb: Vec<f32> =
                chunk.iter().flat_map(|&r| x[r * self.n_inputs..(r + 1) * self.n_inputs].iter().copied()).collect();
            let yb: Vec<f32> = chunk.iter().map(|&r| y[r]).collect();
            let xt = Tensor::from_vec(xb, (chunk.len(), self.n_inputs), &dev)?;
            let yt = Tensor::from_vec(yb, chunk.len(), &dev)?;
            let loss = candle_nn::loss::mse(&self.forward(&xt)?, &yt)?;
            let grads = loss.backward()?;
            opt.apply(Optimizer::Adam, lr, &vars, &grads)?;
            sum += loss.to_scalar::<f32>()? as f64 * chunk.len() as f64;
            count += chunk.len();
        }
        Ok(sum / count.max(1) as f64)
    }
}

/// Forward passes without allocation: per-thread scratch, weights stored input-major
/// with padded rows (`global::Dense`), evaluated by the global model's AVX2 + FMA
/// kernels: a single pass streams each weight once with the outputs held in
/// registers; a batch applies each weight vector to four rows while it is loaded.
#[derive(Clone, Debug)]
pub struct P2pEvaluator {
    residual: bool,
    slices: Vec<LevelSlice>,
    n_inputs: usize,
    blocks: Vec<Vec<Dense>>,
    /// The linear output layer: weights over the last hidden layer, bias.
    out_w: Vec<f32>,
    out_b: f32,
    /// The widest layer input or padded output: the scratch row size.
    widest: usize,
}

/// Scratch space of [`P2pEvaluator`]: sized once, reused.
#[derive(Clone, Debug, Default)]
pub struct P2pScratch {
    a: Vec<f32>,
    b: Vec<f32>,
    prev: Vec<f32>,
}

/// Scratch space of the batched evaluator (sized on first use): BATCH rows.
#[derive(Clone, Debug, Default)]
pub struct P2pBatchScratch {
    width: usize,
    a: Vec<f32>,
    b: Vec<f32>,
    prev: Vec<f32>,
}

/// Rows evaluated together by [`P2pEvaluator::forward_batch`].
pub const BATCH: usize = 8;

const RELU: Option<Activation> = Some(Activation::Relu);

impl P2pEvaluator {
    fn new(
        residual: bool,
        slices: Vec<LevelSlice>,
        n_inputs: usize,
        blocks: Vec<Vec<Dense>>,
        out: (Vec<f32>, f32),
    ) -> Self {
        let widest = blocks.iter().flatten().map(|d| d.inputs.max(d.stride)).max().unwrap_or(1).max(n_inputs);
        P2pEvaluator { residual, slices, n_inputs, blocks, out_w: out.0, out_b: out.1, widest }
    }

    pub fn n_inputs(&self) -> usize {
        self.n_inputs
    }

    pub fn scratch(&self) -> P2pScratch {
        let w = self.widest;
        P2pScratch { a: vec![0.0; w], b: vec![0.0; w], prev: vec![0.0; w] }
    }

    /// The network's output for one feature row, with the fastest layer kernel the CPU
    /// runs ([`Kernel::best`]).
    pub fn forward(&self, x: &[f32], s: &mut P2pScratch) -> f32 {
        let kernel = Kernel::best();
        self.forward_with(x, s, 1, |l, x, y, _| kernel.layer_forward(l, x, y, RELU))
    }

    /// The same pass with the portable kernel (what CPUs without AVX2 + FMA run;
    /// tests check it against candle too).
    pub fn forward_portable(&self, x: &[f32], s: &mut P2pScratch) -> f32 {
        self.forward_with(x, s, 1, |l, x, y, _| layer_forward(l, x, y, RELU))
    }

    /// One output per row of `xs`, BATCH rows at a time.
    pub fn forward_batch(&self, xs: &[f32], out: &mut [f32], s: &mut P2pBatchScratch) {
        #[cfg(target_arch = "x86_64")]
        if Kernel::Avx2.available() {
            // SAFETY: the CPU has AVX2 and FMA, the features the function was compiled for.
            return unsafe { self.forward_batch_avx2(xs, out, s) };
        }
        self.forward_batch_portable(xs, out, s)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn forward_batch_avx2(&self, xs: &[f32], out: &mut [f32], s: &mut P2pBatchScratch) {
        self.forward_batch_with(xs, out, s, |l, x, y, rows, ws| avx2::layer_forward_rows(l, x, y, rows, ws, RELU))
    }

    /// [`P2pEvaluator::forward_batch`] with the portable kernel.
    pub fn forward_batch_portable(&self, xs: &[f32], out: &mut [f32], s: &mut P2pBatchScratch) {
        self.forward_batch_with(xs, out, s, |l, x, y, rows, ws| {
            Kernel::Portable.layer_forward_rows(l, x, y, rows, ws, RELU)
        })
    }

    #[inline(always)]
    fn forward_batch_with(
        &self,
        xs: &[f32],
        out: &mut [f32],
        s: &mut P2pBatchScratch,
        mut layers: impl FnMut(&Dense, &[f32], &mut [f32], usize, usize),
    ) {
        let n = self.n_inputs;
        assert_eq!(xs.len(), n * out.len(), "rows and outputs");
        if s.width < self.widest {
            let w = self.widest;
            *s = P2pBatchScratch {
                width: w,
                a: vec![0.0; BATCH * w],
                b: vec![0.0; BATCH * w],
                prev: vec![0.0; BATCH * w],
            };
        }
        let ws = s.width;
        let mut scratch =
            P2pScratch { a: std::mem::take(&mut s.a), b: std::mem::take(&mut s.b), prev: std::mem::take(&mut s.prev) };
        for (xg, og) in xs.chunks(BATCH * n).zip(out.chunks_mut(BATCH)) {
            let rows = og.len();
            self.pass(
                &mut scratch,
                rows,
                ws,
                |r, dst, k, sl| dst[k..k + sl.len].copy_from_slice(&xg[r * n + sl.start..r * n + sl.start + sl.len]),
                |r| xg[r * n + n - 1],
                &mut layers,
                |r, y| og[r] = y,
            );
        }
        (s.a, s.b, s.prev) = (scratch.a, scratch.b, scratch.prev);
    }

    #[inline(always)]
    fn forward_with(
        &self,
        x: &[f32],
        s: &mut P2pScratch,
        rows: usize,
        mut layer: impl FnMut(&Dense, &[f32], &mut [f32], usize),
    ) -> f32 {
        assert_eq!(x.len(), self.n_inputs, "feature row length");
        // A thread's scratch outlives models of different widths: size it for this one.
        if s.a.len() < self.widest {
            *s = self.scratch();
        }
        let n = self.n_inputs;
        let ws = self.widest;
        let mut y = 0.0;
        self.pass(
            s,
            rows,
            ws,
            |_, dst, k, sl| dst[k..k + sl.len].copy_from_slice(&x[sl.start..sl.start + sl.len]),
            |_| x[n - 1],
            |l: &Dense, x: &[f32], out: &mut [f32], _rows: usize, ws: usize| layer(l, x, out, ws),
            |_, v| y = v,
        );
        y
    }

    /// One pass over `rows` rows held in scratch rows of `ws` values: `slice(r, dst,
    /// k, sl)` writes row r's densities of level slice `sl` into dst[k ..], `phi(r)` is
    /// row r's diffusion feature (residual networks) or ignored, `layer` evaluates
    /// one ReLU layer for all rows, `emit(r, y)` takes the outputs.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn pass(
        &self,
        s: &mut P2pScratch,
        rows: usize,
        ws: usize,
        mut slice: impl FnMut(usize, &mut [f32], usize, &LevelSlice),
        phi: impl Fn(usize) -> f32,
        mut layer: impl FnMut(&Dense, &[f32], &mut [f32], usize, usize),
        mut emit: impl FnMut(usize, f32),
    ) {
        let mut width = 0;
        let (a, b, prev) = (&mut s.a, &mut s.b, &mut s.prev);
        if self.residual {
            let last = self.slices.len() - 1;
            for (bi, (sl, block)) in self.slices.iter().zip(&self.blocks).enumerate() {
                // Block input: the previous blocks' sum, this level's densities, (phi_D).
                for r in 0..rows {
                    let dst = &mut a[r * ws..(r + 1) * ws];
                    let mut k = 0;
                    if bi > 0 {
                        dst[..width].copy_from_slice(&prev[r * ws..r * ws + width]);
                        k = width;
                    }
                    slice(r, dst, k, sl);
                    if bi == last {
                        dst[k + sl.len] = phi(r);
                    }
                }
                let (mut cur, mut next) = (&mut *a, &mut *b);
                for l in block {
                    layer(l, cur, next, rows, ws);
                    std::mem::swap(&mut cur, &mut next);
                }
                let w = block.last().expect("blocks have layers").outputs;
                for r in 0..rows {
                    let (p, c) = (&mut prev[r * ws..r * ws + w], &cur[r * ws..r * ws + w]);
                    if bi > 0 {
                        p.iter_mut().zip(c).for_each(|(p, c)| *p += c);
                    } else {
                        p.copy_from_slice(c);
                    }
                }
                width = w;
            }
        } else {
            let block = &self.blocks[0];
            let whole = LevelSlice { start: 0, len: self.n_inputs };
            for r in 0..rows {
                slice(r, &mut a[r * ws..(r + 1) * ws], 0, &whole);
            }
            let (mut cur, mut next) = (&mut *a, &mut *b);
            for l in block {
                layer(l, cur, next, rows, ws);
                std::mem::swap(&mut cur, &mut next);
            }
            width = block.last().map(|l| l.outputs).unwrap_or(self.n_inputs);
            for r in 0..rows {
                prev[r * ws..r * ws + width].copy_from_slice(&cur[r * ws..r * ws + width]);
            }
        }
        for r in 0..rows {
            let h = &prev[r * ws..r * ws + width];
            let y = self.out_b + self.out_w.iter().zip(h).map(|(w, h)| w * h).sum::<f32>();
            emit(r, y);
        }
    }
}
