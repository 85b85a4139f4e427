//! What both models' networks share: dense layers evaluated without allocation
//! (portable, AVX2 + FMA and AVX-512 kernels), the MLP evaluator, the optimizers and the
//! training schedule check, the shared training loop, and a vectorized ln(1 + x).

pub mod dense;
pub mod fastmath;
pub mod fit;
pub mod mlp;
pub mod optim;
pub mod refit;

pub use dense::{Activation, Kernel};
pub use mlp::{BATCH_ROWS, Mlp, Scratch};
pub use optim::Optimizer;
