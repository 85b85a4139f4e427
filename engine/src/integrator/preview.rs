//! The instant preview: camera rays marched through the density, single scattering
//! from a precomputed sun-transmittance field, the higher orders from a lattice of
//! multiple-scattering radiance (a learned model's, for the current sun and camera) or
//! from the octave approximation.
//!
//! Each sample marches its camera ray over the majorant cells it crosses (skipping
//! empty ones) in steps of at most `step` world units and at most [`MAX_STEP_TAU`]
//! optical depths at the cell's majorant, each step sampled at the same offset within
//! it, so passes average out the discretization and the image keeps refining; dense
//! clouds cost steps by optical depth, not by length. In the renderer the pixel
//! position and the offset of pass i are point i of a Halton sequence rotated per
//! pixel ([`crate::sampling::halton_point`]), so the passes cover each pixel and each
//! step evenly and the image settles faster than with independent samples.
//! Over a step of length h with extinction sigma_t at its sample point, the camera
//! transmittance falls by exp(-sigma_t h) and the step adds
//! T_cam (1 - exp(-sigma_t h)) albedo S, with the source
//! S = L_sun [p(omega_cam, omega_sun) T_sun(x) + L_ms(x)] (per unit sigma_s; omega_cam
//! points back toward the camera). The march ends once T_cam < [`MIN_TRANSMITTANCE`];
//! what the camera sees through the cloud, T_cam times the sky, goes to `direct`.
//! Buffers: `low` = single scattering, `high` = the higher orders (the split of
//! k = 2), `direct` = the sky seen through the medium.
//!
//! It is a consistent estimate of the same image as path tracing up to the error of
//! the fields (the sun transmittance's interpolation, and the multiple-scattering
//! source's: the model's error and the lattice's), not an unbiased one. Sky light
//! scattered in the cloud is not included (as in prediction mode).
//!
//! Multiple scattering ([`MultipleScattering`]):
//! - `Lattice`: L_ms(x, omega) for a unit sun, sampled at the nodes of a lattice with
//!   omega the direction from the node toward the camera, interpolated trilinearly
//!   (multiple scattering varies slowly; [`Preview::learned_lattice`]); a fine lattice
//!   is filled as the marches read it and serves them down to a camera transmittance
//!   of [`FAR_TRANSMITTANCE`], a coarse one beyond ([`LearnedLattice`]);
//! - `Octaves` (Wrenninge et al. 2013, "Oz: The Great and Volumetric"): octave i >= 1
//!   adds b^i p(theta; c^i g) T_sun^(a^i), a Henyey-Greenstein lobe of c^i times the
//!   medium's mean cosine g and a transmittance of a^i times the optical depth (octave
//!   0 is single scattering). Parameters: `octaves` N in 1 ..= 9 (terms 0 .. N-1,
//!   default 3), `a`, `b`, `c` in (0, 1] (default 0.5 each, what game engines use);
//! - `None`: single scattering only.
//!
//! Parameters ([`Preview::new`]): `step` the march step in world units, > 0 (default:
//! the smallest voxel edge, [`Preview::default_step`]).

use super::base::PathSample;
use crate::field::{NodeSource, ScalarLattice, SunTransmittance, lattice_over, lattice_over_per_voxel};
use crate::grid::Bounds3;
use crate::medium::Medium;
use crate::phase::PhaseFunction;
use crate::predictor::InScatterPredictor;
use crate::rng::Rng;
use crate::scene::Scene;
use glam::Vec3;
use std::sync::Arc;

/// Nodes per axis of the learned preview's default lattice
/// ([`Preview::default_lattice`]) over an optically thin cloud. The lattice is lazy,
/// so the nodes cost what the preview's marches read, and they are most of the first
/// pass (the model at each node). On the nine cells of docs/evaluation.md (256x256,
/// 128^3 clouds at rho 40 and 160) 96 nodes reach the floors of 128 within 0.2
/// points in eight cells and 5 % in about 0.6 of the time (scene A frontlit 0.55 s
/// against 1.06 s); 64 nodes lose 1 - 6 points backlit, where the image is the bright
/// fringe, and 48 lost 2 - 13.
pub const BASE_LATTICE_NODES: u32 = 96;

/// Nodes per axis, at most, of the default lattice over an optically thick cloud.
pub const THICK_LATTICE_NODES: u32 = 192;

/// The most optical depth, at the medium's largest extinction, that one spacing of the
/// default lattice spans. Seen against the sun, a dense cloud's image is its lit rim,
/// about a mean free path deep, across which the model's answer changes as fast as
/// the density does: a lattice that spans it in one spacing averages the rim's bright
/// answers with the darker ones behind and outside it. Scene C at rho 160 backlit
/// (1.7 optical depths per spacing at 96 nodes) reads a floor of 9.3 % at 96 nodes,
/// 6.1 % at 160, 5.7 % at 192 and 5.5 % at 256, where the model evaluated at every
/// march step reads 5.1 % (docs/evaluation.md); toplit and frontlit the floors do not
/// move. At 0.85 the clouds at rho 40 (0.42 per spacing) and rho 80 keep 96 nodes.
pub const NODE_SPACING_TAU: f32 = 0.85;

/// Learned lattices of at most this many nodes are filled up front (the window's
/// first look: a few milliseconds, and its passes then only read); larger ones are
/// filled as the marches read them.
pub const EAGER_LATTICE_NODES: u32 = 32 * 32 * 32;

/// Camera transmittance below which a march reads L_ms from the coarse lattice behind
/// a fine lazy one ([`LearnedLattice`]): what lies deeper adds at most this fraction of
/// a ray's light, so its error there is scaled down by it, and the fine lattice's
/// nodes are paid only in the camera-facing skin of the cloud.
pub const FAR_TRANSMITTANCE: f32 = 0.05;

/// Nodes per axis, at most, of the coarse lattice behind a fine lazy one.
pub const FAR_LATTICE_NODES: u32 = 32;

/// Camera transmittance below which a march ends: what lies beyond reaches the
/// camera through at most a thousandth of the ray's light, invisible beside the
/// part of the image already gathered.
pub const MIN_TRANSMITTANCE: f32 = 1e-3;

/// The most optical depth one march step may span, at its cell's majorant: the
/// transmittance is accumulated step by step from jittered samples, whose spread
/// biases it (exp is convex), and the bias grows with the density's variation
/// within a step. Inside a dense cloud this, not the voxel, sets the step, so it
/// sets a pass's cost. At 0.5 (with [`MIN_TRANSMITTANCE`] at 10^-3 and steps of at
/// most a voxel) the nine cells of docs/evaluation.md keep their RMSE floors and
/// first-pass errors within 0.04 points of 0.25, with passes 5 - 40 % shorter
/// (the most in scene C at rho 160); 0.1 read the same floors as 0.25 within 0.11
/// points.
pub const MAX_STEP_TAU: f32 = 0.5;

/// Steps a march looks up together ([`Preview::trace_with_offset`]).
const MARCH_BATCH: usize = 8;

/// Nodes a lattice's source hands the predictor at once (a lattice brick's).
const MAX_SOURCE_NODES: usize = 64;

/// Where the preview's orders >= 2 come from.
#[derive(Clone, Debug)]
pub enum MultipleScattering {
    /// L_ms for a unit sun on a lattice (see the module documentation).
    Lattice(Arc<LearnedLattice>),
    /// The octave approximation with N terms (single scattering included) and
    /// factors a (optical depth), b (amplitude), c (mean cosine).
    Octaves { octaves: u32, a: f32, b: f32, c: f32 },
    /// Single scattering only.
    None,
}

impl MultipleScattering {
    /// The octave approximation with the game engines' defaults: 3 octaves,
    /// a = b = c = 0.5.
    pub const DEFAULT_OCTAVES: MultipleScattering = MultipleScattering::Octaves { octaves: 3, a: 0.5, b: 0.5, c: 0.5 };

    fn validate(&self) -> Result<(), String> {
        if let MultipleScattering::Octaves { octaves, a, b, c } = *self {
            if !(1..=9).contains(&octaves) {
                return Err(format!("the octave approximation takes 1 ..= 9 octaves, got {octaves}"));
            }
            for (name, v) in [("a", a), ("b", b), ("c", c)] {
                if !(v > 0.0 && v <= 1.0) {
                    return Err(format!("octave factor {name} must lie in (0, 1], got {v}"));
                }
            }
        }
        Ok(())
    }
}

/// L_ms for a unit sun on a lattice as fine as asked, and, when that one is filled
/// lazily, a coarse one (at most [`FAR_LATTICE_NODES`] per axis, also lazy) from the
/// same source, read where the camera's transmittance has fallen below
/// [`FAR_TRANSMITTANCE`].
#[derive(Debug)]
pub struct LearnedLattice {
    near: ScalarLattice,
    far: Option<ScalarLattice>,
    /// Bytes the lazy lattices' source keeps alive (the model's fields).
    source_bytes: usize,
}

impl LearnedLattice {
    /// One lattice for every depth.
    pub fn single(lattice: ScalarLattice) -> Self {
        LearnedLattice { near: lattice, far: None, source_bytes: 0 }
    }

    /// The lattice read down to [`FAR_TRANSMITTANCE`], and the one read beyond it.
    pub fn two_tier(near: ScalarLattice, far: ScalarLattice) -> Self {
        LearnedLattice { near, far: Some(far), source_bytes: 0 }
    }

    /// The same lattices, stating that their source holds `bytes` (lazy lattices keep
    /// the model, and its fields, until every node is filled).
    pub fn holding(self, bytes: usize) -> Self {
        LearnedLattice { source_bytes: bytes, ..self }
    }

    /// L_ms at `x` for a march whose camera transmittance is `tr`.
    #[inline]
    pub fn lookup(&self, x: Vec3, tr: f32) -> f32 {
        match &self.far {
            Some(far) if tr < FAR_TRANSMITTANCE => far.lookup(x),
            _ => self.near.lookup(x),
        }
    }

    /// The fine lattice's nodes per axis.
    pub fn nodes(&self) -> glam::UVec3 {
        self.near.nodes()
    }

    /// Bytes the lazy lattices' source keeps (the model's fields; 0 once filled).
    pub fn source_bytes(&self) -> usize {
        self.source_bytes
    }

    /// Bytes held: the lattices and, while they are filled lazily, the model's fields
    /// their source keeps.
    pub fn memory_bytes(&self) -> usize {
        self.near.memory_bytes() + self.far.as_ref().map_or(0, |f| f.memory_bytes()) + self.source_bytes
    }
}

/// Prediction at bounce 1 from a lattice of the model's answers: at the first vertex
/// of a camera path the direction toward the previous vertex is the direction toward
/// the camera, so the model's answer there is, up to trilinear interpolation, the
/// value of a lattice of its answers toward the camera ([`Preview::learned_lattice`]'s
/// fine lattice, each node evaluated when first read and then shared by every pass).
/// A prediction then costs a lattice lookup in place of features and a network, and
/// its cost no longer limits how often to predict. Queries in any other direction
/// (vertices beyond the first) go to the model itself. Bound to the scene's sun and
/// camera: it answers for that sun alone, as the models bound to a cloud do.
pub struct CameraLatticePredictor {
    lattice: LearnedLattice,
    inner: Arc<dyn InScatterPredictor>,
    camera: Vec3,
    name: String,
}

/// The least cosine between a query's direction and the direction toward the camera
/// for which [`CameraLatticePredictor`] answers from its lattice (at the first vertex
/// they are the same direction, up to rounding).
pub const CAMERA_LATTICE_COS: f32 = 1.0 - 1e-4;

impl CameraLatticePredictor {
    /// `inner`'s answers toward `camera` on a lattice of at most `max_nodes` per axis
    /// over the scene's medium. None for a predictor that answers for any light
    /// direction (the integrator would ask it for other directions than the scene's
    /// sun) or a scene without a sun.
    pub fn new(scene: &Scene, inner: Arc<dyn InScatterPredictor>, camera: Vec3, max_nodes: u32) -> Option<Self> {
        if inner.answers_any_light_direction() || scene.sun.is_none() {
            return None;
        }
        // Only the fine lattice is read (at the camera's first vertices): no far one.
        let nodes = lattice_over(&scene.medium, max_nodes);
        let lattice = Preview::lattice_of(scene, None, inner.clone(), camera, nodes, false);
        let name = format!("{} (camera lattice)", inner.name());
        Some(CameraLatticePredictor { lattice, inner, camera, name })
    }

    /// The lattice's nodes per axis.
    pub fn nodes(&self) -> glam::UVec3 {
        self.lattice.nodes()
    }
}

impl InScatterPredictor for CameraLatticePredictor {
    #[inline]
    fn predict(&self, medium: &Medium, sun: &crate::light::Sun, x: Vec3, omega: Vec3) -> f32 {
        match (self.camera - x).try_normalize() {
            Some(to_camera) if to_camera.dot(omega) >= CAMERA_LATTICE_COS => self.lattice.lookup(x, 1.0),
            _ => self.inner.predict(medium, sun, x, omega),
        }
    }

    fn predicts_single_scattering(&self) -> bool {
        self.inner.predicts_single_scattering()
    }

    fn answers_any_light_direction(&self) -> bool {
        false
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn memory_bytes(&self) -> usize {
        self.lattice.memory_bytes()
    }
}

/// The preview's state for one scene: the sun's transmittance and the multiple
/// scattering source, shared by every sample.
#[derive(Clone, Debug)]
pub struct Preview {
    sun: Arc<SunTransmittance>,
    multiple: MultipleScattering,
    step: f32,
}

impl Preview {
    /// The default march step for `medium`: its smallest voxel edge. Each step is
    /// sampled at a jittered offset, so the passes average the density over it; what
    /// the step's length biases is the transmittance (exp of that sample, see
    /// [`MAX_STEP_TAU`], which sets a shorter step in dense parts), and otherwise it
    /// sets one pass's noise. Measured on the nine cells of docs/evaluation.md, with
    /// [`MAX_STEP_TAU`] at 0.25 for both: a whole voxel keeps every floor and every
    /// first pass's error within 0.01 points of half a voxel's, with passes 20 - 30 %
    /// shorter in scenes A and B (rho 40) and as long in scene C (rho 160), whose
    /// steps the optical depth sets.
    pub fn default_step(medium: &Medium) -> f32 {
        medium.grid().voxel_size().min_element()
    }

    /// A preview from its fields; errors name a bad parameter.
    pub fn new(sun: Arc<SunTransmittance>, multiple: MultipleScattering, step: f32) -> Result<Self, String> {
        if !(step > 0.0 && step.is_finite()) {
            return Err(format!("preview step must be a positive length, got {step}"));
        }
        multiple.validate()?;
        Ok(Preview { sun, multiple, step })
    }

    pub fn multiple(&self) -> &MultipleScattering {
        &self.multiple
    }

    /// Bytes held by the fields: the sun's transmittance and a learned lattice (with
    /// the model's fields it keeps).
    pub fn memory_bytes(&self) -> usize {
        let lattice = match &self.multiple {
            MultipleScattering::Lattice(l) => l.memory_bytes(),
            _ => 0,
        };
        self.sun.memory_bytes() + lattice
    }

    pub fn sun_transmittance(&self) -> &Arc<SunTransmittance> {
        &self.sun
    }

    /// L_ms for a unit sun from `predictor` at the nodes of a lattice over the
    /// medium (at most `max_nodes` per axis and two per voxel; None: the default
    /// lattice, [`Preview::default_lattice`]), with omega the direction from each node
    /// toward `camera`. Above [`EAGER_LATTICE_NODES`] each node is evaluated when a
    /// lookup first reads it (a lazy [`ScalarLattice`]: a march reads the nodes around
    /// the camera-facing part of the cloud it reaches, so a lattice as fine as the grid
    /// costs those nodes, not the whole box), and a coarse lattice of at most
    /// [`FAR_LATTICE_NODES`] per axis serves the march where its transmittance is
    /// below [`FAR_TRANSMITTANCE`] ([`LearnedLattice`]). Nodes whose lattice cells are
    /// all empty are 0 (their value only ever multiplies a zero density). A predictor
    /// of total in-scattered radiance gets the single scattering of `sun` subtracted
    /// (clamped at 0).
    pub fn learned_lattice(
        scene: &Scene,
        sun: &Arc<SunTransmittance>,
        predictor: Arc<dyn InScatterPredictor>,
        camera: Vec3,
        max_nodes: Option<u32>,
    ) -> LearnedLattice {
        Self::lattice_of(scene, Some(sun), predictor, camera, Self::lattice_nodes(&scene.medium, max_nodes), true)
    }

    /// The learned preview's lattice over `medium` as (nodes per axis, spacing): at
    /// most `max_nodes` per axis and two per voxel, or the default lattice for None
    /// ([`Preview::default_lattice`]).
    pub fn lattice_nodes(medium: &Medium, max_nodes: Option<u32>) -> (glam::UVec3, Vec3) {
        match max_nodes {
            Some(m) => lattice_over_per_voxel(medium, m, 2),
            None => Self::default_lattice(medium),
        }
    }

    /// The learned preview's lattice when none is asked for, as (nodes per axis,
    /// spacing): [`BASE_LATTICE_NODES`] per axis (at most one per voxel), finer along
    /// an axis where one spacing would span more than [`NODE_SPACING_TAU`] optical
    /// depths at the medium's largest extinction, to that bound, up to
    /// [`THICK_LATTICE_NODES`] per axis and two nodes per voxel; never coarser than
    /// the base lattice along any axis.
    pub fn default_lattice(medium: &Medium) -> (glam::UVec3, Vec3) {
        let grid = medium.grid();
        let (base, _) = lattice_over(medium, BASE_LATTICE_NODES);
        let sigma_max = (medium.rho() * grid.max_value()).min(medium.sigma_cap());
        let extent = grid.support_bounds().extent();
        let mut n = base;
        for a in 0..3 {
            // The nodes along axis a whose spacing spans NODE_SPACING_TAU (as f32: a
            // huge rho must not overflow the cast; NaN keeps the base).
            let needed = (extent[a] * sigma_max / NODE_SPACING_TAU).ceil() + 1.0;
            let cap = THICK_LATTICE_NODES.min(2 * grid.dims()[a] + 1);
            if needed > base[a] as f32 {
                n[a] = needed.min(cap as f32) as u32;
            }
        }
        (n, extent / (n - glam::UVec3::ONE).as_vec3())
    }

    /// [`Preview::learned_lattice`] of a predictor's own quantity: `single` the sun
    /// field whose single scattering is taken off a predictor of total in-scattered
    /// radiance, None to keep what the predictor answers; `far` adds the coarse lattice
    /// read beyond the camera-facing skin (a reader of the skin alone goes without).
    fn lattice_of(
        scene: &Scene,
        single: Option<&Arc<SunTransmittance>>,
        predictor: Arc<dyn InScatterPredictor>,
        camera: Vec3,
        (n, spacing): (glam::UVec3, Vec3),
        far: bool,
    ) -> LearnedLattice {
        let medium = scene.medium.clone();
        let origin = medium.grid().support_bounds().min;
        let Some(light) = scene.sun else {
            // No sun, no multiple scattering: a lattice of zeros, two nodes per axis.
            let extent = medium.grid().support_bounds().extent();
            return LearnedLattice::single(ScalarLattice::new(glam::UVec3::splat(2), origin, extent, vec![0.0; 8]));
        };
        let single = single.filter(|_| predictor.predicts_single_scattering()).cloned();
        let model_bytes = predictor.memory_bytes();
        let source = move |spacing: Vec3| -> NodeSource {
            let (medium, predictor, single) = (medium.clone(), predictor.clone(), single.clone());
            Arc::new(move |ps: &[Vec3], out: &mut [f32]| {
                // A node is read wherever its lattice cells are: it is needed unless
                // the medium is empty across all of them. The needed ones go to the
                // predictor together.
                let mut xs = [Vec3::ZERO; MAX_SOURCE_NODES];
                let mut omegas = [Vec3::ZERO; MAX_SOURCE_NODES];
                let mut slots = [0usize; MAX_SOURCE_NODES];
                let mut li = [0.0f32; MAX_SOURCE_NODES];
                for (pc, oc) in ps.chunks(MAX_SOURCE_NODES).zip(out.chunks_mut(MAX_SOURCE_NODES)) {
                    oc.fill(0.0);
                    let mut m = 0;
                    for (j, &p) in pc.iter().enumerate() {
                        if medium.majorant().max_in(Bounds3::new(p - spacing, p + spacing)) <= 0.0 {
                            continue;
                        }
                        let Some(omega) = (camera - p).try_normalize() else { continue };
                        (xs[m], omegas[m], slots[m]) = (p, omega, j);
                        m += 1;
                    }
                    predictor.predict_many(&medium, &light, &xs[..m], &omegas[..m], &mut li[..m]);
                    for k in 0..m {
                        let (p, omega) = (xs[k], omegas[k]);
                        let ms = match &single {
                            Some(sun) => li[k] - medium.phase().eval(omega, sun.to_sun()) * sun.at(p),
                            None => li[k],
                        };
                        oc[slots[k]] = if ms.is_finite() { ms.max(0.0) } else { 0.0 };
                    }
                }
            })
        };
        if n.x * n.y * n.z <= EAGER_LATTICE_NODES {
            // Few nodes: all of them up front, so the passes only read.
            return LearnedLattice::single(ScalarLattice::filled(n, origin, spacing, source(spacing)));
        }
        let near = ScalarLattice::lazy(n, origin, spacing, source(spacing));
        let lattice = if far {
            let (nf, spacing_far) = lattice_over(&scene.medium, FAR_LATTICE_NODES);
            LearnedLattice::two_tier(near, ScalarLattice::lazy(nf, origin, spacing_far, source(spacing_far)))
        } else {
            LearnedLattice::single(near)
        };
        lattice.holding(model_bytes)
    }

    /// One sample of the radiance arriving at `o` from direction `-d`, split into the
    /// buffers of the module documentation.
    pub fn trace(&self, scene: &Scene, o: Vec3, d: Vec3, rng: &mut Rng) -> PathSample {
        self.trace_with_offset(scene, o, d, rng.uniform())
    }

    /// The octaves' lobes beyond single scattering for a ray leaving toward `wo`:
    /// (b^i p_HG(c^i g), a^i) for i = 1 .. N - 1 in the first N - 1 entries, and
    /// N - 1 (0 without octaves). Computed once per ray: the angle is the ray's.
    fn octave_lobes(&self, phase: &PhaseFunction, wo: Vec3, to_sun: Vec3) -> ([(f32, f32); 8], usize) {
        let mut lobes = [(0.0f32, 0.0f32); 8];
        let MultipleScattering::Octaves { octaves, a, b, c } = self.multiple else {
            return (lobes, 0);
        };
        let g = phase.mean_cosine();
        let n = octaves as usize - 1;
        for (i, lobe) in lobes.iter_mut().enumerate().take(n) {
            let i = i as i32 + 1;
            let p = PhaseFunction::HenyeyGreenstein { g: (c.powi(i) * g).clamp(-0.999, 0.999) }.eval(wo, to_sun);
            *lobe = (b.powi(i) * p, a.powi(i));
        }
        (lobes, n)
    }

    /// The higher orders' radiance per unit of scattered light at a march step at `x`
    /// with camera transmittance `tr` and the sun's optical depth `tau_sun`: the
    /// lattice's, or the octaves' `lobes` (from [`Preview::octave_lobes`]).
    #[inline]
    fn multiple_at(&self, x: Vec3, tr: f32, tau_sun: f32, lobes: &[(f32, f32)]) -> f32 {
        match &self.multiple {
            MultipleScattering::Lattice(l) => l.lookup(x, tr),
            // Octave i sees the sun through a^i of the optical depth.
            MultipleScattering::Octaves { .. } => lobes.iter().map(|&(amp, exp)| amp * (-tau_sun * exp).exp()).sum(),
            MultipleScattering::None => 0.0,
        }
    }

    /// [`Preview::trace`] with the march's offset within its steps given, in [0, 1).
    pub fn trace_with_offset(&self, scene: &Scene, o: Vec3, d: Vec3, offset: f32) -> PathSample {
        let medium = &scene.medium;
        let mut out = PathSample::default();
        let Some(sun) = &scene.sun else {
            out.direct = scene.sky.radiance(d);
            return out;
        };
        let wo = -d;
        let to_sun = self.sun.to_sun();
        let phase = medium.phase();
        let p_single = phase.eval(wo, to_sun);
        let (lobes, octaves) = self.octave_lobes(&phase, wo, to_sun);
        let albedo = medium.albedo();
        let (mut tr, mut single, mut multiple) = (1.0f32, 0.0f32, 0.0f32);
        // Steps are taken in batches: the positions of up to MARCH_BATCH steps, then
        // their densities, then the sun's optical depth at those with a density (eight
        // at a time, `optical_depth_many`), then the running sums in step order. The
        // lookups of a batch are independent, so their memory waits overlap; the sums
        // are the ones a step-by-step march makes, in the same order.
        let mut xs = [Vec3::ZERO; MARCH_BATCH];
        let mut lens = [0.0f32; MARCH_BATCH];
        let mut sigma = [0.0f32; MARCH_BATCH];
        let mut dense = [Vec3::ZERO; MARCH_BATCH];
        let mut tau = [0.0f32; MARCH_BATCH];
        // A ray that misses the support has no segments: it sees the sky.
        'march: for seg in medium.majorant().segments(o, d, 0.0, f32::INFINITY) {
            let sigma_maj = medium.sigma_maj(&seg);
            if sigma_maj <= 0.0 {
                continue;
            }
            // Steps of at most `step` and of at most MAX_STEP_TAU optical depths at the
            // cell's majorant, tiling the segment; each sampled at the ray's offset
            // within it.
            let h = self.step.min(MAX_STEP_TAU / sigma_maj);
            let mut start = seg.t_min;
            while start < seg.t_max {
                let mut m = 0;
                while m < MARCH_BATCH && start < seg.t_max {
                    let len = h.min(seg.t_max - start);
                    xs[m] = o + d * (start + offset * len);
                    lens[m] = len;
                    start += len;
                    m += 1;
                }
                let mut filled = 0;
                for j in 0..m {
                    sigma[j] = medium.sigma_t(xs[j]);
                    if sigma[j] > 0.0 {
                        dense[filled] = xs[j];
                        filled += 1;
                    }
                }
                self.sun.optical_depth_many(&dense[..filled], &mut tau[..filled]);
                let mut next = 0;
                for j in 0..m {
                    let sigma_t = sigma[j];
                    // (The same test as above, so the depths stay in step order.)
                    if !(sigma_t > 0.0) {
                        continue;
                    }
                    let (x, len) = (xs[j], lens[j]);
                    let tau_sun = tau[next];
                    next += 1;
                    let absorbed = 1.0 - (-sigma_t * len).exp();
                    let w = tr * absorbed * albedo;
                    single += w * p_single * (-tau_sun).exp();
                    multiple += w * self.multiple_at(x, tr, tau_sun, &lobes[..octaves]);
                    tr *= 1.0 - absorbed;
                    if tr < MIN_TRANSMITTANCE {
                        break 'march;
                    }
                }
            }
        }
        out.low = sun.radiance() * single;
        out.high = sun.radiance() * multiple;
        out.direct = scene.sky.radiance(d) * tr;
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::grid::DensityGrid;
    use crate::light::Sun;
    use glam::UVec3;

    /// The march one step at a time, as the definition of what the batched march
    /// sums (the test compares the two bit for bit).
    fn march_step_by_step(p: &Preview, scene: &Scene, o: Vec3, d: Vec3, offset: f32) -> (f32, f32, f32) {
        let medium = &scene.medium;
        let to_sun = p.sun.to_sun();
        let phase = medium.phase();
        let p_single = phase.eval(-d, to_sun);
        let (lobes, octaves) = p.octave_lobes(&phase, -d, to_sun);
        let (mut tr, mut single, mut multiple) = (1.0f32, 0.0f32, 0.0f32);
        for seg in medium.majorant().segments(o, d, 0.0, f32::INFINITY) {
            let sigma_maj = medium.sigma_maj(&seg);
            if sigma_maj <= 0.0 {
                continue;
            }
            let h = p.step.min(MAX_STEP_TAU / sigma_maj);
            let mut start = seg.t_min;
            while start < seg.t_max {
                let len = h.min(seg.t_max - start);
                let x = o + d * (start + offset * len);
                start += len;
                let sigma_t = medium.sigma_t(x);
                if sigma_t <= 0.0 {
                    continue;
                }
                let absorbed = 1.0 - (-sigma_t * len).exp();
                let w = tr * absorbed * medium.albedo();
                let tau_sun = p.sun.optical_depth(x);
                single += w * p_single * (-tau_sun).exp();
                multiple += w * p.multiple_at(x, tr, tau_sun, &lobes[..octaves]);
                tr *= 1.0 - absorbed;
                if tr < MIN_TRANSMITTANCE {
                    return (single, multiple, tr);
                }
            }
        }
        (single, multiple, tr)
    }

    /// The batched march makes the step-by-step march's sums bit for bit, for the
    /// three sources of multiple scattering, thin and dense media (rays that leave
    /// the cloud and rays that end inside it), and rays that miss it.
    #[test]
    fn batched_march_matches_the_step_by_step_march() {
        let grid =
            DensityGrid::from_fn(UVec3::new(37, 29, 33), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
                ((1.0 - 2.2 * p.length()).clamp(0.0, 1.0) * (1.2 + (9.0 * p.x).sin() * (7.0 * p.z).cos())).max(0.0)
            })
            .unwrap();
        let grid = Arc::new(grid);
        let mut rng = Rng::new(7, 0, 0);
        let mut ended_inside = 0;
        for rho in [4.0, 60.0] {
            let medium = Medium::new(grid.clone(), rho, 0.9, PhaseFunction::HenyeyGreenstein { g: 0.7 }).unwrap();
            let sun = Sun::new(Vec3::new(0.3, -1.0, 0.2), Vec3::ONE, 0.0).unwrap();
            let scene = Scene {
                medium: medium.clone(),
                sun: Some(sun),
                // (A uniform sky of 1: `direct` is the camera's transmittance.)
                sky: crate::light::Sky::uniform(Vec3::ONE),
                camera: Camera::new(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 30.0, 8, 8).unwrap(),
            };
            let field = Arc::new(SunTransmittance::build(&medium, &sun, 40));
            let (n, spacing) = lattice_over(&medium, 12);
            let nodes: Vec<f32> = (0..n.x * n.y * n.z).map(|i| (i % 17) as f32 * 0.01).collect();
            let (nf, spacing_far) = lattice_over(&medium, 5);
            let far: Vec<f32> = (0..nf.x * nf.y * nf.z).map(|i| 0.2 - (i % 7) as f32 * 0.01).collect();
            let origin = grid.support_bounds().min;
            let lattice = LearnedLattice::two_tier(
                ScalarLattice::new(n, origin, spacing, nodes),
                ScalarLattice::new(nf, origin, spacing_far, far),
            );
            for multiple in [
                MultipleScattering::Lattice(Arc::new(lattice)),
                MultipleScattering::DEFAULT_OCTAVES,
                MultipleScattering::None,
            ] {
                let preview = Preview::new(field.clone(), multiple, Preview::default_step(&medium)).unwrap();
                for _ in 0..2000 {
                    let target = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1.4 - 0.7;
                    let o = Vec3::new(rng.uniform() - 0.5, rng.uniform() - 0.5, 3.0);
                    let d = (target - o).normalize();
                    let offset = rng.uniform();
                    let s = preview.trace_with_offset(&scene, o, d, offset);
                    let (single, multiple, tr) = march_step_by_step(&preview, &scene, o, d, offset);
                    assert_eq!(s.low.x.to_bits(), single.to_bits(), "single, rho {rho}, {o} {d}");
                    assert_eq!(s.high.x.to_bits(), multiple.to_bits(), "multiple, rho {rho}, {o} {d}");
                    assert_eq!(s.direct.x.to_bits(), tr.to_bits(), "direct, rho {rho}, {o} {d}");
                    ended_inside += (tr < MIN_TRANSMITTANCE) as u32;
                }
            }
        }
        assert!(ended_inside > 100, "some rays end inside the dense cloud ({ended_inside})");
    }
}
