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
//! event estimation first, for the sun and for the sky.
//!
//! At k = 1 the vertex is by default not the camera ray's first real collision but one
//! of ratio tracking's tentative collisions along the whole ray, drawn by its weight
//! T^ sigma_t / sigma_maj, with the sum W of the weights as the throughput
//! ([`FirstVertex::Weighted`], [`crate::Medium::sample_collision_weighted`]). W f(x)
//! has the expectation of the free flight's f(x) (both estimate the integral of T
//! sigma_t f along the ray), but a ray through a faint or thin part of the cloud no
//! longer either scatters or passes: it always brings back its share, which removes
//! most of the noise left once the prediction itself is cheap (a lattice,
//! [`crate::integrator::preview::CameraLatticePredictor`]). The sky seen through the
//! ray is weighted by the ratio-tracking transmittance. With a sun-transmittance field
//! as a guide ([`crate::Integrator::with_first_vertex_guide`]) the collision is drawn
//! in proportion to its weight times p(wo, sun) T_sun + [`GUIDE_FLOOR`] (resampled
//! importance sampling; [`crate::Medium::sample_collision_guided`]), so the vertex and
//! its shadow ray go where the sunlight is; the expectation stays the same.
//!
//! Lights other than a delta sun (thesis chapter 7): a predictor that answers for
//! any light direction gets, per predicted path, one direction on the soft sun's
//! disk (the disk's mean over directions, by one sample) and one sky direction drawn
//! from the sky's radiance as a directional light of unit irradiance, weighted by
//! radiance / pdf; that estimates the sky's orders >= k, in expectation exactly what
//! path tracing adds, up to the model's error. A predictor bound to one sun
//! direction gets the sun's centre, and the sky's orders >= k are left out.

use super::base::{FirstVertex, Mode, PathSample, RenderSettings, roulette};
use crate::field::SunTransmittance;
use crate::light::Sun;
use crate::medium::FreeFlight;
use crate::predictor::InScatterPredictor;
use crate::rng::Rng;
use crate::scene::Scene;
use glam::Vec3;

/// The floor of the guided first vertex's guide, beside single scattering p T_sun
/// (see [`trace`]): about the multiple scattering a unit sun leaves inside a cloud,
/// the part of the prediction that does not follow the sun. On scene A (all nine
/// cells, automatic p) 0.1 and 0.3 give the same speedups within timing noise; 0.03
/// loses up to 40 % toplit, where the phase toward the sun is small.
const GUIDE_FLOOR: f32 = 0.1;

/// Radiance arriving at `o` from direction `-d` (along the ray o + t d), split by
/// scattering order: order 0 to `direct`, orders 1 .. k-1 to `low`, >= k to `high`.
#[inline]
pub(crate) fn trace(
    settings: &RenderSettings,
    predictor: Option<&dyn InScatterPredictor>,
    guide: Option<&SunTransmittance>,
    scene: &Scene,
    o: Vec3,
    d: Vec3,
    rng: &mut Rng,
) -> PathSample {
    let mut out = PathSample::default();
    let medium = &scene.medium;
    // The camera ray's vertex, its throughput before the albedo, and the sky seen
    // through the ray: by free flight (path tracing) the first real collision with
    // throughput 1, or the sky wholly; for prediction at k = 1 by default one
    // tentative collision of ratio tracking, weighted (see the module documentation).
    let weighted = matches!(settings.mode, Mode::Predict { .. })
        && settings.k == 1
        && predictor.is_some()
        && settings.first_vertex == FirstVertex::Weighted;
    let (vertex, tr) = match guide {
        // Single scattering along the ray is p(wo, sun) T_sun(x), the phase the same
        // at every point: the guide is that plus a floor for the orders the prediction
        // adds, which dominate where the phase or the sun is small.
        Some(field) if weighted => {
            let phase = medium.phase().eval(-d, field.to_sun());
            medium.sample_collision_guided(o, d, f32::INFINITY, rng, |x| phase * field.at(x) + GUIDE_FLOOR)
        }
        _ if weighted => medium.sample_collision_weighted(o, d, f32::INFINITY, rng),
        _ => match medium.sample_free_flight(o, d, f32::INFINITY, rng) {
            FreeFlight::Escaped => (None, 1.0),
            FreeFlight::Collision { t } => (Some((t, 1.0)), 0.0),
        },
    };
    if tr > 0.0 {
        out.direct = scene.sky.radiance(d) * tr;
    }
    if let Some((t, w)) = vertex {
        let k = settings.k;
        scatter_from(settings, predictor, scene, o + d * t, -d, 1, w * medium.albedo(), 1, rng, &mut |order, v| {
            if order >= k { out.high += v } else { out.low += v }
        });
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
    let phase = scene.medium.phase().eval(wo, wi);
    if !(beta > 0.0 && phase > 0.0) {
        return;
    }
    // Russian roulette on the shadow ray by the phase toward the sun: below the floor
    // (`engine::medium::SHADOW_ROULETTE_PEAK_FRACTION`) it is cast with probability
    // phase / floor and weighted by the inverse, so every shadow ray cast carries at
    // least the floor's weight.
    let floor = scene.medium.shadow_roulette_floor();
    let weight = if phase >= floor {
        phase
    } else {
        if rng.uniform() * floor >= phase {
            return;
        }
        floor
    };
    let tr = scene.medium.transmittance_ratio(x, wi, f32::INFINITY, rng);
    if tr > 0.0 {
        add(order, sun.radiance() * (beta * weight * tr));
    }
}

/// Prediction at vertex k (`x`, outgoing `wo`, throughput `beta`): single
/// scattering by NEE first for a predictor of multiple scattering only, then, with
/// probability `p` and weight 1 / p, the predicted L_i for the sun and for the sky.
#[inline]
#[allow(clippy::too_many_arguments)]
fn predict_at_vertex(
    scene: &Scene,
    pred: &dyn InScatterPredictor,
    p: f32,
    x: Vec3,
    wo: Vec3,
    beta: f32,
    order: u32,
    rng: &mut Rng,
    add: &mut impl FnMut(u32, Vec3),
) {
    let medium = &scene.medium;
    let any_direction = pred.answers_any_light_direction();
    let sky = (!scene.sky.is_black() && any_direction).then_some(&scene.sky);
    if !pred.predicts_single_scattering() {
        if let Some(sun) = &scene.sun {
            next_event(scene, sun, x, wo, beta, order, rng, add);
        }
        if let Some(sky) = sky {
            // The sky's single scattering at x: one phase-sampled direction, its
            // transmittance by ratio tracking (the phase pdf cancels the phase value).
            let wi = medium.phase().sample(wo, rng.uniform2()).wi;
            let tr = medium.transmittance_ratio(x, wi, f32::INFINITY, rng);
            if tr > 0.0 {
                add(order, sky.radiance(wi) * (beta * tr));
            }
        }
    }
    if rng.uniform() >= p {
        return;
    }
    if let Some(sun) = &scene.sun {
        let light = if any_direction && sun.angular_radius() > 0.0 {
            Sun::new(-sun.sample_wi(rng.uniform2()), Vec3::ONE, 0.0).ok()
        } else {
            None
        };
        let li = pred.predict(medium, light.as_ref().unwrap_or(sun), x, wo);
        if li.is_finite() && li >= 0.0 {
            add(order, sun.radiance() * (beta * li / p));
        }
    }
    if let Some(sky) = sky {
        let (wi, pdf) = sky.sample(rng.uniform2());
        if let Ok(light) = Sun::new(-wi, Vec3::ONE, 0.0) {
            let li = pred.predict(medium, &light, x, wo);
            if li.is_finite() && li >= 0.0 && pdf > 0.0 {
                add(order, sky.radiance(wi) * (beta * li / (p * pdf)));
            }
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
                if let Some(pred) = predictor {
                    predict_at_vertex(scene, pred, p, x, wo, beta, order, rng, add);
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
