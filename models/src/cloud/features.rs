//! The cloud-aware model's input: a light-oriented stencil of the real cloud around
//! the query point (after Kallweit et al. 2017 and Hu et al. 2023, sized for a CPU).
//!
//! The stencil has [`LEVELS`] levels of 3 x 3 x 3 points. Level l has spacing
//! h_l = h_0 2^l, with h_0 = (largest extent of the medium's box) / 64, so the
//! coarsest level spans the box. Its points sit at x + h_l (a u + b v + c w) for
//! a, b, c in {-1, 0, 1}, in the frame whose w points toward the sun and whose u is
//! the query direction's part across w (so the query direction lies in the u-w
//! plane, and its angle to the sun is the only angle the network needs).
//!
//! Per point, two values (each 3 x 3 plane of them encoded by [`encode_plane`]):
//! - the density filtered by a Gaussian of standard deviation h_l / 2 (the density
//!   pyramid of the point-to-point model, 16-bit), as the optical thickness of one
//!   stencil cell, ln(1 + rho d h_l);
//! - the optical depth toward the sun there, from the engine's sun-transmittance
//!   field, as tau_hat = ln(1 / (1 + tau)) (thesis eq. 5.7).
//!
//! and seven for the query: ln(1 - albedo + 10^-3) (multiple scattering depends on
//! the albedo through the absorption per event, steeply near 1), g, cos theta (query
//! direction against the direction toward the sun), and ln(4 pi p_HG(g^n, mu)) for
//! n = 1 .. 4 with mu = -cos theta the scattering cosine from the sun's light into the
//! query direction: light scattered n times through Henyey-Greenstein lobes of mean
//! cosine g has an angular spread close to a lobe of g^n, so these resolve the
//! forward peak of strongly anisotropic clouds that cos theta alone leaves to the
//! network. Last, twelve derived from those ([`derive_inputs`]): each phase term
//! times exp(-a tau) at three attenuations a, tau the optical depth toward the sun at
//! the query point, so that the network weighs the angular terms by how deep the
//! light has come. Data sets store the others and loading derives these. Everything a
//! cloud and a sun share (the pyramid, the field) is built once in a [`CloudField`].

use crate::p2p::DensityPyramid;
use crate::p2p::pyramid::LevelBlend;
use engine::field::SunTransmittance;
use engine::{Cancel, DensityGrid, Medium, Sun};
use glam::Vec3;
use std::sync::{Arc, Mutex, Weak};

/// Stencil levels.
pub const LEVELS: usize = 6;
/// Points per level (3 x 3 x 3).
pub const POINTS: usize = 27;
/// Features before the stencil: ln(1 - albedo + 10^-3), g, cos theta and the four
/// phase terms.
pub const HEAD: usize = 3 + PHASE_TERMS;
/// Phase terms ln(4 pi p_HG(g^n, mu)), n = 1 ..= PHASE_TERMS.
pub const PHASE_TERMS: usize = 4;
/// Where the phase terms start (after the albedo, g and cos theta).
const PHASE_START: usize = HEAD - PHASE_TERMS;
/// Features a data set stores: the query's and the stencil's.
pub const STORED_FEATURES: usize = HEAD + 2 * LEVELS * 3 * PLANE_FEATURES;
/// Attenuations a_j of the coupling features ([`derive_inputs`]).
pub const COUPLING_ATTENUATIONS: [f32; 3] = [1.0, 0.25, 0.0625];
/// Features derived from the stored ones: each phase term times exp(-a_j tau) for
/// each attenuation a_j ([`derive_inputs`]).
pub const COUPLING_FEATURES: usize = PHASE_TERMS * COUPLING_ATTENUATIONS.len();
/// Length of the feature vector: the stored features, then the coupling.
pub const N_FEATURES: usize = STORED_FEATURES + COUPLING_FEATURES;

/// The derived features a network reads beside the stored ones; each choice is a
/// length of the feature vector's prefix that a model may read.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DerivedInputs {
    /// The stored features alone (the models before the coupling; a training
    /// configuration that does not name its derived inputs was made before there were
    /// any).
    #[default]
    None,
    /// And the coupling ([`derive_inputs`]; the default of new runs).
    Coupling,
}

impl DerivedInputs {
    pub const ALL: [DerivedInputs; 2] = [DerivedInputs::None, DerivedInputs::Coupling];
    /// The words of the command line, in the order of [`Self::ALL`].
    pub const NAMES: [&str; 2] = [Self::ALL[0].name(), Self::ALL[1].name()];

    pub const fn name(self) -> &'static str {
        match self {
            DerivedInputs::None => "none",
            DerivedInputs::Coupling => "coupling",
        }
    }

    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|d| d.name() == name)
    }

    /// How many of the feature vector's values a network of these inputs reads.
    pub const fn inputs(self) -> usize {
        match self {
            DerivedInputs::None => STORED_FEATURES,
            DerivedInputs::Coupling => N_FEATURES,
        }
    }

    /// The choice whose networks read `inputs` values, if any.
    pub fn of_inputs(inputs: usize) -> Option<Self> {
        Self::ALL.into_iter().find(|d| d.inputs() == inputs)
    }
}
/// Where the optical depth toward the sun at the query point itself is stored, as
/// tau_hat: the centre of level 0's middle plane in the sun's block.
pub const TAU_HAT_AT_X: usize = HEAD + (LEVELS * 3 + 1) * PLANE_FEATURES;
/// h_0 = largest box extent / this.
pub const BASE_DIVISIONS: f32 = 64.0;

/// Names of the features, in order (stored in the model's sidecar and checked on load):
/// the stored ones, then the coupling.
pub fn feature_names() -> Vec<String> {
    let mut names = stored_feature_names();
    for n in 1..=PHASE_TERMS {
        names.extend(COUPLING_ATTENUATIONS.iter().map(|a| format!("ln_phase_g{n}_x_sun_{a}")));
    }
    names
}

/// Names of the features a data set stores (the first [`STORED_FEATURES`]).
pub fn stored_feature_names() -> Vec<String> {
    let mut names: Vec<String> = ["ln_absorption", "g", "cos_theta"].iter().map(|s| s.to_string()).collect();
    names.extend((1..=PHASE_TERMS).map(|n| format!("ln_phase_g{n}")));
    for what in ["density", "tau_sun"] {
        for l in 0..LEVELS {
            for c in 0..3 {
                names.push(format!("{what}_{l}_{c}_centre"));
                names.push(format!("{what}_{l}_{c}_ring"));
                names.extend((0..7).map(|k| format!("{what}_{l}_{c}_dev{k}")));
                names.push(format!("{what}_{l}_{c}_gradient"));
                names.push(format!("{what}_{l}_{c}_ring_min"));
                names.push(format!("{what}_{l}_{c}_ring_max"));
            }
        }
    }
    names
}

/// The albedo feature, ln(1 - albedo + 10^-3).
#[inline]
pub fn absorption_feature(albedo: f32) -> f32 {
    (1.0 - albedo + 1e-3).max(1e-3).ln()
}

/// The derived features of `row` (length [`N_FEATURES`]) from its stored part, the
/// coupling: ln(4 pi p_HG(g^n, mu)) exp(-a_j tau) for n = 1 ..= [`PHASE_TERMS`] and
/// a_j in [`COUPLING_ATTENUATIONS`], tau the optical depth toward the sun at the query
/// point (from its stored tau_hat). How sharply the light arriving at a point is
/// peaked depends on how deep it lies: near the lit surface few bounces have turned
/// it, deep inside many have, so the angular dependence the phase terms describe fades
/// with tau. A network of ReLUs builds that product only piecewise; given it, the
/// first layer weighs each phase term by the light's depth directly.
///
/// Derived, not stored: data sets keep the stored features and loading appends these.
#[inline]
pub fn derive_inputs(row: &mut [f32]) {
    assert_eq!(row.len(), N_FEATURES, "feature vector length");
    let (stored, coupling) = row.split_at_mut(STORED_FEATURES);
    // tau_hat = -ln(1 + tau).
    let tau = (-stored[TAU_HAT_AT_X]).exp_m1().max(0.0);
    let s = COUPLING_ATTENUATIONS.map(|a| (-a * tau).exp());
    for (n, out) in coupling.chunks_exact_mut(COUPLING_ATTENUATIONS.len()).enumerate() {
        for (o, s) in out.iter_mut().zip(&s) {
            *o = stored[PHASE_START + n] * s;
        }
    }
}

/// Rows of [`STORED_FEATURES`] at the front of `features` (`rows` of them) spread in
/// place to rows of [`N_FEATURES`] with their derived features; `features` holds
/// `rows * STORED_FEATURES` values on entry and `rows * N_FEATURES` on return. Rows
/// move from the last to the first, so none is overwritten before it has moved.
pub fn expand_stored_rows(features: &mut Vec<f32>, start: usize, rows: usize) {
    assert_eq!(features.len(), start + rows * STORED_FEATURES, "stored rows");
    features.resize(start + rows * N_FEATURES, 0.0);
    for i in (0..rows).rev() {
        let (from, to) = (start + i * STORED_FEATURES, start + i * N_FEATURES);
        features.copy_within(from..from + STORED_FEATURES, to);
        derive_inputs(&mut features[to..to + N_FEATURES]);
    }
}

/// ln(4 pi p_HG(g, mu)) = ln((1 - g^2) / (1 + g^2 - 2 g mu)^1.5).
#[inline]
pub fn ln_phase(g: f32, mu: f32) -> f32 {
    (1.0 - g * g).ln() - 1.5 * (1.0 + g * g - 2.0 * g * mu).max(1e-12).ln()
}

/// The stencil offset of point `p` (0 .. 27) in units of h: (a, b, c) in {-1, 0, 1}^3,
/// a along u, b along v, c toward the sun; point 13 is the centre.
#[inline]
pub fn offset(p: usize) -> Vec3 {
    Vec3::new((p % 3) as f32 - 1.0, ((p / 3) % 3) as f32 - 1.0, (p / 9) as f32 - 1.0)
}

/// What the features of one cloud under one sun read: the density pyramid and the
/// sun-transmittance field, with the medium's constants.
#[derive(Clone, Debug)]
pub struct CloudField {
    pyramid: Arc<DensityPyramid>,
    sun: Arc<SunTransmittance>,
    /// Whether `sun` is another's (the preview's), which that owner counts.
    shared_sun: bool,
    blends: [LevelBlend; LEVELS],
    h: [f32; LEVELS],
    rho: f32,
    /// Toward the sun.
    w: Vec3,
}

impl CloudField {
    /// Builds the pyramid (the levels the stencil's widths read, from at most
    /// `2 max_nodes` samples per axis: see [`pyramid_axis`]) and the sun field (at
    /// most `max_nodes` per axis); both in parallel, independent of the thread count.
    pub fn build(medium: &Medium, sun: &Sun, max_nodes: u32) -> Self {
        Self::build_until(medium, sun, max_nodes, Cancel::NEVER).expect("never cancelled")
    }

    /// [`CloudField::build`], or None when `cancel` asks to stop (the sun field
    /// checks it per column, the pyramid between its filter passes).
    pub fn build_until(medium: &Medium, sun: &Sun, max_nodes: u32, cancel: Cancel) -> Option<Self> {
        let h = Self::widths(medium);
        let (pyramid, field) = rayon::join(
            || shared_pyramid(medium.grid(), &h.map(|h| 0.5 * h), pyramid_axis(max_nodes), cancel),
            || SunTransmittance::build_until(medium, sun, max_nodes, cancel),
        );
        Some(Self::assemble(medium, pyramid?, Arc::new(field?), false, h))
    }

    /// The field of [`CloudField::build_until`] reading `sun_field`, built by the
    /// caller for this medium and sun (the preview's, at least as fine as the
    /// `max_nodes` it stands for), instead of a sun field of its own; only the
    /// pyramid is built, or found (see [`shared_pyramid`]). Its memory is left to the
    /// caller to count ([`CloudField::memory_bytes`]).
    pub fn with_sun_field_until(
        medium: &Medium,
        sun_field: Arc<SunTransmittance>,
        max_nodes: u32,
        cancel: Cancel,
    ) -> Option<Self> {
        let h = Self::widths(medium);
        let pyramid = shared_pyramid(medium.grid(), &h.map(|h| 0.5 * h), pyramid_axis(max_nodes), cancel)?;
        Some(Self::assemble(medium, pyramid, sun_field, true, h))
    }

    /// The stencil's spacing per level: h_0 2^l, h_0 the box's largest extent over
    /// [`BASE_DIVISIONS`].
    fn widths(medium: &Medium) -> [f32; LEVELS] {
        let h0 = medium.bounds().extent().max_element() / BASE_DIVISIONS;
        std::array::from_fn(|l| h0 * (1u32 << l) as f32)
    }

    fn assemble(
        medium: &Medium,
        pyramid: Arc<DensityPyramid>,
        sun: Arc<SunTransmittance>,
        shared_sun: bool,
        h: [f32; LEVELS],
    ) -> Self {
        let blends = std::array::from_fn(|l| pyramid.select(0.5 * h[l]));
        CloudField { pyramid, w: sun.to_sun(), sun, shared_sun, blends, h, rho: medium.rho() }
    }

    /// Bytes held: the pyramid and the sun field, unless the sun field is shared
    /// ([`CloudField::with_sun_field_until`]: its owner counts it).
    pub fn memory_bytes(&self) -> usize {
        self.pyramid.bytes() + if self.shared_sun { 0 } else { self.sun.memory_bytes() }
    }

    /// The sun-transmittance field the features read.
    pub fn sun_field(&self) -> &Arc<SunTransmittance> {
        &self.sun
    }

    /// The stencil frame at a query: (u, v, w) with w toward the sun and `omega` in the
    /// u-w plane (u along omega's part across w; any u when omega is parallel to w).
    #[inline]
    pub fn frame(&self, omega: Vec3) -> (Vec3, Vec3, Vec3) {
        let w = self.w;
        let across = omega - w * omega.dot(w);
        let u = match across.try_normalize() {
            Some(u) if across.length_squared() > 1e-8 => u,
            _ => engine::sampling::coordinate_system(w).0,
        };
        (u, w.cross(u), w)
    }

    /// The stencil's world positions: `out[l * 27 + p]`.
    #[inline]
    pub fn stencil(&self, x: Vec3, omega: Vec3, out: &mut [Vec3; LEVELS * POINTS]) {
        let (u, v, w) = self.frame(omega);
        for l in 0..LEVELS {
            for p in 0..POINTS {
                let o = offset(p) * self.h[l];
                out[l * POINTS + p] = x + u * o.x + v * o.y + w * o.z;
            }
        }
    }

    /// The feature vector at `x` for query direction `omega` (unit, pointing away from
    /// x) of a medium with `albedo` and phase mean cosine `g` into `out` (length
    /// [`N_FEATURES`]): the stored features ([`CloudField::stored_features`]), then
    /// the derived ones ([`derive_inputs`]). No allocation.
    pub fn features(&self, albedo: f32, g: f32, x: Vec3, omega: Vec3, out: &mut [f32]) {
        assert_eq!(out.len(), N_FEATURES, "feature vector length");
        self.stored_features(albedo, g, x, omega, &mut out[..STORED_FEATURES]);
        derive_inputs(out);
    }

    /// The first [`STORED_FEATURES`] of [`CloudField::features`] into `out` (that
    /// length): what a data set stores.
    pub fn stored_features(&self, albedo: f32, g: f32, x: Vec3, omega: Vec3, out: &mut [f32]) {
        assert_eq!(out.len(), STORED_FEATURES, "stored feature vector length");
        let mut pts = [Vec3::ZERO; LEVELS * POINTS];
        self.stencil(x, omega, &mut pts);
        out[0] = absorption_feature(albedo);
        out[1] = g;
        let cos = omega.dot(self.w).clamp(-1.0, 1.0);
        out[2] = cos;
        let mut gn = g;
        for o in &mut out[PHASE_START..HEAD] {
            *o = ln_phase(gn, -cos);
            gn *= g;
        }
        let mut raw = [0.0f32; 2 * LEVELS * POINTS];
        self.raw_stencil(&pts, &mut raw);
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        for (o, r) in out[HEAD..].chunks_exact_mut(PLANE_FEATURES).zip(raw.chunks_exact(PLANE)) {
            encode_plane(r, sin, o);
        }
    }

    /// The stencil's raw values at `pts` (from [`CloudField::stencil`]): the cell
    /// optical thicknesses ln(1 + rho d h_l) in `raw[..162]`, the sun's tau_hat in
    /// `raw[162..]`, both indexed l * 27 + p.
    pub fn raw_stencil(&self, pts: &[Vec3; LEVELS * POINTS], raw: &mut [f32; 2 * LEVELS * POINTS]) {
        let (dens, taus) = raw.split_at_mut(LEVELS * POINTS);
        for l in 0..LEVELS {
            let range = l * POINTS..(l + 1) * POINTS;
            self.pyramid.lookup_many(self.blends[l], &pts[range.clone()], &mut dens[range.clone()]);
            let cell = self.rho * self.h[l];
            for d in &mut dens[range] {
                *d *= cell;
            }
        }
        self.sun.optical_depth_many(pts, taus);
        // ln(1 + max(v, 0)) of all 324 at once (eight at a time); tau_hat is its negative.
        crate::nn::fastmath::ln_1p_many(raw);
        for t in &mut raw[LEVELS * POINTS..] {
            *t = -*t;
        }
    }
}

/// The 16-bit density pyramids built last, with the grid and the filter widths each
/// was built for. A pyramid depends on the grid and the widths only (not on rho, the
/// sun or the sun field's size), so the bindings of one cloud share one: the window
/// binds a cloud at three field sizes per change (its first look, the render's coarse
/// start, the full field) and again for every new sun or rho, and rebuilding the
/// pyramid each time made every change wait for it. The grids are held weakly: the
/// cache keeps no cloud alive, and a dropped grid's entry can never match a new grid
/// at the same address (a live `Weak` keeps the address allocated). Grids are not
/// changed once shared behind an `Arc`.
static PYRAMIDS: Mutex<Vec<PyramidEntry>> = Mutex::new(Vec::new());

/// A grid, the filter widths (as bits) with the block size of the pyramid's samples,
/// and the pyramid built for them.
type PyramidEntry = (Weak<DensityGrid>, ([u32; LEVELS], u32), Arc<DensityPyramid>);

/// The pyramid of a field of `max_nodes` sun-field nodes per axis is built from at
/// most twice as many samples per axis (block averages of a finer grid): a binding's
/// node count is its budget of detail and time. The renderer's fields (128 nodes and
/// up) and the data generator's read every voxel of grids up to 256^3; the window's
/// first look after a change (32 nodes) filters 2^3-voxel blocks of its 96^3 cloud,
/// an eighth of the voxels, so that a new cloud shows within the latency goal.
pub fn pyramid_axis(max_nodes: u32) -> u32 {
    max_nodes.saturating_mul(2)
}

/// Pyramids that no field holds kept by [`shared_pyramid`] (a cloud and the one
/// before it: dragging a slider back and forth, or a coarse and a full build of one
/// cloud). A pyramid some field holds stays findable while it does, at no cost in
/// memory.
const PYRAMIDS_KEPT: usize = 2;

/// The quantized pyramid of `grid` for the stencil's filter `widths`, from block
/// averages with at most `max_axis` samples per axis
/// ([`DensityPyramid::for_widths_until`]), from the cache when it holds one (the same
/// pyramid, bit for bit: bindings whose `max_axis` gives the same blocks share it),
/// else built and kept; None when `cancel` asks to stop before it is built.
pub fn shared_pyramid(
    grid: &Arc<DensityGrid>,
    widths: &[f32; LEVELS],
    max_axis: u32,
    cancel: Cancel,
) -> Option<Arc<DensityPyramid>> {
    let key = (widths.map(f32::to_bits), DensityPyramid::block_factor(grid.dims(), max_axis));
    let same = |e: &PyramidEntry| e.1 == key && std::ptr::eq(e.0.as_ptr(), Arc::as_ptr(grid));
    {
        let mut cache = PYRAMIDS.lock().unwrap_or_else(|p| p.into_inner());
        cache.retain(|e| e.0.strong_count() > 0);
        if let Some(e) = cache.iter().find(|e| same(e)) {
            return Some(e.2.clone());
        }
    }
    let pyramid = Arc::new(DensityPyramid::for_widths_until(grid, widths, max_axis, cancel)?.quantized());
    let mut cache = PYRAMIDS.lock().unwrap_or_else(|p| p.into_inner());
    if !cache.iter().any(same) {
        cache.insert(0, (Arc::downgrade(grid), key, pyramid.clone()));
        // Most recent first: drop the unused ones beyond the first PYRAMIDS_KEPT.
        let mut unused = 0;
        cache.retain(|e| {
            unused += usize::from(Arc::strong_count(&e.2) == 1);
            Arc::strong_count(&e.2) > 1 || unused <= PYRAMIDS_KEPT
        });
    }
    Some(pyramid)
}

/// Empties [`shared_pyramid`]'s cache, so that the next binding of any cloud builds
/// its pyramid as for a new cloud (pyramids that fields hold stay with them). For
/// measurements of a new cloud's set-up (`nimbus eval --preview`).
pub fn forget_pyramids() {
    PYRAMIDS.lock().unwrap_or_else(|p| p.into_inner()).clear();
}

/// Points of one stencil plane (fixed c): 3 x 3.
pub const PLANE: usize = 9;
/// Features of one plane: centre, ring mean, seven scaled deviations, gradient, the
/// ring's least and greatest values.
pub const PLANE_FEATURES: usize = 12;

/// One plane's nine raw values (index (a + 1) + 3 (b + 1)) as the network sees them:
/// the centre, the mean m of the ring of eight around it, sin(theta) (v - m) for
/// the first seven ring points (the eighth follows from the mean), and the magnitude
/// of the plane's gradient. The ring's layout depends on the azimuth of the query
/// about the sun, which is undefined when the query points along the sun's axis;
/// scaling what depends on it by sin(theta) makes the features continuous there (they
/// tend to rotation-invariant ones), so a frontlit or backlit view is not a
/// discontinuity the network has to learn around. That leaves an aligned view with
/// the ring's mean alone, which cannot tell a point beside a thick body (a fringe)
/// from one in a thin even layer; the gradient's magnitude can, and it does not
/// depend on the azimuth: the root mean square of the central differences along the
/// two axes and, divided by sqrt 2, along the two diagonals, which for a field
/// linear over the plane is |grad| h at any azimuth. The ring's least and greatest
/// values follow: they do not depend on the azimuth either, and say what a mean and a
/// slope cannot, whether an empty or a lit neighbour lies on some side (a gap in a
/// thick layer, light reaching a shadowed point from beside it), which a network
/// would otherwise have to build from the scaled deviations, and cannot at alignment.
#[inline]
pub fn encode_plane(raw: &[f32], sin_theta: f32, out: &mut [f32]) {
    const RING: [usize; 8] = [0, 1, 2, 3, 5, 6, 7, 8];
    let m = RING.iter().map(|&i| raw[i]).sum::<f32>() / 8.0;
    out[0] = raw[4];
    out[1] = m;
    for (o, &i) in out[2..9].iter_mut().zip(&RING[..7]) {
        *o = sin_theta * (raw[i] - m);
    }
    let (ax, ay) = (0.5 * (raw[5] - raw[3]), 0.5 * (raw[7] - raw[1]));
    let (d1, d2) = (0.5 * (raw[8] - raw[0]), 0.5 * (raw[6] - raw[2]));
    // The diagonals are sqrt 2 h long: (d1^2 + d2^2) / 2 is |grad|^2 h^2 too.
    out[9] = (0.5 * (ax * ax + ay * ay + 0.5 * (d1 * d1 + d2 * d2))).sqrt();
    let (lo, hi) =
        RING.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &i| (lo.min(raw[i]), hi.max(raw[i])));
    out[10] = lo;
    out[11] = hi;
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::{Bounds3, DensityGrid, PhaseFunction};
    use glam::UVec3;
    use std::sync::Arc;

    fn blob_medium() -> Medium {
        let grid = DensityGrid::from_fn(UVec3::splat(48), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
            let r = (p - Vec3::new(0.05, 0.0, -0.03)).length();
            (1.0 - r / 0.35).clamp(0.0, 1.0) * (1.0 + 0.5 * (9.0 * p.x).sin() * (7.0 * p.y).cos())
        })
        .unwrap();
        Medium::new(Arc::new(grid), 30.0, 0.97, PhaseFunction::HenyeyGreenstein { g: 0.6 }).unwrap()
    }

    #[test]
    fn layout_names_and_offsets() {
        assert_eq!(feature_names().len(), N_FEATURES);
        assert_eq!(offset(13), Vec3::ZERO);
        assert_eq!(offset(0), Vec3::splat(-1.0));
        assert_eq!(offset(26), Vec3::splat(1.0));
        let mut seen = std::collections::HashSet::new();
        for p in 0..POINTS {
            let o = offset(p);
            assert!(o.abs().max_element() <= 1.0);
            assert!(seen.insert(o.to_array().map(|v| v as i32)), "offset {p} repeats");
        }
    }

    /// The frame is orthonormal, w points to the sun, omega lies in the u-w plane with
    /// a non-negative u component.
    #[test]
    fn frame_holds_the_query_in_the_u_w_plane() {
        let m = blob_medium();
        let sun = Sun::new(Vec3::new(0.3, -1.0, 0.2), Vec3::ONE, 0.0).unwrap();
        let f = CloudField::build(&m, &sun, 64);
        let mut rng = engine::Rng::new(3, 0, 0);
        for _ in 0..200 {
            let omega = engine::sampling::sample_uniform_sphere(rng.uniform2());
            let (u, v, w) = f.frame(omega);
            assert!((w + sun.direction()).length() < 1e-5);
            for (a, b) in [(u, v), (u, w), (v, w)] {
                assert!(a.dot(b).abs() < 1e-5);
            }
            assert!((u.length() - 1.0).abs() < 1e-5 && (v.length() - 1.0).abs() < 1e-5);
            assert!(omega.dot(v).abs() < 1e-4 && omega.dot(u) >= -1e-6);
        }
        // Parallel to the sun: still a frame.
        let (u, v, _) = f.frame(-sun.direction());
        assert!((u.length() - 1.0).abs() < 1e-5 && u.dot(v).abs() < 1e-5);
    }

    /// Every feature against brute force: the density by a direct Gaussian-weighted sum
    /// over the voxels, the sun's optical depth by marching the medium toward the sun.
    #[test]
    fn features_match_brute_force() {
        let m = blob_medium();
        let sun = Sun::new(Vec3::new(-0.4, -1.0, 0.5), Vec3::ONE, 0.0).unwrap();
        let f = CloudField::build(&m, &sun, 128);
        let grid = m.grid();
        let vs = grid.voxel_size().x;
        let mut out = vec![0.0; N_FEATURES];
        let mut pts = [Vec3::ZERO; LEVELS * POINTS];
        let mut rng = engine::Rng::new(5, 0, 0);
        for _ in 0..6 {
            let x = (Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5) * 0.5;
            let omega = engine::sampling::sample_uniform_sphere(rng.uniform2());
            f.features(0.97, 0.6, x, omega, &mut out);
            assert_eq!(out[0], absorption_feature(0.97));
            assert!((out[0] - (0.031f32).ln()).abs() < 1e-5);
            assert!((out[1] - 0.6).abs() < 1e-6);
            let cos = omega.dot(-sun.direction());
            assert!((out[2] - cos).abs() < 1e-5);
            // The phase terms against the engine's Henyey-Greenstein: light from the sun
            // (travelling along its direction) scattered into omega.
            for n in 1..=PHASE_TERMS {
                let hg = PhaseFunction::HenyeyGreenstein { g: 0.6f32.powi(n as i32) };
                let p = hg.eval(omega, -sun.direction());
                assert!((out[2 + n] - (4.0 * std::f32::consts::PI * p).ln()).abs() < 1e-4, "term {n}");
            }
            f.stencil(x, omega, &mut pts);
            let mut raw = [0.0f32; 2 * LEVELS * POINTS];
            f.raw_stencil(&pts, &mut raw);
            // The encoding keeps the raw values: centre, ring mean and the scaled
            // deviations give them back.
            let sin = (1.0 - cos * cos).sqrt();
            for (plane, enc) in out[HEAD..STORED_FEATURES].chunks_exact(PLANE_FEATURES).enumerate() {
                let r = &raw[plane * PLANE..(plane + 1) * PLANE];
                assert_eq!(enc[0], r[4]);
                let ring = [0, 1, 2, 3, 5, 6, 7, 8];
                let mean = ring.iter().map(|&i| r[i]).sum::<f32>() / 8.0;
                assert!((enc[1] - mean).abs() < 1e-5);
                for (k, &i) in ring[..7].iter().enumerate() {
                    assert!((enc[2 + k] / sin + mean - r[i]).abs() < 1e-3, "plane {plane} point {i}");
                }
                let lo = ring.iter().map(|&i| r[i]).fold(f32::INFINITY, f32::min);
                let hi = ring.iter().map(|&i| r[i]).fold(f32::NEG_INFINITY, f32::max);
                assert_eq!((enc[10], enc[11]), (lo, hi), "plane {plane}: the ring's extremes");
            }
            for l in 0..LEVELS {
                let s = 0.5 * f.h[l];
                for p in [0, 4, 13, 22, 26] {
                    let q = pts[l * POINTS + p];
                    // Gaussian of std s over voxel centres (density zero outside).
                    let (mut num, mut den) = (0.0f64, 0.0f64);
                    let r = (4.0 * s / vs).ceil() as i32 + 1;
                    let c = ((q - grid.origin()) / vs - 0.5).round().as_ivec3();
                    for dz in -r..=r {
                        for dy in -r..=r {
                            for dx in -r..=r {
                                let i = c + glam::IVec3::new(dx, dy, dz);
                                let pc = grid.origin() + (i.as_vec3() + 0.5) * vs;
                                let wgt = (-(pc - q).length_squared() as f64 / (2.0 * (s * s) as f64)).exp();
                                den += wgt;
                                let inside = i.cmpge(glam::IVec3::ZERO).all() && i.cmplt(grid.dims().as_ivec3()).all();
                                if inside {
                                    num += wgt * grid.voxel(i.x as u32, i.y as u32, i.z as u32) as f64;
                                }
                            }
                        }
                    }
                    let brute = (num / den) as f32;
                    let got = (raw[l * POINTS + p].exp() - 1.0) / (m.rho() * f.h[l]);
                    // The pyramid's filter is Gaussian up to its trilinear interpolation
                    // and 16-bit samples: a few per cent of the peak density.
                    assert!((got - brute).abs() < 0.04 + 0.05 * brute, "level {l} point {p}: {got} vs {brute}");
                    // The sun's optical depth: a fine march from the stencil point.
                    // The field is trilinear between nodes one voxel apart: within a
                    // voxel's optical thickness at the peak density (1.5) of the march.
                    let march = m.optical_depth(q, -sun.direction(), f32::INFINITY, 0.25 * vs, f32::INFINITY);
                    let tau = (-raw[LEVELS * POINTS + l * POINTS + p]).exp() - 1.0;
                    assert!((tau - march).abs() <= 0.05 * march + 1.5 * m.rho() * vs, "{tau} vs {march}");
                }
            }
            // The coupling reads tau_hat at x itself, the centre of level 0's middle
            // plane (exactly; the tolerances below could not tell a neighbour apart).
            assert_eq!(feature_names()[TAU_HAT_AT_X], "tau_sun_0_1_centre");
            assert_eq!(out[TAU_HAT_AT_X], raw[LEVELS * POINTS + 13]);
            assert_eq!(offset(13), Vec3::ZERO);
            // The coupling: each phase term times exp(-a tau) with tau marched from x;
            // the field's error in tau (as above) bounds the factor's by a dtau.
            let march = m.optical_depth(x, -sun.direction(), f32::INFINITY, 0.25 * vs, f32::INFINITY);
            let dtau = 0.05 * march + 1.5 * m.rho() * vs;
            for n in 1..=PHASE_TERMS {
                let hg = PhaseFunction::HenyeyGreenstein { g: 0.6f32.powi(n as i32) };
                let ln_p = (4.0 * std::f32::consts::PI * hg.eval(omega, -sun.direction())).ln();
                for (j, a) in COUPLING_ATTENUATIONS.iter().enumerate() {
                    let got = out[STORED_FEATURES + (n - 1) * COUPLING_ATTENUATIONS.len() + j];
                    let want = ln_p * (-a * march).exp();
                    let tol = ln_p.abs() * (-a * (march - dtau).max(0.0)).exp() * (1.0 - (-a * dtau).exp()) + 1e-4;
                    assert!((got - want).abs() <= tol, "coupling n {n} a {a}: {got} vs {want} (tau {march})");
                }
            }
        }
    }

    /// Data sets store the first STORED_FEATURES values; spreading stored rows in place
    /// gives back every row's whole vector, derived as `features` derives it.
    #[test]
    fn stored_rows_expand_to_whole_vectors() {
        let m = blob_medium();
        let sun = Sun::new(Vec3::new(0.3, -1.0, -0.2), Vec3::ONE, 0.0).unwrap();
        let f = CloudField::build(&m, &sun, 64);
        let mut rng = engine::Rng::new(11, 0, 0);
        let (mut whole, mut stored) = (vec![], vec![1.5f32; 3]);
        let mut row = vec![0.0; N_FEATURES];
        for k in 0..20 {
            let x = (Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5) * 0.6;
            let omega = engine::sampling::sample_uniform_sphere(rng.uniform2());
            f.features(0.9 + 0.005 * k as f32, 0.85, x, omega, &mut row);
            whole.extend_from_slice(&row);
            stored.extend_from_slice(&row[..STORED_FEATURES]);
        }
        // Rows after three values already in the buffer, which stay.
        expand_stored_rows(&mut stored, 3, 20);
        assert_eq!(&stored[..3], &[1.5; 3]);
        assert_eq!(&stored[3..], &whole[..]);
        assert_eq!(feature_names()[..STORED_FEATURES], stored_feature_names()[..]);
    }

    /// The features are continuous where the frame is not: queries ever closer to the
    /// sun's axis from different azimuths give ever closer feature vectors.
    #[test]
    fn features_are_continuous_along_the_sun_axis() {
        let m = blob_medium();
        let sun = Sun::new(Vec3::new(0.2, -1.0, 0.3), Vec3::ONE, 0.0).unwrap();
        let f = CloudField::build(&m, &sun, 64);
        let w = -sun.direction();
        let (a, b) = engine::sampling::coordinate_system(w);
        let x = Vec3::new(0.05, 0.02, -0.04);
        let (mut p, mut q) = (vec![0.0; N_FEATURES], vec![0.0; N_FEATURES]);
        let mut last = f32::INFINITY;
        for eps in [1e-1f32, 1e-2, 1e-3, 1e-4] {
            f.features(1.0, 0.8, x, (w + a * eps).normalize(), &mut p);
            f.features(1.0, 0.8, x, (w - b * eps).normalize(), &mut q);
            let d = p.iter().zip(&q).map(|(u, v)| (u - v).abs()).fold(0.0, f32::max);
            assert!(d < last, "eps {eps}: {d} does not shrink (was {last})");
            last = d;
        }
        assert!(last < 1e-3, "{last}");
    }

    /// The gradient feature of a plane sampled from a linear field is |grad| h
    /// whatever the ring's azimuth about the plane's normal.
    #[test]
    fn plane_gradient_does_not_depend_on_the_azimuth() {
        let (grad, h) = (glam::Vec2::new(0.7, -0.3), 1.3f32);
        let mut out = [0.0f32; PLANE_FEATURES];
        for k in 0..12 {
            let phi = 0.37 * k as f32;
            let (c, s) = (phi.cos(), phi.sin());
            let raw: Vec<f32> = (0..PLANE)
                .map(|i| {
                    let (a, b) = ((i % 3) as f32 - 1.0, (i / 3) as f32 - 1.0);
                    let p = glam::Vec2::new(c * a - s * b, s * a + c * b) * h;
                    2.0 + grad.dot(p)
                })
                .collect();
            encode_plane(&raw, 0.5, &mut out);
            assert!((out[9] - grad.length() * h).abs() < 1e-5, "azimuth {phi}: {} vs {}", out[9], grad.length() * h);
        }
    }

    /// Same inputs, same features, to the bit, and a field built for one sun answers
    /// for that sun only.
    #[test]
    fn features_are_deterministic() {
        let m = blob_medium();
        let sun = Sun::new(Vec3::new(0.0, -1.0, 0.0), Vec3::ONE, 0.0).unwrap();
        let a = CloudField::build(&m, &sun, 64);
        // Another grid of the same cloud, so that its pyramid is built again.
        let m1 = blob_medium();
        let b = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| CloudField::build(&m1, &sun, 64));
        assert!(!Arc::ptr_eq(&a.pyramid, &b.pyramid));
        let (mut fa, mut fb) = (vec![0.0; N_FEATURES], vec![0.0; N_FEATURES]);
        a.features(0.9, 0.5, Vec3::new(0.1, 0.0, 0.05), Vec3::X, &mut fa);
        b.features(0.9, 0.5, Vec3::new(0.1, 0.0, 0.05), Vec3::X, &mut fb);
        assert_eq!(fa, fb);
        assert!(fa.iter().all(|v| v.is_finite()));
    }

    /// A field reading a sun field built by its caller (the preview's) gives the
    /// features of one that built the same field itself, bit for bit, shares the
    /// caller's field and pyramid, and counts the pyramid only; another field changes
    /// the sun's features (and those derived from them) and nothing else.
    #[test]
    fn a_shared_sun_field_reads_as_its_own() {
        let m = blob_medium();
        let sun = Sun::new(Vec3::new(0.4, -1.0, 0.3), Vec3::ONE, 0.0).unwrap();
        let own = CloudField::build(&m, &sun, 24);
        let field = Arc::new(SunTransmittance::build(&m, &sun, 24));
        let shared = CloudField::with_sun_field_until(&m, field.clone(), 24, Cancel::NEVER).unwrap();
        assert!(Arc::ptr_eq(shared.sun_field(), &field));
        assert!(Arc::ptr_eq(&own.pyramid, &shared.pyramid));
        assert_eq!(own.memory_bytes(), shared.memory_bytes() + field.memory_bytes());
        assert_eq!(shared.memory_bytes(), shared.pyramid.bytes());
        let finer =
            CloudField::with_sun_field_until(&m, Arc::new(SunTransmittance::build(&m, &sun, 96)), 24, Cancel::NEVER)
                .unwrap();
        let (mut fo, mut fs, mut ff) = (vec![0.0; N_FEATURES], vec![0.0; N_FEATURES], vec![0.0; N_FEATURES]);
        let names = feature_names();
        let mut moved = 0;
        for (i, x) in [Vec3::new(0.1, 0.0, 0.05), Vec3::new(-0.2, 0.1, 0.0), Vec3::ZERO].into_iter().enumerate() {
            let omega = Vec3::new(1.0, 0.2 * i as f32, -0.3).normalize();
            own.features(0.95, 0.8, x, omega, &mut fo);
            shared.features(0.95, 0.8, x, omega, &mut fs);
            finer.features(0.95, 0.8, x, omega, &mut ff);
            assert_eq!(fo, fs);
            for (j, (a, b)) in fo.iter().zip(&ff).enumerate() {
                // The sun's optical depths and the features derived from them.
                if names[j].starts_with("tau_sun") || names[j].contains("_x_sun_") {
                    moved += (a != b) as usize;
                } else {
                    assert_eq!(a, b, "{}", names[j]);
                }
            }
        }
        assert!(moved > 0, "the finer field is another field");
    }

    /// The fields of one grid share its pyramid whatever the sun, rho and sun-field
    /// size down to half the grid's voxels per axis (coarser fields share a coarser
    /// one); another grid (even of the same cloud) gets its own; a grid dropped leaves
    /// the cache.
    #[test]
    fn fields_of_one_grid_share_the_pyramid() {
        let m = blob_medium();
        let sun = Sun::new(Vec3::new(0.0, -1.0, 0.0), Vec3::ONE, 0.0).unwrap();
        let side = Sun::new(Vec3::new(1.0, -0.3, 0.2), Vec3::ONE, 0.0).unwrap();
        let a = CloudField::build(&m, &sun, 64);
        let thicker = Medium::new(m.grid().clone(), 60.0, 0.9, PhaseFunction::HenyeyGreenstein { g: 0.8 }).unwrap();
        let b = CloudField::build(&thicker, &side, 24);
        assert!(Arc::ptr_eq(&a.pyramid, &b.pyramid));
        // A field coarser than half the grid's voxels per axis reads block averages:
        // a pyramid of its own, shared by the fields that give the same blocks.
        let coarse = CloudField::build(&m, &side, 16);
        let coarser = CloudField::build(&thicker, &sun, 12);
        assert!(!Arc::ptr_eq(&a.pyramid, &coarse.pyramid));
        assert!(Arc::ptr_eq(&coarse.pyramid, &coarser.pyramid));
        assert!(coarse.pyramid.bytes() * 4 < a.pyramid.bytes(), "{} / {}", coarse.pyramid.bytes(), a.pyramid.bytes());
        let other = blob_medium();
        let c = CloudField::build(&other, &sun, 64);
        assert!(!Arc::ptr_eq(&a.pyramid, &c.pyramid));
        let weak = Arc::downgrade(other.grid());
        drop((other, c));
        assert_eq!(weak.strong_count(), 0, "the cache holds no grid");
        let live = |w: &Weak<DensityGrid>| PYRAMIDS.lock().unwrap().iter().any(|e| Weak::ptr_eq(&e.0, w));
        let _ = CloudField::build(&blob_medium(), &sun, 16);
        assert!(!live(&weak), "a dropped grid's entry is gone");
    }
}
