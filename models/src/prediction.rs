//! The models that answer prediction at bounce k, behind one type: the cloud-aware
//! model (the default under a sun alone) and the thesis's global model (the default
//! under a sky or a soft sun, which it answers and the cloud-aware model does not). A
//! model file says which it is
//! (its sidecar's `format`); binding one to a cloud and a sun gives the engine's
//! [`InScatterPredictor`].

use crate::cloud::{BoundCloudModel, CloudModel};
use crate::global::model::ModelError;
use crate::global::{BoundGlobalModel, GlobalModel};
use engine::field::SunTransmittance;
use engine::{Cancel, InScatterPredictor, Medium, Scene, Sky, Sun};
use std::path::Path;
use std::sync::Arc;

/// Which shipped model: `render.predictor` in scene files, `--predictor` on the
/// command line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PredictorKind {
    /// The cloud-aware model where it answers every light of the scene (a sun alone,
    /// no softer than the global model's sun field), else the global model
    /// ([`PredictorKind::resolve`]); the default.
    #[default]
    Auto,
    /// The cloud-aware model ([`crate::cloud`]): bound to one sun direction, it leaves
    /// a sky's orders >= k out.
    Cloud,
    /// The thesis's global model ([`crate::global`]).
    Global,
}

impl PredictorKind {
    pub const NAMES: &'static str = "auto, cloud, global";

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "auto" => Some(PredictorKind::Auto),
            "cloud" => Some(PredictorKind::Cloud),
            "global" => Some(PredictorKind::Global),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            PredictorKind::Auto => "auto",
            PredictorKind::Cloud => "cloud",
            PredictorKind::Global => "global",
        }
    }

    /// The model for a scene lit by `sky` and `sun`: `Auto` becomes the cloud-aware
    /// model unless prediction there needs other light directions
    /// ([`needs_other_lights_of`]), which only the global model answers; the others
    /// stay as they are.
    pub fn resolve(self, sky: &Sky, sun: Option<&Sun>) -> PredictorKind {
        match self {
            PredictorKind::Auto if needs_other_lights_of(sky, sun) => PredictorKind::Global,
            PredictorKind::Auto => PredictorKind::Cloud,
            k => k,
        }
    }
}

/// A loaded model of prediction at bounce k.
#[derive(Clone, Debug)]
pub enum PredictionModel {
    Cloud(Arc<CloudModel>),
    Global(Arc<GlobalModel>),
}

impl PredictionModel {
    /// The model compiled into Nimbus (`Auto` unresolved: the cloud-aware one).
    pub fn shipped(kind: PredictorKind) -> Result<Self, ModelError> {
        Ok(match kind {
            PredictorKind::Auto | PredictorKind::Cloud => PredictionModel::Cloud(CloudModel::shipped()?),
            PredictorKind::Global => PredictionModel::Global(GlobalModel::shipped()?),
        })
    }

    /// A model file (.safetensors with its .json sidecar), of either kind.
    pub fn load(path: &Path) -> Result<Self, ModelError> {
        #[derive(serde::Deserialize)]
        struct Tag {
            format: String,
        }
        let (bytes, text) = crate::global::model::read_model_files(path)?;
        let format = serde_json::from_str::<Tag>(&text).map(|t| t.format).unwrap_or_default();
        Ok(if format == crate::cloud::model::MODEL_FORMAT {
            PredictionModel::Cloud(Arc::new(CloudModel::from_bytes(&bytes, &text, path)?))
        } else {
            PredictionModel::Global(Arc::new(GlobalModel::from_bytes(&bytes, &text, path)?))
        })
    }

    /// `path` if given, else the shipped model of `kind`.
    pub fn load_or_shipped(path: Option<&Path>, kind: PredictorKind) -> Result<Self, ModelError> {
        match path {
            Some(p) => Self::load(p),
            None => Self::shipped(kind),
        }
    }

    /// Binds the model to `medium` and `sun`: the fields its features read. The
    /// global model's depth field gets at most `max_nodes` nodes per axis (64 values a
    /// node); the cloud model's sun field, one value a node, twice as many (at most 256).
    /// None when `cancel` asks to stop before the fields are built.
    pub fn bind(
        &self,
        medium: &Medium,
        sun: &Sun,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<Arc<dyn InScatterPredictor>> {
        Some(match self {
            PredictionModel::Cloud(m) => {
                Arc::new(BoundCloudModel::new_until(m.clone(), medium, sun, cloud_sun_nodes(max_nodes), cancel)?)
            }
            PredictionModel::Global(m) => {
                Arc::new(BoundGlobalModel::new_until(m.clone(), medium, sun, max_nodes, cancel)?)
            }
        })
    }

    /// Binds the model to `scene`'s cloud and sun as [`PredictionModel::bind`] does,
    /// and, when the scene has a sky or a soft sun ([`needs_other_lights`]), the global
    /// model also to every light direction ([`crate::global::SkyDepthField`] at half
    /// the nodes per axis), so that the integrator can predict the sky's high orders
    /// and sample the sun's disk. The cloud model answers its sun only.
    /// None for a scene without a sun (prediction has nothing to answer for), or when
    /// `cancel` asks to stop.
    pub fn bind_scene(&self, scene: &Scene, max_nodes: u32, cancel: Cancel) -> Option<Arc<dyn InScatterPredictor>> {
        let sun = scene.sun.as_ref()?;
        Some(match self {
            PredictionModel::Global(m) if needs_other_lights(scene) => Arc::new(
                BoundGlobalModel::new_until(m.clone(), &scene.medium, sun, max_nodes, cancel)?
                    .with_other_lights_until(
                        &scene.medium,
                        crate::global::sky_field::DEFAULT_TEXELS,
                        (max_nodes / 2).max(2),
                        cancel,
                    )?,
            ),
            _ => self.bind(&scene.medium, sun, max_nodes, cancel)?,
        })
    }

    /// [`PredictionModel::bind_scene`] for the preview, which holds `sun_field`, the
    /// sun's transmittance over this scene's cloud (at least as fine as the cloud
    /// model's own field would be): the cloud model reads it instead of a field of its
    /// own, so the preview keeps one sun field, not two. The global model's fields are
    /// of another kind and built as by `bind_scene`.
    pub fn bind_scene_with_sun(
        &self,
        scene: &Scene,
        sun_field: &Arc<SunTransmittance>,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<Arc<dyn InScatterPredictor>> {
        let sun = scene.sun.as_ref()?;
        match self {
            PredictionModel::Cloud(m) => Some(Arc::new(BoundCloudModel::with_sun_field_until(
                m.clone(),
                &scene.medium,
                sun,
                sun_field.clone(),
                cloud_sun_nodes(max_nodes),
                cancel,
            )?)),
            PredictionModel::Global(_) => self.bind_scene(scene, max_nodes, cancel),
        }
    }
}

/// The cloud-aware model's sun-field nodes per axis for a binding of `max_nodes`: one
/// value a node where the global model's depth field has 64, so twice as many, at
/// most 256.
fn cloud_sun_nodes(max_nodes: u32) -> u32 {
    (2 * max_nodes).clamp(2, 256)
}

/// Whether prediction in `scene` asks about lights other than the sun's centre: a sky,
/// or a sun softer than [`crate::global::model::SUN_FIELD_ANGLE`].
pub fn needs_other_lights(scene: &Scene) -> bool {
    needs_other_lights_of(&scene.sky, scene.sun.as_ref())
}

/// [`needs_other_lights`] for a scene lit by `sky` and `sun`.
pub fn needs_other_lights_of(sky: &Sky, sun: Option<&Sun>) -> bool {
    !sky.is_black() || sun.is_some_and(|s| s.angular_radius() > crate::global::model::SUN_FIELD_ANGLE)
}

/// The fingerprint of the shipped model of `kind` (render caches key on it).
pub fn shipped_fingerprint(kind: PredictorKind) -> u64 {
    match kind {
        PredictorKind::Auto | PredictorKind::Cloud => crate::cloud::model::shipped_fingerprint(),
        PredictorKind::Global => crate::global::model::shipped_fingerprint(),
    }
}
