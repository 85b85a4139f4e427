//! BDPT's strategy settings, its subpaths and their vertices, and the record of one
//! strategy's contribution.

use crate::integrator::base::{MisHeuristic, roulette};
use crate::light::Sun;
use crate::medium::FreeFlight;
use crate::rng::Rng;
use crate::sampling::{coordinate_system, sample_uniform_disk};
use crate::scene::Scene;
use glam::Vec3;
use std::f32::consts::PI;

/// BDPT's strategy set.
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
pub(super) const RING: usize = 64;
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

/// A scattering vertex of a subpath.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Vertex {
    pub(super) x: Vec3,
    /// Unit direction toward the vertex before it on its own subpath (or the sun).
    pub(super) wo: Vec3,
    /// Throughput of the subpath up to and including this vertex's albedo.
    pub(super) beta: f32,
    pub(super) sigma_t: f32,
}

/// A light subpath: up to MAX_LIGHT_VERTICES scattering vertices from the sun's beam.
pub(super) struct LightPath {
    pub(super) verts: [Vertex; MAX_LIGHT_VERTICES as usize],
    pub(super) len: usize,
    /// Direction the sun's light travels in (sampled within the sun's cone).
    pub(super) beam: Vec3,
    /// Area of the beam's disk, pi R^2: the light vertices' throughputs are per unit
    /// sun radiance times this.
    pub(super) area: f32,
}

/// The camera subpath's latest vertices, and the camera position as vertex 0.
pub(super) struct CameraRing {
    pub(super) origin: Vec3,
    pub(super) verts: [Vertex; RING],
}

impl CameraRing {
    #[inline]
    pub(super) fn get(&self, i: usize) -> &Vertex {
        &self.verts[i % RING]
    }
}

impl std::ops::Index<usize> for LightPath {
    type Output = Vertex;
    fn index(&self, i: usize) -> &Vertex {
        &self.verts[i]
    }
}

/// Traces a light subpath: from a uniform point on a disk perpendicular to the sun
/// that covers the cloud's bounding sphere, into the cloud by delta tracking and on by
/// phase sampling and Russian roulette, up to `b.max_light_vertices` vertices.
pub(super) fn light_path(b: &BdptSettings, scene: &Scene, sun: &Sun, rng: &mut Rng) -> LightPath {
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
        let Ok(next) = medium.scatter(x, wo, rng) else { return lp };
        (x, wo) = next;
        beta *= medium.albedo();
    }
}
