//! The global transport model as the renderer uses it: the model files (safetensors
//! weights + JSON sidecar), the target transformation (thesis eqs. 5.8-5.9), and an
//! allocation-free f32 evaluator of the MLP that implements the engine's
//! [`InScatterPredictor`].
//!
//! Target transformation: y = ln(1 + L_i / p(omega_q, omega_L)) with p the
//! Henyey-Greenstein phase value of single scattering toward omega_q (cos = cos theta,
//! theta the query angle from the light), then standardized; every feature is
//! standardized too. Statistics come from the training split and live in the sidecar.

use crate::depth_field::DepthField;
use crate::directions::{DirectionSetKind, LightFrame};
use crate::features::FeatureExtractor;
use engine::{InScatterPredictor, Medium, PhaseFunction, Sun};
use glam::Vec3;
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

pub const MODEL_FORMAT: &str = "nimbus-global-model";
pub const MODEL_FORMAT_VERSION: u32 = 1;

/// Where the shipped model lives in the repository (its bytes are compiled in).
pub const SHIPPED_PATH: &str = "assets/models/global.safetensors";
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../assets/models/global.safetensors");
const SHIPPED_SIDECAR: &str = include_str!("../../assets/models/global.json");

/// [`crate::fingerprint`] of the shipped model's weights and sidecar.
pub fn shipped_fingerprint() -> u64 {
    crate::fingerprint(&[SHIPPED_WEIGHTS, SHIPPED_SIDECAR.as_bytes()])
}

/// How theta and phi are measured; a model trained under another convention is refused.
pub const ANGLE_CONVENTION: &str = "light frame: z = -omega_L (toward the light), x, y = engine::sampling::coordinate_system(z); theta = acos(z) of omega_q in [0, pi], phi = atan2(y, x) in [0, 2 pi); omega_q points away from the query point";

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
    fn apply(self, x: f32) -> f32 {
        match self {
            Activation::Relu => x.max(0.0),
            Activation::Tanh => x.tanh(),
            Activation::Silu => x / (1.0 + (-x).exp()),
        }
    }
}

/// The feature layout a model expects.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureLayout {
    pub n_dirs: usize,
    pub direction_set: DirectionSetKind,
    pub names: Vec<String>,
    pub angle_convention: String,
    /// "tau_hat = ln(1 / (1 + tau))" (thesis eq. 5.7)
    pub optical_depth: String,
}

impl FeatureLayout {
    /// What this code computes for `n_dirs` directions of `set`.
    pub fn current(set: DirectionSetKind, n_dirs: usize) -> Self {
        let mut names: Vec<String> = ["albedo", "g", "theta", "phi"].iter().map(|s| s.to_string()).collect();
        names.extend((1..=n_dirs).map(|i| format!("tau_hat_{i}")));
        FeatureLayout {
            n_dirs,
            direction_set: set,
            names,
            angle_convention: ANGLE_CONVENTION.into(),
            optical_depth: "tau_hat = ln(1 / (1 + tau))".into(),
        }
    }

    /// Differences from what the code computes, one per line; None if it matches.
    pub fn mismatch(&self) -> Option<String> {
        if self.direction_set.directions(self.n_dirs).is_none() {
            return Some(format!("n_dirs {} is not offered by the {} set", self.n_dirs, self.direction_set.name()));
        }
        let cur = FeatureLayout::current(self.direction_set, self.n_dirs);
        let mut out = vec![];
        if self.names != cur.names {
            out.push(format!("feature names {:?} differ from the code's {:?}", self.names, cur.names));
        }
        if self.angle_convention != cur.angle_convention {
            out.push(format!(
                "angle convention {:?} differs from the code's {:?}",
                self.angle_convention, cur.angle_convention
            ));
        }
        if self.optical_depth != cur.optical_depth {
            out.push(format!(
                "optical depth transform {:?} differs from the code's {:?}",
                self.optical_depth, cur.optical_depth
            ));
        }
        (!out.is_empty()).then(|| out.join("; "))
    }
}

/// Feature and target standardization, from the training split.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Standardization {
    pub feature_mean: Vec<f32>,
    /// 1 where a feature is constant in the training data.
    pub feature_std: Vec<f32>,
    /// "ln(1 + L_i / p_HG(g, cos theta))" (thesis eqs. 5.8-5.9)
    pub target: String,
    pub target_mean: f32,
    pub target_std: f32,
}

pub const TARGET_TRANSFORM: &str = "ln(1 + L_i / p_HG(g, cos theta))";
pub const TARGET_TRANSFORM_MULTIPLE: &str = "ln(1 + 4 pi max(0, L_i - p_HG(g, cos theta) exp(-tau_1)))";

/// What the network predicts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TargetKind {
    /// The thesis's target: all of L_i, single scattering included, transformed by eqs.
    /// 5.8-5.9 ([`TARGET_TRANSFORM`]).
    #[default]
    Total,
    /// Multiple scattering only: L_ms = L_i - p_HG(g, cos theta) exp(-tau_1), the
    /// ground truth minus its exact single-scattering term (tau_1 is the feature toward
    /// the light, so L_ms follows from the stored data), transformed by
    /// ln(1 + 4 pi L_ms) ([`TARGET_TRANSFORM_MULTIPLE`]). The renderer path traces single
    /// scattering at vertex k by NEE and adds the prediction; the peaked part of L_i
    /// (forward scattering toward a backlit camera) is then never learned. A departure
    /// from the thesis, see the README.
    Multiple,
}

impl TargetKind {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "total" => Some(TargetKind::Total),
            "multiple" => Some(TargetKind::Multiple),
            _ => None,
        }
    }

    /// The transform's description, stored in the sidecar and checked on load.
    pub fn transform(self) -> &'static str {
        match self {
            TargetKind::Total => TARGET_TRANSFORM,
            TargetKind::Multiple => TARGET_TRANSFORM_MULTIPLE,
        }
    }

    fn from_transform(s: &str) -> Option<Self> {
        [TargetKind::Total, TargetKind::Multiple].into_iter().find(|k| k.transform() == s)
    }
}

/// The single-scattering phase value of eq. 5.8 from a feature row (g and theta).
#[inline]
pub fn single_scattering_phase(features: &[f32]) -> f32 {
    PhaseFunction::HenyeyGreenstein { g: features[1] }.eval_cos(features[2].cos())
}

/// Exact single scattering of a unit light from a feature row: the phase value times
/// the transmittance toward the light, exp(-tau_1) with tau_1 = exp(-tau_hat_1) - 1.
#[inline]
pub fn single_scattering(features: &[f32]) -> f32 {
    single_scattering_phase(features) * (1.0 - (-features[4]).exp()).exp()
}

/// The transformed target (before standardization) of a measured L_i.
#[inline]
pub fn transform_target(kind: TargetKind, features: &[f32], l_i: f32) -> f32 {
    match kind {
        TargetKind::Total => (l_i.max(0.0) / single_scattering_phase(features)).ln_1p(),
        TargetKind::Multiple => ((l_i - single_scattering(features)).max(0.0) * 4.0 * std::f32::consts::PI).ln_1p(),
    }
}

/// The inverse: what the network predicts (L_i, or L_ms for [`TargetKind::Multiple`])
/// from its un-standardized output.
#[inline]
pub fn untransform_target(kind: TargetKind, features: &[f32], y: f32) -> f32 {
    match kind {
        TargetKind::Total => (y.exp_m1() * single_scattering_phase(features)).max(0.0),
        TargetKind::Multiple => (y.exp_m1() / (4.0 * std::f32::consts::PI)).max(0.0),
    }
}

/// L_i from the network's un-standardized output (single scattering added back for a
/// multiple-scattering model): the figure the training report compares.
#[inline]
pub fn predicted_l_i(kind: TargetKind, features: &[f32], y: f32) -> f32 {
    let v = untransform_target(kind, features, y);
    if kind == TargetKind::Multiple { v + single_scattering(features) } else { v }
}

/// Everything about a model but its weights.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Sidecar {
    pub format: String,
    pub format_version: u32,
    pub features: FeatureLayout,
    pub standardization: Standardization,
    /// Widths of the hidden layers, e.g. [200, 100].
    pub hidden: Vec<usize>,
    pub activation: Activation,
    /// Free-form records of the training run (data, settings, errors, command, time).
    pub training: serde_json::Value,
}

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("{path}: {why}")]
    File { path: PathBuf, why: String },
    #[error("{path}: the model does not fit this version of Nimbus: {why}")]
    Layout { path: PathBuf, why: String },
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
    w: Vec<f32>,
    b: Vec<f32>,
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
    features: Vec<f32>,
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

/// The forward pass with a given layer kernel.
#[inline(always)]
fn forward_with(
    mlp: &Mlp,
    x: &[f32],
    scratch: &mut Scratch,
    mut layer_fn: impl FnMut(&Dense, &[f32], &mut [f32], Option<Activation>),
) -> f32 {
    let (mut cur, mut next) = (std::mem::take(&mut scratch.a), std::mem::take(&mut scratch.b));
    cur[..x.len()].copy_from_slice(x);
    let last = mlp.layers.len() - 1;
    for (l, layer) in mlp.layers.iter().enumerate() {
        layer_fn(layer, &cur, &mut next, (l < last).then_some(mlp.activation));
        std::mem::swap(&mut cur, &mut next);
    }
    let out = cur[0];
    scratch.a = cur;
    scratch.b = next;
    out
}

#[inline(always)]
fn forward_generic(mlp: &Mlp, x: &[f32], scratch: &mut Scratch) -> f32 {
    forward_with(mlp, x, scratch, layer_forward)
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

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn forward_avx2(mlp: &Mlp, x: &[f32], scratch: &mut Scratch) -> f32 {
    // The closure inherits this function's target features, so the kernel call is safe.
    forward_with(mlp, x, scratch, |l, x, y, a| avx2::layer_forward(l, x, y, a))
}

impl Mlp {
    /// Layers as (inputs, outputs, row-major [out][in] weights, bias).
    pub fn new(layers: &[(usize, usize, Vec<f32>, Vec<f32>)], activation: Activation) -> Self {
        let layers: Vec<Dense> = layers.iter().map(|(i, o, w, b)| Dense::new(*i, *o, w, b)).collect();
        let width = layers.iter().map(|l| l.stride.max(l.inputs)).max().unwrap_or(16);
        Mlp { layers, activation, width }
    }

    pub fn n_inputs(&self) -> usize {
        self.layers[0].inputs
    }

    /// Scratch space for this network (allocate once per thread).
    pub fn scratch(&self) -> Scratch {
        Scratch { a: vec![0.0; self.width], b: vec![0.0; self.width], features: vec![0.0; self.n_inputs()] }
    }

    fn ensure(&self, scratch: &mut Scratch) {
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
    fn forward_sized(&self, x: &[f32], scratch: &mut Scratch) -> f32 {
        debug_assert_eq!(x.len(), self.n_inputs());
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU supports the features the function was compiled for.
            return unsafe { forward_avx2(self, x, scratch) };
        }
        forward_generic(self, x, scratch)
    }

    /// The portable forward pass (what CPUs without AVX2 + FMA run), for tests.
    pub fn forward_portable(&self, x: &[f32], scratch: &mut Scratch) -> f32 {
        self.ensure(scratch);
        forward_generic(self, x, scratch)
    }

    /// Batched entry point: `xs` holds rows of n_inputs values, one output per row.
    pub fn forward_batch(&self, xs: &[f32], out: &mut [f32], scratch: &mut Scratch) {
        let n = self.n_inputs();
        for (row, o) in xs.chunks_exact(n).zip(out.iter_mut()) {
            *o = self.forward(row, scratch);
        }
    }
}

/// A trained global model: layout, standardization and network.
#[derive(Clone, Debug)]
pub struct GlobalModel {
    pub sidecar: Sidecar,
    pub mlp: Mlp,
    features: FeatureExtractor,
    /// What the network predicts (from the sidecar's target transform).
    target: TargetKind,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

impl GlobalModel {
    pub fn new(sidecar: Sidecar, mlp: Mlp) -> Self {
        let features = FeatureExtractor::with_set(sidecar.features.direction_set, sidecar.features.n_dirs)
            .expect("layout checked");
        let target = TargetKind::from_transform(&sidecar.standardization.target)
            .expect("the sidecar's target transform is one this code knows (checked by from_bytes)");
        GlobalModel { sidecar, mlp, features, target }
    }

    /// Loads `path` (.safetensors) and its sidecar (same name, .json); checks that the
    /// sidecar's feature layout is what this code computes and that the weights have
    /// the shapes the sidecar's architecture says, all finite.
    pub fn load(path: &Path) -> Result<GlobalModel, ModelError> {
        let json_path = path.with_extension("json");
        let text = std::fs::read_to_string(&json_path)
            .map_err(|e| ModelError::File { path: json_path.clone(), why: e.to_string() })?;
        let bytes = std::fs::read(path).map_err(|e| ModelError::File { path: path.to_owned(), why: e.to_string() })?;
        Self::from_bytes(&bytes, &text, path)
    }

    /// The model shipped in `assets/models/global.*`, compiled into the binary so a
    /// fresh build predicts without any file. Loaded (and checked) once.
    pub fn shipped() -> Result<Arc<GlobalModel>, ModelError> {
        static SHIPPED: OnceLock<Result<Arc<GlobalModel>, String>> = OnceLock::new();
        SHIPPED
            .get_or_init(|| {
                Self::from_bytes(SHIPPED_WEIGHTS, SHIPPED_SIDECAR, Path::new(SHIPPED_PATH))
                    .map(Arc::new)
                    .map_err(|e| e.to_string())
            })
            .clone()
            .map_err(|why| ModelError::File { path: SHIPPED_PATH.into(), why })
    }

    /// A model from the bytes of its weights and the text of its sidecar; `path` (the
    /// weights file) only names the model in messages.
    pub fn from_bytes(bytes: &[u8], sidecar_json: &str, path: &Path) -> Result<GlobalModel, ModelError> {
        let file_err = |p: &Path, why: String| ModelError::File { path: p.to_owned(), why };
        let json_path = path.with_extension("json");
        let sidecar: Sidecar = serde_json::from_str(sidecar_json)
            .map_err(|e| file_err(&json_path, format!("not a Nimbus global-model sidecar: {e}")))?;
        if sidecar.format != MODEL_FORMAT || sidecar.format_version != MODEL_FORMAT_VERSION {
            return Err(ModelError::Layout {
                path: json_path,
                why: format!(
                    "format {} v{} is not {MODEL_FORMAT} v{MODEL_FORMAT_VERSION}",
                    sidecar.format, sidecar.format_version
                ),
            });
        }
        if let Some(why) = sidecar.features.mismatch() {
            return Err(ModelError::Layout { path: json_path, why });
        }
        let n_f = sidecar.features.names.len();
        let st = &sidecar.standardization;
        let kind = TargetKind::from_transform(&st.target);
        if st.feature_mean.len() != n_f || st.feature_std.len() != n_f || kind.is_none() {
            return Err(ModelError::Layout {
                path: json_path,
                why: format!(
                    "standardization has {} means / {} deviations for {n_f} features, target {:?} (the code knows {TARGET_TRANSFORM:?} and {TARGET_TRANSFORM_MULTIPLE:?})",
                    st.feature_mean.len(),
                    st.feature_std.len(),
                    st.target
                ),
            });
        }
        let tensors = candle_core::safetensors::load_buffer(bytes, &candle_core::Device::Cpu)
            .map_err(|e| file_err(path, format!("not a readable safetensors file: {e}")))?;
        let mut widths = vec![n_f];
        widths.extend(&sidecar.hidden);
        widths.push(1);
        let mut layers = vec![];
        for l in 0..widths.len() - 1 {
            let (i, o) = (widths[l], widths[l + 1]);
            let get = |name: String, shape: &[usize]| -> Result<Vec<f32>, ModelError> {
                let t = tensors.get(&name).ok_or_else(|| file_err(path, format!("tensor {name} is missing")))?;
                if t.dims() != shape {
                    return Err(file_err(path, format!("tensor {name} has shape {:?}, expected {shape:?}", t.dims())));
                }
                let v: Vec<f32> = t
                    .to_dtype(candle_core::DType::F32)
                    .and_then(|t| t.flatten_all())
                    .and_then(|t| t.to_vec1())
                    .map_err(|e| file_err(path, format!("tensor {name}: {e}")))?;
                if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                    return Err(file_err(path, format!("tensor {name} holds a non-finite value at {k}")));
                }
                Ok(v)
            };
            layers.push((i, o, get(format!("layers.{l}.weight"), &[o, i])?, get(format!("layers.{l}.bias"), &[o])?));
        }
        let mlp = Mlp::new(&layers, sidecar.activation);
        Ok(GlobalModel::new(sidecar, mlp))
    }

    /// L_i for one raw feature row (standardized here), using `scratch`.
    #[inline]
    pub fn predict_features(&self, raw: &[f32], scratch: &mut Scratch) -> f32 {
        let st = &self.sidecar.standardization;
        self.mlp.ensure(scratch);
        let mut x = std::mem::take(&mut scratch.features);
        for (k, v) in raw.iter().enumerate() {
            x[k] = (v - st.feature_mean[k]) / st.feature_std[k];
        }
        let y = self.mlp.forward_sized(&x, scratch);
        scratch.features = x;
        untransform_target(self.target, raw, y * st.target_std + st.target_mean)
    }

    pub fn feature_extractor(&self) -> &FeatureExtractor {
        &self.features
    }

    pub fn target(&self) -> TargetKind {
        self.target
    }
}

impl InScatterPredictor for GlobalModel {
    /// Features ray marched through the grid (skipping empty space, stopping once the
    /// transmittance is negligible), then the network; per-thread scratch, no allocation.
    fn predict(&self, medium: &Medium, sun: &Sun, x: Vec3, omega: Vec3) -> f32 {
        let mut feat = [0.0f32; 4 + 256];
        let n = self.features.len();
        self.features.extract_grid(medium, sun.direction(), x, omega, &mut feat[..n]);
        let v = SCRATCH.with(|s| self.predict_features(&feat[..n], &mut s.borrow_mut()));
        if v.is_finite() { v } else { 0.0 }
    }

    fn predicts_single_scattering(&self) -> bool {
        self.target == TargetKind::Total
    }

    fn name(&self) -> &str {
        "global MLP"
    }
}

/// A global model bound to one cloud and one sun: the optical depths of the features
/// come from a precomputed [`DepthField`] (trilinear lookups) instead of n_D ray
/// marches per prediction. What the renderer uses; see `depth_field.rs` for the
/// construction and its accuracy.
#[derive(Clone, Debug)]
pub struct BoundGlobalModel {
    model: Arc<GlobalModel>,
    field: Arc<DepthField>,
    frame: LightFrame,
    /// What the field was built for: another medium or sun falls back to marching.
    grid: Arc<engine::DensityGrid>,
    rho: f32,
    omega_l: Vec3,
}

impl BoundGlobalModel {
    /// Builds the depth field of `medium` for `sun` (about a second at 64^3 nodes on two
    /// cores; `max_nodes` per axis trades accuracy for time and memory).
    pub fn new(model: Arc<GlobalModel>, medium: &Medium, sun: &Sun, max_nodes: u32) -> Self {
        let omega_l = sun.direction();
        let field = DepthField::for_light(medium, model.features.directions(), omega_l, max_nodes);
        BoundGlobalModel {
            model,
            field: Arc::new(field),
            frame: LightFrame::new(omega_l),
            grid: medium.grid().clone(),
            rho: medium.rho(),
            omega_l,
        }
    }

    pub fn model(&self) -> &Arc<GlobalModel> {
        &self.model
    }

    pub fn field(&self) -> &DepthField {
        &self.field
    }

    /// The raw feature row at `x` for query direction `omega` (written to `out`).
    #[inline]
    pub fn features(&self, medium: &Medium, x: Vec3, omega: Vec3, out: &mut [f32]) {
        FeatureExtractor::write_head(medium.albedo(), medium.phase().mean_cosine(), &self.frame, omega, out);
        self.field.lookup(x, &mut out[4..]);
    }

    fn matches(&self, medium: &Medium, sun: &Sun) -> bool {
        Arc::ptr_eq(medium.grid(), &self.grid) && medium.rho() == self.rho && sun.direction() == self.omega_l
    }
}

impl InScatterPredictor for BoundGlobalModel {
    fn predict(&self, medium: &Medium, sun: &Sun, x: Vec3, omega: Vec3) -> f32 {
        if !self.matches(medium, sun) {
            return self.model.predict(medium, sun, x, omega);
        }
        let mut feat = [0.0f32; 4 + 256];
        let n = self.model.features.len();
        self.features(medium, x, omega, &mut feat[..n]);
        let v = SCRATCH.with(|s| self.model.predict_features(&feat[..n], &mut s.borrow_mut()));
        if v.is_finite() { v } else { 0.0 }
    }

    fn predicts_single_scattering(&self) -> bool {
        self.model.target == TargetKind::Total
    }

    fn name(&self) -> &str {
        "global MLP (depth field)"
    }
}
