//! Unidirectional volumetric path tracing: delta tracking, next event estimation
//! toward the sun at every vertex, Russian roulette on throughput, and prediction at
//! bounce k.
//!
//! Every contribution is tagged with its scattering order (docs/conventions.md): next
//! event estimation at the j-th vertex and a path that escapes to the sky after j
//! scattering events both count as order j. The medium is grey (scalar sigma_t and
//! albedo), so the path throughput is a scalar and only the lights carry colour.
//!
//! Prediction at bounce k (`Mode::Predict { p }`, thesis section 5.4): vertices
//! 1 .. k-1 are path traced; at vertex k the predictor's L_i(x_k -> omega), times the
//! sun's radiance, is added with probability p and weighted 1/p, and the path ends.
//! A predictor of multiple scattering only gets single scattering at vertex k by next
//! event estimation first. The predictor answers for the sun: sky light of orders
//! >= k is not added in this mode.

use super::base::{Mode, PathSample, RenderSettings, roulette};
use crate::light::Sun;
use crate::medium::FreeFlight;
use crate::predictor::InScatterPredictor;
use crate::rng::Rng;
use crate::scene::Scene;
use glam::Vec3;

/// Radiance arriving at `o` from direction `-d` (along the ray o + t d), split by
/// scattering order: order 0 to `direct`, orders 1 .. k-1 to `low`, >= k to `high`.
#[inline]
pub(crate) fn trace(
    settings: &RenderSettings,
    predictor: Option<&dyn InScatterPredictor>,
    scene: &Scene,
    o: Vec3,
    d: Vec3,
    rng: &mut Rng,
) -> PathSample {
    let mut out = PathSample::default();
    match scene.medium.sample_free_flight(o, d, f32::INFINITY, rng) {
        FreeFlight::Escaped => out.direct = scene.sky.radiance(d),
        FreeFlight::Collision { t } => {
            let k = settings.k;
            scatter_from(
                settings,
                predictor,
                scene,
                o + d * t,
                -d,
                1,
                scene.medium.albedo(),
                1,
                rng,
                &mut |order, v| {
                    if order >= k { out.high += v } else { out.low += v }
                },
            );
        }
    }
    out
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

/// The path from a scattering vertex at `x` (the `order`-th) with outgoing
/// direction `wo` and throughput `beta` (albedo of this vertex included); next
/// event estimation from orders >= `min_order` only. Every contribution goes to
/// `add(order, value)`.
#[inline]
#[allow(clippy::too_many_arguments)]
pub(crate) fn scatter_from(
    settings: &RenderSettings,
    predictor: Option<&dyn InScatterPredictor>,
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
    let max_order = settings.max_order.unwrap_or(u32::MAX);
    loop {
        if order > max_order {
            return;
        }
        if let Mode::Predict { p } = settings.mode {
            if order == settings.k {
                // Predict L_i at vertex k, roulette with probability p. A predictor
                // of multiple scattering only gets single scattering by NEE here.
                if let (Some(pred), Some(sun)) = (predictor, &scene.sun) {
                    if !pred.predicts_single_scattering() {
                        next_event(scene, sun, x, wo, beta, order, rng, add);
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
                next_event(scene, sun, x, wo, beta, order, rng, add);
            }
        }
        if !roulette(order, &mut beta, rng) {
            return;
        }
        let next = match medium.scatter(x, wo, rng) {
            Ok(next) => next,
            Err(wi) => {
                if !scene.sky.is_black() && order >= min_order {
                    add(order, scene.sky.radiance(wi) * beta);
                }
                return;
            }
        };
        (x, wo) = next;
        order += 1;
        beta *= medium.albedo();
        if beta <= 0.0 {
            return;
        }
    }
}
