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

use crate::density_features::{LevelSlice, P2pFeatures};
use crate::train::{OptState, Optimizer};
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

/// One dense layer: weight [out, in] row-major, bias [out].
#[derive(Clone, Debug)]
struct Dense {
    inputs: usize,
    outputs: usize,
    w: Vec<f32>,
    b: Vec<f32>,
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
            Ok(Dense { inputs: i, outputs: o, w: w.as_tensor().flatten_all()?.to_vec1()?, b: b.as_tensor().to_vec1()? })
        };
        let blocks: Vec<Vec<Dense>> =
            self.blocks.iter().map(|b| b.iter().map(conv).collect()).collect::<candle_core::Result<_>>()?;
        let widest = blocks.iter().flatten().map(|d| d.inputs.max(d.outputs)).max().unwrap_or(1);
        Ok(P2pEvaluator {
            residual: matches!(self.arch, P2pArch::Residual { .. }),
            slices: self.slices.clone(),
            n_inputs: self.n_inputs,
            blocks,
            out: conv(&self.out)?,
            widest,
        })
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

/// Forward passes without allocation: per-thread scratch, weights row-major.
#[derive(Clone, Debug)]
pub struct P2pEvaluator {
    residual: bool,
    slices: Vec<LevelSlice>,
    n_inputs: usize,
    blocks: Vec<Vec<Dense>>,
    out: Dense,
    /// The widest layer: the scratch size.
    widest: usize,
}

/// Scratch space of [`P2pEvaluator`]: sized once, reused.
#[derive(Clone, Debug, Default)]
pub struct P2pScratch {
    input: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
    prev: Vec<f32>,
}

/// Dot product with 16 independent partial sums, so that the compiler can keep them
/// in vector registers (a single running sum is a serial dependency it must not
/// reorder).
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    const L: usize = 16;
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f32; L];
    let (ac, bc) = (a.chunks_exact(L), b.chunks_exact(L));
    let (ar, br) = (ac.remainder(), bc.remainder());
    for (x, y) in ac.zip(bc) {
        for l in 0..L {
            acc[l] += x[l] * y[l];
        }
    }
    let mut tail = 0.0;
    for (x, y) in ar.iter().zip(br) {
        tail += x * y;
    }
    acc.iter().sum::<f32>() + tail
}

#[inline]
fn dense_relu(l: &Dense, x: &[f32], y: &mut [f32]) {
    let y = &mut y[..l.outputs];
    for (o, yo) in y.iter_mut().enumerate() {
        let row = &l.w[o * l.inputs..(o + 1) * l.inputs];
        *yo = (l.b[o] + dot(row, &x[..l.inputs])).max(0.0);
    }
}

impl P2pEvaluator {
    pub fn n_inputs(&self) -> usize {
        self.n_inputs
    }

    pub fn scratch(&self) -> P2pScratch {
        let widest = self.widest;
        P2pScratch { input: vec![0.0; widest], a: vec![0.0; widest], b: vec![0.0; widest], prev: vec![0.0; widest] }
    }

    /// The network's output for one feature row.
    pub fn forward(&self, x: &[f32], s: &mut P2pScratch) -> f32 {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports the feature the function was compiled for.
            return unsafe { self.forward_avx2(x, s) };
        }
        self.forward_impl(x, s)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn forward_avx2(&self, x: &[f32], s: &mut P2pScratch) -> f32 {
        self.forward_impl(x, s)
    }

    /// The same pass compiled for any x86-64 (tests check it against candle too).
    pub fn forward_portable(&self, x: &[f32], s: &mut P2pScratch) -> f32 {
        self.forward_impl(x, s)
    }

    #[inline(always)]
    fn forward_impl(&self, x: &[f32], s: &mut P2pScratch) -> f32 {
        // Scratch sized for another network (a thread's scratch outlives models of
        // different widths): size it for this one, once.
        if s.a.len() < self.widest {
            *s = self.scratch();
        }
        assert_eq!(x.len(), self.n_inputs, "feature row length");
        if s.a.is_empty() {
            *s = self.scratch();
        }
        let mut width = 0;
        if self.residual {
            for (bi, (sl, block)) in self.slices.iter().zip(&self.blocks).enumerate() {
                // Block input: previous output, this level's densities, (phi_D).
                let mut n = 0;
                if bi > 0 {
                    s.input[..width].copy_from_slice(&s.prev[..width]);
                    n = width;
                }
                s.input[n..n + sl.len].copy_from_slice(&x[sl.start..sl.start + sl.len]);
                n += sl.len;
                if bi + 1 == self.slices.len() {
                    s.input[n] = x[self.n_inputs - 1];
                }
                let (mut cur, mut next) = (&mut s.a, &mut s.b);
                cur[..block[0].inputs].copy_from_slice(&s.input[..block[0].inputs]);
                for l in block {
                    dense_relu(l, cur, next);
                    std::mem::swap(&mut cur, &mut next);
                }
                let w = block.last().unwrap().outputs;
                if bi > 0 {
                    for (p, c) in s.prev[..w].iter_mut().zip(&cur[..w]) {
                        *p += c;
                    }
                } else {
                    s.prev[..w].copy_from_slice(&cur[..w]);
                }
                width = w;
            }
        } else {
            let block = &self.blocks[0];
            let (mut cur, mut next) = (&mut s.a, &mut s.b);
            cur[..x.len()].copy_from_slice(x);
            for l in block {
                dense_relu(l, cur, next);
                std::mem::swap(&mut cur, &mut next);
            }
            width = block.last().map(|l| l.outputs).unwrap_or(x.len());
            s.prev[..width].copy_from_slice(&cur[..width]);
        }
        let mut y = self.out.b[0];
        for (w, h) in self.out.w.iter().zip(&s.prev[..width]) {
            y += w * h;
        }
        y
    }

    /// One output per row of `xs`, BATCH rows at a time: each weight row is read
    /// once per group and applied to every row of it while it is in the L1 cache.
    pub fn forward_batch(&self, xs: &[f32], out: &mut [f32], s: &mut P2pBatchScratch) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports the feature the function was compiled for.
            return unsafe { self.forward_batch_avx2(xs, out, s) };
        }
        self.forward_batch_impl(xs, out, s)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn forward_batch_avx2(&self, xs: &[f32], out: &mut [f32], s: &mut P2pBatchScratch) {
        self.forward_batch_impl(xs, out, s)
    }

    #[inline(always)]
    fn forward_batch_impl(&self, xs: &[f32], out: &mut [f32], s: &mut P2pBatchScratch) {
        let n = self.n_inputs;
        assert_eq!(xs.len(), n * out.len(), "rows and outputs");
        let widest = self.blocks.iter().flatten().map(|d| d.inputs.max(d.outputs)).max().unwrap_or(1).max(n);
        if s.width < widest {
            *s = P2pBatchScratch {
                width: widest,
                a: vec![0.0; BATCH * widest],
                b: vec![0.0; BATCH * widest],
                prev: vec![0.0; BATCH * widest],
            };
        }
        let ws = s.width;
        for (xg, og) in xs.chunks(BATCH * n).zip(out.chunks_mut(BATCH)) {
            let rows = og.len();
            let layers = |block: &[Dense], cur: &mut Vec<f32>, next: &mut Vec<f32>| {
                for l in block {
                    for o in 0..l.outputs {
                        let w = &l.w[o * l.inputs..(o + 1) * l.inputs];
                        for r in 0..rows {
                            let x = &cur[r * ws..r * ws + l.inputs];
                            next[r * ws + o] = (l.b[o] + dot(w, x)).max(0.0);
                        }
                    }
                    std::mem::swap(cur, next);
                }
            };
            let mut width = 0;
            if self.residual {
                for (bi, (sl, block)) in self.slices.iter().zip(&self.blocks).enumerate() {
                    for r in 0..rows {
                        let x = &xg[r * n..(r + 1) * n];
                        let dst = &mut s.a[r * ws..(r + 1) * ws];
                        let mut k = 0;
                        if bi > 0 {
                            dst[..width].copy_from_slice(&s.prev[r * ws..r * ws + width]);
                            k = width;
                        }
                        dst[k..k + sl.len].copy_from_slice(&x[sl.start..sl.start + sl.len]);
                        if bi + 1 == self.slices.len() {
                            dst[k + sl.len] = x[n - 1];
                        }
                    }
                    layers(block, &mut s.a, &mut s.b);
                    let w = block.last().unwrap().outputs;
                    for r in 0..rows {
                        let (p, c) = (&mut s.prev[r * ws..r * ws + w], &s.a[r * ws..r * ws + w]);
                        if bi > 0 {
                            p.iter_mut().zip(c).for_each(|(p, c)| *p += c);
                        } else {
                            p.copy_from_slice(c);
                        }
                    }
                    width = w;
                }
            } else {
                for r in 0..rows {
                    s.a[r * ws..r * ws + n].copy_from_slice(&xg[r * n..(r + 1) * n]);
                }
                layers(&self.blocks[0], &mut s.a, &mut s.b);
                width = self.blocks[0].last().map(|l| l.outputs).unwrap_or(n);
                for r in 0..rows {
                    let (p, c) = (&mut s.prev[r * ws..r * ws + width], &s.a[r * ws..r * ws + width]);
                    p.copy_from_slice(c);
                }
            }
            for (r, o) in og.iter_mut().enumerate() {
                let mut y = self.out.b[0];
                for (w, h) in self.out.w.iter().zip(&s.prev[r * ws..r * ws + width]) {
                    y += w * h;
                }
                *o = y;
            }
        }
    }
}

/// Rows evaluated together by [`P2pEvaluator::forward_batch`].
pub const BATCH: usize = 8;

/// Scratch space of the batched evaluator (sized on first use).
#[derive(Clone, Debug, Default)]
pub struct P2pBatchScratch {
    width: usize,
    a: Vec<f32>,
    b: Vec<f32>,
    prev: Vec<f32>,
}
