//! BDPT's prediction mode (thesis 6.4): the [`Prediction`] settings, the pass's pool
//! of light subpaths, the resampled choice of the light end vertex, and predictions
//! deferred to a batch. The [`super`] module documentation describes the estimator.

use super::subpath::{BdptSettings, Contribution, LightPath, MAX_LIGHT_VERTICES, Strategy, Vertex, light_path};
use crate::integrator::base::PathSample;
use crate::integrator::p2p::{P2pSettings, sample_transport_by_segments};
use crate::light::Sun;
use crate::medium::Medium;
use crate::predictor::{P2pQuery, TransportPredictor};
use crate::rng::Rng;
use crate::sampling::INV_4PI;
use crate::scene::Scene;
use glam::Vec3;
use std::sync::Arc;

/// BDPT's prediction mode (thesis 6.4; see the [`super`] module documentation).
#[derive(Clone)]
pub struct Prediction {
    pub predictor: Arc<dyn TransportPredictor>,
    /// Segments of each subpath, the thesis's k (1 ..= MAX_LIGHT_VERTICES).
    pub segments: u32,
    /// Distance threshold r: closer end vertices are extended, not predicted.
    pub r: f32,
    /// Probability of evaluating the high-order term, (0, 1]; weighted 1/p.
    pub p: f32,
    /// Light subpaths offered to each camera end vertex (>= 1): the sample's own and
    /// `candidates - 1` more, one of them chosen by resampling (module docs). 1 is
    /// the thesis's pairing.
    pub candidates: u32,
    /// Point-to-point samples averaged for a pair closer than r (>= 1; module docs).
    pub extension_samples: u32,
}

impl std::fmt::Debug for Prediction {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Prediction")
            .field("predictor", &self.predictor.name())
            .field("segments", &self.segments)
            .field("r", &self.r)
            .field("p", &self.p)
            .field("candidates", &self.candidates)
            .field("extension_samples", &self.extension_samples)
            .finish()
    }
}

impl Prediction {
    /// The default distance threshold r: 0.04, one mean free path at rho = 25, half
    /// the thesis's [`Prediction::THESIS_R`] (docs/point-to-point.md measures both).
    pub const DEFAULT_R: f32 = 0.04;
    /// The thesis's distance threshold (0.08, about two mean free paths at rho = 25).
    pub const THESIS_R: f32 = 0.08;
    /// Light subpath candidates per camera end vertex by default. Picked from the
    /// pass's pool, a candidate costs a weight, not a subpath (docs/point-to-point.md
    /// measures 8 to 1024).
    pub const DEFAULT_CANDIDATES: u32 = 256;
    /// At most this many candidates.
    pub const MAX_CANDIDATES: u32 = 4096;
    /// Point-to-point samples per extended pair by default (docs/point-to-point.md
    /// measures 1 to 16).
    pub const DEFAULT_EXTENSION_SAMPLES: u32 = 8;
    /// At most this many extension samples.
    pub const MAX_EXTENSION_SAMPLES: u32 = 256;
    /// The close-pair resampling target's floor, as a fraction of r (module docs).
    pub const CLOSE_TARGET_FLOOR: f32 = 0.125;

    /// The first order the high buffer holds: 2k + 1.
    pub fn first_predicted_order(&self) -> u32 {
        2 * self.segments + 1
    }

    pub fn validate(&self) -> Result<(), String> {
        if !(1..=MAX_LIGHT_VERTICES).contains(&self.segments) {
            return Err(format!(
                "BDPT prediction needs 1 ..= {MAX_LIGHT_VERTICES} segments per subpath, got {}",
                self.segments
            ));
        }
        // r = infinity extends every pair: exact, and the check of the extension.
        if !(self.r >= 0.0) {
            return Err(format!("distance threshold r must be >= 0, got {}", self.r));
        }
        if !(self.p > 0.0 && self.p <= 1.0) {
            return Err(format!("prediction probability p must lie in (0, 1], got {}", self.p));
        }
        if !(1..=Self::MAX_CANDIDATES).contains(&self.candidates) {
            return Err(format!(
                "light subpath candidates must lie in 1 ..= {}, got {}",
                Self::MAX_CANDIDATES,
                self.candidates
            ));
        }
        if !(1..=Self::MAX_EXTENSION_SAMPLES).contains(&self.extension_samples) {
            return Err(format!(
                "extension samples must lie in 1 ..= {}, got {}",
                Self::MAX_EXTENSION_SAMPLES,
                self.extension_samples
            ));
        }
        Ok(())
    }
}

/// The end vertices of light subpaths that the camera samples of one pass share as
/// resampling candidates in prediction mode (the [`super`] module
/// documentation, "light subpath candidates"). Each subpath is traced like a sample's own, k segments, with a
/// random stream of its own and independently of every camera sample, so a uniform
/// pick from the pool is distributed as an own subpath's end; a subpath that ends
/// early (absorbed, escaped, roulette) stays in the count as a candidate of weight 0.
#[derive(Clone, Debug, Default)]
pub struct LightPool {
    /// End vertices of the subpaths that reached k segments, with their beam area.
    ends: Vec<(Vertex, f32)>,
    /// Subpaths traced, the failed ones included.
    traced: u32,
}

impl LightPool {
    /// The most subpaths a pool holds (2.3 MB); with more samples per pass, few of
    /// them share a candidate already.
    pub const MAX_LEN: u32 = 1 << 16;

    /// Traces `n` light subpaths of `pr.segments` segments in parallel, subpath i
    /// with the stream `stream(i)`, so the pool does not depend on the thread count
    /// (empty without a sun).
    pub fn trace(
        b: &BdptSettings,
        pr: &Prediction,
        scene: &Scene,
        n: u32,
        stream: impl Fn(u32) -> Rng + Sync,
    ) -> LightPool {
        use rayon::prelude::*;
        let Some(sun) = &scene.sun else { return LightPool::default() };
        let capped = BdptSettings { max_light_vertices: pr.segments, ..*b };
        let k = pr.segments as usize;
        let ends = (0..n)
            .into_par_iter()
            .with_min_len(64)
            .filter_map(|i| {
                let lp = light_path(&capped, scene, sun, &mut stream(i));
                (lp.len == k).then(|| (lp.verts[k - 1], lp.area))
            })
            .collect();
        LightPool { ends, traced: n }
    }

    /// Subpaths traced (the failed ones included).
    pub fn len(&self) -> usize {
        self.traced as usize
    }

    pub fn is_empty(&self) -> bool {
        self.traced == 0
    }

    /// A uniformly chosen subpath's end vertex and beam area, or None if the chosen
    /// one ended early (or the pool is empty). Index i < n is taken as the i-th
    /// successful subpath if there are more than i, else as a failed one: the
    /// subpaths are exchangeable (i.i.d. and traced apart from the camera samples),
    /// so which ones failed does not matter, only how many. The index is a 32-bit
    /// draw scaled by multiplication, so no index's probability is off 1 / n by more
    /// than n / 2^32 of itself (scaling a 24-bit float would allow 1 part in
    /// 2^24 / n); being content-blind, no pick biases the estimate either way.
    fn pick(&self, rng: &mut Rng) -> Option<(Vertex, f32)> {
        if self.traced == 0 {
            return None;
        }
        let i = ((rng.next_u32() as u64 * self.traced as u64) >> 32) as usize;
        self.ends.get(i).copied()
    }
}

/// The high orders of one camera sample in prediction mode, at camera end vertex x
/// (leaving toward `wo`, throughput `beta`); `lp` is the sample's light subpath and
/// `t1_own` the one-segment term x <-> its end vertex already estimated for the low
/// buffer (the path of order 2k, which BDPT makes).
///
/// The end vertex y is chosen among the sample's own light subpath and
/// `candidates - 1` more (picks from `pool`, or subpaths of their own without one)
/// by resampled importance sampling: candidate j
/// with probability w_j / sum w, w_j = beta_j A f_p(wo, y_j) f_p(y_j) g(d_j), g the
/// unoccluded one-segment term's 1 / d^2 from r on and 1 / (r max(d, r / 8)) below
/// (continuous at r; the transport between close points grows like 1 / d), weighted
/// sum w / (M w_j). That is the M-candidate average of the thesis's estimator, so it
/// stays unbiased for any M, while pairs whose transport is large (near ones) are
/// picked more often than pairs it is small for: the pairing's variance, which
/// dominates frontlit, falls at the cost of M - 1 weights (with a pool) or light
/// subpaths (without), not M predictions.
#[allow(clippy::too_many_arguments)]
pub(super) fn predict_high(
    pr: &Prediction,
    b: &BdptSettings,
    scene: &Scene,
    sun: &Sun,
    lp: &LightPath,
    x: Vec3,
    wo: Vec3,
    beta: f32,
    t1_own: f32,
    rng: &mut Rng,
    pool: Option<&LightPool>,
    deferred: Option<&mut Vec<DeferredPrediction>>,
    sink: &mut impl FnMut(Contribution),
) {
    let medium = &scene.medium;
    let phase = medium.phase();
    let k = pr.segments as usize;
    let first = pr.first_predicted_order();
    // The clamp distance: r, or with r = infinity (every pair extended) the cloud's
    // diagonal D, which no pair exceeds (then the target is 1 / (D max(d, D / 8))).
    let clamp = pr.r.min(medium.bounds().extent().length()).max(1e-6);
    let (clamp2, floor) = (clamp * clamp, Prediction::CLOSE_TARGET_FLOOR * clamp);
    // The resampling weight of a light subpath's end vertex y (beam area `area`).
    let weight_of = |y: &Vertex, area: f32| -> f32 {
        let dv = y.x - x;
        let d2 = dv.length_squared();
        let dir = if d2 > 0.0 { dv / d2.sqrt() } else { wo };
        // Floored so that no candidate whose transport may be non-zero gets weight 0
        // (resampling stays unbiased only then): a phase value of 0 on the direct
        // segment leaves the paths that scatter in between.
        let phases = (phase.eval(wo, dir) * phase.eval(y.wo, -dir)).max(1e-3 * INV_4PI * INV_4PI);
        // 1 / d^2 clamped at r, and below r 1 / (r max(d, r / 8)): the transport
        // between two close points grows like 1 / d, and a flat target there left
        // the few closest pairs, chosen rarely, to carry large values (module docs).
        let geometry = if d2 >= clamp2 { 1.0 / d2 } else { 1.0 / (clamp * d2.sqrt().max(floor)) };
        let w = y.beta * area * phases * geometry;
        if w.is_finite() { w } else { 0.0 }
    };
    // The same for a whole subpath (0 if it is shorter than k).
    let weight = |l: &LightPath| -> (f32, Vertex) {
        if l.len != k {
            return (0.0, Vertex::default());
        }
        let y = l.verts[k - 1];
        (weight_of(&y, l.area), y)
    };
    let (w_own, y_own) = weight(lp);
    let (mut total, mut chosen) = (w_own, (w_own > 0.0).then_some((y_own, lp.area, w_own, true)));
    // Streaming resampling: keep each newcomer with probability w / total.
    let mut offer = |w: f32, y: Vertex, area: f32, rng: &mut Rng| {
        if w > 0.0 {
            total += w;
            if chosen.is_none() || rng.uniform() * total < w {
                chosen = Some((y, area, w, false));
            }
        }
    };
    // Candidates besides the sample's own subpath, and so M in sum w / (M w_j).
    let others = pr.candidates as usize - 1;
    let m = match pool {
        // A pool no larger than the candidates asked for: every subpath in it once
        // (each is distributed as an own subpath, so M counts them all, the failed
        // ones, shorter than k, included with weight 0).
        Some(pool) if others >= pool.len() => {
            for &(y, area) in &pool.ends {
                offer(weight_of(&y, area), y, area, rng);
            }
            1 + pool.len()
        }
        // Otherwise uniform picks from it, with replacement.
        Some(pool) => {
            for _ in 0..others {
                if let Some((y, area)) = pool.pick(rng) {
                    offer(weight_of(&y, area), y, area, rng);
                }
            }
            pr.candidates as usize
        }
        // Without a pool, a subpath of its own for each candidate.
        None => {
            for _ in 0..others {
                let other = light_path(b, scene, sun, rng);
                let (w, y) = weight(&other);
                offer(w, y, other.area, rng);
            }
            pr.candidates as usize
        }
    };
    let Some((y, area, w, own)) = chosen else { return };
    let q = P2pQuery { emitter: y.x, omega_e: y.wo, sensor: x, omega_s: wo };
    // With M = 1, total / (M w) = 1: the thesis's estimator.
    let scale = beta * y.beta * area * (total / (m as f32 * w)) / pr.p;
    let dist = (y.x - x).length();
    let (strategy, t_multi) = if dist >= pr.r {
        // The one-segment term to leave out (it is order 2k, in the low buffer): the
        // sample's own was estimated with its connection; another's is estimated here.
        let t1 = if own {
            t1_own
        } else {
            let dir = (y.x - x) / dist;
            let segment = phase.eval(wo, dir) * phase.eval(y.wo, -dir) / (dist * dist);
            segment * medium.transmittance_ratio(x, dir, dist, rng)
        };
        // The prediction's own stream, split off the path's, so that evaluating it
        // now or with its tile gives the same answer.
        let mut stream = prediction_stream(rng);
        if let Some(list) = deferred {
            list.push(DeferredPrediction { query: q, rng: stream, scale: sun.radiance() * scale, t1, owner: 0 });
            // Nothing to add now: the value arrives with the batch.
            return;
        }
        (Strategy::Predicted, pr.predictor.predict(medium, &q, &mut stream) - t1)
    } else {
        let mut t = 0.0f32;
        let n = pr.extension_samples.max(1);
        for _ in 0..n {
            sample_transport_by_segments(medium, &q, &P2pSettings::default(), rng, &mut |k, v| {
                if k >= 2 {
                    t += v
                }
            });
        }
        (Strategy::Extended, t / n as f32)
    };
    let value = sun.radiance() * (scale * t_multi);
    if value.is_finite() {
        sink(Contribution { order: first, strategy, value, weight: 1.0 });
    }
}

/// A prediction of BDPT's prediction mode left for the caller to evaluate with
/// others (a tile's worth) through [`TransportPredictor::predict_batch`]: the sample
/// it belongs to gains `scale * (T - t1)` in its high buffer, T the prediction for
/// `query` with stream `rng`. `t1` is the one-segment term already in the low buffer.
#[derive(Clone, Debug)]
pub struct DeferredPrediction {
    pub query: P2pQuery,
    pub rng: Rng,
    pub scale: Vec3,
    pub t1: f32,
    /// The caller's tag: which sample it belongs to.
    pub owner: u32,
}

impl DeferredPrediction {
    /// What the prediction `t` adds to the high buffer (zero if not finite).
    pub fn value(&self, t: f32) -> Vec3 {
        let v = self.scale * (t - self.t1);
        if v.is_finite() { v } else { Vec3::ZERO }
    }
}

/// The random stream of one prediction, split off the path's stream `rng` (two
/// draws from it seed a new PCG stream in a family of its own).
fn prediction_stream(rng: &mut Rng) -> Rng {
    let seed = rng.next_u32() as u64 | (rng.next_u32() as u64) << 32;
    Rng::new(seed, 0x7072_6564, 0)
}

/// Evaluates `deferred` in one batch and adds each value to the high buffer of
/// `samples[owner]`.
pub fn resolve_deferred(
    predictor: &dyn TransportPredictor,
    medium: &Medium,
    deferred: &mut [DeferredPrediction],
    samples: &mut [PathSample],
) {
    if deferred.is_empty() {
        return;
    }
    let queries: Vec<P2pQuery> = deferred.iter().map(|d| d.query).collect();
    let mut rngs: Vec<Rng> = deferred.iter().map(|d| d.rng.clone()).collect();
    let mut t = vec![0.0f32; deferred.len()];
    predictor.predict_batch(medium, &queries, &mut rngs, &mut t);
    for (d, t) in deferred.iter().zip(t) {
        samples[d.owner as usize].high += d.value(t);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phase::PhaseFunction;

    /// A predictor that is never asked: the tests below read the deferred queries.
    struct Unasked;
    impl TransportPredictor for Unasked {
        fn predict(&self, _: &crate::medium::Medium, _: &P2pQuery, _: &mut Rng) -> f32 {
            unreachable!("predictions are deferred in these tests")
        }
    }

    /// A homogeneous unit cube (isotropic, so every resampling weight is
    /// beta * area / d^2 with the same phase factor) and a sun.
    fn cube_scene(phase: PhaseFunction) -> (Scene, crate::light::Sun) {
        let bounds = crate::grid::Bounds3::new(Vec3::ZERO, Vec3::ONE);
        let grid = crate::grid::DensityGrid::from_fn(glam::UVec3::splat(4), bounds, |_| 1.0).unwrap();
        let medium = crate::medium::Medium::new(Arc::new(grid), 10.0, 0.9, phase).unwrap();
        let sun = crate::light::Sun::new(Vec3::new(0.0, 0.0, -1.0), Vec3::ONE, 0.0).unwrap();
        let camera =
            crate::camera::Camera::new(Vec3::new(0.5, 0.5, -3.0), Vec3::splat(0.5), Vec3::Y, 30.0, 4, 4).unwrap();
        let scene = Scene { medium, sun: Some(sun), sky: crate::light::Sky::default(), camera };
        (scene, sun)
    }

    /// The light end vertex at `x` with throughput `beta`, as a one-segment subpath.
    fn light_end(x: Vec3, beta: f32) -> Vertex {
        Vertex { x, wo: Vec3::Z, beta, sigma_t: 10.0 }
    }

    /// What the high-order term of one camera end vertex did.
    enum Outcome {
        /// A far pair, deferred: the prediction's scale (one channel) and emitter.
        Predicted(f32, Vec3),
        /// A pair closer than r, extended.
        Extended,
        /// No candidate with a non-zero weight.
        Nothing,
    }

    /// Runs the high-order term of one camera end vertex (at (0.5, 0.5, 0.1), far
    /// enough from every light end vertex these callers use to be predicted) with M
    /// candidates and `pool`; returns the deferred prediction's scale (one channel)
    /// and its emitter.
    fn resampled(
        cube: &(Scene, crate::light::Sun),
        m: u32,
        own: Vertex,
        pool: Option<&LightPool>,
        rng: &mut Rng,
    ) -> Option<(f32, Vec3)> {
        match resampled_with(cube, m, (own, 2.0), pool, rng) {
            Outcome::Predicted(scale, emitter) => Some((scale, emitter)),
            Outcome::Extended => panic!("a far pair is predicted, not extended"),
            Outcome::Nothing => None,
        }
    }

    /// The high-order term of the camera end vertex at (0.5, 0.5, 0.1) with the own
    /// subpath's beam area given.
    fn resampled_with(
        (scene, sun): &(Scene, crate::light::Sun),
        m: u32,
        (own, area): (Vertex, f32),
        pool: Option<&LightPool>,
        rng: &mut Rng,
    ) -> Outcome {
        let pr = Prediction {
            predictor: Arc::new(Unasked),
            segments: 1,
            r: 0.08,
            p: 1.0,
            candidates: m,
            extension_samples: 1,
        };
        let mut lp =
            LightPath { verts: [Vertex::default(); MAX_LIGHT_VERTICES as usize], len: 1, beam: -Vec3::Z, area };
        lp.verts[0] = own;
        let mut deferred = vec![];
        let mut extended = false;
        let x = Vec3::new(0.5, 0.5, 0.1);
        predict_high(
            &pr,
            &BdptSettings::default(),
            scene,
            sun,
            &lp,
            x,
            Vec3::Y,
            0.5,
            0.0,
            rng,
            pool,
            Some(&mut deferred),
            &mut |c| {
                assert_eq!(c.strategy, Strategy::Extended, "only a close pair reaches the sink now");
                extended = true;
            },
        );
        assert!(deferred.len() <= 1);
        match (deferred.first(), extended) {
            (Some(d), false) => Outcome::Predicted(d.scale.x, d.query.emitter),
            (None, true) => Outcome::Extended,
            (None, false) => Outcome::Nothing,
            (Some(_), true) => panic!("one pair per camera vertex, predicted or extended"),
        }
    }

    /// White-box check of the resampling weight sum w / (M w_chosen): M counts every
    /// candidate, the failed subpaths in the pool included. With every candidate
    /// equal to the sample's own the weight is exactly 1 (both pool branches); with
    /// failed ones it is (1 + successes) / M. A miscounted M (say 16 for 13) moves it
    /// far beyond rounding.
    #[test]
    fn resampling_weight_counts_every_candidate() {
        let own = light_end(Vec3::new(0.5, 0.5, 0.9), 0.3);
        let cube = cube_scene(PhaseFunction::Isotropic);
        let mut rng = Rng::new(11, 0, 0);
        let (alone, _) = resampled(&cube, 1, own, None, &mut rng).unwrap();
        // beta * y.beta * area / p, times total / (M w) = 1.
        assert!((alone - 0.5 * 0.3 * 2.0).abs() < 1e-6, "{alone}");
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-5 * b.abs();
        for (traced, successes) in [(12u32, 12usize), (12, 0), (12, 5), (300, 300), (300, 0)] {
            let pool = LightPool { ends: vec![(own, 2.0); successes], traced };
            // M - 1 >= the pool: all entries once, M = 1 + traced.
            let whole = resampled(&cube, traced + 4, own, Some(&pool), &mut rng).unwrap().0;
            let want = alone * (1 + successes) as f32 / (1 + traced) as f32;
            assert!(close(whole, want), "all of {traced} ({successes} successful): {whole} vs {want}");
            // Fewer candidates than the pool holds: uniform picks, M as asked.
            if successes == 0 || successes == traced as usize {
                let m = 8;
                let picked = resampled(&cube, m, own, Some(&pool), &mut rng).unwrap().0;
                let want = if successes == 0 { alone / m as f32 } else { alone };
                assert!(close(picked, want), "8 picked of {traced} ({successes} successful): {picked} vs {want}");
            }
        }
        // Picks from a half-failed pool: the weight is (1 + successful picks) / M, so
        // its mean over many draws is alone * (1 + (M - 1) / 2) / M.
        let pool = LightPool { ends: vec![(own, 2.0); 100], traced: 200 };
        let (m, n) = (9u32, 20_000);
        let mut stats = crate::stats::Welford::default();
        for _ in 0..n {
            let w = resampled(&cube, m, own, Some(&pool), &mut rng).unwrap().0 / alone * m as f32;
            let successes = w.round();
            assert!((w - successes).abs() < 1e-4 && (1.0..=m as f32).contains(&successes), "{w}");
            stats.add(successes as f64 - 1.0);
        }
        // Successful picks ~ Binomial(8, 1/2): mean 4, standard error sqrt(2 / n).
        let z = (stats.mean - 4.0) / (2.0f64 / n as f64).sqrt();
        assert!(z.abs() < crate::stats::z_bound(0.001, 1), "successful picks {} vs 4: z = {z:.2}", stats.mean);
    }

    /// Which candidate is chosen: with the whole pool offered, candidate i is taken
    /// with probability w_i / sum w (a chi-square test over 6 candidates of unequal
    /// weight: throughputs, beam areas, distances and, with a forward-scattering phase
    /// function, the phase terms of the direct segment all differ), and the weight sum
    /// w / (M w_i) matches the chosen one. One candidate lies closer than r: once
    /// between r / 8 and r (target 1 / (r d)), once below r / 8 (1 / (r r / 8)); it
    /// is extended when chosen, so it is counted by the extension.
    #[test]
    fn resampling_chooses_in_proportion_to_the_weights() {
        let x = Vec3::new(0.5, 0.5, 0.1);
        let wo = Vec3::Y;
        let r = 0.08f64;
        for close in [Vec3::new(0.5, 0.47, 0.14), Vec3::new(0.5, 0.5, 0.104)] {
            // (position, throughput, beam area); the first five farther from x than r.
            let ends: Vec<(Vertex, f32)> = [
                (Vec3::new(0.5, 0.5, 0.9), 0.3, 2.0),
                (Vec3::new(0.5, 0.2, 0.7), 0.3, 1.0),
                (Vec3::new(0.9, 0.5, 0.5), 1.0, 3.0),
                (Vec3::new(0.5, 0.8, 0.95), 2.0, 0.5),
                (Vec3::new(0.2, 0.6, 0.6), 0.05, 4.0),
                (close, 0.004, 1.0),
            ]
            .iter()
            .map(|&(p, beta, area)| (light_end(p, beta), area))
            .collect();
            chooses_in_proportion(x, wo, r, &ends);
        }
    }

    fn chooses_in_proportion(x: Vec3, wo: Vec3, r: f64, ends: &[(Vertex, f32)]) {
        let n_ends = ends.len();
        for phase in [PhaseFunction::Isotropic, PhaseFunction::HenyeyGreenstein { g: 0.6 }] {
            let cube = cube_scene(phase);
            // w_i = beta_i area_i phase(wo, dir) phase(wo_i, -dir) g(d_i), dir from x
            // toward y_i (none of these phase products is near the floor), g = 1 / d^2
            // from r on, 1 / (r max(d, r / 8)) below.
            let w: Vec<f64> = ends
                .iter()
                .map(|(v, area)| {
                    let d = v.x - x;
                    let dir = d.normalize();
                    let phases = phase.eval(wo, dir) as f64 * phase.eval(v.wo, -dir) as f64;
                    assert!(phases > 1e-3 * (INV_4PI as f64).powi(2));
                    let dist = d.length() as f64;
                    let g = if dist >= r { 1.0 / (dist * dist) } else { 1.0 / (r * dist.max(r / 8.0)) };
                    v.beta as f64 * *area as f64 * phases * g
                })
                .collect();
            let total: f64 = w.iter().sum();
            let pool = LightPool { ends: ends[1..].to_vec(), traced: n_ends as u32 - 1 };
            let mut rng = Rng::new(12, 0, 0);
            let n = 40_000;
            let mut counts = vec![0.0f64; n_ends];
            for _ in 0..n {
                let (scale, emitter) = match resampled_with(&cube, n_ends as u32, ends[0], Some(&pool), &mut rng) {
                    Outcome::Predicted(scale, emitter) => (scale, emitter),
                    // The close pair (the only one closer than r).
                    Outcome::Extended => {
                        counts[n_ends - 1] += 1.0;
                        continue;
                    }
                    Outcome::Nothing => panic!("every candidate has a non-zero weight"),
                };
                let i = ends.iter().position(|(v, _)| v.x == emitter).expect("the emitter is a candidate");
                counts[i] += 1.0;
                // scale = beta (0.5) * y.beta * area_i * total / (M w_i) / p.
                let want = 0.5 * ends[i].0.beta as f64 * ends[i].1 as f64 * total / (n_ends as f64 * w[i]);
                assert!((scale as f64 - want).abs() <= 1e-4 * want, "{phase:?}, candidate {i}: {scale} vs {want}");
            }
            let expected: Vec<f64> = w.iter().map(|wi| n as f64 * wi / total).collect();
            assert!(expected.iter().all(|e| *e > 100.0), "{expected:?}");
            let chi2 = crate::stats::chi2_test(&counts, &expected, 5.0);
            assert!(chi2.p_value > 1e-3, "{phase:?}: choices {counts:?} vs {expected:?}: {chi2:?}");
            // The close candidate's share is not negligible (the test sees its target).
            assert!(expected[n_ends - 1] > 0.05 * n as f64, "{expected:?}");
        }
    }
}
