//! The global transport model (thesis chapter 5): the light-frame features with
//! optical depths along a direction set (thesis 5.1), the ground truth in
//! homogeneous convex media and its data generator (5.3), training (5.2), and the
//! model files and evaluator the renderer uses at bounce k, with the precomputed
//! depth field that makes its features cheap.

pub mod datagen;
pub mod depth_field;
pub mod directions;
pub mod features;
pub mod ground_truth;
pub mod model;
pub mod sky_field;
pub mod train;

pub use datagen::{Dataset, GlobalManifest, GlobalSpec, ShapeKind};
pub use depth_field::DepthField;
pub use model::{BoundGlobalModel, GlobalModel, ModelError, Sidecar, TargetKind};
pub use sky_field::SkyDepthField;
pub use train::{TrainConfig, TrainData, TrainError};
