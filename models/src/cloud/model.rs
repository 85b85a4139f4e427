//! The cloud-aware model as the renderer uses it: the model files (safetensors weights
//! + JSON sidecar), the target transformation, and the predictor of multiple
//! scattering bound to one cloud and one sun ([`BoundCloudModel`]).
//!
//! The network predicts o; the multiple-scattering radiance is
//! L_ms = (exp(o std + mean) - 1) / (4 pi) for a sun of unit radiance, with mean and
//! std those of ln(1 + 4 pi L_ms) over the training split. Features are standardized
//! by the sidecar's statistics. Single scattering at the query point is left to the
//! renderer's next event estimation.

use super::features::{CloudField, DerivedInputs, N_FEATURES, feature_names};
use crate::global::model::{ModelError, read_model_files, shipped_once};
use crate::nn::dense::Activation;
use crate::nn::mlp::{BATCH_ROWS, Mlp, Scratch};
use engine::field::SunTransmittance;
use engine::{Cancel, DensityGrid, InScatterPredictor, Medium, Sun};
use glam::Vec3;
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use std::path::Path;
use std::sync::{Arc, OnceLock};

pub const MODEL_FORMAT: &str = "nimbus-cloud-model";
pub const MODEL_FORMAT_VERSION: u32 = 1;
pub const TARGET_TRANSFORM: &str = "L_ms = (exp(o std + mean) - 1) / (4 pi), unit sun, orders >= 2 from the point";

/// Where the shipped model lives in the repository (its bytes are compiled in).
pub const SHIPPED_PATH: &str = "assets/models/cloud.safetensors";
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../../assets/models/cloud.safetensors");
const SHIPPED_SIDECAR: &str = include_str!("../../../assets/models/cloud.json");

/// [`crate::fingerprint::fingerprint`] of the shipped model's weights and sidecar.
pub fn shipped_fingerprint() -> u64 {
    crate::fingerprint::fingerprint(&[SHIPPED_WEIGHTS, SHIPPED_SIDECAR.as_bytes()])
}

/// The sidecar: what the weights mean.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CloudSidecar {
    pub format: String,
    pub format_version: u32,
    pub feature_names: Vec<String>,
    pub feature_mean: Vec<f32>,
    /// 1 where a feature is constant in the training data.
    pub feature_std: Vec<f32>,
    pub target: String,
    pub target_mean: f32,
    pub target_std: f32,
    pub hidden: Vec<usize>,
    pub activation: Activation,
    /// How the model was made: command, data, configuration, report, history.
    pub training: serde_json::Value,
}

/// A trained cloud-aware model.
#[derive(Clone, Debug)]
pub struct CloudModel {
    pub sidecar: CloudSidecar,
    pub mlp: Mlp,
    inv_std: Vec<f32>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

impl CloudModel {
    /// Loads `path` (.safetensors) and its sidecar (same name, .json), checked.
    pub fn load(path: &Path) -> Result<CloudModel, ModelError> {
        let (bytes, text) = read_model_files(path)?;
        Self::from_bytes(&bytes, &text, path)
    }

    /// The model shipped in `assets/models/cloud.*`, compiled in; loaded once.
    pub fn shipped() -> Result<Arc<CloudModel>, ModelError> {
        static SHIPPED: OnceLock<Result<Arc<CloudModel>, String>> = OnceLock::new();
        shipped_once(&SHIPPED, SHIPPED_PATH, || {
            Self::from_bytes(SHIPPED_WEIGHTS, SHIPPED_SIDECAR, Path::new(SHIPPED_PATH))
        })
    }

    /// A model from its weights' bytes and its sidecar's text; `path` names it in
    /// messages. Refuses another format, another feature layout, statistics of the
    /// wrong length or non-finite, and weights that do not fit.
    pub fn from_bytes(bytes: &[u8], sidecar_json: &str, path: &Path) -> Result<CloudModel, ModelError> {
        let json_path = path.with_extension("json");
        let layout = |why: String| ModelError::Layout { path: json_path.clone(), why };
        let sidecar: CloudSidecar = serde_json::from_str(sidecar_json).map_err(|e| ModelError::File {
            path: json_path.clone(),
            why: format!("not a Nimbus cloud-model sidecar: {e}"),
        })?;
        if sidecar.format != MODEL_FORMAT || sidecar.format_version != MODEL_FORMAT_VERSION {
            return Err(layout(format!(
                "format {} v{} is not {MODEL_FORMAT} v{MODEL_FORMAT_VERSION}",
                sidecar.format, sidecar.format_version
            )));
        }
        // A model reads the first n of the features: the stored ones, and the derived
        // ones its training chose.
        let n = sidecar.feature_names.len();
        if DerivedInputs::of_inputs(n).is_none() || sidecar.feature_names[..] != feature_names()[..n] {
            let lengths = DerivedInputs::ALL.map(DerivedInputs::inputs);
            return Err(layout(format!(
                "its {n} features are not the first {lengths:?} of the {N_FEATURES} this code computes"
            )));
        }
        if sidecar.target != TARGET_TRANSFORM {
            return Err(layout(format!("target {:?} is not {TARGET_TRANSFORM:?}", sidecar.target)));
        }
        let stats_ok = sidecar.feature_mean.len() == n
            && sidecar.feature_std.len() == n
            && sidecar.feature_mean.iter().chain(&sidecar.feature_std).all(|v| v.is_finite())
            && sidecar.feature_std.iter().all(|v| *v > 0.0)
            && sidecar.target_mean.is_finite()
            && sidecar.target_std.is_finite()
            && sidecar.target_std > 0.0;
        if !stats_ok {
            return Err(layout("the standardization statistics are missing, of the wrong length or not finite".into()));
        }
        let mut widths = vec![n];
        widths.extend(&sidecar.hidden);
        widths.push(1);
        let mlp = Mlp::from_safetensors(bytes, &widths, sidecar.activation)
            .map_err(|why| ModelError::File { path: path.to_owned(), why })?;
        Ok(CloudModel::new(sidecar, mlp))
    }

    pub fn new(sidecar: CloudSidecar, mlp: Mlp) -> Self {
        let inv_std = sidecar.feature_std.iter().map(|s| 1.0 / s).collect();
        CloudModel { sidecar, mlp, inv_std }
    }

    /// How many of the feature vector's values the network reads (its first ones).
    pub fn inputs(&self) -> usize {
        self.inv_std.len()
    }

    /// The network output o for a raw feature row (its first [`CloudModel::inputs`]
    /// values are read).
    #[inline]
    pub fn output(&self, raw: &[f32], scratch: &mut Scratch) -> f32 {
        self.mlp.ensure(scratch);
        let mut x = std::mem::take(&mut scratch.features);
        for (k, v) in raw[..self.inputs()].iter().enumerate() {
            x[k] = (v - self.sidecar.feature_mean[k]) * self.inv_std[k];
        }
        // The scratch row may be longer (another model on this thread read more inputs).
        let o = self.mlp.forward_sized(&x[..self.inputs()], scratch);
        scratch.features = x;
        o
    }

    /// L_ms from the network output (clamped at 0; 0 for a non-finite output).
    #[inline]
    pub fn untransform(&self, o: f32) -> f32 {
        let v = (o * self.sidecar.target_std + self.sidecar.target_mean).exp_m1() / (4.0 * std::f32::consts::PI);
        if v.is_finite() { v.max(0.0) } else { 0.0 }
    }

    /// L_ms for one raw feature row.
    #[inline]
    pub fn predict_features(&self, raw: &[f32], scratch: &mut Scratch) -> f32 {
        self.untransform(self.output(raw, scratch))
    }

    /// L_ms for raw feature rows `stride` apart (each row's first
    /// [`CloudModel::inputs`] values are read), one per output: the same bits as
    /// [`CloudModel::predict_features`] on each row, the network run on several rows
    /// per pass ([`Mlp::forward_batch`]).
    pub fn predict_features_many(&self, raw: &[f32], stride: usize, out: &mut [f32], scratch: &mut Scratch) {
        let (mean, inv_std) = (&self.sidecar.feature_mean, &self.inv_std);
        self.mlp.forward_batch_standardized(raw, stride, out, scratch, |k, v| (v - mean[k]) * inv_std[k]);
        for o in out.iter_mut() {
            *o = self.untransform(*o);
        }
    }
}

/// The cloud-aware model bound to one cloud and one sun: the density pyramid and the
/// sun-transmittance field it reads, built once (see [`CloudField::build`]).
#[derive(Clone, Debug)]
pub struct BoundCloudModel {
    model: Arc<CloudModel>,
    field: Arc<CloudField>,
    /// What the field was built for.
    grid: Arc<DensityGrid>,
    rho: f32,
    omega_l: Vec3,
}

impl BoundCloudModel {
    /// Builds the field for `medium` and `sun` (sun field at most `max_nodes` per axis).
    pub fn new(model: Arc<CloudModel>, medium: &Medium, sun: &Sun, max_nodes: u32) -> Self {
        Self::new_until(model, medium, sun, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`BoundCloudModel::new`], or None when `cancel` asks to stop.
    pub fn new_until(
        model: Arc<CloudModel>,
        medium: &Medium,
        sun: &Sun,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<Self> {
        Some(Self::binding(model, CloudField::build_until(medium, sun, max_nodes, cancel)?, medium, sun))
    }

    /// The binding of `model` to `field`, built for `medium` and `sun`.
    fn binding(model: Arc<CloudModel>, field: CloudField, medium: &Medium, sun: &Sun) -> Self {
        BoundCloudModel {
            model,
            field: Arc::new(field),
            grid: medium.grid().clone(),
            rho: medium.rho(),
            omega_l: sun.direction(),
        }
    }

    /// [`BoundCloudModel::new_until`] reading `sun_field`, the caller's field for this
    /// medium and sun (the preview's), instead of building one; the pyramid is read
    /// from at most `2 max_nodes` samples per axis as with a field of its own. Its
    /// memory leaves the shared field to the caller
    /// ([`CloudField::with_sun_field_until`]).
    pub fn with_sun_field_until(
        model: Arc<CloudModel>,
        medium: &Medium,
        sun: &Sun,
        sun_field: Arc<SunTransmittance>,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<Self> {
        debug_assert!((sun_field.to_sun() + sun.direction()).length() < 1e-4, "a sun field built for another sun");
        let field = CloudField::with_sun_field_until(medium, sun_field, max_nodes, cancel)?;
        Some(Self::binding(model, field, medium, sun))
    }

    pub fn model(&self) -> &Arc<CloudModel> {
        &self.model
    }

    pub fn field(&self) -> &CloudField {
        &self.field
    }

    /// Whether this binding answers for `medium` and `sun` (the field depends on the
    /// cloud, rho and the sun's direction; albedo and g are read per query).
    pub fn matches(&self, medium: &Medium, sun: &Sun) -> bool {
        Arc::ptr_eq(medium.grid(), &self.grid) && medium.rho() == self.rho && sun.direction() == self.omega_l
    }
}

impl InScatterPredictor for BoundCloudModel {
    /// L_ms at `x`. A medium or sun other than the bound ones is a caller's error
    /// (the scene binds the model to its own cloud and sun); it is answered with 0,
    /// which leaves single scattering by NEE, and caught by a debug assertion.
    fn predict(&self, medium: &Medium, sun: &Sun, x: Vec3, omega: Vec3) -> f32 {
        if !self.matches(medium, sun) {
            debug_assert!(false, "BoundCloudModel asked about a medium or sun it was not built for");
            return 0.0;
        }
        let mut feat = [0.0f32; N_FEATURES];
        self.field.features(medium.albedo(), medium.phase().mean_cosine(), x, omega, &mut feat);
        SCRATCH.with(|s| self.model.predict_features(&feat, &mut s.borrow_mut()))
    }

    /// The features of up to [`BATCH_ROWS`] points at a time, then the network on all
    /// of them in one batched pass: the same bits as `predict` on each point.
    fn predict_many(&self, medium: &Medium, sun: &Sun, xs: &[Vec3], omegas: &[Vec3], out: &mut [f32]) {
        assert!(xs.len() == omegas.len() && xs.len() == out.len(), "one direction and one output per point");
        if !self.matches(medium, sun) {
            debug_assert!(false, "BoundCloudModel asked about a medium or sun it was not built for");
            out.fill(0.0);
            return;
        }
        let (albedo, g) = (medium.albedo(), medium.phase().mean_cosine());
        let mut feat = [0.0f32; BATCH_ROWS * N_FEATURES];
        for ((xc, wc), oc) in xs.chunks(BATCH_ROWS).zip(omegas.chunks(BATCH_ROWS)).zip(out.chunks_mut(BATCH_ROWS)) {
            for ((&x, &omega), row) in xc.iter().zip(wc).zip(feat.chunks_exact_mut(N_FEATURES)) {
                self.field.features(albedo, g, x, omega, row);
            }
            SCRATCH.with(|s| self.model.predict_features_many(&feat, N_FEATURES, oc, &mut s.borrow_mut()));
        }
    }

    fn predicts_single_scattering(&self) -> bool {
        false
    }

    /// Its sun-transmittance field holds one sun direction.
    fn answers_any_light_direction(&self) -> bool {
        false
    }

    fn memory_bytes(&self) -> usize {
        self.field.memory_bytes()
    }

    fn name(&self) -> &str {
        "cloud-aware MLP"
    }
}
