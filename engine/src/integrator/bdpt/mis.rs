//! Multiple importance sampling between BDPT's strategies (balance or power
//! heuristic). A path with n scattering vertices can come from the strategies
//! c = 1 ..= n, c the number of its vertices the camera walk made (c = n is next event
//! estimation, c < n connects x_c to light vertex x_{c+1}). The per-vertex densities
//! are the phase pdf, sigma_t at the vertex and the inverse squared distance; they
//! leave out the transmittance of the edge that sampled the vertex, which has no
//! closed form in a heterogeneous medium. Weights that depend on the path alone and
//! sum to one over the strategies that can make it keep the estimator unbiased (Veach
//! 1997, sec. 9.2), so this costs variance at most. Strategies outside the caps of
//! [`BdptSettings`] get no weight.

use super::subpath::{BdptSettings, CameraRing, LightPath};
use crate::integrator::base::MisHeuristic;
use crate::phase::PhaseFunction;
use glam::Vec3;

/// One full path for the weights: x_0 the camera, x_1 .. x_c from the camera walk,
/// x_{c+1} .. x_n the light walk's vertices l .. 1, and the direction toward the sun
/// at x_n.
pub(super) struct PathView<'a> {
    pub(super) cam: &'a CameraRing,
    pub(super) light: Option<&'a LightPath>,
    pub(super) c: usize,
    pub(super) n: usize,
    pub(super) to_sun: Vec3,
}

impl PathView<'_> {
    #[inline]
    pub(super) fn vertex(&self, i: usize) -> (Vec3, f32) {
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

/// The heuristic's density of x_i sampled from x_{i-1} by the camera walk (i >= 2).
#[inline]
fn q_camera(p: &PathView, phase: PhaseFunction, i: usize) -> f64 {
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
fn q_light(p: &PathView, phase: PhaseFunction, area: f32, i: usize) -> f64 {
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
pub(super) fn mis_weight(p: &PathView, phase: PhaseFunction, area: f32, b: &BdptSettings, max_depth: usize) -> f32 {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrator::bdpt::subpath::{MAX_LIGHT_VERTICES, RING, Vertex};
    use crate::rng::Rng;

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
}
