//! The hooks through which a learned model plugs into the renderer, and the queries
//! they answer.
//!
//! The engine knows nothing of the model's framework: anything that can estimate the
//! in-scattered radiance at a point implements [`InScatterPredictor`] (the path
//! tracer's prediction at bounce k), anything that can estimate the transport between
//! two points implements [`TransportPredictor`] (BDPT's prediction between its
//! subpaths).

use crate::light::Sun;
use crate::medium::Medium;
use crate::rng::Rng;
use glam::Vec3;

/// Predicts the total in-scattered radiance L_i(x -> omega) (thesis eq. 2.7 and the
/// model target of eq. 5.5, single scattering at x included) at a point `x` inside
/// `medium` lit by `sun`, for a sun of UNIT radiance; the integrator multiplies by the
/// sun's radiance. `omega` points away from `x`, toward the previous path vertex (the
/// direction the radiance leaves in).
///
/// Called from many render threads at once, once per predicted path: implementations
/// must not allocate per call (keep per-thread scratch space instead).
pub trait InScatterPredictor: Send + Sync {
    fn predict(&self, medium: &Medium, sun: &Sun, x: Vec3, omega: Vec3) -> f32;

    /// [`InScatterPredictor::predict`] at `xs[i]` toward `omegas[i]` into `out[i]`,
    /// each value the same bits as a call of `predict` would give (a lattice filled a
    /// brick at a time reads the same values as one filled node by node). A model
    /// whose network evaluates several rows per pass over its weights answers a batch
    /// faster than one query at a time; the default asks `predict` for each.
    fn predict_many(&self, medium: &Medium, sun: &Sun, xs: &[Vec3], omegas: &[Vec3], out: &mut [f32]) {
        assert!(xs.len() == omegas.len() && xs.len() == out.len(), "one direction and one output per point");
        for ((o, &x), &omega) in out.iter_mut().zip(xs).zip(omegas) {
            *o = self.predict(medium, sun, x, omega);
        }
    }

    /// Whether `predict` includes single scattering at `x` (the thesis's target, eq.
    /// 5.5). A predictor that answers only the multiple-scattering part (orders >= 2
    /// counted from `x`) returns false, and the integrator then path traces single
    /// scattering at vertex k by next event estimation before adding the prediction.
    fn predicts_single_scattering(&self) -> bool {
        true
    }

    /// Whether `predict` answers for a light of any direction, not only the sun it was
    /// built for. The integrator then predicts the sky's high orders too (sky
    /// directions sampled as directional lights, thesis chapter 7) and samples a soft
    /// sun's disk; a predictor bound to one sun direction (false) gets the scene's sun
    /// only, and the sky's orders >= k are left out.
    fn answers_any_light_direction(&self) -> bool {
        true
    }

    /// A short name for logs and reports.
    fn name(&self) -> &str {
        "predictor"
    }

    /// Bytes of what the predictor holds for its cloud and light (the fields its
    /// features read; parts shared with other bindings counted whole, a field lent by
    /// its caller, such as the preview's sun field, left to the caller), so that a
    /// preview can state all the memory it keeps. 0 for one that holds nothing per
    /// cloud.
    fn memory_bytes(&self) -> usize {
        0
    }
}

/// Predicts the point-to-point transport T(x_e, w_e <-> x_s, w_s) of thesis eq. 6.1
/// (see [`crate::integrator::p2p`]) between two points inside `medium`, for BDPT's prediction
/// mode (thesis 6.4): every path between the two points, the single segment joining
/// them included, with the phase function as the directional profile at both ends
/// and no scattering coefficient at the ends. World units (T scales as 1 / length^2).
///
/// `rng` is there for predictors that are themselves estimators (an unbiased one
/// makes the prediction mode unbiased, which the tests use) or that randomise their
/// input (a network's random rotation about the emitter-sensor axis). Called from
/// many render threads at once: no allocation per call.
pub trait TransportPredictor: Send + Sync {
    fn predict(&self, medium: &Medium, q: &P2pQuery, rng: &mut Rng) -> f32;

    /// `out[i] = predict(medium, &queries[i], &mut rngs[i])` for every i. The renderer
    /// collects a tile's queries and asks for them at once, so that a network can
    /// apply each weight to several rows while it is loaded. The default answers
    /// them one at a time; an override must give the same answers (up to rounding).
    fn predict_batch(&self, medium: &Medium, queries: &[P2pQuery], rngs: &mut [Rng], out: &mut [f32]) {
        assert!(queries.len() == rngs.len() && queries.len() == out.len(), "one stream and one output per query");
        for ((q, rng), o) in queries.iter().zip(rngs.iter_mut()).zip(out.iter_mut()) {
            *o = self.predict(medium, q, rng);
        }
    }

    /// A short name for logs and reports.
    fn name(&self) -> &str {
        "transport predictor"
    }
}

/// One point-to-point query.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct P2pQuery {
    pub emitter: Vec3,
    /// Unit direction at the emitter toward where its light came from.
    pub omega_e: Vec3,
    pub sensor: Vec3,
    /// Unit direction at the sensor toward where its path came from.
    pub omega_s: Vec3,
}

impl P2pQuery {
    /// The same query with emitter and sensor exchanged (T is symmetric).
    pub fn swapped(&self) -> Self {
        P2pQuery { emitter: self.sensor, omega_e: self.omega_s, sensor: self.emitter, omega_s: self.omega_e }
    }
}
