//! Nimbus engine: a progressive CPU volumetric path tracer for cloud density grids.
//!
//! Delta tracking over a majorant grid, next event estimation toward a directional
//! sun, ratio-tracked shadow rays, deterministic ray-marched optical depth, phase
//! functions of the thesis, and accumulation buffers split by scattering order
//! (docs/conventions.md). A learned predictor plugs in through [`InScatterPredictor`]
//! (the path tracer's prediction at bounce k) or [`TransportPredictor`] (BDPT's
//! prediction between its two subpaths).
//!
//! Modules, bottom up: [`rng`], [`sampling`], [`stats`]; [`phase`], [`grid`],
//! [`medium`], [`light`], [`camera`], [`scene`], [`field`]; [`predictor`]; [`integrator`] (path
//! tracing, BDPT, the point-to-point estimator); [`film`] and [`render`] (progressive
//! tiles and passes).

pub mod blocks;
pub mod camera;
pub mod control;
pub mod field;
pub mod film;
pub mod grid;
pub mod integrator;
pub mod light;
pub mod medium;
pub mod phase;
pub mod predictor;
pub mod render;
pub mod rng;
pub mod sampling;
pub mod scene;
pub mod stats;

pub use camera::Camera;
pub use control::{Cancel, RenderControl};
pub use film::{Buffer, Film};
pub use grid::{Bounds3, DensityGrid, GridError, SparseBuilder};
pub use integrator::bdpt::BdptSettings;
pub use integrator::{FirstVertex, Integrator, MisHeuristic, Mode, PathSample, RenderSettings, Technique};
pub use light::{Sky, Sun};
pub use medium::{FreeFlight, Medium, RATIO_TRACKING_OVERSAMPLING};
pub use phase::PhaseFunction;
pub use predictor::{InScatterPredictor, P2pQuery, TransportPredictor};
pub use render::{PassOutcome, Renderer};
pub use rng::Rng;
pub use scene::Scene;
