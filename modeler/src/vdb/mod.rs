//! OpenVDB files in and out.

mod read;
mod write;

pub use read::{MAX_DENSE_VOXELS, MAX_SPARSE_VOXELS, VdbImport, VdbReadError, read_vdb, read_vdb_bytes};
pub use write::{VdbWriteError, vdb_bytes};
