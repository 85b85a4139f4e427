//! Scene files (TOML): what to render and how. Unknown keys and out-of-range values
//! are errors that name the key and the allowed range.
//!
//! ```toml
//! seed = 1                 # random streams derive from (seed, pass, pixel)
//! k = 2                    # first scattering order of the high-order buffer
//! [grid]
//! preset = "scene-a"       # scene-a|b|c, set-01 .. set-12; or builtin = "cumulus"
//! resolution = 128         # (or a [grid.params] table of modeler parameters)
//! [medium]
//! rho = 40.0               # density scale: sigma_t = rho * density (1 / world unit)
//! albedo = 1.0
//! phase = "hg"             # isotropic | hg | rayleigh | hazy | murky
//! g = 0.85
//! [sun]
//! direction = [0, -1, 0]   # direction the light travels
//! radiance = 1.0           # or [r, g, b]
//! [camera]
//! preset = "toplit"        # toplit | backlit | frontlit, or position/target/up
//! width = 256
//! height = 256
//! ```

use crate::cloud::Builtin;
use engine::field::SunTransmittance;
use engine::integrator::preview::{CameraLatticePredictor, MultipleScattering, Preview};
use engine::{
    Camera, Cancel, DensityGrid, InScatterPredictor, Integrator, Medium, Mode, PhaseFunction, RenderSettings, Scene,
    Sky, Sun,
};
use glam::Vec3;
use models::global::ModelError;
use models::p2p::model::{BoundP2pModel, P2pModel};
use models::prediction::{PredictionModel, PredictorKind};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// (The I/O error is part of the message, not a source, so that an error chain
    /// does not print it twice.)
    #[error("cannot read scene file {path}: {error}")]
    Io { path: String, error: std::io::Error },
    #[error("scene file {path}: {message}")]
    Parse { path: String, message: String },
    #[error("{key} = {value} is out of range: {range}")]
    Range { key: &'static str, value: String, range: &'static str },
    #[error("{0}")]
    Invalid(String),
    /// The set-up was abandoned on request (the render it was for was superseded).
    #[error("cancelled")]
    Cancelled,
}

fn range_err(key: &'static str, value: impl std::fmt::Display, range: &'static str) -> SceneError {
    SceneError::Range { key, value: value.to_string(), range }
}

/// Radiance given as one number (grey) or as [r, g, b].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Rgb {
    Grey(f32),
    Rgb([f32; 3]),
}

impl Rgb {
    pub fn to_vec3(self) -> Vec3 {
        match self {
            Rgb::Grey(v) => Vec3::splat(v),
            Rgb::Rgb(c) => Vec3::from_array(c),
        }
    }
}

/// The unit vector toward a sun at `elevation_deg` above the horizon and
/// `azimuth_deg` around the vertical (0 = +z, 90 = +x).
pub fn sun_vector(elevation_deg: f32, azimuth_deg: f32) -> Vec3 {
    let (el, az) = (elevation_deg.to_radians(), azimuth_deg.to_radians());
    Vec3::new(el.cos() * az.sin(), el.sin(), el.cos() * az.cos())
}

/// (elevation, azimuth) in degrees of the direction `to_sun`, azimuth in [0, 360).
pub fn sun_angles_of(to_sun: Vec3) -> (f32, f32) {
    let v = to_sun.normalize_or(Vec3::Y);
    (v.y.clamp(-1.0, 1.0).asin().to_degrees(), v.x.atan2(v.z).to_degrees().rem_euclid(360.0))
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// Scene seed (any u64). Default 0.
    #[serde(default)]
    pub seed: u64,
    /// First order of the high-order buffer, 1 ..= 64. Default 1.
    #[serde(default = "default_k")]
    pub k: u32,
    /// Highest scattering order rendered, >= 1; absent = all.
    #[serde(default)]
    pub max_order: Option<u32>,
    pub grid: GridDesc,
    /// Directory relative paths in the scene resolve against (the scene file's).
    #[serde(skip)]
    pub base_dir: Option<std::path::PathBuf>,
    #[serde(default)]
    pub medium: MediumDesc,
    #[serde(default)]
    pub sun: SunDesc,
    #[serde(default)]
    pub sky: SkyDesc,
    #[serde(default)]
    pub camera: CameraDesc,
    #[serde(default)]
    pub render: RenderDesc,
}

fn default_k() -> u32 {
    1
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GridDesc {
    /// A built-in analytic cloud: "cumulus" or "sphere".
    pub builtin: Option<String>,
    /// A modeler preset: scene-a, scene-b, scene-c, set-01 .. set-12.
    pub preset: Option<String>,
    /// Modeler parameters given inline (see `modeler::CloudParams`).
    pub params: Option<modeler::CloudParams>,
    /// An OpenVDB file (relative to the scene file).
    pub file: Option<String>,
    /// The float grid to read from `file` (default "density", else the first float grid).
    pub grid_name: Option<String>,
    /// Voxels per axis for generated clouds, 2 ..= 2048 (sparse bricks above 256).
    /// Default 128.
    #[serde(default = "default_resolution")]
    pub resolution: u32,
}

fn default_resolution() -> u32 {
    128
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MediumDesc {
    /// Density scale, 0 ..= 10000 per world unit. Default 40.
    pub rho: f32,
    /// Single-scattering albedo, 0 ..= 1. Default 1.
    pub albedo: f32,
    /// isotropic | hg | rayleigh | hazy | murky. Default hg.
    pub phase: String,
    /// Henyey-Greenstein asymmetry, -0.99 ..= 0.99 (hg only). Default 0.85.
    pub g: f32,
}

impl Default for MediumDesc {
    fn default() -> Self {
        MediumDesc { rho: 40.0, albedo: 1.0, phase: "hg".into(), g: 0.85 }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SunDesc {
    /// Direction the light travels (need not be normalized). Default straight down.
    pub direction: [f32; 3],
    /// Irradiance perpendicular to the sun, >= 0 (grey or [r, g, b]). Default 1.
    pub radiance: Rgb,
    /// Angular radius of a soft sun disk, 0 ..= 20 degrees. Default 0 (delta light).
    pub angular_radius_deg: f32,
}

impl Default for SunDesc {
    fn default() -> Self {
        SunDesc { direction: [0.0, -1.0, 0.0], radiance: Rgb::Grey(1.0), angular_radius_deg: 0.0 }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SkyDesc {
    /// Environment radiance at the zenith, >= 0 (grey or [r, g, b]); the whole sky
    /// when `horizon` is not given. Default 0 (black).
    pub radiance: Rgb,
    /// Radiance at the horizon, >= 0: the sky runs from it to `radiance` at the
    /// zenith, linear in the sine of the elevation. Default: `radiance` (uniform).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub horizon: Option<Rgb>,
    /// Albedo of a ground plane below the horizon, 0 ..= 1: seen from the cloud it
    /// has the radiance albedo / pi x (the sun's irradiance on it + the sky's),
    /// unshadowed by the cloud. Default: none, the sky's horizon continues below.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ground_albedo: Option<f32>,
}

impl Default for SkyDesc {
    fn default() -> Self {
        SkyDesc { radiance: Rgb::Grey(0.0), horizon: None, ground_albedo: None }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraDesc {
    /// toplit | backlit | frontlit: the thesis's lighting configurations relative to
    /// the sun, looking at `target` from `distance`. Ignored when `position` is set.
    pub preset: Option<String>,
    pub position: Option<[f32; 3]>,
    /// Default the origin.
    pub target: [f32; 3],
    /// Default +y.
    pub up: [f32; 3],
    /// Distance from target for presets, > 0. Default 2.8.
    pub distance: f32,
    /// Vertical field of view, 1 ..= 170 degrees. Default 30.
    pub fov_y_deg: f32,
    /// Pixels, 1 ..= 16384. Default 256 x 256.
    pub width: u32,
    pub height: u32,
}

impl Default for CameraDesc {
    fn default() -> Self {
        CameraDesc {
            preset: None,
            position: None,
            target: [0.0; 3],
            up: [0.0, 1.0, 0.0],
            distance: 2.8,
            fov_y_deg: 30.0,
            width: 256,
            height: 256,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderDesc {
    /// reference | predict | preview. Default reference. `preview` is the instant
    /// preview: ray marching with single scattering from a precomputed sun
    /// transmittance and the higher orders from `render.preview`.
    pub mode: String,
    /// Prediction probability for mode = "predict", (0, 1]. Default 0.25.
    pub p: f32,
    /// A model of prediction at bounce k (.safetensors with its .json sidecar, a
    /// cloud-aware or a global model, as its sidecar says) for mode = "predict" and
    /// the learned preview, relative to the scene file. Default: the shipped model of
    /// `render.predictor`, compiled into nimbus.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// The shipped model used when `render.model` is unset: "auto" (the default: the
    /// cloud-aware model, docs/cloud-model.md, under a sun alone; the thesis's global
    /// model under a sky or a soft sun, whose light the cloud-aware model does not
    /// answer), "cloud" or "global".
    #[serde(skip_serializing_if = "is_auto")]
    pub predictor: String,
    /// Light transport: "path" (unidirectional path tracing, the default) or "bdpt"
    /// (volumetric bidirectional path tracing with MIS). With mode = "predict",
    /// "path" predicts at bounce k with the model of `render.predictor` and "bdpt"
    /// predicts the transport between k-segment subpaths with the point-to-point
    /// model (thesis 6.4; the buffers then split at order 2k + 1).
    #[serde(skip_serializing_if = "is_path")]
    pub integrator: String,
    /// A point-to-point model for integrator = "bdpt", mode = "predict", relative to
    /// the scene file. Default: the shipped single-cloud model.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub p2p_model: Option<String>,
    /// Distance threshold r of BDPT prediction: closer end vertices are extended, not
    /// predicted. Default 0.04 (one mean free path at rho = 25; the thesis's 0.08).
    #[serde(skip_serializing_if = "is_default_r")]
    pub r: f32,
    /// Light subpaths offered to each camera end vertex in BDPT prediction, one chosen
    /// by resampling. Default 256 (picked from the pass's pool); 1 is the thesis's pairing (see engine::bdpt).
    #[serde(skip_serializing_if = "is_default_candidates")]
    pub candidates: u32,
    /// Point-to-point samples averaged for each pair of end vertices closer than r in
    /// BDPT prediction. Default 8 (see engine::bdpt).
    #[serde(skip_serializing_if = "is_default_extension_samples")]
    pub extension_samples: u32,
    /// The preview's higher orders: "learned" (the model of prediction mode, on a
    /// lattice for the current sun and camera; the default) or "octaves" (Wrenninge
    /// et al. 2013).
    #[serde(skip_serializing_if = "is_learned")]
    pub preview: String,
    /// Nodes per axis, at most, of the learned preview's multiple-scattering lattice,
    /// 2 ..= 256 (at most two per voxel; each node evaluated when the preview first
    /// reads it). Default (unset): 96, finer over optically thick clouds, up to 192
    /// and two per voxel (engine::integrator::preview::Preview::default_lattice).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub preview_nodes: Option<u32>,
    /// Prediction at bounce 1 reads the model's answers from a lattice toward the
    /// camera of at most this many nodes per axis, filled as the paths read it
    /// (engine::integrator::preview::CameraLatticePredictor), instead of evaluating
    /// the model at every predicted vertex; 0 evaluates the model at every one, 2 ..=
    /// 256 otherwise. Default 128 (one node per voxel of a 128^3 cloud).
    #[serde(skip_serializing_if = "is_default_prediction_lattice")]
    pub prediction_lattice: u32,
    /// Where prediction at k = 1 places its vertex on the camera ray: "guided" (one of
    /// ratio tracking's tentative collisions drawn by its weight times the sun's
    /// transmittance there, plus a floor; the default), "weighted" (by its weight
    /// alone) or "free-flight" (the first real collision, as path tracing).
    #[serde(skip_serializing_if = "is_guided")]
    pub first_vertex: String,
    /// The octave approximation: octaves N (terms 0 .. N-1, 1 ..= 9, default 3) and
    /// its factors a (optical depth), b (amplitude), c (mean cosine), each in (0, 1],
    /// default 0.5.
    #[serde(skip_serializing_if = "is_default_octaves")]
    pub octaves: u32,
    #[serde(skip_serializing_if = "is_half")]
    pub octave_a: f32,
    #[serde(skip_serializing_if = "is_half")]
    pub octave_b: f32,
    #[serde(skip_serializing_if = "is_half")]
    pub octave_c: f32,
}

fn is_auto(s: &str) -> bool {
    s == "auto"
}

fn is_learned(s: &str) -> bool {
    s == "learned"
}

fn is_guided(s: &str) -> bool {
    FirstVertexChoice::parse(s) == Some(FirstVertexChoice::Guided)
}

fn is_default_prediction_lattice(n: &u32) -> bool {
    *n == DEFAULT_PREDICTION_LATTICE
}

fn is_default_octaves(n: &u32) -> bool {
    *n == 3
}

fn is_half(v: &f32) -> bool {
    *v == 0.5
}

/// Nodes per axis, at most, of prediction's lattice at bounce 1, by default.
pub const DEFAULT_PREDICTION_LATTICE: u32 = 128;

/// Where prediction at k = 1 places its vertex on the camera ray (`render.first_vertex`,
/// `--first-vertex`): the one place its words are spelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FirstVertexChoice {
    /// One of ratio tracking's tentative collisions, drawn by its weight times the
    /// sun's transmittance there, plus a floor (the default).
    Guided,
    /// A tentative collision drawn by its weight alone.
    Weighted,
    /// The first real collision, as path tracing.
    FreeFlight,
}

impl FirstVertexChoice {
    pub const ALL: [FirstVertexChoice; 3] =
        [FirstVertexChoice::Guided, FirstVertexChoice::Weighted, FirstVertexChoice::FreeFlight];
    /// The words of the scene file and the CLI, in the order of [`Self::ALL`].
    pub const NAMES: [&'static str; 3] = [Self::ALL[0].name(), Self::ALL[1].name(), Self::ALL[2].name()];

    pub const fn name(self) -> &'static str {
        match self {
            FirstVertexChoice::Guided => "guided",
            FirstVertexChoice::Weighted => "weighted",
            FirstVertexChoice::FreeFlight => "free-flight",
        }
    }

    pub fn parse(name: &str) -> Option<FirstVertexChoice> {
        Self::ALL.into_iter().find(|c| c.name() == name)
    }

    /// The engine's vertex sampling: guided is weighted sampling with the sun's guide
    /// added ([`engine::integrator::Integrator::with_first_vertex_guide`]).
    pub fn engine(self) -> engine::FirstVertex {
        match self {
            FirstVertexChoice::FreeFlight => engine::FirstVertex::FreeFlight,
            FirstVertexChoice::Guided | FirstVertexChoice::Weighted => engine::FirstVertex::Weighted,
        }
    }
}

fn is_default_extension_samples(n: &u32) -> bool {
    *n == engine::integrator::bdpt::Prediction::DEFAULT_EXTENSION_SAMPLES
}

fn is_default_r(r: &f32) -> bool {
    *r == engine::integrator::bdpt::Prediction::DEFAULT_R
}

fn is_default_candidates(m: &u32) -> bool {
    *m == engine::integrator::bdpt::Prediction::DEFAULT_CANDIDATES
}

fn is_path(s: &str) -> bool {
    s == "path"
}

impl Default for RenderDesc {
    fn default() -> Self {
        RenderDesc {
            mode: "reference".into(),
            p: 0.25,
            model: None,
            predictor: "auto".into(),
            integrator: "path".into(),
            p2p_model: None,
            r: engine::integrator::bdpt::Prediction::DEFAULT_R,
            candidates: engine::integrator::bdpt::Prediction::DEFAULT_CANDIDATES,
            extension_samples: engine::integrator::bdpt::Prediction::DEFAULT_EXTENSION_SAMPLES,
            preview: "learned".into(),
            preview_nodes: None,
            prediction_lattice: DEFAULT_PREDICTION_LATTICE,
            first_vertex: FirstVertexChoice::Guided.name().into(),
            octaves: 3,
            octave_a: 0.5,
            octave_b: 0.5,
            octave_c: 0.5,
        }
    }
}

/// Densities above this draw a warning: a grid holds values of order 1, scaled by
/// `medium.rho`.
pub const DENSITY_WARNING: f32 = 100.0;

/// A warning when `grid` holds densities far above 1: a grid of another quantity
/// (a temperature in kelvin, say) renders as a nearly opaque cloud, and slowly.
pub fn density_warning(grid: &DensityGrid) -> Option<String> {
    let max = grid.max_value();
    (max > DENSITY_WARNING).then(|| {
        format!(
            "the cloud's densities reach {max:.3e}; Nimbus expects values of order 1 scaled by medium.rho, \
             so this grid renders as a nearly opaque cloud (is it density, or another quantity?)"
        )
    })
}

/// The lighting configurations of the evaluation (thesis 5.5; docs/conventions.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraPreset {
    /// Viewing direction perpendicular to the light.
    Toplit,
    /// Looking toward the sun through the cloud: c = -omega_L.
    Backlit,
    /// Sun behind the camera: c = omega_L.
    Frontlit,
}

impl CameraPreset {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "toplit" => Some(CameraPreset::Toplit),
            "backlit" => Some(CameraPreset::Backlit),
            "frontlit" => Some(CameraPreset::Frontlit),
            _ => None,
        }
    }

    /// Camera viewing direction for light travelling along `omega_l` (unit).
    pub fn view_direction(&self, omega_l: Vec3) -> Vec3 {
        match self {
            CameraPreset::Backlit => -omega_l,
            CameraPreset::Frontlit => omega_l,
            CameraPreset::Toplit => {
                // The horizontal direction -z made perpendicular to the light.
                let c = Vec3::NEG_Z - omega_l * omega_l.dot(Vec3::NEG_Z);
                c.try_normalize().unwrap_or(Vec3::X - omega_l * omega_l.x).normalize()
            }
        }
    }
}

/// An up vector not parallel to `view`: +y, or -z when looking (nearly) vertically.
pub fn default_up(view: Vec3) -> Vec3 {
    if view.cross(Vec3::Y).length() > 1e-3 { Vec3::Y } else { Vec3::NEG_Z }
}

impl SceneFile {
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, SceneError> {
        toml::from_str(text)
            .map_err(|e| SceneError::Parse { path: origin.to_string(), message: e.to_string().trim().to_string() })
    }

    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let text = std::fs::read_to_string(path)
            .map_err(|error| SceneError::Io { path: path.display().to_string(), error })?;
        let mut file = Self::from_toml_str(&text, &path.display().to_string())?;
        file.base_dir = path.parent().map(|d| d.to_path_buf());
        Ok(file)
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("scene serializes")
    }

    /// Checks every value against its documented range.
    pub fn validate(&self) -> Result<(), SceneError> {
        if !(1..=64).contains(&self.k) {
            return Err(range_err("k", self.k, "1 ..= 64"));
        }
        if let Some(m) = self.max_order {
            if m < 1 {
                return Err(range_err("max_order", m, ">= 1"));
            }
        }
        let g = &self.grid;
        let sources = [g.builtin.is_some(), g.preset.is_some(), g.params.is_some(), g.file.is_some()]
            .iter()
            .filter(|x| **x)
            .count();
        if sources != 1 {
            return Err(SceneError::Invalid(format!(
                "grid: give exactly one source (grid.builtin, grid.preset, grid.params or grid.file), found {sources}"
            )));
        }
        if let Some(name) = &g.builtin {
            if Builtin::from_name(name).is_none() {
                return Err(SceneError::Invalid(format!(
                    "grid.builtin = \"{name}\" is not a built-in cloud; choose one of: {}",
                    Builtin::NAMES.join(", ")
                )));
            }
        }
        if let Some(name) = &g.preset {
            if modeler::preset(name).is_none() {
                return Err(SceneError::Invalid(format!(
                    "grid.preset = \"{name}\" is not a preset; choose one of: {}",
                    modeler::PRESET_NAMES.join(", ")
                )));
            }
        }
        if let Some(p) = &g.params {
            p.validate().map_err(|e| SceneError::Invalid(format!("grid.params.{e}")))?;
        }
        if !(2..=2048).contains(&self.grid.resolution) {
            return Err(range_err("grid.resolution", self.grid.resolution, "2 ..= 2048"));
        }
        let m = &self.medium;
        if !(m.rho.is_finite() && (0.0..=10000.0).contains(&m.rho)) {
            return Err(range_err("medium.rho", m.rho, "0 ..= 10000"));
        }
        if !(0.0..=1.0).contains(&m.albedo) {
            return Err(range_err("medium.albedo", m.albedo, "0 ..= 1"));
        }
        if !(-0.99..=0.99).contains(&m.g) {
            return Err(range_err("medium.g", m.g, "-0.99 ..= 0.99"));
        }
        if !["isotropic", "hg", "rayleigh", "hazy", "murky"].contains(&m.phase.as_str()) {
            return Err(SceneError::Invalid(format!(
                "medium.phase = \"{}\" is not a phase function; choose one of: isotropic, hg, rayleigh, hazy, murky",
                m.phase
            )));
        }
        let s = &self.sun;
        if Vec3::from_array(s.direction).try_normalize().is_none() {
            return Err(range_err("sun.direction", format!("{:?}", s.direction), "a non-zero finite vector"));
        }
        let rad = s.radiance.to_vec3();
        if !(rad.is_finite() && rad.min_element() >= 0.0) {
            return Err(range_err("sun.radiance", format!("{rad}"), ">= 0 and finite"));
        }
        if !(0.0..=20.0).contains(&s.angular_radius_deg) {
            return Err(range_err("sun.angular_radius_deg", s.angular_radius_deg, "0 ..= 20"));
        }
        let sky = self.sky.radiance.to_vec3();
        if !(sky.is_finite() && sky.min_element() >= 0.0) {
            return Err(range_err("sky.radiance", format!("{sky}"), ">= 0 and finite"));
        }
        if let Some(h) = self.sky.horizon.map(Rgb::to_vec3) {
            if !(h.is_finite() && h.min_element() >= 0.0) {
                return Err(range_err("sky.horizon", format!("{h}"), ">= 0 and finite"));
            }
        }
        if let Some(a) = self.sky.ground_albedo {
            if !(0.0..=1.0).contains(&a) {
                return Err(range_err("sky.ground_albedo", a, "0 ..= 1"));
            }
        }
        let c = &self.camera;
        if let Some(p) = &c.preset {
            if CameraPreset::from_name(p).is_none() {
                return Err(SceneError::Invalid(format!(
                    "camera.preset = \"{p}\" is unknown; choose one of: toplit, backlit, frontlit"
                )));
            }
        }
        if !(c.distance.is_finite() && c.distance > 0.0) {
            return Err(range_err("camera.distance", c.distance, "> 0"));
        }
        if !(1.0..=170.0).contains(&c.fov_y_deg) {
            return Err(range_err("camera.fov_y_deg", c.fov_y_deg, "1 ..= 170"));
        }
        if !(1..=16384).contains(&c.width) {
            return Err(range_err("camera.width", c.width, "1 ..= 16384"));
        }
        if !(1..=16384).contains(&c.height) {
            return Err(range_err("camera.height", c.height, "1 ..= 16384"));
        }
        match self.render.mode.as_str() {
            "reference" | "predict" | "preview" => {}
            other => {
                return Err(SceneError::Invalid(format!(
                    "render.mode = \"{other}\" is unknown; choose reference, predict or preview"
                )));
            }
        }
        if PredictorKind::parse(&self.render.predictor).is_none() {
            return Err(SceneError::Invalid(format!(
                "render.predictor = \"{}\" is unknown; choose {}",
                self.render.predictor,
                PredictorKind::NAMES
            )));
        }
        if !matches!(self.render.preview.as_str(), "learned" | "octaves") {
            return Err(SceneError::Invalid(format!(
                "render.preview = \"{}\" is unknown; choose learned or octaves",
                self.render.preview
            )));
        }
        if FirstVertexChoice::parse(&self.render.first_vertex).is_none() {
            let [a, b, c] = FirstVertexChoice::NAMES;
            return Err(SceneError::Invalid(format!(
                "render.first_vertex must be \"{a}\", \"{b}\" or \"{c}\", got {:?}",
                self.render.first_vertex
            )));
        }
        if self.render.prediction_lattice == 1 || self.render.prediction_lattice > 256 {
            return Err(range_err("render.prediction_lattice", self.render.prediction_lattice, "0 or 2 ..= 256"));
        }
        if let Some(n) = self.render.preview_nodes.filter(|n| !(2..=256).contains(n)) {
            return Err(range_err("render.preview_nodes", n, "2 ..= 256"));
        }
        if !(1..=9).contains(&self.render.octaves) {
            return Err(range_err("render.octaves", self.render.octaves, "1 ..= 9"));
        }
        for (key, v) in [
            ("render.octave_a", self.render.octave_a),
            ("render.octave_b", self.render.octave_b),
            ("render.octave_c", self.render.octave_c),
        ] {
            if !(v > 0.0 && v <= 1.0) {
                return Err(range_err(key, v, "(0, 1]"));
            }
        }
        if !matches!(self.render.integrator.as_str(), "path" | "bdpt") {
            return Err(SceneError::Invalid(format!(
                "render.integrator = \"{}\" is unknown; choose path or bdpt",
                self.render.integrator
            )));
        }
        if !(self.render.p > 0.0 && self.render.p <= 1.0) {
            return Err(range_err("render.p", self.render.p, "(0, 1]"));
        }
        if !(self.render.r >= 0.0) {
            return Err(range_err("render.r", self.render.r, "[0, infinity]"));
        }
        const _: () = assert!(engine::integrator::bdpt::Prediction::MAX_CANDIDATES == 4096, "the message below");
        if !(1..=engine::integrator::bdpt::Prediction::MAX_CANDIDATES).contains(&self.render.candidates) {
            return Err(range_err("render.candidates", self.render.candidates, "1 ..= 4096"));
        }
        const _: () = assert!(engine::integrator::bdpt::Prediction::MAX_EXTENSION_SAMPLES == 256, "the message below");
        if !(1..=engine::integrator::bdpt::Prediction::MAX_EXTENSION_SAMPLES).contains(&self.render.extension_samples) {
            return Err(range_err("render.extension_samples", self.render.extension_samples, "1 ..= 256"));
        }
        Ok(())
    }

    pub fn phase(&self) -> PhaseFunction {
        match self.medium.phase.as_str() {
            "isotropic" => PhaseFunction::Isotropic,
            "rayleigh" => PhaseFunction::Rayleigh,
            "hazy" => PhaseFunction::Hazy,
            "murky" => PhaseFunction::Murky,
            _ => PhaseFunction::HenyeyGreenstein { g: self.medium.g },
        }
    }

    pub fn build_grid(&self) -> Result<DensityGrid, SceneError> {
        self.validate()?;
        let g = &self.grid;
        if let Some(name) = &g.builtin {
            return Ok(Builtin::from_name(name).expect("validated").grid(g.resolution));
        }
        if let Some(file) = &g.file {
            let path = match &self.base_dir {
                Some(dir) => dir.join(file),
                None => std::path::PathBuf::from(file),
            };
            let imported = modeler::vdb::read_vdb(&path, g.grid_name.as_deref())
                .map_err(|e| SceneError::Invalid(format!("grid.file: {e}")))?;
            return Ok(imported.grid);
        }
        let params = match (&g.preset, &g.params) {
            (Some(name), _) => modeler::preset(name).expect("validated"),
            (None, Some(p)) => p.clone(),
            (None, None) => unreachable!("validated"),
        };
        modeler::build_grid(&params, g.resolution).map_err(|e| SceneError::Invalid(format!("grid: {e}")))
    }

    pub fn build_sun(&self) -> Result<Sun, SceneError> {
        Sun::new(
            Vec3::from_array(self.sun.direction),
            self.sun.radiance.to_vec3(),
            self.sun.angular_radius_deg.to_radians(),
        )
        .map_err(|e| SceneError::Invalid(format!("sun: {e}")))
    }

    pub fn build_camera(&self) -> Result<Camera, SceneError> {
        let c = &self.camera;
        let target = Vec3::from_array(c.target);
        let (position, up) = match (c.position, &c.preset) {
            (Some(p), _) => (Vec3::from_array(p), Vec3::from_array(c.up)),
            (None, preset) => {
                let preset = preset
                    .as_deref()
                    .map(|p| CameraPreset::from_name(p).expect("validated"))
                    .unwrap_or(CameraPreset::Toplit);
                let view = preset.view_direction(self.build_sun()?.direction());
                (target - view * c.distance, default_up(view))
            }
        };
        Camera::new(position, target, up, c.fov_y_deg, c.width, c.height)
            .map_err(|e| SceneError::Invalid(format!("camera: {e}")))
    }

    /// Makes the scene's relative cloud file and model absolute (against the scene
    /// file's folder), so they keep working once the scene lives elsewhere (in the
    /// window's memory, in a turntable's manifest).
    pub fn absolutize_paths(&mut self) {
        if let (Some(f), Some(dir)) = (&self.grid.file, &self.base_dir) {
            self.grid.file = Some(dir.join(f).display().to_string());
        }
        if let Some(m) = self.model_path() {
            self.render.model = Some(m.display().to_string());
        }
    }

    /// The engine's sky: the gradient from the horizon to the zenith and the ground
    /// lit by the sun and the sky (docs/conventions.md).
    pub fn build_sky(&self) -> Result<Sky, SceneError> {
        let zenith = self.sky.radiance.to_vec3();
        let horizon = self.sky.horizon.map_or(zenith, Rgb::to_vec3);
        let mut sky = Sky { zenith, horizon, ground: horizon };
        if let Some(albedo) = self.sky.ground_albedo {
            let sun = self.build_sun()?;
            let up = (-sun.direction().y).max(0.0);
            let irradiance = sun.radiance() * up + sky.upper_irradiance();
            sky.ground = irradiance * (albedo / std::f32::consts::PI);
        }
        Ok(sky)
    }

    /// The engine scene, with `grid` reused if given (so several renders of one cloud
    /// share it).
    pub fn build_scene(&self, grid: Option<Arc<DensityGrid>>) -> Result<Scene, SceneError> {
        self.validate()?;
        let grid = match grid {
            Some(g) => g,
            None => Arc::new(self.build_grid()?),
        };
        let medium = Medium::new(grid, self.medium.rho, self.medium.albedo, self.phase())
            .map_err(|e| SceneError::Invalid(format!("medium: {e}")))?;
        Ok(Scene { medium, sun: Some(self.build_sun()?), sky: self.build_sky()?, camera: self.build_camera()? })
    }

    /// `render.first_vertex` (the default where a file that skipped validation
    /// names none known).
    pub fn first_vertex(&self) -> FirstVertexChoice {
        FirstVertexChoice::parse(&self.render.first_vertex).unwrap_or(FirstVertexChoice::Guided)
    }

    pub fn settings(&self) -> RenderSettings {
        RenderSettings {
            seed: self.seed,
            k: self.k,
            max_order: self.max_order,
            mode: if self.render.mode == "predict" { Mode::Predict { p: self.render.p } } else { Mode::Reference },
            first_vertex: self.first_vertex().engine(),
        }
    }

    /// The integrator of the reference mode, or of prediction mode with a given
    /// predictor.
    pub fn integrator_with(&self, predictor: Option<Arc<dyn InScatterPredictor>>) -> Result<Integrator, SceneError> {
        let err = |e: engine::integrator::IntegratorError| SceneError::Invalid(format!("render: {e}"));
        let integrator = Integrator::new(self.settings(), predictor).map_err(err)?;
        if self.render.integrator == "bdpt" && self.render.mode == "reference" {
            return integrator.with_technique(engine::Technique::Bdpt(Default::default())).map_err(err);
        }
        Ok(integrator)
    }

    /// Where `render.model` points (resolved against the scene file), if set.
    pub fn model_path(&self) -> Option<PathBuf> {
        self.resolve(self.render.model.as_ref()?)
    }

    /// A path written in the scene file, relative to the file's folder.
    fn resolve(&self, m: &str) -> Option<PathBuf> {
        Some(match &self.base_dir {
            Some(dir) => dir.join(m),
            None => PathBuf::from(m),
        })
    }

    /// The shipped model `render.predictor` names, "auto" resolved for this scene's
    /// sky and sun ([`PredictorKind::resolve`]): never `Auto`.
    pub fn predictor_kind(&self) -> PredictorKind {
        let kind = PredictorKind::parse(&self.render.predictor).unwrap_or_default();
        let sky = self.build_sky().unwrap_or_else(|_| Sky::uniform(Vec3::ZERO));
        kind.resolve(&sky, self.build_sun().ok().as_ref())
    }

    /// The model of prediction mode: `render.model`, else the shipped one of
    /// `render.predictor`.
    pub fn load_model(&self) -> Result<PredictionModel, ModelError> {
        PredictionModel::load_or_shipped(self.model_path().as_deref(), self.predictor_kind())
    }

    /// The integrator for the built `scene`. In prediction mode the model is loaded
    /// and bound to the scene's cloud and sun (its depth field has at most
    /// `max_nodes` nodes per axis). A model that cannot be loaded does not stop the
    /// render: it falls back to path tracing and returns a warning naming the file
    /// and the problem.
    pub fn integrator(&self, scene: &Scene, max_nodes: u32) -> Result<IntegratorSetup, SceneError> {
        self.integrator_cached(scene, max_nodes, &mut PredictorCache::default(), Cancel::NEVER)
    }

    /// [`SceneFile::integrator`], reusing the bound model of `cache` when the cloud,
    /// rho, sun direction, model and field size are the same (camera, k, p, albedo or
    /// g changes then cost nothing), and leaving the new one there. The fields' builds
    /// stop when `cancel` asks ([`SceneError::Cancelled`]; nothing is cached then).
    pub fn integrator_cached(
        &self,
        scene: &Scene,
        max_nodes: u32,
        cache: &mut PredictorCache,
        cancel: Cancel,
    ) -> Result<IntegratorSetup, SceneError> {
        if self.render.mode == "preview" {
            return self.preview(scene, max_nodes, cache, cancel);
        }
        if self.render.mode != "predict" {
            return Ok(IntegratorSetup { integrator: self.integrator_with(None)?, warning: None });
        }
        if self.render.integrator == "bdpt" {
            return self.bdpt_prediction(scene, cache);
        }
        match self.bound_model(scene, max_nodes, None, cache, cancel)? {
            Ok(bound) => Ok(IntegratorSetup {
                integrator: self.prediction_integrator(scene, bound, cache, cancel)?,
                warning: None,
            }),
            Err(e) => {
                let mut reference = self.clone();
                reference.render.mode = "reference".into();
                Ok(IntegratorSetup {
                    integrator: reference.integrator_with(None)?,
                    warning: Some(format!("cannot use the model ({e}); rendering by path tracing instead")),
                })
            }
        }
    }

    /// The sun's transmittance over `scene`'s medium at most `nodes` per axis, from
    /// `cache` for the same cloud, rho and sun, else built (stopping when `cancel`
    /// asks) and left there. Two are kept: the window asks for two sizes per change
    /// (the first look's preview, the full one's).
    fn sun_field(
        &self,
        scene: &Scene,
        sun: &Sun,
        nodes: u32,
        cache: &mut PredictorCache,
        cancel: Cancel,
    ) -> Result<Arc<SunTransmittance>, SceneError> {
        let key = PredictorKey { model: None, other_lights: false, ..PredictorKey::new(self, scene, nodes) };
        if let Some((_, f)) = cache.sun.iter().find(|(k, _)| *k == key) {
            return Ok(f.clone());
        }
        let f =
            Arc::new(SunTransmittance::build_until(&scene.medium, sun, nodes, cancel).ok_or(SceneError::Cancelled)?);
        cache.sun.insert(0, (key, f.clone()));
        cache.sun.truncate(2);
        Ok(f)
    }

    /// Prediction mode's integrator for the model `bound` to `scene`: at k = 1, unless
    /// `render.prediction_lattice` is 0, the model read from a lattice of its answers
    /// toward the camera ([`CameraLatticePredictor`]), and under `render.first_vertex =
    /// "guided"` the first vertex guided by the sun's transmittance (from `cache` as
    /// the preview's field, [`SceneFile::sun_field`]).
    pub fn prediction_integrator(
        &self,
        scene: &Scene,
        bound: Arc<dyn InScatterPredictor>,
        cache: &mut PredictorCache,
        cancel: Cancel,
    ) -> Result<Integrator, SceneError> {
        let first = self.k == 1;
        let nodes = self.render.prediction_lattice;
        let lattice = (first && nodes > 0)
            .then(|| CameraLatticePredictor::new(scene, bound.clone(), scene.camera.position(), nodes))
            .flatten();
        let predictor: Arc<dyn InScatterPredictor> = match lattice {
            Some(lattice) => Arc::new(lattice),
            None => bound,
        };
        let integrator = self.integrator_with(Some(predictor))?;
        match scene.sun.as_ref() {
            Some(sun) if first && self.first_vertex() == FirstVertexChoice::Guided => {
                let field = self.sun_field(scene, sun, SunTransmittance::DEFAULT_MAX_NODES, cache, cancel)?;
                Ok(integrator.with_first_vertex_guide(field))
            }
            _ => Ok(integrator),
        }
    }

    /// The model of prediction at bounce k bound to `scene`'s cloud and sun (fields of
    /// at most `max_nodes` per axis), from `cache` when it holds this binding, else
    /// loaded, bound and left there; the inner error is a model that cannot be loaded.
    /// With `shared_sun` (the preview's sun field) a cloud-aware model reads that field
    /// instead of building its own ([`PredictionModel::bind_scene_with_sun`]), a
    /// binding cached apart from prediction mode's and keyed on that very field.
    fn bound_model(
        &self,
        scene: &Scene,
        max_nodes: u32,
        shared_sun: Option<&Arc<SunTransmittance>>,
        cache: &mut PredictorCache,
        cancel: Cancel,
    ) -> Result<Result<Arc<dyn InScatterPredictor>, ModelError>, SceneError> {
        if scene.sun.is_none() {
            return Err(SceneError::Invalid("prediction needs a sun".into()));
        }
        // Only the cloud-aware model reads a sun field; the global model's binding is
        // the same either way, and prediction mode's is reused.
        let shared_sun = shared_sun.filter(|_| self.predictor_kind() == PredictorKind::Cloud);
        let key = PredictorKey {
            shared_sun: shared_sun.map_or(0, |f| Arc::as_ptr(f) as usize),
            ..PredictorKey::new(self, scene, max_nodes)
        };
        if let Some(i) = cache.bound.iter().position(|(k, _)| *k == key) {
            // Most recently used first.
            let hit = cache.bound.remove(i);
            let bound = hit.1.clone();
            cache.bound.insert(0, hit);
            return Ok(Ok(bound));
        }
        let model = match self.load_model() {
            Ok(m) => m,
            Err(e) => return Ok(Err(e)),
        };
        // With a sun (checked above) None is a cancelled build.
        let bound = match shared_sun {
            Some(field) => model.bind_scene_with_sun(scene, field, max_nodes, cancel),
            None => model.bind_scene(scene, max_nodes, cancel),
        };
        let bound = bound.ok_or(SceneError::Cancelled)?;
        cache.bound.insert(0, (key, bound.clone()));
        cache.bound.truncate(PredictorCache::BINDINGS);
        Ok(Ok(bound))
    }
}

impl SceneFile {
    /// The octave approximation of `render.octaves` and its factors.
    pub fn octaves(&self) -> MultipleScattering {
        let r = &self.render;
        MultipleScattering::Octaves { octaves: r.octaves, a: r.octave_a, b: r.octave_b, c: r.octave_c }
    }

    /// The instant preview of `scene`: the sun's transmittance (reused from `cache`
    /// for the same cloud, rho and sun) and the higher orders by `render.preview`; the
    /// learned ones use the model of prediction mode bound with fields of at most
    /// `max_nodes` nodes per axis (cached as in prediction mode) on a lattice of
    /// `render.preview_nodes` (the default lattice when unset). A model that cannot be loaded falls back to the octave
    /// approximation, with a warning.
    fn preview(
        &self,
        scene: &Scene,
        max_nodes: u32,
        cache: &mut PredictorCache,
        cancel: Cancel,
    ) -> Result<IntegratorSetup, SceneError> {
        let err = |e: String| SceneError::Invalid(format!("render: {e}"));
        let sun = scene.sun.as_ref().ok_or_else(|| SceneError::Invalid("the preview needs a sun".into()))?;
        // The sun's field: 4 nodes per depth-field node per axis (256 at the default
        // 64, the field's own default; 96 for the window's coarse 24).
        let sun_nodes = (4 * max_nodes).clamp(2, SunTransmittance::DEFAULT_MAX_NODES);
        let field = self.sun_field(scene, sun, sun_nodes, cache, cancel)?;
        let mut warning = None;
        let multiple = if self.render.preview == "octaves" {
            self.octaves()
        } else {
            match self.bound_model(scene, max_nodes, Some(&field), cache, cancel)? {
                Ok(predictor) => MultipleScattering::Lattice(Arc::new(Preview::learned_lattice(
                    scene,
                    &field,
                    predictor,
                    scene.camera.position(),
                    self.render.preview_nodes,
                ))),
                Err(e) => {
                    warning = Some(format!("cannot use the model ({e}); the preview uses the octave approximation"));
                    self.octaves()
                }
            }
        };
        let preview = Preview::new(field, multiple, Preview::default_step(&scene.medium)).map_err(err)?;
        let integrator = Integrator::preview(self.settings(), Arc::new(preview)).map_err(|e| err(e.to_string()))?;
        Ok(IntegratorSetup { integrator, warning })
    }

    /// Where `render.p2p_model` points (resolved against the scene file), if set.
    pub fn p2p_model_path(&self) -> Option<PathBuf> {
        self.resolve(self.render.p2p_model.as_ref()?)
    }

    /// The point-to-point model: `render.p2p_model`, else the shipped one.
    pub fn load_p2p_model(&self) -> Result<Arc<P2pModel>, String> {
        match self.p2p_model_path() {
            Some(path) => P2pModel::load(&path).map(Arc::new),
            None => P2pModel::shipped(),
        }
    }

    /// BDPT with the point-to-point model between its subpaths; the model bound to
    /// the cloud (its density pyramid) is reused from `cache` while the cloud, rho
    /// and model stay the same. A model that cannot be loaded falls back to BDPT
    /// without prediction, with a warning.
    fn bdpt_prediction(&self, scene: &Scene, cache: &mut PredictorCache) -> Result<IntegratorSetup, SceneError> {
        let err = |e: engine::integrator::IntegratorError| SceneError::Invalid(format!("render: {e}"));
        if scene.sun.is_none() {
            return Err(SceneError::Invalid("prediction mode needs a sun".into()));
        }
        let key = PredictorKey::p2p(self, scene);
        let bound = match &cache.p2p {
            Some((k, bound)) if *k == key => bound.clone(),
            _ => match self.load_p2p_model() {
                Ok(model) => {
                    let bound = Arc::new(BoundP2pModel::new(model, &scene.medium));
                    cache.p2p = Some((key, bound.clone()));
                    bound
                }
                Err(e) => {
                    let mut reference = self.clone();
                    reference.render.mode = "reference".into();
                    return Ok(IntegratorSetup {
                        integrator: reference.integrator_with(None)?,
                        warning: Some(format!(
                            "cannot use the point-to-point model ({e}); rendering by BDPT without prediction instead"
                        )),
                    });
                }
            },
        };
        let warning = bound.mismatch(&scene.medium);
        let integrator = Integrator::bdpt_prediction(self.settings(), Default::default(), bound, self.render.r)
            .and_then(|i| i.with_light_candidates(self.render.candidates))
            .and_then(|i| i.with_extension_samples(self.render.extension_samples))
            .map_err(err)?;
        Ok(IntegratorSetup { integrator, warning })
    }
}

/// What a bound model depends on (the grid by identity: a cached grid is shared).
#[derive(Clone, Debug, PartialEq)]
struct PredictorKey {
    grid: usize,
    rho: u32,
    sun: [u32; 3],
    model: Option<PathBuf>,
    predictor: &'static str,
    nodes: u32,
    /// Whether the binding answers other lights too (a sky, a soft sun).
    other_lights: bool,
    /// The address of the preview's sun field that a cloud-model binding reads
    /// instead of its own (0: its own). The binding holds the field, so the address
    /// cannot be reused by another field while the key is cached; a binding always
    /// reads the very field its preview holds, which counts it once.
    shared_sun: usize,
}

/// The models bound last (see [`SceneFile::integrator_cached`]). Holding them keeps their
/// grids alive, so a grid's address cannot be reused by another cloud meanwhile.
#[derive(Default)]
pub struct PredictorCache {
    /// The models bound last, most recent first (at most [`PredictorCache::BINDINGS`]):
    /// the window binds one model at several field sizes per change (a coarse first
    /// look, the render's coarse start, its full field), and each must stay cached for
    /// the next camera change.
    bound: Vec<(PredictorKey, Arc<dyn InScatterPredictor>)>,
    p2p: Option<(PredictorKey, Arc<BoundP2pModel>)>,
    /// The preview's sun transmittance (keyed by cloud, rho and sun; no model).
    sun: Vec<(PredictorKey, Arc<SunTransmittance>)>,
}

impl PredictorCache {
    /// Bindings kept.
    pub const BINDINGS: usize = 3;
}

impl PredictorKey {
    /// A point-to-point model depends on the cloud, rho and the model file only.
    fn p2p(file: &SceneFile, scene: &Scene) -> Self {
        PredictorKey {
            sun: [0; 3],
            nodes: 0,
            model: file.p2p_model_path(),
            other_lights: false,
            ..PredictorKey::new(file, scene, 0)
        }
    }

    fn new(file: &SceneFile, scene: &Scene, nodes: u32) -> Self {
        PredictorKey {
            grid: Arc::as_ptr(scene.medium.grid()) as usize,
            rho: scene.medium.rho().to_bits(),
            sun: scene.sun.map(|s| s.direction().to_array().map(f32::to_bits)).unwrap_or_default(),
            model: file.model_path(),
            predictor: file.predictor_kind().name(),
            nodes,
            other_lights: models::prediction::needs_other_lights(scene),
            shared_sun: 0,
        }
    }
}

impl PredictorCache {
    /// Whether the cache holds the model of `file` bound for `scene` with `max_nodes`.
    pub fn has(&self, file: &SceneFile, scene: &Scene, max_nodes: u32) -> bool {
        let key = PredictorKey::new(file, scene, max_nodes);
        self.bound.iter().any(|(k, _)| *k == key)
    }
}

/// An integrator and, if prediction mode fell back to path tracing, why.
#[derive(Clone, Debug)]
pub struct IntegratorSetup {
    pub integrator: Integrator,
    pub warning: Option<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = "[grid]\nbuiltin = \"cumulus\"\nresolution = 16\n";

    /// `render.predictor` picks the shipped model of prediction at bounce k: by
    /// default ("auto", not written back) the cloud-aware one under a sun alone and the
    /// global one under a sky or a soft sun, whose light the cloud-aware model does not
    /// answer; either by name; both predict multiple scattering only; a model file of
    /// either kind is taken by its sidecar; an unknown name is refused.
    #[test]
    fn the_predictor_key_picks_the_shipped_model() {
        let text = format!("{MINIMAL}[render]\nmode = \"predict\"\n");
        let s = SceneFile::from_toml_str(&text, "t").unwrap();
        assert_eq!(s.render.predictor, "auto");
        assert!(!s.to_toml().contains("predictor"));
        let name = |f: &SceneFile| {
            let scene = f.build_scene(None).unwrap();
            let setup = f.integrator(&scene, 16).unwrap();
            assert!(setup.warning.is_none(), "{:?}", setup.warning);
            let p = setup.integrator.predictor().expect("a predictor");
            assert!(!p.predicts_single_scattering());
            p.name().to_string()
        };
        assert!(name(&s).contains("cloud-aware"), "{}", name(&s));
        let mut sky = s.clone();
        sky.sky.radiance = Rgb::Grey(0.1);
        assert_eq!(sky.predictor_kind(), PredictorKind::Global);
        assert!(name(&sky).contains("global"), "{}", name(&sky));
        let mut soft = s.clone();
        soft.sun.angular_radius_deg = 5.0;
        assert_eq!(soft.predictor_kind(), PredictorKind::Global);
        let mut global = s.clone();
        global.render.predictor = "global".into();
        global.validate().unwrap();
        assert!(name(&global).contains("global"), "{}", name(&global));
        assert!(global.to_toml().contains("predictor = \"global\""));
        let mut cloud = sky.clone();
        cloud.render.predictor = "cloud".into();
        assert_eq!(cloud.predictor_kind(), PredictorKind::Cloud);
        assert!(name(&cloud).contains("cloud-aware"), "{}", name(&cloud));
        // The model file names its kind, whatever render.predictor says.
        let mut file = global.clone();
        file.render.model =
            Some(concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/models/cloud.safetensors").to_string());
        assert!(name(&file).contains("cloud-aware"), "{}", name(&file));
        let mut bad = s.clone();
        bad.render.predictor = "deep".into();
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("render.predictor") && e.contains("cloud"), "{e}");
    }

    /// Prediction at k = 1 reads the cloud-aware model from a lattice toward the camera
    /// (render.prediction_lattice, written back only when not the default); at other k,
    /// with 0, and for the global model, which answers any light direction, it asks
    /// the model; a lattice of 1 node or more than 256 is refused. Its vertex is
    /// guided by the sun's transmittance unless render.first_vertex says otherwise.
    #[test]
    fn prediction_at_the_first_vertex_reads_a_lattice() {
        let text = format!("k = 1\n{MINIMAL}[render]\nmode = \"predict\"\npredictor = \"cloud\"\n");
        let s = SceneFile::from_toml_str(&text, "t").unwrap();
        assert_eq!(s.render.prediction_lattice, DEFAULT_PREDICTION_LATTICE);
        assert!(!s.to_toml().contains("prediction_lattice"));
        let name = |f: &SceneFile| {
            let scene = f.build_scene(None).unwrap();
            f.integrator(&scene, 16).unwrap().integrator.predictor().expect("a predictor").name().to_string()
        };
        assert!(name(&s).contains("camera lattice"), "{}", name(&s));
        let mut k2 = s.clone();
        k2.k = 2;
        assert!(!name(&k2).contains("camera lattice"), "{}", name(&k2));
        let mut off = s.clone();
        off.render.prediction_lattice = 0;
        off.validate().unwrap();
        assert!(off.to_toml().contains("prediction_lattice = 0"));
        assert!(!name(&off).contains("camera lattice"), "{}", name(&off));
        let mut global = s.clone();
        global.render.predictor = "global".into();
        assert!(!name(&global).contains("camera lattice"), "{}", name(&global));
        for bad in [1, 257] {
            let mut f = s.clone();
            f.render.prediction_lattice = bad;
            let e = f.validate().unwrap_err().to_string();
            assert!(e.contains("render.prediction_lattice"), "{e}");
        }
        // The first vertex: guided by the sun's transmittance by default, by weight
        // alone, or by free flight; another word is refused.
        let setup = |f: &SceneFile| f.integrator(&f.build_scene(None).unwrap(), 16).unwrap().integrator;
        assert_eq!(s.render.first_vertex, "guided");
        assert!(!s.to_toml().contains("first_vertex"));
        assert!(setup(&s).first_vertex_guide().is_some());
        assert_eq!(setup(&s).settings().first_vertex, engine::FirstVertex::Weighted);
        // Another p (the automatic p's pilots and render) keeps the guide and the
        // lattice; a p outside (0, 1] is refused.
        let guided = setup(&s);
        let other = RenderSettings { mode: Mode::Predict { p: 0.3 }, ..*guided.settings() };
        let again = guided.with_settings(other).unwrap();
        assert!(again.first_vertex_guide().is_some());
        assert!(again.predictor().unwrap().name().contains("camera lattice"));
        assert!(guided.with_settings(RenderSettings { mode: Mode::Predict { p: 0.0 }, ..other }).is_err());
        assert!(setup(&k2).first_vertex_guide().is_none());
        let mut weighted = s.clone();
        weighted.render.first_vertex = "weighted".into();
        assert!(setup(&weighted).first_vertex_guide().is_none());
        assert_eq!(setup(&weighted).settings().first_vertex, engine::FirstVertex::Weighted);
        let mut free = s.clone();
        free.render.first_vertex = "free-flight".into();
        assert!(free.to_toml().contains("first_vertex = \"free-flight\""));
        assert_eq!(setup(&free).settings().first_vertex, engine::FirstVertex::FreeFlight);
        free.render.first_vertex = "first".into();
        let e = free.validate().unwrap_err().to_string();
        assert!(e.contains("render.first_vertex"), "{e}");
        for c in FirstVertexChoice::ALL {
            assert_eq!(FirstVertexChoice::parse(c.name()), Some(c));
        }
    }

    /// BDPT prediction loads the shipped point-to-point model without any file, splits
    /// the buffers at 2k + 1, warns about a medium the model was not trained for,
    /// falls back with a warning naming a missing model file, and rejects a bad r.
    #[test]
    fn bdpt_prediction_uses_the_shipped_p2p_model() {
        let text = format!(
            "k = 2\n{MINIMAL}[medium]\nrho = 25.0\nalbedo = 0.99\nphase = \"isotropic\"\n\
             [render]\nmode = \"predict\"\nintegrator = \"bdpt\"\n"
        );
        let s = SceneFile::from_toml_str(&text, "t").unwrap();
        s.validate().unwrap();
        let scene = s.build_scene(None).unwrap();
        let setup = s.integrator(&scene, 16).unwrap();
        assert!(setup.warning.is_none(), "{:?}", setup.warning);
        let pr = setup.integrator.transport_prediction().expect("BDPT prediction");
        assert_eq!(
            (pr.segments, pr.first_predicted_order(), pr.candidates),
            (2, 5, engine::integrator::bdpt::Prediction::DEFAULT_CANDIDATES)
        );
        assert!(pr.predictor.name().contains("point-to-point"), "{}", pr.predictor.name());
        let mut many = s.clone();
        many.render.candidates = 3;
        let setup = many.integrator(&scene, 16).unwrap();
        assert_eq!(setup.integrator.transport_prediction().unwrap().candidates, 3);
        let mut other = s.clone();
        other.medium.albedo = 0.8;
        let warn = other.integrator(&other.build_scene(None).unwrap(), 16).unwrap().warning.unwrap();
        assert!(warn.contains("albedo 0.99") && warn.contains("extrapolation"), "{warn}");
        let mut missing = s.clone();
        missing.render.p2p_model = Some("/nonexistent/p2p-model.safetensors".into());
        let setup = missing.integrator(&scene, 16).unwrap();
        assert!(setup.integrator.transport_prediction().is_none());
        let warn = setup.warning.unwrap();
        assert!(warn.contains("p2p-model.json") || warn.contains("p2p-model.safetensors"), "{warn}");
        // The shipped (compiled-in) model is the MLP; the thesis's residual network
        // beside it loads from its file.
        let shipped = s.integrator(&scene, 16).unwrap();
        assert!(shipped.integrator.transport_prediction().unwrap().predictor.name().contains("MLP"));
        let mut residual = s.clone();
        residual.render.p2p_model =
            Some(concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/models/p2p_residual.safetensors").to_string());
        let setup = residual.integrator(&scene, 16).unwrap();
        assert!(setup.warning.is_none(), "{:?}", setup.warning);
        assert!(setup.integrator.transport_prediction().unwrap().predictor.name().contains("residual"));
        let mut bad = s.clone();
        bad.render.r = -1.0;
        assert!(bad.validate().unwrap_err().to_string().contains("render.r"));
        bad.render.r = 0.08;
        bad.render.candidates = 0;
        assert!(bad.validate().unwrap_err().to_string().contains("render.candidates"));
        bad.render.candidates = 16;
        bad.render.extension_samples = 0;
        assert!(bad.validate().unwrap_err().to_string().contains("render.extension_samples"));
        // The extension samples reach the integrator.
        let mut more = s.clone();
        more.render.extension_samples = 9;
        let setup = more.integrator(&scene, 16).unwrap();
        assert_eq!(setup.integrator.transport_prediction().unwrap().extension_samples, 9);
    }

    #[test]
    fn minimal_scene_has_defaults() {
        let s = SceneFile::from_toml_str(MINIMAL, "t").unwrap();
        s.validate().unwrap();
        assert_eq!(s.medium, MediumDesc::default());
        let scene = s.build_scene(None).unwrap();
        // Toplit default: camera looks perpendicular to the sun.
        assert!(scene.camera.forward().dot(scene.sun.unwrap().direction()).abs() < 1e-6);
        // Round trip through TOML.
        assert_eq!(SceneFile::from_toml_str(&s.to_toml(), "t").unwrap(), s);
    }

    #[test]
    fn unknown_keys_are_named() {
        let e = SceneFile::from_toml_str(&format!("{MINIMAL}[medium]\nrho = 3\nalbedoo = 1\n"), "s.toml").unwrap_err();
        assert!(e.to_string().contains("albedoo"), "{e}");
        let e = SceneFile::from_toml_str(&format!("colour = 1\n{MINIMAL}"), "s.toml").unwrap_err();
        assert!(e.to_string().contains("colour"), "{e}");
    }

    #[test]
    fn out_of_range_values_name_key_and_range() {
        let cases = [
            ("[medium]\nalbedo = 1.5\n", "medium.albedo = 1.5 is out of range: 0 ..= 1"),
            ("[medium]\nrho = -2\n", "medium.rho = -2 is out of range: 0 ..= 10000"),
            ("[camera]\nfov_y_deg = 0\n", "camera.fov_y_deg = 0 is out of range: 1 ..= 170"),
            ("[render]\np = 0\n", "render.p = 0 is out of range: (0, 1]"),
            ("[render]\npreview_nodes = 1\n", "render.preview_nodes = 1 is out of range: 2 ..= 256"),
            ("[render]\npreview_nodes = 257\n", "render.preview_nodes = 257 is out of range: 2 ..= 256"),
        ];
        for (extra, msg) in cases {
            let s = SceneFile::from_toml_str(&format!("{MINIMAL}{extra}"), "t");
            let e = s.and_then(|s| s.validate()).unwrap_err();
            assert_eq!(e.to_string(), msg);
        }
        // The preview's lattice: unset (the default lattice) unless a count is given,
        // and written back only when given.
        let unset = SceneFile::from_toml_str(MINIMAL, "t").unwrap();
        assert_eq!(unset.render.preview_nodes, None);
        assert!(!unset.to_toml().contains("preview_nodes"));
        let set = SceneFile::from_toml_str(&format!("{MINIMAL}[render]\npreview_nodes = 200\n"), "t").unwrap();
        set.validate().unwrap();
        assert_eq!(set.render.preview_nodes, Some(200));
        assert!(set.to_toml().contains("preview_nodes = 200"));
        let s = SceneFile::from_toml_str("k = 0\n[grid]\nbuiltin = \"cumulus\"\n", "t").unwrap();
        assert_eq!(s.validate().unwrap_err().to_string(), "k = 0 is out of range: 1 ..= 64");
        let s = SceneFile::from_toml_str("[grid]\nbuiltin = \"cirrus\"\n", "t").unwrap();
        assert!(s.validate().unwrap_err().to_string().contains("cirrus"));
        let s = SceneFile::from_toml_str("[grid]\npreset = \"scene-z\"\n", "t").unwrap();
        assert!(s.validate().unwrap_err().to_string().contains("scene-z"));
        let s = SceneFile::from_toml_str("[grid]\npreset = \"scene-a\"\nbuiltin = \"sphere\"\n", "t").unwrap();
        assert!(s.validate().unwrap_err().to_string().contains("exactly one source"));
        let s = SceneFile::from_toml_str("[grid.params]\noctaves = 20\n", "t").unwrap();
        assert_eq!(s.validate().unwrap_err().to_string(), "grid.params.octaves = 20 is out of range: 1 ..= 8");
        let e = SceneFile::from_toml_str("[grid.params]\noctavez = 2\n", "t").unwrap_err();
        assert!(e.to_string().contains("octavez"));
    }

    #[test]
    fn presets_follow_the_light() {
        let omega = Vec3::new(0.3, -0.9, 0.1).normalize();
        assert!(CameraPreset::Toplit.view_direction(omega).dot(omega).abs() < 1e-6);
        assert_eq!(CameraPreset::Backlit.view_direction(omega), -omega);
        assert_eq!(CameraPreset::Frontlit.view_direction(omega), omega);
        // Backlit with the sun straight down looks straight up: a valid camera.
        let s = SceneFile::from_toml_str(&format!("{MINIMAL}[camera]\npreset = \"backlit\"\n"), "t").unwrap();
        let cam = s.build_camera().unwrap();
        assert!((cam.forward() - Vec3::Y).length() < 1e-6);
    }

    #[test]
    fn predict_mode_loads_the_shipped_model() {
        let s = SceneFile::from_toml_str(&format!("{MINIMAL}[render]\nmode = \"predict\"\n"), "t").unwrap();
        let scene = s.build_scene(None).unwrap();
        let setup = s.integrator(&scene, 8).unwrap();
        assert!(setup.warning.is_none(), "{:?}", setup.warning);
        assert!(matches!(setup.integrator.settings().mode, Mode::Predict { .. }));
        // Without a predictor the engine refuses prediction mode, naming what is missing.
        let e = s.integrator_with(None).unwrap_err().to_string();
        assert!(e.contains("needs a predictor"), "{e}");
    }

    #[test]
    fn missing_or_corrupt_model_falls_back_to_path_tracing() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().to_path_buf();
        std::fs::write(dir.join("broken.safetensors"), b"not a model").unwrap();
        std::fs::copy(concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/models/global.json"), dir.join("broken.json"))
            .unwrap();
        for (file, why) in [("nowhere.safetensors", "nowhere.json"), ("broken.safetensors", "safetensors")] {
            let text = format!("{MINIMAL}[render]\nmode = \"predict\"\nmodel = \"{file}\"\n");
            let mut s = SceneFile::from_toml_str(&text, "t").unwrap();
            s.base_dir = Some(dir.clone());
            let scene = s.build_scene(None).unwrap();
            let setup = s.integrator(&scene, 8).unwrap();
            let w = setup.warning.expect("a warning");
            assert!(w.contains(why) && w.contains("path tracing"), "{w}");
            assert_eq!(setup.integrator.settings().mode, Mode::Reference);
        }
    }
}
