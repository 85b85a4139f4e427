//! The procedural cloud modeler: a seeded sphere hierarchy (roots, children on their
//! parents' surfaces, biased outward and upward, an optional flat base), a smooth
//! density with a controllable falloff at the boundary, noise displacement of the
//! boundary, a domain warp ("advection") for wispy detail, and an interior noise
//! multiplier for heterogeneous clouds (thesis appendix A, scene C).
//!
//! Everything is a pure function of [`CloudParams`] (seed included), evaluated in
//! parallel per z-slice, so the same parameters give the same grid on any thread
//! count.

pub mod params;
pub mod presets;
pub mod vdb;

mod build;

pub use build::{CloudModel, build_grid};
pub use params::{CloudParams, Group, PARAMS, ParamError, ParamSpec};
pub use presets::{PRESET_NAMES, preset};
