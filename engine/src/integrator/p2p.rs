//! Point-to-point transport (thesis eqs. 6.1-6.2): the total transport
//! T(x_e, w_e <-> x_s, w_s) between a point emitter and a point sensor inside the
//! medium, whose directional profiles are the phase function about fixed directions
//! w_e and w_s (each pointing from its point back toward where its path came from,
//! so the profile at the emitter is p(w_e, w_{x_e x_1}) in this crate's convention).
//! Interior vertices carry sigma_s p, every segment T / d^2.
//!
//! The estimator is bidirectional. The emitter walk starts at x_e (phase sampling
//! about w_e, delta tracking, Russian roulette on throughput) and is not capped; the
//! sensor subpath starts at x_s the same way and keeps at most `max_sensor_vertices`
//! interior vertices. Every emitter-walk vertex (x_e included) connects to every
//! sensor vertex (x_s included) through a ratio-tracked segment, so a path of k
//! segments can come from the strategies s + t = k - 1 (s interior vertices from the
//! emitter, t from the sensor) with t <= max_sensor_vertices; s = k - 1, t = 0 is
//! always there, so no order is cut off. Multiple importance sampling weighs them
//! with densities that leave out the edges' transmittance (as in [`super::bdpt`]:
//! weights that are functions of the path and sum to one keep it unbiased).
//! `max_sensor_vertices = 0` is path tracing with a connection to the sensor at every
//! vertex, the thesis's "PT" column (its estimator has infinite variance: nothing
//! samples vertices near the point sensor).
//!
//! Connection schemes (thesis 6.3.1): `All` connects every pair; `Rr1` keeps a
//! connection with probability min(1, product of the two phase values / (1/4pi)^2)
//! and `Rr2` also multiplies by the geometry term relative to 1 / |x_e - x_s|^2;
//! kept connections are divided by that probability, so both stay unbiased and skip
//! the transmittance estimate of most weak connections.

use super::base::{MisHeuristic, roulette};
use crate::medium::{FreeFlight, Medium};
use crate::predictor::{P2pQuery, TransportPredictor};
use crate::rng::Rng;
use crate::sampling::INV_4PI;
use glam::Vec3;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConnectionScheme {
    All,
    Rr1,
    Rr2,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct P2pSettings {
    pub scheme: ConnectionScheme,
    pub heuristic: MisHeuristic,
    /// Interior vertices of the sensor subpath (0 ..= MAX_SENSOR_VERTICES; 0 is
    /// path tracing).
    pub max_sensor_vertices: u32,
    /// Only paths of at most this many segments (None: all).
    pub max_segments: Option<u32>,
}

impl Default for P2pSettings {
    fn default() -> Self {
        P2pSettings {
            scheme: ConnectionScheme::Rr2,
            heuristic: MisHeuristic::Power,
            max_sensor_vertices: 8,
            max_segments: None,
        }
    }
}

pub const MAX_SENSOR_VERTICES: u32 = 32;
/// Emitter-walk vertices kept for the weights (the last RING).
const RING: usize = 64;

#[derive(Clone, Copy, Debug, Default)]
struct Vertex {
    x: Vec3,
    /// Unit direction toward the previous vertex of its own subpath (w_e or w_s at
    /// the end points).
    wo: Vec3,
    beta: f32,
    sigma_t: f32,
}

/// The full path x_0 = x_e, x_1 .. x_s from the emitter walk, x_{s+1} .. x_{k-1} the
/// sensor subpath's t .. 1, x_k = x_s.
struct View<'a> {
    emit: &'a [Vertex; RING],
    sens: &'a [Vertex],
    s: usize,
    k: usize,
}

impl View<'_> {
    #[inline]
    fn x(&self, i: usize) -> &Vertex {
        if i <= self.s { &self.emit[i % RING] } else { &self.sens[self.k - i] }
    }
}

/// Density proxy of interior x_i sampled from x_{i-1} by the emitter walk.
#[inline]
fn q_emit(v: &View, phase: crate::phase::PhaseFunction, i: usize) -> f64 {
    let (a, t) = (v.x(i - 1), v.x(i));
    let from = if i == 1 { a.wo } else { (v.x(i - 2).x - a.x).normalize_or_zero() };
    let d = t.x - a.x;
    let d2 = d.length_squared().max(1e-12);
    phase.pdf(from, d / d2.sqrt()) as f64 * t.sigma_t as f64 / d2 as f64
}

/// Density proxy of interior x_i sampled from x_{i+1} by the sensor subpath.
#[inline]
fn q_sens(v: &View, phase: crate::phase::PhaseFunction, i: usize) -> f64 {
    let (a, t) = (v.x(i + 1), v.x(i));
    let from = if i + 1 == v.k { a.wo } else { (v.x(i + 2).x - a.x).normalize_or_zero() };
    let d = t.x - a.x;
    let d2 = d.length_squared().max(1e-12);
    phase.pdf(from, d / d2.sqrt()) as f64 * t.sigma_t as f64 / d2 as f64
}

fn weight(v: &View, phase: crate::phase::PhaseFunction, set: &P2pSettings) -> f32 {
    let (s, k) = (v.s, v.k);
    let max_t = set.max_sensor_vertices as usize;
    let power = |r: f64| match set.heuristic {
        MisHeuristic::Balance => r,
        MisHeuristic::Power => r * r,
    };
    let mut sum = 1.0f64;
    // Fewer emitter vertices: x_{s'+1} .. x_s from the sensor side.
    let mut ratio = 1.0;
    for sp in (0..s).rev() {
        if k - 1 - sp > max_t {
            break;
        }
        ratio *= q_sens(v, phase, sp + 1) / q_emit(v, phase, sp + 1);
        sum += power(ratio);
    }
    // More emitter vertices: x_{s+1} .. x_{s'} from the emitter side.
    let mut ratio = 1.0;
    for sp in s + 1..k {
        ratio *= q_emit(v, phase, sp) / q_sens(v, phase, sp);
        sum += power(ratio);
    }
    let w = 1.0 / sum;
    if w.is_finite() { w as f32 } else { 0.0 }
}

/// Builds a subpath from `x` (interior vertices only; the end point itself is
/// vertex 0) into `out`, returns its length including vertex 0.
fn subpath(medium: &Medium, x: Vec3, wo: Vec3, max: usize, rng: &mut Rng, out: &mut [Vertex]) -> usize {
    out[0] = Vertex { x, wo, beta: 1.0, sigma_t: medium.sigma_t(x) };
    let (mut x, mut wo, mut beta) = (x, wo, 1.0f32);
    let mut len = 1;
    while len <= max {
        if !roulette(len as u32 - 1, &mut beta, rng) {
            break;
        }
        let Ok(next) = medium.scatter(x, wo, rng) else { break };
        (x, wo) = next;
        beta *= medium.albedo();
        if beta <= 0.0 {
            break;
        }
        out[len] = Vertex { x, wo, beta, sigma_t: medium.sigma_t(x) };
        len += 1;
    }
    len
}

/// One sample of T, with every weighted contribution reported with its number of
/// segments (their sum is the sample).
pub fn sample_transport_by_segments(
    medium: &Medium,
    q: &P2pQuery,
    set: &P2pSettings,
    rng: &mut Rng,
    sink: &mut impl FnMut(u32, f32),
) {
    let phase = medium.phase();
    let max_t = set.max_sensor_vertices.min(MAX_SENSOR_VERTICES) as usize;
    let max_k = set.max_segments.unwrap_or(u32::MAX) as usize;
    let mut sens = [Vertex::default(); MAX_SENSOR_VERTICES as usize + 1];
    let n_sens = subpath(medium, q.sensor, q.omega_s, max_t.min(max_k.saturating_sub(1)), rng, &mut sens);
    let g_ref = 1.0 / (q.emitter - q.sensor).length_squared().max(1e-12);
    let p_ref = INV_4PI * INV_4PI;
    let mut emit = [Vertex::default(); RING];
    emit[0] = Vertex { x: q.emitter, wo: q.omega_e, beta: 1.0, sigma_t: medium.sigma_t(q.emitter) };
    let (mut x, mut wo, mut beta) = (q.emitter, q.omega_e, 1.0f32);
    let mut s = 0usize;
    loop {
        // Connect emitter vertex s to every sensor vertex t.
        for t in 0..n_sens {
            let k = s + t + 1;
            if k > max_k {
                break;
            }
            let z = &sens[t];
            let dv = z.x - x;
            let d2 = dv.length_squared();
            if d2 <= 1e-12 {
                continue;
            }
            let dist = d2.sqrt();
            let dir = dv / dist;
            let (fe, fs) = (phase.eval(wo, dir), phase.eval(z.wo, -dir));
            let mut f = beta * z.beta * fe * fs / d2;
            let keep = match set.scheme {
                ConnectionScheme::All => 1.0,
                ConnectionScheme::Rr1 => (fe * fs / p_ref).min(1.0),
                ConnectionScheme::Rr2 => (fe * fs / p_ref * (1.0 / d2) / g_ref).min(1.0),
            };
            if keep < 1.0 {
                if !(keep > 0.0) || rng.uniform() >= keep {
                    continue;
                }
                f /= keep;
            }
            if !(f > 0.0 && f.is_finite()) {
                continue;
            }
            let tr = medium.transmittance_ratio(x, dir, dist, rng);
            if tr <= 0.0 {
                continue;
            }
            let w = if k == 1 { 1.0 } else { weight(&View { emit: &emit, sens: &sens[..n_sens], s, k }, phase, set) };
            sink(k as u32, f * tr * w);
        }
        if s + 1 >= max_k {
            return;
        }
        if !roulette(s as u32, &mut beta, rng) {
            return;
        }
        let Ok(next) = medium.scatter(x, wo, rng) else { return };
        (x, wo) = next;
        beta *= medium.albedo();
        if beta <= 0.0 {
            return;
        }
        s += 1;
        emit[s % RING] = Vertex { x, wo, beta, sigma_t: medium.sigma_t(x) };
    }
}

/// An end point of a data point's query (thesis 6.3, steps 1-2): a walk of `k`
/// segments entering the medium from a uniformly random point and direction on a
/// sphere around it (the first segment ending at its first real collision), its
/// last vertex and the direction back toward the vertex before. None when the walk
/// left the medium first (the caller draws again).
pub fn sample_query_end(medium: &Medium, k: u32, rng: &mut Rng) -> Option<(Vec3, Vec3)> {
    let b = medium.bounds();
    let (center, radius) = (b.center(), 0.5 * b.extent().length() * 1.01 + 1e-4);
    let o = center + radius * crate::sampling::sample_uniform_sphere(rng.uniform2());
    // Inward: uniform over the hemisphere facing the centre.
    let mut d = crate::sampling::sample_uniform_sphere(rng.uniform2());
    if d.dot(center - o) < 0.0 {
        d = -d;
    }
    let FreeFlight::Collision { t } = medium.sample_free_flight(o, d, f32::INFINITY, rng) else { return None };
    let (mut x, mut wo) = (o + d * t, -d);
    for _ in 1..k.max(1) {
        let wi = medium.phase().sample(wo, rng.uniform2()).wi;
        let FreeFlight::Collision { t } = medium.sample_free_flight(x, wi, f32::INFINITY, rng) else { return None };
        x += wi * t;
        wo = -wi;
    }
    Some((x, wo))
}

/// One sample of T(x_e, w_e <-> x_s, w_s).
pub fn sample_transport(medium: &Medium, q: &P2pQuery, set: &P2pSettings, rng: &mut Rng) -> f32 {
    let mut sum = 0.0;
    sample_transport_by_segments(medium, q, set, rng, &mut |_, v| sum += v);
    sum
}

/// The point-to-point estimator as a [`TransportPredictor`]: one sample of T
/// per query. Unbiased, so BDPT's prediction mode with it is exact; it is the
/// thesis's own baseline for the speedup of table 6.3 (the same two k-segment
/// subpaths, the transport between them "by the bidirectional path tracer used for
/// the ground truth" instead of the network).
#[derive(Clone, Copy, Debug, Default)]
pub struct EstimatedTransport {
    pub settings: P2pSettings,
}

impl TransportPredictor for EstimatedTransport {
    fn predict(&self, medium: &Medium, q: &P2pQuery, rng: &mut Rng) -> f32 {
        sample_transport(medium, q, &self.settings, rng)
    }

    fn name(&self) -> &str {
        "point-to-point estimator (one sample)"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phase::PhaseFunction;

    /// The weights of all strategies that can make a k-segment path sum to one.
    #[test]
    fn weights_sum_to_one() {
        let mut rng = Rng::new(9, 0, 0);
        let phase = PhaseFunction::HenyeyGreenstein { g: 0.5 };
        for heuristic in [MisHeuristic::Balance, MisHeuristic::Power] {
            for max_t in [0u32, 1, 3, 8] {
                let set = P2pSettings { heuristic, max_sensor_vertices: max_t, ..Default::default() };
                for k in 2..=12usize {
                    let pts: Vec<Vertex> = (0..=k)
                        .map(|_| Vertex {
                            x: Vec3::from_array(std::array::from_fn(|_| rng.uniform())),
                            wo: crate::sampling::sample_uniform_sphere(rng.uniform2()),
                            beta: 1.0,
                            sigma_t: 0.5 + 5.0 * rng.uniform(),
                        })
                        .collect();
                    let mut total = 0.0f64;
                    for s in 0..k {
                        let t = k - 1 - s;
                        if t > max_t as usize {
                            continue;
                        }
                        let mut emit = [Vertex::default(); RING];
                        for (i, p) in pts.iter().enumerate().take(s + 1) {
                            emit[i] = *p;
                        }
                        // Sensor subpath: index j is x_{k-j}; x_k keeps its own w_s.
                        let sens: Vec<Vertex> = (0..=t).map(|j| pts[k - j]).collect();
                        total += weight(&View { emit: &emit, sens: &sens, s, k }, phase, &set) as f64;
                    }
                    assert!((total - 1.0).abs() < 1e-4, "k {k} max_t {max_t} {heuristic:?}: {total}");
                }
            }
        }
    }
}
