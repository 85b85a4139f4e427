//! The integrator: which light transport algorithm renders a sample, and how the
//! high orders are made (path traced, or predicted at bounce k).
//!
//! - [`path`]: unidirectional path tracing with next event estimation, and prediction
//!   at bounce k through an [`InScatterPredictor`] (thesis section 5.4);
//! - [`bdpt`]: volumetric bidirectional path tracing, and its prediction mode through
//!   a [`TransportPredictor`] between the two subpaths (thesis section 6.4);
//! - [`p2p`]: the point-to-point transport estimator (thesis eqs. 6.1-6.2), BDPT's
//!   extension of close pairs and the models' ground truth;
//! - [`preview`]: the instant preview, ray marching with a precomputed sun
//!   transmittance and multiple scattering from a lattice or the octave approximation;
//! - [`base`]: render settings, the order-split [`PathSample`], Russian roulette.
//!
//! Every sample's contribution is split by scattering order into the buffers of
//! docs/conventions.md: order 0 (the sky seen through the medium) -> `direct`,
//! orders 1 .. k-1 -> `low`, orders >= k -> `high` (k = 2k' + 1 in BDPT's prediction
//! mode with k' segments per subpath).

pub mod base;
pub mod bdpt;
pub mod p2p;
pub mod path;
pub mod preview;

pub use base::{FirstVertex, MisHeuristic, Mode, PathSample, RenderSettings};

use crate::predictor::{InScatterPredictor, TransportPredictor};
use crate::rng::Rng;
use crate::scene::Scene;
use glam::Vec3;
use std::sync::Arc;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IntegratorError {
    #[error("k must be at least 1, got {0}")]
    BadK(u32),
    #[error("prediction probability p must lie in (0, 1], got {0}")]
    BadP(f32),
    #[error("prediction mode needs a predictor (a trained model), and none is loaded")]
    NoPredictor,
    #[error("prediction mode needs a sun: the model predicts light from a directional light")]
    NoSun,
    #[error(
        "prediction with BDPT needs a point-to-point transport model (a trained `nimbus train p2p` model); \
         the path tracer's prediction needs the global model"
    )]
    BdptPredict,
    #[error("{0}")]
    BadBdpt(String),
    #[error("the preview technique needs its fields (Integrator::preview)")]
    NoPreview,
}

/// The light transport algorithm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Technique {
    /// Unidirectional path tracing with next event estimation ([`path`]).
    PathTracing,
    /// Volumetric bidirectional path tracing ([`bdpt`]).
    Bdpt(bdpt::BdptSettings),
    /// The instant preview: ray marching with precomputed fields ([`preview`]).
    Preview,
}

#[derive(Clone)]
pub struct Integrator {
    settings: RenderSettings,
    predictor: Option<Arc<dyn InScatterPredictor>>,
    technique: Technique,
    /// BDPT's prediction mode (thesis 6.4), set by [`Integrator::bdpt_prediction`].
    transport: Option<bdpt::Prediction>,
    /// The preview's fields, set by [`Integrator::preview`].
    preview: Option<Arc<preview::Preview>>,
    /// The sun's transmittance that guides the weighted first vertex of prediction
    /// at k = 1, set by [`Integrator::with_first_vertex_guide`].
    guide: Option<Arc<crate::field::SunTransmittance>>,
}

impl std::fmt::Debug for Integrator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Integrator")
            .field("settings", &self.settings)
            .field("predictor", &self.predictor.as_ref().map(|p| p.name().to_string()))
            .field("technique", &self.technique)
            .field("transport", &self.transport)
            .field("preview", &self.preview)
            .finish()
    }
}

impl Integrator {
    pub fn new(
        settings: RenderSettings,
        predictor: Option<Arc<dyn InScatterPredictor>>,
    ) -> Result<Self, IntegratorError> {
        Self::check(&settings, predictor.is_some())?;
        Ok(Integrator {
            settings,
            predictor,
            technique: Technique::PathTracing,
            transport: None,
            preview: None,
            guide: None,
        })
    }

    /// The weighted first vertex of prediction at k = 1 drawn among the camera ray's
    /// tentative collisions in proportion to their weight times the single scattering
    /// `field` predicts there (plus a floor), not to their weight alone (see
    /// [`path`]): the same expectation, the vertex sent where the sunlight is.
    pub fn with_first_vertex_guide(mut self, field: Arc<crate::field::SunTransmittance>) -> Self {
        self.guide = Some(field);
        self
    }

    /// Settings a path-tracing integrator accepts: k >= 1, and in prediction mode a p
    /// in (0, 1] and a predictor.
    fn check(settings: &RenderSettings, has_predictor: bool) -> Result<(), IntegratorError> {
        if settings.k < 1 {
            return Err(IntegratorError::BadK(settings.k));
        }
        if let Mode::Predict { p } = settings.mode {
            if !(p > 0.0 && p <= 1.0) {
                return Err(IntegratorError::BadP(p));
            }
            if !has_predictor {
                return Err(IntegratorError::NoPredictor);
            }
        }
        Ok(())
    }

    /// The same integrator (technique, predictor, fields, guide) with other render
    /// settings, checked as [`Integrator::new`] checks them.
    pub fn with_settings(&self, settings: RenderSettings) -> Result<Self, IntegratorError> {
        Self::check(&settings, self.predictor.is_some())?;
        Ok(Integrator { settings, ..self.clone() })
    }

    /// The field guiding the first vertex, if any ([`Integrator::with_first_vertex_guide`]).
    pub fn first_vertex_guide(&self) -> Option<&Arc<crate::field::SunTransmittance>> {
        self.guide.as_ref()
    }

    /// BDPT with prediction between the subpaths (thesis 6.4): `settings.mode` must be
    /// `Predict { p }`, `settings.k` is the number of segments of each subpath, and the
    /// buffers split at order 2k + 1 (see [`bdpt`]). `r` is the distance
    /// threshold below which the subpaths are extended instead of predicted.
    pub fn bdpt_prediction(
        settings: RenderSettings,
        b: bdpt::BdptSettings,
        predictor: Arc<dyn TransportPredictor>,
        r: f32,
    ) -> Result<Self, IntegratorError> {
        let Mode::Predict { p } = settings.mode else {
            return Err(IntegratorError::BadBdpt("BDPT prediction needs mode = predict".into()));
        };
        if settings.k < 1 {
            return Err(IntegratorError::BadK(settings.k));
        }
        b.validate().map_err(IntegratorError::BadBdpt)?;
        let prediction = bdpt::Prediction {
            predictor,
            segments: settings.k,
            r,
            p,
            candidates: bdpt::Prediction::DEFAULT_CANDIDATES,
            extension_samples: bdpt::Prediction::DEFAULT_EXTENSION_SAMPLES,
        };
        prediction.validate().map_err(IntegratorError::BadBdpt)?;
        Ok(Integrator {
            settings,
            predictor: None,
            technique: Technique::Bdpt(b),
            transport: Some(prediction),
            preview: None,
            guide: None,
        })
    }

    /// The instant preview with `preview`'s fields ([`preview`]): its buffers split
    /// as k = 2 (low = single scattering, high = the higher orders), whatever
    /// `settings.k`; `settings.mode` is not used.
    pub fn preview(settings: RenderSettings, preview: Arc<preview::Preview>) -> Result<Self, IntegratorError> {
        let settings = RenderSettings { k: 2, mode: Mode::Reference, ..settings };
        Ok(Integrator {
            settings,
            predictor: None,
            technique: Technique::Preview,
            transport: None,
            preview: Some(preview),
            guide: None,
        })
    }

    /// The preview's fields, in that technique.
    pub fn preview_state(&self) -> Option<&Arc<preview::Preview>> {
        self.preview.as_ref()
    }

    /// The preview when it is the technique that traces (what
    /// [`Integrator::trace_deferring`] hands a ray to).
    pub fn active_preview(&self) -> Option<&preview::Preview> {
        match (&self.technique, &self.preview) {
            (Technique::Preview, Some(p)) => Some(p),
            _ => None,
        }
    }

    /// BDPT prediction with `m` light subpath candidates per camera end vertex (see
    /// [`bdpt::Prediction::candidates`]); an error outside prediction mode.
    pub fn with_light_candidates(self, m: u32) -> Result<Self, IntegratorError> {
        self.with_prediction("light subpath candidates", |pr| pr.candidates = m)
    }

    /// BDPT prediction averaging `n` point-to-point samples for each pair closer
    /// than r (see [`bdpt::Prediction::extension_samples`]); an error outside
    /// prediction mode.
    pub fn with_extension_samples(self, n: u32) -> Result<Self, IntegratorError> {
        self.with_prediction("extension samples", |pr| pr.extension_samples = n)
    }

    /// The same integrator with one setting of BDPT's prediction changed by `edit`
    /// and validated; `what` names the setting when there is no prediction to change.
    fn with_prediction(
        mut self,
        what: &str,
        edit: impl FnOnce(&mut bdpt::Prediction),
    ) -> Result<Self, IntegratorError> {
        let Some(pr) = self.transport.as_mut() else {
            return Err(IntegratorError::BadBdpt(format!("{what} need BDPT's prediction mode")));
        };
        edit(pr);
        pr.validate().map_err(IntegratorError::BadBdpt)?;
        Ok(self)
    }

    /// The same integrator with another light transport algorithm.
    pub fn with_technique(mut self, technique: Technique) -> Result<Self, IntegratorError> {
        match technique {
            Technique::Bdpt(b) => {
                if matches!(self.settings.mode, Mode::Predict { .. }) && self.transport.is_none() {
                    return Err(IntegratorError::BdptPredict);
                }
                b.validate().map_err(IntegratorError::BadBdpt)?;
            }
            Technique::PathTracing => {
                if matches!(self.settings.mode, Mode::Predict { .. }) && self.predictor.is_none() {
                    return Err(IntegratorError::NoPredictor);
                }
                self.transport = None;
                self.preview = None;
            }
            Technique::Preview => {
                if self.preview.is_none() {
                    return Err(IntegratorError::NoPreview);
                }
            }
        }
        self.technique = technique;
        Ok(self)
    }

    /// BDPT's prediction settings, in that mode.
    pub fn transport_prediction(&self) -> Option<&bdpt::Prediction> {
        self.transport.as_ref()
    }

    /// The first scattering order of the high buffer: k, or 2k + 1 for BDPT's
    /// prediction mode.
    pub fn high_order_start(&self) -> u32 {
        self.transport.as_ref().map_or(self.settings.k, bdpt::Prediction::first_predicted_order)
    }

    pub fn technique(&self) -> Technique {
        self.technique
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    pub fn predictor(&self) -> Option<&Arc<dyn InScatterPredictor>> {
        self.predictor.as_ref()
    }

    /// Checks what the scene must provide for this integrator.
    pub fn check_scene(&self, scene: &Scene) -> Result<(), IntegratorError> {
        if matches!(self.settings.mode, Mode::Predict { .. }) && scene.sun.is_none() {
            return Err(IntegratorError::NoSun);
        }
        Ok(())
    }

    /// Radiance arriving at `o` from direction `-d` (i.e. along the ray o + t d),
    /// split by scattering order.
    #[inline]
    pub fn trace(&self, scene: &Scene, o: Vec3, d: Vec3, rng: &mut Rng) -> PathSample {
        self.trace_deferring(scene, o, d, rng, None, None)
    }

    /// In BDPT's prediction mode with more than one light subpath candidate (and
    /// predicted orders within `max_order`): a pool of light subpaths for the `n`
    /// camera samples of pass `pass` to share as candidates, one per sample up to
    /// [`bdpt::LightPool::MAX_LEN`] (see [`bdpt::LightPool`]); None
    /// otherwise. Subpath i has the stream (seed, POOL | pass, i): pixels use
    /// (seed, pass, pixel) and predictions (random, 0x7072_6564, 0), all with
    /// pass < 2^32, so no stream is shared. Outside the renderer ([`Integrator::trace`]) there is no pool and each
    /// of the M - 1 candidates is a light subpath of its own.
    pub fn light_pool(&self, scene: &Scene, pass: u32, n: u32) -> Option<bdpt::LightPool> {
        let (Technique::Bdpt(b), Some(pr)) = (&self.technique, &self.transport) else { return None };
        let predicts = self.settings.max_order.is_none_or(|m| pr.first_predicted_order() <= m);
        if pr.candidates <= 1 || scene.sun.is_none() || !predicts {
            return None;
        }
        let n = n.min(bdpt::LightPool::MAX_LEN);
        const POOL: u64 = 0x504f_4f4c << 32;
        let (seed, family) = (self.settings.seed, POOL | pass as u64);
        Some(bdpt::LightPool::trace(b, pr, scene, n, |i| Rng::new(seed, family, i as u64)))
    }

    /// [`Integrator::trace`], but in BDPT's prediction mode with `deferred` the
    /// predictions are pushed there instead of evaluated, to be evaluated together by
    /// [`Integrator::resolve_deferred`] (the same estimate, batched).
    #[inline]
    pub fn trace_deferring(
        &self,
        scene: &Scene,
        o: Vec3,
        d: Vec3,
        rng: &mut Rng,
        pool: Option<&bdpt::LightPool>,
        deferred: Option<&mut Vec<bdpt::DeferredPrediction>>,
    ) -> PathSample {
        if let Technique::Bdpt(b) = &self.technique {
            return bdpt::trace(&self.settings, b, self.transport.as_ref(), scene, o, d, rng, pool, deferred);
        }
        if let Some(p) = self.active_preview() {
            return p.trace(scene, o, d, rng);
        }
        path::trace(&self.settings, self.predictor.as_deref(), self.guide.as_deref(), scene, o, d, rng)
    }

    /// Evaluates predictions left by [`Integrator::trace_deferring`] in one batch and
    /// adds them to `samples[owner]`.
    pub fn resolve_deferred(
        &self,
        scene: &Scene,
        deferred: &mut [bdpt::DeferredPrediction],
        samples: &mut [PathSample],
    ) {
        if let Some(pr) = &self.transport {
            bdpt::resolve_deferred(pr.predictor.as_ref(), &scene.medium, deferred, samples);
        }
    }

    /// Estimates the in-scattered radiance L_i(x -> wo) (eq. 2.7) at a point inside the
    /// medium, all orders, by path tracing from that point: the quantity the learned
    /// model predicts (for a unit sun), and the ground truth it is trained on.
    pub fn in_scattered_radiance(&self, scene: &Scene, x: Vec3, wo: Vec3, rng: &mut Rng) -> Vec3 {
        let mut sum = Vec3::ZERO;
        path::scatter_from(&self.settings, self.predictor.as_deref(), scene, x, wo, 1, 1.0, 1, rng, &mut |_, v| {
            sum += v
        });
        sum
    }

    /// The multiple-scattering part of [`Integrator::in_scattered_radiance`]: orders
    /// >= 2 counted from `x` (single scattering at `x` left out), what a predictor
    /// with `predicts_single_scattering() == false` answers.
    pub fn multiple_scattered_radiance(&self, scene: &Scene, x: Vec3, wo: Vec3, rng: &mut Rng) -> Vec3 {
        let mut sum = Vec3::ZERO;
        path::scatter_from(&self.settings, self.predictor.as_deref(), scene, x, wo, 1, 1.0, 2, rng, &mut |_, v| {
            sum += v
        });
        sum
    }
}
