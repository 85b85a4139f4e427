//! The cloud-aware model: prediction at bounce k from the real cloud around the query
//! point. Features from a light-oriented density stencil and the sun-transmittance
//! field ([`features`]), data from the modeler's clouds ([`datagen`]), training with a
//! loss that noisy targets do not bias ([`train`]) and the predictor the renderer
//! calls ([`model`]).

pub mod datagen;
pub mod features;
pub mod model;
pub mod train;

pub use datagen::{CloudManifest, CloudSpec};
pub use features::CloudField;
pub use model::{BoundCloudModel, CloudModel};
pub use train::CloudTrainConfig;
