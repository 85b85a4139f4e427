//! The point-to-point transport model (thesis chapter 6): the density pyramid, the
//! local frame and the density features (6.1.1), the networks (6.2.1), the ground
//! truth and its data generator (6.3), training, and the predictor that BDPT's
//! prediction mode calls (6.4).

pub mod datagen;
pub mod features;
pub mod frame;
pub mod model;
pub mod net;
pub mod pyramid;
pub mod train;

pub use datagen::{P2pManifest, P2pSpec};
pub use features::P2pFeatures;
pub use frame::LocalFrame;
pub use model::{BoundP2pModel, P2pModel, P2pSidecar};
pub use net::{P2pArch, P2pNetwork};
pub use pyramid::DensityPyramid;
pub use train::P2pTrainConfig;
