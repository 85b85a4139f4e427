//! The learned transport models of the thesis, their data, training and inference.
//!
//! - [`global`]: the global model (thesis chapter 5): features, ground truth, data
//!   generation, training and the renderer's evaluator at bounce k;
//! - [`p2p`]: the point-to-point model (thesis chapter 6): density pyramid, features,
//!   networks, data generation, training and the predictor for BDPT;
//! - [`nn`]: what both networks share: dense layers with AVX2 kernels, the MLP, the
//!   optimizers and the fast ln(1 + x);
//! - [`dataset`]: what both data generators share: `.npy` files, manifests, chunks,
//!   shards, resume and merge;
//! - [`cloud`]: the cloud-aware model of prediction at bounce k:
//!   stencil features of the real cloud, data from the modeler's clouds, training, the
//!   predictor; [`prediction`] puts it and the global model behind one type;
//! - [`plot`] (loss curves as PNG) and [`fingerprint`] (model files' identity).

pub mod cloud;
pub mod dataset;
pub mod fingerprint;
pub mod global;
pub mod nn;
pub mod p2p;
pub mod plot;
pub mod prediction;
