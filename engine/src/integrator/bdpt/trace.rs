//! One camera sample of BDPT: the light subpath, the camera walk with next event
//! estimation and connections to every light vertex, the MIS weights, and in
//! prediction mode the high-order term between the subpaths' end vertices.

use super::mis::{PathView, mis_weight};
use super::prediction::{DeferredPrediction, LightPool, Prediction, predict_high};
use super::subpath::{BdptSettings, CameraRing, Contribution, RING, Strategy, Vertex, light_path};
use crate::integrator::base::{PathSample, RenderSettings, roulette};
use crate::medium::FreeFlight;
use crate::rng::Rng;
use crate::scene::Scene;
use glam::Vec3;

/// Traces one camera sample along o + t d and reports every strategy's unweighted
/// contribution with its weight (their weighted sum is the sample's estimate).
/// With `prediction`, BDPT makes orders 1 ..= 2k only and the transport between
/// the k-th vertices of the two subpaths is predicted (or extended below r).
/// With `deferred`, predictions are not evaluated here but pushed there (their value
/// then goes into the high buffer: see [`DeferredPrediction`]); without it they are
/// evaluated at once, with the same random stream, so both give the same estimate.
#[allow(clippy::too_many_arguments)]
pub fn trace_strategies(
    settings: &RenderSettings,
    b: &BdptSettings,
    prediction: Option<&Prediction>,
    scene: &Scene,
    o: Vec3,
    d: Vec3,
    rng: &mut Rng,
    pool: Option<&LightPool>,
    mut deferred: Option<&mut Vec<DeferredPrediction>>,
    sink: &mut impl FnMut(Contribution),
) {
    // Prediction caps the light subpath at k vertices and the camera walk at 2k, and
    // BDPT makes orders up to 2k only; the weights know it.
    let capped;
    let (b, max_depth) = match prediction {
        Some(pr) => {
            capped = BdptSettings {
                heuristic: b.heuristic,
                max_camera_connect: 2 * pr.segments,
                max_light_vertices: pr.segments,
            };
            (&capped, 2 * pr.segments as usize)
        }
        None => (b, usize::MAX),
    };
    let medium = &scene.medium;
    let phase = medium.phase();
    let max_order = settings.max_order.unwrap_or(u32::MAX);
    let max_bdpt_order = prediction.map_or(max_order, |pr| max_order.min(2 * pr.segments));
    let t = match medium.sample_free_flight(o, d, f32::INFINITY, rng) {
        FreeFlight::Escaped => {
            sink(Contribution { order: 0, strategy: Strategy::Direct, value: scene.sky.radiance(d), weight: 1.0 });
            return;
        }
        FreeFlight::Collision { t } => t,
    };
    // The light subpath only once the camera ray has hit the cloud.
    let light = scene.sun.as_ref().map(|sun| light_path(b, scene, sun, rng));
    let mut cam = CameraRing { origin: o, verts: [Vertex::default(); RING] };
    let (mut x, mut wo, mut beta, mut order) = (o + d * t, -d, medium.albedo(), 1u32);
    loop {
        if order > max_bdpt_order || beta <= 0.0 {
            return;
        }
        let c = order as usize;
        cam.verts[c % RING] = Vertex { x, wo, beta, sigma_t: medium.sigma_t(x) };
        if let (Some(sun), Some(lp)) = (&scene.sun, &light) {
            // c = n: next event estimation toward the sun.
            let wi = sun.sample_wi(rng.uniform2());
            let f = beta * phase.eval(wo, wi);
            if f > 0.0 {
                let tr = medium.transmittance_ratio(x, wi, f32::INFINITY, rng);
                if tr > 0.0 {
                    let view = PathView { cam: &cam, light: None, c, n: c, to_sun: wi };
                    let weight = mis_weight(&view, phase, lp.area, b, max_depth);
                    sink(Contribution {
                        order,
                        strategy: Strategy::NextEvent,
                        value: sun.radiance() * (f * tr),
                        weight,
                    });
                }
            }
            // c < n: connect to each light vertex.
            let mut t1 = 0.0f32; // prediction mode: the one-segment term x_k <-> y_k
            if order <= b.max_camera_connect {
                for j in 1..=lp.len {
                    let n = c + j;
                    if n as u64 > max_bdpt_order as u64 {
                        break;
                    }
                    let y = &lp.verts[j - 1];
                    let dv = y.x - x;
                    let dist2 = dv.length_squared();
                    if dist2 <= 1e-12 {
                        continue;
                    }
                    let dist = dist2.sqrt();
                    let dir = dv / dist;
                    // The segment's phase and geometry terms: T's one-segment term
                    // without the transmittance.
                    let segment = phase.eval(wo, dir) * phase.eval(y.wo, -dir) / dist2;
                    let f = beta * segment * y.beta * lp.area;
                    if !(f > 0.0 && f.is_finite()) {
                        continue;
                    }
                    let tr = medium.transmittance_ratio(x, dir, dist, rng);
                    if tr <= 0.0 {
                        continue;
                    }
                    if prediction.is_some_and(|pr| order == pr.segments && j == lp.len) {
                        t1 = segment * tr;
                    }
                    let view = PathView { cam: &cam, light: Some(lp), c, n, to_sun: -lp.beam };
                    let weight = mis_weight(&view, phase, lp.area, b, max_depth);
                    sink(Contribution {
                        order: n as u32,
                        strategy: Strategy::Connect { camera: order, light: j as u32 },
                        value: sun.radiance() * (f * tr),
                        weight,
                    });
                }
            }
            if let Some(pr) = prediction.filter(|pr| order == pr.segments) {
                let first = pr.first_predicted_order();
                if first <= max_order && rng.uniform() < pr.p {
                    predict_high(pr, b, scene, sun, lp, x, wo, beta, t1, rng, pool, deferred.as_deref_mut(), sink);
                }
            }
        }
        if max_depth <= c {
            return;
        }
        if !roulette(order, &mut beta, rng) {
            return;
        }
        let next = match medium.scatter(x, wo, rng) {
            Ok(next) => next,
            Err(wi) => {
                if !scene.sky.is_black() {
                    let value = scene.sky.radiance(wi) * beta;
                    sink(Contribution { order, strategy: Strategy::Sky, value, weight: 1.0 });
                }
                return;
            }
        };
        (x, wo) = next;
        order += 1;
        beta *= medium.albedo();
    }
}

/// One camera sample's MIS-weighted estimate, split by order into the buffers.
/// In prediction mode the split is at 2k + 1 (module documentation); with
/// `deferred`, its predictions are left there (see [`trace_strategies`]).
#[allow(clippy::too_many_arguments)]
pub fn trace(
    settings: &RenderSettings,
    b: &BdptSettings,
    prediction: Option<&Prediction>,
    scene: &Scene,
    o: Vec3,
    d: Vec3,
    rng: &mut Rng,
    pool: Option<&LightPool>,
    deferred: Option<&mut Vec<DeferredPrediction>>,
) -> PathSample {
    let mut out = PathSample::default();
    let k = prediction.map_or(settings.k, Prediction::first_predicted_order);
    trace_strategies(settings, b, prediction, scene, o, d, rng, pool, deferred, &mut |c| {
        let v = c.value * c.weight;
        if c.order == 0 {
            out.direct += v;
        } else if c.order >= k {
            out.high += v;
        } else {
            out.low += v;
        }
    });
    out
}
