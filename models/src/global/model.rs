//! The global transport model as the renderer uses it: the model files (safetensors
//! weights + JSON sidecar), the target transformation (thesis eqs. 5.8-5.9), and an
//! allocation-free f32 evaluator of the MLP that implements the engine's
//! [`InScatterPredictor`].
//!
//! Target transformation: y = ln(1 + L_i / p(omega_q, omega_L)) with p the
//! Henyey-Greenstein phase value of single scattering toward omega_q (cos = cos theta,
//! theta the query angle from the light), then standardized; every feature is
//! standardized too. Statistics come from the training split and live in the sidecar.

use super::depth_field::DepthField;
use super::directions::{DirectionSetKind, LightFrame};
use super::features::FeatureExtractor;
use super::sky_field::SkyDepthField;
use crate::nn::dense::Activation;
use crate::nn::mlp::{BATCH_ROWS, Mlp, Scratch};
use engine::{Cancel, InScatterPredictor, Medium, PhaseFunction, Sun};
use glam::Vec3;
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

pub const MODEL_FORMAT: &str = "nimbus-global-model";
pub const MODEL_FORMAT_VERSION: u32 = 1;

/// Where the shipped model lives in the repository (its bytes are compiled in).
pub const SHIPPED_PATH: &str = "assets/models/global.safetensors";
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../../assets/models/global.safetensors");
const SHIPPED_SIDECAR: &str = include_str!("../../../assets/models/global.json");

/// [`crate::fingerprint::fingerprint`] of the shipped model's weights and sidecar.
pub fn shipped_fingerprint() -> u64 {
    crate::fingerprint::fingerprint(&[SHIPPED_WEIGHTS, SHIPPED_SIDECAR.as_bytes()])
}

/// How theta and phi are measured; a model trained under another convention is refused.
pub const ANGLE_CONVENTION: &str = "light frame: z = -omega_L (toward the light), x, y = engine::sampling::coordinate_system(z); theta = acos(z) of omega_q in [0, pi], phi = atan2(y, x) in [0, 2 pi); omega_q points away from the query point";

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
    /// from the thesis (docs/conventions.md, "Where Nimbus departs").
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

/// The bytes of a model's weights (`path`, .safetensors) and the text of its sidecar
/// (same name, .json), each error naming its file.
pub fn read_model_files(path: &Path) -> Result<(Vec<u8>, String), ModelError> {
    let json_path = path.with_extension("json");
    let text =
        std::fs::read_to_string(&json_path).map_err(|e| ModelError::File { path: json_path, why: e.to_string() })?;
    let bytes = std::fs::read(path).map_err(|e| ModelError::File { path: path.to_owned(), why: e.to_string() })?;
    Ok((bytes, text))
}

/// A shipped model, loaded (and checked) once into `cell` by `load`; its error names
/// `path`.
pub fn shipped_once<T>(
    cell: &'static OnceLock<Result<Arc<T>, String>>,
    path: &str,
    load: impl FnOnce() -> Result<T, ModelError>,
) -> Result<Arc<T>, ModelError> {
    cell.get_or_init(|| load().map(Arc::new).map_err(|e| e.to_string()))
        .clone()
        .map_err(|why| ModelError::File { path: path.into(), why })
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
        let (bytes, text) = read_model_files(path)?;
        Self::from_bytes(&bytes, &text, path)
    }

    /// The model shipped in `assets/models/global.*`, compiled into the binary so a
    /// fresh build predicts without any file. Loaded (and checked) once.
    pub fn shipped() -> Result<Arc<GlobalModel>, ModelError> {
        static SHIPPED: OnceLock<Result<Arc<GlobalModel>, String>> = OnceLock::new();
        shipped_once(&SHIPPED, SHIPPED_PATH, || {
            Self::from_bytes(SHIPPED_WEIGHTS, SHIPPED_SIDECAR, Path::new(SHIPPED_PATH))
        })
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
        let mut widths = vec![n_f];
        widths.extend(&sidecar.hidden);
        widths.push(1);
        let mlp = Mlp::from_safetensors(bytes, &widths, sidecar.activation).map_err(|why| file_err(path, why))?;
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

    /// [`GlobalModel::predict_features`] on feature rows `stride` apart (each row's first
    /// n values, n the extractor's length), one per output: the same bits on each row,
    /// the network run on several rows per pass ([`crate::nn::Mlp::forward_batch`]).
    pub fn predict_features_many(&self, raw: &[f32], stride: usize, out: &mut [f32], scratch: &mut Scratch) {
        let st = &self.sidecar.standardization;
        let n = self.features.len();
        let standardize = |k: usize, v: f32| (v - st.feature_mean[k]) / st.feature_std[k];
        self.mlp.forward_batch_standardized(raw, stride, out, scratch, standardize);
        for (r, o) in out.iter_mut().enumerate() {
            *o = untransform_target(self.target, &raw[r * stride..r * stride + n], *o * st.target_std + st.target_mean);
        }
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
    /// Optical depths along every direction, for other lights (sky directions, a
    /// soft sun's disk): built by [`BoundGlobalModel::with_other_lights`].
    sky: Option<Arc<SkyDepthField>>,
    /// cos [`SUN_FIELD_ANGLE`].
    near_cos: f32,
}

/// Lights within this angle of the bound sun (radians, 2 degrees) are answered from the
/// sun's own field, as if they were its centre: a nearly delta sun keeps the sun
/// field's accuracy.
pub const SUN_FIELD_ANGLE: f32 = 0.035;

impl BoundGlobalModel {
    /// Builds the depth field of `medium` for `sun` (about a second at 64^3 nodes on two
    /// cores; `max_nodes` per axis trades accuracy for time and memory).
    pub fn new(model: Arc<GlobalModel>, medium: &Medium, sun: &Sun, max_nodes: u32) -> Self {
        Self::new_until(model, medium, sun, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`BoundGlobalModel::new`], or None when `cancel` asks to stop.
    pub fn new_until(
        model: Arc<GlobalModel>,
        medium: &Medium,
        sun: &Sun,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<Self> {
        let omega_l = sun.direction();
        let field = DepthField::for_light_until(medium, model.features.directions(), omega_l, max_nodes, cancel)?;
        Some(BoundGlobalModel {
            model,
            field: Arc::new(field),
            frame: LightFrame::new(omega_l),
            grid: medium.grid().clone(),
            rho: medium.rho(),
            omega_l,
            sky: None,
            near_cos: SUN_FIELD_ANGLE.cos(),
        })
    }

    /// Adds the field of optical depths along every direction ([`SkyDepthField`],
    /// `texels`^2 directions, at most `max_nodes` nodes per axis), with which the
    /// model answers lights other than its sun without ray marching.
    pub fn with_other_lights(self, medium: &Medium, texels: u32, max_nodes: u32) -> Self {
        self.with_other_lights_until(medium, texels, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`BoundGlobalModel::with_other_lights`], or None when `cancel` asks to stop.
    pub fn with_other_lights_until(
        mut self,
        medium: &Medium,
        texels: u32,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<Self> {
        self.sky = Some(Arc::new(SkyDepthField::build_until(medium, texels, max_nodes, cancel)?));
        Some(self)
    }

    pub fn sky_field(&self) -> Option<&SkyDepthField> {
        self.sky.as_deref()
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
}

impl InScatterPredictor for BoundGlobalModel {
    /// The bound sun (or a light within [`SUN_FIELD_ANGLE`] of it) from the sun's
    /// field, any other light of the same medium from the all-direction field when it
    /// was built, anything else by ray marching.
    fn predict(&self, medium: &Medium, sun: &Sun, x: Vec3, omega: Vec3) -> f32 {
        if !(Arc::ptr_eq(medium.grid(), &self.grid) && medium.rho() == self.rho) {
            return self.model.predict(medium, sun, x, omega);
        }
        let mut feat = [0.0f32; 4 + 256];
        let n = self.model.features.len();
        if sun.direction().dot(self.omega_l) >= self.near_cos {
            self.features(medium, x, omega, &mut feat[..n]);
        } else if let Some(sky) = &self.sky {
            let frame = LightFrame::new(sun.direction());
            FeatureExtractor::write_head(medium.albedo(), medium.phase().mean_cosine(), &frame, omega, &mut feat[..n]);
            sky.lookup(x, &frame, self.model.features.directions(), &mut feat[4..n]);
        } else {
            return self.model.predict(medium, sun, x, omega);
        }
        let v = SCRATCH.with(|s| self.model.predict_features(&feat[..n], &mut s.borrow_mut()));
        if v.is_finite() { v } else { 0.0 }
    }

    /// For the bound cloud and sun, the features of up to [`BATCH_ROWS`] points at a
    /// time from the sun's field, then the network on all of them in one batched pass
    /// (the same bits as `predict` on each point); other lights point by point.
    fn predict_many(&self, medium: &Medium, sun: &Sun, xs: &[Vec3], omegas: &[Vec3], out: &mut [f32]) {
        assert!(xs.len() == omegas.len() && xs.len() == out.len(), "one direction and one output per point");
        let bound = Arc::ptr_eq(medium.grid(), &self.grid) && medium.rho() == self.rho;
        if !(bound && sun.direction().dot(self.omega_l) >= self.near_cos) {
            for ((o, &x), &omega) in out.iter_mut().zip(xs).zip(omegas) {
                *o = self.predict(medium, sun, x, omega);
            }
            return;
        }
        const ROW: usize = 4 + 256;
        let n = self.model.features.len();
        let mut feat = [0.0f32; BATCH_ROWS * ROW];
        for ((xc, wc), oc) in xs.chunks(BATCH_ROWS).zip(omegas.chunks(BATCH_ROWS)).zip(out.chunks_mut(BATCH_ROWS)) {
            for ((&x, &omega), row) in xc.iter().zip(wc).zip(feat.chunks_exact_mut(ROW)) {
                self.features(medium, x, omega, &mut row[..n]);
            }
            SCRATCH.with(|s| self.model.predict_features_many(&feat, ROW, oc, &mut s.borrow_mut()));
            for o in oc.iter_mut() {
                if !o.is_finite() {
                    *o = 0.0;
                }
            }
        }
    }

    fn predicts_single_scattering(&self) -> bool {
        self.model.target == TargetKind::Total
    }

    fn memory_bytes(&self) -> usize {
        self.field.memory_bytes() + self.sky.as_ref().map_or(0, |s| s.memory_bytes())
    }

    fn name(&self) -> &str {
        "global MLP (depth field)"
    }
}
