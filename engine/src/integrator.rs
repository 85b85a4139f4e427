//! Unidirectional volumetric path tracing with next event estimation at every vertex,
//! Russian roulette on throughput, and the split of every sample's contribution by
//! scattering order into the buffers of CONVENTIONS.md:
//! order 0 (the sky seen through the medium) -> `direct`, orders 1 .. k-1 -> `low`,
//! orders >= k -> `high`. Next event estimation at the j-th vertex and a path that
//! escapes to the sky after j scattering events both count as order j.
//!
//! The medium is grey (scalar sigma_t and albedo), so the path throughput is a scalar
//! and only the lights carry colour.

use crate::light::{Sky, Sun};
use crate::medium::{FreeFlight, Medium};
use crate::predictor::InScatterPredictor;
use crate::rng::Rng;
use glam::Vec3;
use std::sync::Arc;

/// Everything a render reads: immutable once built, shared between threads.
#[derive(Clone, Debug)]
pub struct Scene {
    pub medium: Medium,
    pub sun: Option<Sun>,
    pub sky: Sky,
    pub camera: crate::camera::Camera,
}

/// How the high orders are computed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Mode {
    /// Full path tracing.
    Reference,
    /// Vertices 1 .. k-1 path traced; at vertex k the predictor's L_i, Russian-rouletted
    /// with probability `p` and weighted 1/p (thesis section 5.4); the path ends there.
    Predict { p: f32 },
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// Scene seed: every random stream derives from (seed, pass, pixel).
    pub seed: u64,
    /// First scattering order of the high-order buffer (k >= 1).
    pub k: u32,
    /// Highest scattering order rendered (None = all).
    pub max_order: Option<u32>,
    pub mode: Mode,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings { seed: 0, k: 1, max_order: None, mode: Mode::Reference }
    }
}

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
}

/// The light transport algorithm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Technique {
    /// Unidirectional path tracing with next event estimation (this module).
    PathTracing,
    /// Volumetric bidirectional path tracing ([`crate::bdpt`]).
    Bdpt(crate::bdpt::BdptSettings),
}

/// One path's contribution, split by scattering order.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PathSample {
    pub direct: Vec3,
    pub low: Vec3,
    pub high: Vec3,
}

impl PathSample {
    pub fn full(&self) -> Vec3 {
        self.direct + self.low + self.high
    }
    pub fn is_finite(&self) -> bool {
        self.direct.is_finite() && self.low.is_finite() && self.high.is_finite()
    }
}

/// Russian roulette on throughput starts after this many scattering events.
pub(crate) const RR_MIN_ORDER: u32 = 3;

/// Russian roulette on throughput after `order` scattering events: from order
/// RR_MIN_ORDER on, a path with throughput below 1 survives with probability
/// max(beta, 0.05) and is reweighted. Returns false when the path ends. Shared by the
/// path tracer, BDPT's subpaths and the point-to-point walks.
#[inline(always)]
pub(crate) fn roulette(order: u32, beta: &mut f32, rng: &mut Rng) -> bool {
    if order >= RR_MIN_ORDER && *beta < 1.0 {
        let q = beta.max(0.05);
        if rng.uniform() >= q {
            return false;
        }
        *beta /= q;
    }
    true
}

#[derive(Clone)]
pub struct Integrator {
    settings: RenderSettings,
    predictor: Option<Arc<dyn InScatterPredictor>>,
    technique: Technique,
    /// BDPT's prediction mode (thesis 6.4), set by [`Integrator::bdpt_prediction`].
    transport: Option<crate::bdpt::Prediction>,
}

impl std::fmt::Debug for Integrator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Integrator")
            .field("settings", &self.settings)
            .field("predictor", &self.predictor.as_ref().map(|p| p.name().to_string()))
            .field("technique", &self.technique)
            .field("transport", &self.transport)
            .finish()
    }
}

impl Integrator {
    pub fn new(
        settings: RenderSettings,
        predictor: Option<Arc<dyn InScatterPredictor>>,
    ) -> Result<Self, IntegratorError> {
        if settings.k < 1 {
            return Err(IntegratorError::BadK(settings.k));
        }
        if let Mode::Predict { p } = settings.mode {
            if !(p > 0.0 && p <= 1.0) {
                return Err(IntegratorError::BadP(p));
            }
            if predictor.is_none() {
                return Err(IntegratorError::NoPredictor);
            }
        }
        Ok(Integrator { settings, predictor, technique: Technique::PathTracing, transport: None })
    }

    /// BDPT with prediction between the subpaths (thesis 6.4): `settings.mode` must be
    /// `Predict { p }`, `settings.k` is the number of segments of each subpath, and the
    /// buffers split at order 2k + 1 (see [`crate::bdpt`]). `r` is the distance
    /// threshold below which the subpaths are extended instead of predicted.
    pub fn bdpt_prediction(
        settings: RenderSettings,
        b: crate::bdpt::BdptSettings,
        predictor: Arc<dyn crate::predictor::TransportPredictor>,
        r: f32,
    ) -> Result<Self, IntegratorError> {
        let Mode::Predict { p } = settings.mode else {
            return Err(IntegratorError::BadBdpt("BDPT prediction needs mode = predict".into()));
        };
        if settings.k < 1 {
            return Err(IntegratorError::BadK(settings.k));
        }
        b.validate().map_err(IntegratorError::BadBdpt)?;
        let prediction = crate::bdpt::Prediction {
            predictor,
            segments: settings.k,
            r,
            p,
            candidates: crate::bdpt::Prediction::DEFAULT_CANDIDATES,
            extension_samples: crate::bdpt::Prediction::DEFAULT_EXTENSION_SAMPLES,
        };
        prediction.validate().map_err(IntegratorError::BadBdpt)?;
        Ok(Integrator { settings, predictor: None, technique: Technique::Bdpt(b), transport: Some(prediction) })
    }

    /// BDPT prediction with `m` light subpath candidates per camera end vertex (see
    /// [`crate::bdpt::Prediction::candidates`]); an error outside prediction mode.
    pub fn with_light_candidates(self, m: u32) -> Result<Self, IntegratorError> {
        self.with_prediction("light subpath candidates", |pr| pr.candidates = m)
    }

    /// BDPT prediction averaging `n` point-to-point samples for each pair closer
    /// than r (see [`crate::bdpt::Prediction::extension_samples`]); an error outside
    /// prediction mode.
    pub fn with_extension_samples(self, n: u32) -> Result<Self, IntegratorError> {
        self.with_prediction("extension samples", |pr| pr.extension_samples = n)
    }

    /// The same integrator with one setting of BDPT's prediction changed by `edit`
    /// and validated; `what` names the setting when there is no prediction to change.
    fn with_prediction(
        mut self,
        what: &str,
        edit: impl FnOnce(&mut crate::bdpt::Prediction),
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
            }
        }
        self.technique = technique;
        Ok(self)
    }

    /// BDPT's prediction settings, in that mode.
    pub fn transport_prediction(&self) -> Option<&crate::bdpt::Prediction> {
        self.transport.as_ref()
    }

    /// The first scattering order of the high buffer: k, or 2k + 1 for BDPT's
    /// prediction mode.
    pub fn high_order_start(&self) -> u32 {
        self.transport.as_ref().map_or(self.settings.k, crate::bdpt::Prediction::first_predicted_order)
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
    /// [`crate::bdpt::LightPool::MAX_LEN`] (see [`crate::bdpt::LightPool`]); None
    /// otherwise. Subpath i has the stream (seed, POOL | pass, i): pixels use
    /// (seed, pass, pixel) and predictions (random, 0x7072_6564, 0), all with
    /// pass < 2^32, so no stream is shared. Outside the renderer ([`Integrator::trace`]) there is no pool and each
    /// of the M - 1 candidates is a light subpath of its own.
    pub fn light_pool(&self, scene: &Scene, pass: u32, n: u32) -> Option<crate::bdpt::LightPool> {
        let (Technique::Bdpt(b), Some(pr)) = (&self.technique, &self.transport) else { return None };
        let predicts = self.settings.max_order.is_none_or(|m| pr.first_predicted_order() <= m);
        if pr.candidates <= 1 || scene.sun.is_none() || !predicts {
            return None;
        }
        let n = n.min(crate::bdpt::LightPool::MAX_LEN);
        const POOL: u64 = 0x504f_4f4c << 32;
        let (seed, family) = (self.settings.seed, POOL | pass as u64);
        Some(crate::bdpt::LightPool::trace(b, pr, scene, n, |i| Rng::new(seed, family, i as u64)))
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
        pool: Option<&crate::bdpt::LightPool>,
        deferred: Option<&mut Vec<crate::bdpt::DeferredPrediction>>,
    ) -> PathSample {
        if let Technique::Bdpt(b) = &self.technique {
            return crate::bdpt::trace(&self.settings, b, self.transport.as_ref(), scene, o, d, rng, pool, deferred);
        }
        let mut out = PathSample::default();
        match scene.medium.sample_free_flight(o, d, f32::INFINITY, rng) {
            FreeFlight::Escaped => out.direct = scene.sky.radiance,
            FreeFlight::Collision { t } => {
                let k = self.settings.k;
                self.scatter_from(scene, o + d * t, -d, 1, scene.medium.albedo(), 1, rng, &mut |order, v| {
                    if order >= k { out.high += v } else { out.low += v }
                });
            }
        }
        out
    }

    /// Evaluates predictions left by [`Integrator::trace_deferring`] in one batch and
    /// adds them to `samples[owner]`.
    pub fn resolve_deferred(
        &self,
        scene: &Scene,
        deferred: &mut [crate::bdpt::DeferredPrediction],
        samples: &mut [PathSample],
    ) {
        if let Some(pr) = &self.transport {
            crate::bdpt::resolve_deferred(pr.predictor.as_ref(), &scene.medium, deferred, samples);
        }
    }

    /// Estimates the in-scattered radiance L_i(x -> wo) (eq. 2.7) at a point inside the
    /// medium, all orders, by path tracing from that point: the quantity the learned
    /// model predicts (for a unit sun), and the ground truth it is trained on.
    pub fn in_scattered_radiance(&self, scene: &Scene, x: Vec3, wo: Vec3, rng: &mut Rng) -> Vec3 {
        let mut sum = Vec3::ZERO;
        self.scatter_from(scene, x, wo, 1, 1.0, 1, rng, &mut |_, v| sum += v);
        sum
    }

    /// Next event estimation toward the sun from the vertex at `x` (order `order`).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn next_event(
        scene: &Scene,
        sun: &Sun,
        x: Vec3,
        wo: Vec3,
        beta: f32,
        order: u32,
        rng: &mut Rng,
        add: &mut impl FnMut(u32, Vec3),
    ) {
        let wi = sun.sample_wi(rng.uniform2());
        let f = beta * scene.medium.phase().eval(wo, wi);
        if f > 0.0 {
            let tr = scene.medium.transmittance_ratio(x, wi, f32::INFINITY, rng);
            if tr > 0.0 {
                add(order, sun.radiance() * (f * tr));
            }
        }
    }

    /// The multiple-scattering part of [`Integrator::in_scattered_radiance`]: orders
    /// >= 2 counted from `x` (single scattering at `x` left out), what a predictor
    /// with `predicts_single_scattering() == false` answers.
    pub fn multiple_scattered_radiance(&self, scene: &Scene, x: Vec3, wo: Vec3, rng: &mut Rng) -> Vec3 {
        let mut sum = Vec3::ZERO;
        self.scatter_from(scene, x, wo, 1, 1.0, 2, rng, &mut |_, v| sum += v);
        sum
    }

    /// The path from a scattering vertex at `x` (the `order`-th) with outgoing
    /// direction `wo` and throughput `beta` (albedo of this vertex included); next
    /// event estimation from orders >= `min_order` only.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    fn scatter_from(
        &self,
        scene: &Scene,
        mut x: Vec3,
        mut wo: Vec3,
        mut order: u32,
        mut beta: f32,
        min_order: u32,
        rng: &mut Rng,
        add: &mut impl FnMut(u32, Vec3),
    ) {
        let medium = &scene.medium;
        let max_order = self.settings.max_order.unwrap_or(u32::MAX);
        loop {
            if order > max_order {
                return;
            }
            if let Mode::Predict { p } = self.settings.mode {
                if order == self.settings.k {
                    // Predict L_i at vertex k, roulette with probability p. A predictor
                    // of multiple scattering only gets single scattering by NEE here.
                    if let (Some(pred), Some(sun)) = (&self.predictor, &scene.sun) {
                        if !pred.predicts_single_scattering() {
                            Self::next_event(scene, sun, x, wo, beta, order, rng, add);
                        }
                        if rng.uniform() < p {
                            let li = pred.predict(medium, sun, x, wo);
                            if li.is_finite() && li >= 0.0 {
                                add(order, sun.radiance() * (beta * li / p));
                            }
                        }
                    }
                    return;
                }
            }
            if order >= min_order {
                if let Some(sun) = &scene.sun {
                    Self::next_event(scene, sun, x, wo, beta, order, rng, add);
                }
            }
            if !roulette(order, &mut beta, rng) {
                return;
            }
            let Some(next) = medium.scatter(x, wo, rng) else {
                if !scene.sky.is_black() && order >= min_order {
                    add(order, scene.sky.radiance * beta);
                }
                return;
            };
            (x, wo) = next;
            order += 1;
            beta *= medium.albedo();
            if beta <= 0.0 {
                return;
            }
        }
    }
}
