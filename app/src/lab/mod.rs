//! Research tooling, apart from the user's path: the thesis's evaluations
//! (`nimbus eval`) and the benchmarks (`nimbus bench`).

pub mod bench;
pub mod eval;
