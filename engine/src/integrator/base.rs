//! What the integrators share: render settings, the order-split sample record,
//! Russian roulette on throughput and the choice of MIS heuristic.
//!
//! Scattering orders follow docs/conventions.md: the order of a path is the number of
//! scattering events in the medium; order 0 is the sky seen through the medium.

use crate::rng::Rng;
use glam::Vec3;

/// How the high orders are computed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Mode {
    /// Full path tracing.
    Reference,
    /// Vertices 1 .. k-1 path traced; at vertex k the predictor's L_i, Russian-rouletted
    /// with probability `p` and weighted 1/p (thesis section 5.4); the path ends there.
    Predict { p: f32 },
}

/// Where prediction at bounce 1 places its vertex on the camera ray.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FirstVertex {
    /// At the first real collision, by free-flight sampling (as path tracing does): a
    /// camera ray through a thin or faint part of the cloud either scatters there or
    /// passes, which is most of the noise left when the prediction is cheap.
    FreeFlight,
    /// At one tentative collision of ratio tracking along the whole camera ray, drawn
    /// by its weight, with the sum of the weights as the throughput
    /// ([`crate::Medium::sample_collision_weighted`]): the same expectation, without
    /// the binary choice.
    #[default]
    Weighted,
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
    /// Prediction at k = 1: how the vertex is placed on the camera ray.
    pub first_vertex: FirstVertex,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings { seed: 0, k: 1, max_order: None, mode: Mode::Reference, first_vertex: FirstVertex::Weighted }
    }
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

/// How strategies are weighed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MisHeuristic {
    Balance,
    /// Exponent 2 (Veach's recommendation).
    Power,
}
