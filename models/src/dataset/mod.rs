//! What both data generators share: `.npy` files written atomically, the manifest,
//! chunks, shards, resume and merge.

pub mod chunks;
pub mod manifest;
pub mod npy;
pub mod stopping;

pub use chunks::{chunk_path, generate, merge};
pub use manifest::{Counts, DataSpec, DatagenError, Manifest, Shard, parse_range};
