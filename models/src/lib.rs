//! The thesis's learned transport models: the global model's features (thesis section
//! 5.1), ground truth and data generation (5.3), training and inference (5.2).

pub mod datagen;
pub mod density_features;
pub mod depth_field;
pub mod directions;
pub mod features;
pub mod global;
pub mod ground_truth;
pub mod npy;
pub mod p2p_datagen;
pub mod p2p_net;
pub mod p2p_train;
pub mod plot;
pub mod train;
