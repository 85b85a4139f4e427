//! Nimbus engine: a progressive CPU volumetric path tracer for cloud density grids.
//!
//! Delta tracking over a majorant grid, next event estimation toward a directional
//! sun, ratio-tracked shadow rays, deterministic ray-marched optical depth, phase
//! functions of the thesis, and accumulation buffers split by scattering order
//! (CONVENTIONS.md). A learned predictor plugs in through [`InScatterPredictor`] (the
//! path tracer's prediction at bounce k) or [`TransportPredictor`] (BDPT's prediction
//! between its two subpaths).

pub mod bdpt;
pub mod camera;
pub mod film;
pub mod grid;
pub mod integrator;
pub mod light;
pub mod medium;
pub mod p2p;
pub mod phase;
pub mod predictor;
pub mod render;
pub mod rng;
pub mod sampling;
pub mod stats;

pub use bdpt::{BdptSettings, MisHeuristic};
pub use camera::Camera;
pub use film::{Buffer, Film};
pub use grid::{Bounds3, DensityGrid, GridError};
pub use integrator::{Integrator, Mode, PathSample, RenderSettings, Scene, Technique};
pub use light::{Sky, Sun};
pub use medium::{FreeFlight, Medium};
pub use phase::PhaseFunction;
pub use predictor::{InScatterPredictor, TransportPredictor};
pub use render::{PassOutcome, RenderControl, Renderer};
pub use rng::Rng;
