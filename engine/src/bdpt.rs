//! Volumetric bidirectional path tracing (Veach 1997, ch. 10; Lafortune and Willems
//! 1996 for participating media) for the scenes of the path tracer: a heterogeneous
//! cloud in vacuum, a directional sun (optionally a small cone), a constant sky and
//! a pinhole camera.
//!
//! Each camera sample traces one light subpath and one camera subpath:
//! - the light subpath starts on a disk perpendicular to the sun's direction that
//!   covers the cloud's bounding sphere (a parallel beam, area pdf 1 / (pi R^2)) and
//!   scatters by delta tracking and phase sampling, up to `max_light_vertices`;
//! - the camera subpath is the path tracer's walk (delta tracking, phase sampling,
//!   Russian roulette on throughput) and at every vertex it does next event
//!   estimation toward the sun and, at its first `max_camera_connect` vertices,
//!   connects to every light vertex with a ratio-tracked transmittance.
//!
//! A path with n scattering vertices x_1 .. x_n can therefore come from n strategies,
//! told apart by c, the number of its vertices the camera walk made: c = n is next
//! event estimation, c < n connects x_c to the light vertex x_{c+1}. (Light tracing
//! onto the image, c = 0, is not used: it needs splatting into arbitrary pixels, and
//! in a cloud seen from outside it rarely helps. The sun is a delta light or a tiny
//! cone that only next event estimation reaches, as in the path tracer, so an
//! escaping camera path never hits it; the sky is reached only by escaping camera
//! paths, with weight one.)
//!
//! Multiple importance sampling weighs the strategies by the balance or power
//! heuristic. The heuristic's per-vertex densities leave out the transmittance of the
//! edge that sampled the vertex: in a heterogeneous medium it is unknown in closed
//! form. Any weights that are functions of the path alone and sum to one over the
//! strategies that can make it keep the estimator unbiased (Veach 1997, sec. 9.2), so
//! this costs variance at most, never bias; the densities kept (phase pdf, sigma_t at
//! the vertex, inverse squared distance) are the ones that make close connections and
//! grazing turns expensive. Strategies the caps exclude (camera depth above
//! `max_camera_connect`, light depth above `max_light_vertices`) get no weight.
//!
//! Every contribution keeps the path tracer's order bookkeeping: a path with n
//! scattering vertices is order n, and goes to the low or high buffer by k.
//!
//! **Prediction mode** (thesis 6.4, [`Prediction`]): the light subpath stops after k
//! segments (y_1 .. y_k) and BDPT makes exactly the orders 1 ..= 2k, into the low
//! buffer, with the MIS weights of that capped strategy set. The camera walk goes on
//! to x_{2k} for them: had it stopped at x_k like the light subpath, the order-2k
//! paths would have only one strategy, the connection x_k <-> y_k with its
//! unweighted 1/d^2, whose variance is infinite in a volume (the test against the
//! path tracer showed it); with the deeper walk, next event estimation and the other
//! connections share those paths. Every longer path is x_1 .. x_k, then at
//! least one vertex in between, then y_k .. y_1; their sum over the middle part is
//! the point-to-point transport T(y_k <-> x_k) minus its one-segment term (the
//! order-2k path, which BDPT already made). The high buffer therefore gets
//! L_sun beta_x beta_y A (T_pred - T_1), with T_pred from a [`TransportPredictor`]
//! and T_1 the one-segment term with the same ratio-tracked transmittance the 2k
//! connection used (unbiased, and correlated with it). So in this mode the buffers
//! split at order 2k + 1, not at k: low = 1 ..= 2k, high = 2k + 1 and up.
//! Pairs closer than the distance threshold r (default 0.04; the thesis's 0.08, about two mean
//! free paths at rho = 25) are not predicted: the 1/d^2 of the network's answer would
//! dominate the variance. There the subpaths are extended instead: the multi-segment
//! transport estimated by the bidirectional point-to-point estimator of
//! [`crate::p2p`], which walks on from both end vertices, averaged over
//! `Prediction::extension_samples` samples (default 8). (The thesis dropped these
//! pairs, a bias; extending keeps the estimate exact up to the network's error.)
//! Frontlit, where both subpaths stay near the lit face and close pairs are common,
//! these pairs held almost all of the prediction render's variance (96 % at r = 0.08,
//! measured in session 18), so they get more than one sample. The
//! high term is evaluated with probability p and weighted 1/p, as in the path tracer's
//! prediction mode. Like that mode, prediction covers the sun: sky light of orders above 2k
//! (camera walks that escape after x_{2k}) is not added.
//!
//! Two additions to the thesis's rendering, both keeping the estimate exact up to the
//! network's error:
//! - **Light subpath candidates** (`Prediction::candidates`, M). Joining each camera
//!   end vertex to the end of one random light subpath is a weak estimator: most
//!   pairs are far apart and carry almost nothing, a few near ones carry much. With
//!   M > 1 the camera end vertex is offered M light subpaths (its own and M - 1
//!   more, k segments each) and one is chosen by resampled importance sampling on
//!   the unoccluded one-segment term, its 1 / d^2 replaced below r by 1 / (r d)
//!   (floored at d = r / 8): the transport between two close points grows like
//!   1 / d, and a target flat below r left the closest pairs to be chosen rarely and
//!   weighted high. One prediction still serves one camera sample (`predict_high`).
//!   The renderer traces
//!   one pool of light subpaths per pass ([`LightPool`], one per pixel) and the M - 1
//!   are uniform picks from it, so a candidate costs a weight, not a subpath, and M
//!   can be large (default 256). Every candidate is still distributed as a sample's
//!   own subpath, so the estimate stays unbiased; what sharing costs is correlation:
//!   the samples of one pass share candidates, so their errors are not independent
//!   within the pass (passes are). With a pool no larger than M - 1 every subpath in
//!   it is taken once; without a pool (single samples outside the renderer) each
//!   candidate is a subpath of its own.
//! - **Batched predictions.** The renderer defers a tile's predictions
//!   ([`DeferredPrediction`], each with its own random stream) and asks the predictor
//!   for them at once ([`TransportPredictor::predict_batch`]), so that a network
//!   applies each weight to several rows while it is loaded; immediate and deferred
//!   evaluation give the same estimate.

use crate::integrator::{PathSample, RenderSettings, Scene, roulette};
use crate::medium::FreeFlight;
use crate::p2p::{P2pQuery, P2pSettings};
use crate::predictor::TransportPredictor;
use crate::rng::Rng;
use crate::sampling::{INV_4PI, coordinate_system, sample_uniform_disk};
use glam::Vec3;
use std::f32::consts::PI;
use std::sync::Arc;

/// How strategies are weighed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MisHeuristic {
    Balance,
    /// Exponent 2 (Veach's recommendation).
    Power,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BdptSettings {
    pub heuristic: MisHeuristic,
    /// Camera vertices 1 ..= this connect to the light subpath; deeper ones still do
    /// next event estimation and see the sky.
    pub max_camera_connect: u32,
    /// Scattering vertices of the light subpath (1 ..= MAX_LIGHT_VERTICES).
    pub max_light_vertices: u32,
}

impl Default for BdptSettings {
    fn default() -> Self {
        BdptSettings { heuristic: MisHeuristic::Power, max_camera_connect: 8, max_light_vertices: 8 }
    }
}

/// The largest light subpath (fixed storage, no allocation per sample).
pub const MAX_LIGHT_VERTICES: u32 = 32;
/// Camera vertices kept for the weights: the last RING of the walk.
const RING: usize = 64;
const _: () = assert!(RING >= MAX_LIGHT_VERTICES as usize + 4);

impl BdptSettings {
    pub fn validate(&self) -> Result<(), String> {
        if !(1..=MAX_LIGHT_VERTICES).contains(&self.max_light_vertices) {
            return Err(format!(
                "BDPT light subpath length must lie in 1 ..= {MAX_LIGHT_VERTICES}, got {}",
                self.max_light_vertices
            ));
        }
        if self.max_camera_connect < 1 {
            return Err("BDPT must connect at least the first camera vertex".into());
        }
        Ok(())
    }
}

/// BDPT's prediction mode (thesis 6.4; see the module documentation).
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
    /// The default distance threshold: 0.04, one mean free path at rho = 25, half the
    /// thesis's 0.08 ([`Prediction::THESIS_R`]). With 256 pooled candidates and the
    /// close-pair target, halving r doubled the speedups in every cell of the
    /// evaluation at the same bias (README, sessions 18 and 19).
    pub const DEFAULT_R: f32 = 0.04;
    /// The thesis's distance threshold (0.08, about two mean free paths at rho = 25).
    pub const THESIS_R: f32 = 0.08;
    /// Light subpath candidates per camera end vertex by default. Picked from the
    /// pass's pool, a candidate costs a weight, not a subpath. Measured on scene A at
    /// rho 25 (`nimbus eval p2p --size 64 --spp-ref 1024 --spp 256 --k 1,2,4
    /// --candidates M`, M = 8, 64, 256, 1024, backlit and frontlit): high-order TTUV
    /// fell with M up to 256 in all six cells, at M = 256 4.8-7.4x below the earlier
    /// default (8 candidates, each a subpath of its own); M = 1024 was within
    /// run-to-run scatter of 256 (1.4x better at backlit k = 1, 1.5x worse at k = 2,
    /// within 1.25x elsewhere) and its prediction renders took 12 % longer (README).
    pub const DEFAULT_CANDIDATES: u32 = 256;
    /// At most this many candidates.
    pub const MAX_CANDIDATES: u32 = 4096;
    /// Point-to-point samples per extended pair by default. Measured on scene A at
    /// rho 25, r = 0.04, 256 candidates (`nimbus eval p2p --size 96 --spp-ref 4096
    /// --spp 1024 --extension-samples N`, session 19, README): the close-pair
    /// resampling target with 4 samples, against the flat target with 1, cut the
    /// frontlit prediction render's TTUV 1.6-2.8x (64x64 study; 4 samples against 1
    /// with the same target: 1.6-1.7x), and 8 instead of 4 lowered it further in 21
    /// of the evaluation's 24 cells (three models; up to 1.25x), the estimated
    /// baseline's TTUV within -3 .. +8 %.
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

/// Which strategy made a contribution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Strategy {
    /// The camera ray left the cloud: the sky seen through it (order 0).
    Direct,
    /// The camera walk escaped to the sky after `order` scattering events.
    Sky,
    /// Next event estimation toward the sun from camera vertex `order` (c = n).
    NextEvent,
    /// Camera vertex `camera` connected to light vertex `light` (c + l = n).
    Connect { camera: u32, light: u32 },
    /// Prediction mode: the predicted transport between the subpaths' end vertices
    /// (all orders >= 2k + 1; `order` says 2k + 1).
    Predicted,
    /// Prediction mode, end vertices closer than r: the subpaths extended by the
    /// point-to-point estimator (all orders >= 2k + 1; `order` says 2k + 1).
    Extended,
}

/// One unweighted contribution of a strategy and its MIS weight.
#[derive(Clone, Copy, Debug)]
pub struct Contribution {
    pub order: u32,
    pub strategy: Strategy,
    pub value: Vec3,
    pub weight: f32,
}

#[derive(Clone, Copy, Debug, Default)]
struct Vertex {
    x: Vec3,
    /// Unit direction toward the vertex before it on its own subpath (or the sun).
    wo: Vec3,
    /// Throughput of the subpath up to and including this vertex's albedo.
    beta: f32,
    sigma_t: f32,
}

struct LightPath {
    verts: [Vertex; MAX_LIGHT_VERTICES as usize],
    len: usize,
    /// Direction the sun's light travels in (sampled within the sun's cone).
    beam: Vec3,
    /// Area of the beam's disk, pi R^2: the light vertices' throughputs are per unit
    /// sun radiance times this.
    area: f32,
}

/// The camera subpath's latest vertices, and the camera position as vertex 0.
struct CameraRing {
    origin: Vec3,
    verts: [Vertex; RING],
}

impl CameraRing {
    #[inline]
    fn get(&self, i: usize) -> &Vertex {
        &self.verts[i % RING]
    }
}

/// One full path for the weights: x_0 the camera, x_1 .. x_c from the camera walk,
/// x_{c+1} .. x_n the light walk's vertices l .. 1, and the direction toward the sun
/// at x_n.
struct PathView<'a> {
    cam: &'a CameraRing,
    light: Option<&'a LightPath>,
    c: usize,
    n: usize,
    to_sun: Vec3,
}

impl PathView<'_> {
    #[inline]
    fn vertex(&self, i: usize) -> (Vec3, f32) {
        if i == 0 {
            (self.cam.origin, 0.0)
        } else if i <= self.c {
            let v = self.cam.get(i);
            (v.x, v.sigma_t)
        } else {
            let v = &self.light.expect("a light vertex")[self.n - i];
            (v.x, v.sigma_t)
        }
    }
}

impl std::ops::Index<usize> for LightPath {
    type Output = Vertex;
    fn index(&self, i: usize) -> &Vertex {
        &self.verts[i]
    }
}

/// The heuristic's density of x_i sampled from x_{i-1} by the camera walk (i >= 2).
#[inline]
fn q_camera(p: &PathView, phase: crate::phase::PhaseFunction, i: usize) -> f64 {
    let (a, _) = p.vertex(i - 1);
    let (b, _) = p.vertex(i - 2);
    let (t, sigma) = p.vertex(i);
    let (to_prev, to_next) = (b - a, t - a);
    let d2 = to_next.length_squared().max(1e-12);
    let pdf = phase.pdf(to_prev.normalize_or_zero(), to_next / d2.sqrt());
    pdf as f64 * sigma as f64 / d2 as f64
}

/// The heuristic's density of x_i sampled by the light walk: from the beam's disk for
/// i = n, else from x_{i+1}.
#[inline]
fn q_light(p: &PathView, phase: crate::phase::PhaseFunction, area: f32, i: usize) -> f64 {
    let (t, sigma) = p.vertex(i);
    if i == p.n {
        return sigma as f64 / area as f64;
    }
    let (a, _) = p.vertex(i + 1);
    let from = if i + 1 == p.n { p.to_sun } else { (p.vertex(i + 2).0 - a).normalize_or_zero() };
    let to_next = t - a;
    let d2 = to_next.length_squared().max(1e-12);
    phase.pdf(from, to_next / d2.sqrt()) as f64 * sigma as f64 / d2 as f64
}

/// The MIS weight of strategy c for the path `p` (camera vertices 1 ..= c).
/// `max_depth` is the deepest camera vertex the walk makes (next event estimation
/// from x_n needs n <= max_depth; usize::MAX but in prediction mode).
fn mis_weight(p: &PathView, phase: crate::phase::PhaseFunction, area: f32, b: &BdptSettings, max_depth: usize) -> f32 {
    let (c, n) = (p.c, p.n);
    let (max_c, max_l) = (b.max_camera_connect as usize, b.max_light_vertices as usize);
    let power = |r: f64| match b.heuristic {
        MisHeuristic::Balance => r,
        MisHeuristic::Power => r * r,
    };
    let mut sum = 1.0f64;
    // Strategies with fewer camera vertices: x_{c'+1} .. x_c come from the light.
    let mut ratio = 1.0f64;
    for cp in (1..c).rev() {
        if n - cp > max_l {
            break;
        }
        ratio *= q_light(p, phase, area, cp + 1) / q_camera(p, phase, cp + 1);
        if cp <= max_c {
            sum += power(ratio);
        }
    }
    // Strategies with more camera vertices: x_{c+1} .. x_{c'} come from the camera.
    let mut ratio = 1.0f64;
    for cp in c + 1..=n {
        ratio *= q_camera(p, phase, cp) / q_light(p, phase, area, cp);
        if (cp == n && n <= max_depth) || cp <= max_c {
            sum += power(ratio);
        }
    }
    let w = 1.0 / sum;
    if w.is_finite() { w as f32 } else { 0.0 }
}

fn light_path(b: &BdptSettings, scene: &Scene, sun: &crate::light::Sun, rng: &mut Rng) -> LightPath {
    let medium = &scene.medium;
    let bounds = medium.bounds();
    let (center, radius) = (bounds.center(), 0.5 * bounds.extent().length() * 1.0001 + 1e-4);
    let beam = -sun.sample_wi(rng.uniform2());
    let (t1, t2) = coordinate_system(beam);
    let q = sample_uniform_disk(rng.uniform2()) * radius;
    let origin = center + t1 * q.x + t2 * q.y - beam * (1.01 * radius);
    let mut lp =
        LightPath { verts: [Vertex::default(); MAX_LIGHT_VERTICES as usize], len: 0, beam, area: PI * radius * radius };
    let FreeFlight::Collision { t } = medium.sample_free_flight(origin, beam, f32::INFINITY, rng) else {
        return lp;
    };
    let (mut x, mut wo, mut beta) = (origin + beam * t, -beam, medium.albedo());
    loop {
        lp.verts[lp.len] = Vertex { x, wo, beta, sigma_t: medium.sigma_t(x) };
        lp.len += 1;
        if lp.len >= b.max_light_vertices as usize || beta <= 0.0 {
            return lp;
        }
        if !roulette(lp.len as u32, &mut beta, rng) {
            return lp;
        }
        let Some(next) = medium.scatter(x, wo, rng) else { return lp };
        (x, wo) = next;
        beta *= medium.albedo();
    }
}

/// The end vertices of light subpaths that the camera samples of one pass share as
/// resampling candidates in prediction mode (module documentation, "light subpath
/// candidates"). Each subpath is traced like a sample's own, k segments, with a
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
fn predict_high(
    pr: &Prediction,
    b: &BdptSettings,
    scene: &Scene,
    sun: &crate::light::Sun,
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
            crate::p2p::sample_transport_by_segments(medium, &q, &P2pSettings::default(), rng, &mut |k, v| {
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
            sink(Contribution { order: 0, strategy: Strategy::Direct, value: scene.sky.radiance, weight: 1.0 });
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
        let Some(next) = medium.scatter(x, wo, rng) else {
            if !scene.sky.is_black() {
                sink(Contribution { order, strategy: Strategy::Sky, value: scene.sky.radiance * beta, weight: 1.0 });
            }
            return;
        };
        (x, wo) = next;
        order += 1;
        beta *= medium.albedo();
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
    medium: &crate::medium::Medium,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phase::PhaseFunction;

    /// The weights of all strategies that can make a path sum to one, for random
    /// paths of every length, with and without the caps binding, for both heuristics.
    #[test]
    fn weights_sum_to_one() {
        let mut rng = Rng::new(5, 0, 0);
        let phase = PhaseFunction::HenyeyGreenstein { g: 0.7 };
        for heuristic in [MisHeuristic::Balance, MisHeuristic::Power] {
            // depth < usize::MAX: prediction mode, the camera walk stops at max_c.
            for (max_c, max_l, depth) in [
                (8u32, 8u32, usize::MAX),
                (2, 3, usize::MAX),
                (1, 1, usize::MAX),
                (20, 32, usize::MAX),
                (2, 2, 2),
                (4, 4, 4),
            ] {
                let b = BdptSettings { heuristic, max_camera_connect: max_c, max_light_vertices: max_l };
                let max_n = if depth == usize::MAX { 14 } else { 2 * depth };
                for n in 1..=max_n {
                    for _ in 0..20 {
                        let pts: Vec<(Vec3, f32)> = (0..=n)
                            .map(|_| {
                                (Vec3::from_array(std::array::from_fn(|_| rng.uniform())), 0.5 + 10.0 * rng.uniform())
                            })
                            .collect();
                        let to_sun = crate::sampling::sample_uniform_sphere(rng.uniform2());
                        let area = 2.0;
                        let mut total = 0.0f64;
                        for c in 1..=n {
                            let l = n - c;
                            let feasible = (c == n && n <= depth) || (c <= max_c as usize && l <= max_l as usize);
                            if !feasible {
                                continue;
                            }
                            // Build the two subpaths the strategy would have made.
                            let mut cam = CameraRing { origin: pts[0].0, verts: [Vertex::default(); RING] };
                            for i in 1..=c {
                                cam.verts[i % RING] = Vertex { x: pts[i].0, sigma_t: pts[i].1, ..Default::default() };
                            }
                            let mut lp = LightPath {
                                verts: [Vertex::default(); MAX_LIGHT_VERTICES as usize],
                                len: l,
                                beam: -to_sun,
                                area,
                            };
                            for j in 1..=l {
                                let p = pts[n + 1 - j];
                                lp.verts[j - 1] = Vertex { x: p.0, sigma_t: p.1, ..Default::default() };
                            }
                            let view = PathView { cam: &cam, light: (l > 0).then_some(&lp), c, n, to_sun };
                            total += mis_weight(&view, phase, area, &b, depth) as f64;
                        }
                        assert!((total - 1.0).abs() < 1e-4, "n {n} caps ({max_c}, {max_l}) {heuristic:?}: {total}");
                    }
                }
            }
        }
    }

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
        let scene = Scene { medium, sun: Some(sun), sky: crate::light::Sky { radiance: Vec3::ZERO }, camera };
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
