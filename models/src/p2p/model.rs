//! The point-to-point model as the renderer uses it: the model files (safetensors
//! weights + JSON sidecar with the architecture, the feature set and every
//! transform), the shipped model compiled into the binary, and [`BoundP2pModel`], a
//! model bound to one cloud that plugs into BDPT's prediction mode.
//!
//! Inputs: every feature through ln(1 + x) (densities and phi_D span decades), then
//! standardized with the training split's means and deviations. Output: the
//! standardized ln of the local-frame transport D^2 T; T in world units is that
//! divided by D^2 (D the emitter-sensor distance).

use super::features::P2pFeatures;
use super::frame::LocalFrame;
use super::net::{P2pArch, P2pBatchScratch, P2pEvaluator, P2pNetwork, P2pScratch};
use super::pyramid::DensityPyramid;
use candle_core::Device;
use engine::{P2pQuery, Rng};
use serde::{Deserialize, Serialize};
use std::path::Path;

pub const MODEL_FORMAT: &str = "nimbus-p2p-model";

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum ArchDesc {
    Residual { width: usize, layers: usize },
    Mlp { hidden: Vec<usize> },
}

impl From<&P2pArch> for ArchDesc {
    fn from(a: &P2pArch) -> Self {
        match a {
            P2pArch::Residual { width, layers } => ArchDesc::Residual { width: *width, layers: *layers },
            P2pArch::Mlp { hidden } => ArchDesc::Mlp { hidden: hidden.clone() },
        }
    }
}

impl ArchDesc {
    pub fn describe(&self) -> String {
        match self {
            ArchDesc::Residual { width, layers } => format!("residual, {width} units x {layers} layers per block"),
            ArchDesc::Mlp { hidden } => format!("MLP {hidden:?}"),
        }
    }

    pub fn arch(&self) -> P2pArch {
        match self {
            ArchDesc::Residual { width, layers } => P2pArch::Residual { width: *width, layers: *layers },
            ArchDesc::Mlp { hidden } => P2pArch::Mlp { hidden: hidden.clone() },
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct P2pSidecar {
    pub format: String,
    pub arch: ArchDesc,
    pub features: P2pFeatures,
    pub feature_mean: Vec<f32>,
    pub feature_std: Vec<f32>,
    pub target_mean: f32,
    pub target_std: f32,
    /// Medium the data came from (the model is trained for one albedo and g).
    pub albedo: f32,
    pub g: f32,
    pub data: Vec<String>,
    pub epochs: usize,
    /// Learning-rate factor per epoch of the training (1: constant; a sidecar
    /// without the field reads as 1).
    #[serde(default = "constant_lr")]
    pub lr_decay: f64,
    pub test_mse: f64,
    /// Median and 90th percentile of |predicted T / true T - 1| on the test points.
    pub test_rel_error_median: f64,
    pub test_rel_error_p90: f64,
}

/// The default of a sidecar's or checkpoint's `lr_decay`: 1, a constant rate.
pub(crate) fn constant_lr() -> f64 {
    1.0
}

pub(crate) fn err(e: impl std::fmt::Display) -> String {
    e.to_string()
}

/// A trained model ready to predict.
pub struct P2pModel {
    pub sidecar: P2pSidecar,
    eval: P2pEvaluator,
}

/// Where the shipped point-to-point model lives in the repository; it is compiled
/// into the binary, so BDPT's prediction mode works without any file.
pub const SHIPPED_PATH: &str = "assets/models/p2p.safetensors";
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../../assets/models/p2p.safetensors");
const SHIPPED_SIDECAR: &str = include_str!("../../../assets/models/p2p.json");

/// [`crate::fingerprint::fingerprint`] of the shipped point-to-point model's weights and sidecar.
pub fn shipped_fingerprint() -> u64 {
    crate::fingerprint::fingerprint(&[SHIPPED_WEIGHTS, SHIPPED_SIDECAR.as_bytes()])
}

impl P2pModel {
    /// Loads OUT.safetensors with its OUT.json sidecar, naming the file on any problem.
    pub fn load(weights: &Path) -> Result<Self, String> {
        let side = weights.with_extension("json");
        let text = std::fs::read_to_string(&side).map_err(|e| format!("{}: {e}", side.display()))?;
        let bytes = std::fs::read(weights).map_err(|e| format!("{}: {e}", weights.display()))?;
        Self::from_bytes(&bytes, &text, weights)
    }

    /// The shipped single-cloud model (`assets/models/p2p.*`), loaded once.
    pub fn shipped() -> Result<std::sync::Arc<P2pModel>, String> {
        static SHIPPED: std::sync::OnceLock<Result<std::sync::Arc<P2pModel>, String>> = std::sync::OnceLock::new();
        SHIPPED
            .get_or_init(|| {
                Self::from_bytes(SHIPPED_WEIGHTS, SHIPPED_SIDECAR, Path::new(SHIPPED_PATH)).map(std::sync::Arc::new)
            })
            .clone()
    }

    /// A model from its weights' bytes and its sidecar's text; `weights` names it in
    /// messages.
    pub fn from_bytes(bytes: &[u8], text: &str, weights: &Path) -> Result<Self, String> {
        let side = weights.with_extension("json");
        let sidecar: P2pSidecar = serde_json::from_str(text)
            .map_err(|e| format!("{}: not a point-to-point model sidecar: {e}", side.display()))?;
        if sidecar.format != MODEL_FORMAT {
            return Err(format!("{}: format {:?} is not {MODEL_FORMAT}", side.display(), sidecar.format));
        }
        let n = sidecar.features.len();
        if sidecar.feature_mean.len() != n || sidecar.feature_std.len() != n {
            return Err(format!(
                "{}: transforms for {} features, the feature set has {n}",
                side.display(),
                sidecar.feature_mean.len()
            ));
        }
        let named = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)
            .map_err(|e| format!("{}: {e}", weights.display()))?;
        let net = P2pNetwork::new(&sidecar.features, sidecar.arch.arch(), 0, &Device::Cpu).map_err(err)?;
        net.load_named(&named).map_err(|e| format!("{}: {e}", weights.display()))?;
        Ok(P2pModel { eval: net.evaluator().map_err(err)?, sidecar })
    }

    /// Predicted T (world units) between the ends of `frame`, from raw features.
    pub fn predict_features(
        &self,
        raw: &[f32],
        frame_scale: f32,
        input: &mut Vec<f32>,
        scratch: &mut P2pScratch,
    ) -> f32 {
        input.resize(raw.len(), 0.0);
        self.standardize(raw, input);
        self.finish(self.eval.forward(input, scratch), frame_scale)
    }

    /// The network's input from raw features: ln(1 + x), standardized.
    pub(crate) fn standardize(&self, raw: &[f32], input: &mut [f32]) {
        let s = &self.sidecar;
        crate::nn::fastmath::standardize(raw, &s.feature_mean, &s.feature_std, input);
    }

    /// T in world units from the network's output for a pair `frame_scale` apart.
    fn finish(&self, y: f32, frame_scale: f32) -> f32 {
        let s = &self.sidecar;
        (y * s.target_std + s.target_mean).exp() / (frame_scale * frame_scale)
    }

    /// Features and prediction for an emitter-sensor pair.
    pub fn predict(&self, pyramid: &DensityPyramid, rho: f32, frame: &LocalFrame) -> f32 {
        let mut raw = vec![0.0; self.sidecar.features.len()];
        self.sidecar.features.write(pyramid, rho, self.sidecar.albedo, frame, &mut raw);
        self.predict_features(&raw, frame.scale, &mut Vec::new(), &mut P2pScratch::default())
    }
}

thread_local! {
    /// Per render thread: raw features, network input and the network's scratch.
    static SCRATCH: std::cell::RefCell<(Vec<f32>, Vec<f32>, P2pScratch)> =
        std::cell::RefCell::new((Vec::new(), Vec::new(), P2pScratch::default()));
    /// Per render thread, for batches: network inputs, frame scales, batch scratch
    /// (grown to the largest batch seen, then reused).
    static BATCH_SCRATCH: std::cell::RefCell<(Vec<f32>, Vec<f32>, Vec<f32>, P2pBatchScratch)> =
        std::cell::RefCell::new(Default::default());
}

/// A point-to-point model bound to one cloud: its density pyramid is built once
/// here (about 0.7 s and 28 MiB for a 128^3 grid), after which a prediction is the
/// feature lookups and one network evaluation, without allocation (per-thread
/// scratch). Plugs into BDPT's prediction mode as an [`engine::TransportPredictor`].
pub struct BoundP2pModel {
    model: std::sync::Arc<P2pModel>,
    pyramid: DensityPyramid,
    rho: f32,
    name: String,
}

impl BoundP2pModel {
    pub fn new(model: std::sync::Arc<P2pModel>, medium: &engine::Medium) -> Self {
        let grid = medium.grid();
        let pyramid = super::features::pyramid_for(grid, &model.sidecar.features, grid.bounds().extent().length());
        let name = format!("point-to-point model ({})", model.sidecar.arch.describe());
        BoundP2pModel { model, pyramid, rho: medium.rho(), name }
    }

    /// Why this model may not fit `medium` (it is trained for one albedo and an
    /// isotropic phase function), if it may not.
    pub fn mismatch(&self, medium: &engine::Medium) -> Option<String> {
        let s = &self.model.sidecar;
        let g = match medium.phase() {
            engine::PhaseFunction::HenyeyGreenstein { g } => g,
            engine::PhaseFunction::Isotropic => 0.0,
            _ => f32::NAN,
        };
        let off = (medium.albedo() - s.albedo).abs() > 1e-3 || !((g - s.g).abs() <= 1e-3);
        off.then(|| {
            format!(
                "the point-to-point model was trained for albedo {} and g {}; this medium has albedo {} and {:?}: \
                 its predictions are extrapolations",
                s.albedo,
                s.g,
                medium.albedo(),
                medium.phase()
            )
        })
    }

    pub fn model(&self) -> &P2pModel {
        &self.model
    }
}

impl engine::TransportPredictor for BoundP2pModel {
    fn predict(&self, _medium: &engine::Medium, q: &P2pQuery, rng: &mut Rng) -> f32 {
        // A random rotation about the emitter-sensor axis, as in training.
        let Some(frame) = LocalFrame::new(q.emitter, q.sensor, std::f32::consts::TAU * rng.uniform()) else {
            return 0.0;
        };
        SCRATCH.with_borrow_mut(|(raw, input, scratch)| {
            let s = &self.model.sidecar;
            raw.resize(s.features.len(), 0.0);
            s.features.write(&self.pyramid, self.rho, s.albedo, &frame, raw);
            self.model.predict_features(raw, frame.scale, input, scratch)
        })
    }

    /// Features for every query, then the network over all rows at once (four rows
    /// per weight pass), which costs a fraction of single passes.
    fn predict_batch(&self, _medium: &engine::Medium, queries: &[P2pQuery], rngs: &mut [Rng], out: &mut [f32]) {
        assert!(queries.len() == rngs.len() && queries.len() == out.len(), "one stream and one output per query");
        BATCH_SCRATCH.with_borrow_mut(|(raw, input, scales, bs)| {
            let s = &self.model.sidecar;
            let n = s.features.len();
            raw.resize(n, 0.0);
            input.resize(queries.len() * n, 0.0);
            scales.clear();
            for ((q, rng), row) in queries.iter().zip(rngs.iter_mut()).zip(input.chunks_exact_mut(n)) {
                // The same draw as `predict`: a random rotation about the axis.
                match LocalFrame::new(q.emitter, q.sensor, std::f32::consts::TAU * rng.uniform()) {
                    Some(frame) => {
                        s.features.write(&self.pyramid, self.rho, s.albedo, &frame, raw);
                        self.model.standardize(raw, row);
                        scales.push(frame.scale);
                    }
                    None => {
                        row.fill(0.0);
                        scales.push(f32::NAN);
                    }
                }
            }
            self.model.eval.forward_batch(&input[..queries.len() * n], out, bs);
            for (o, &scale) in out.iter_mut().zip(scales.iter()) {
                *o = if scale.is_nan() { 0.0 } else { self.model.finish(*o, scale) };
            }
        })
    }

    fn name(&self) -> &str {
        &self.name
    }
}
