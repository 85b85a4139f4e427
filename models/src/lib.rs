//! The thesis's learned transport models. So far: the feature extraction of the global
//! transport model (thesis section 5.1), shared by data generation and rendering.

pub mod directions;
pub mod features;
pub mod ground_truth;
