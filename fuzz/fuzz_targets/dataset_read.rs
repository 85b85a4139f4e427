//! The data-set readers: a chunk or array file (.npy), and the manifests of both
//! generators with what a resume or merge computes from their settings. Any bytes
//! give a value or an error, never a panic. The first byte chooses the reader.
#![no_main]
use libfuzzer_sys::fuzz_target;
use models::dataset::{DataSpec, Manifest, Shard};
use std::path::Path;

fn manifest<S: DataSpec>(text: &str) {
    if let Ok(m) = Manifest::<S>::from_json(text, Path::new("fuzz/manifest.json")) {
        let s = &m.settings;
        for c in 0..s.n_chunks().min(64) {
            let _ = s.chunk_len(c);
        }
        let _ = s.shard_points(Shard { index: 0, count: 3 });
        let _ = (s.points() * s.rows_per_point(), s.n_features());
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&kind, rest)) = data.split_first() else { return };
    match kind % 3 {
        0 => {
            if let Ok((shape, values)) = models::dataset::npy::parse_f32(rest) {
                assert_eq!(shape.iter().product::<usize>(), values.len());
            }
        }
        1 => manifest::<models::global::GlobalSpec>(&String::from_utf8_lossy(rest)),
        _ => manifest::<models::p2p::P2pSpec>(&String::from_utf8_lossy(rest)),
    }
});
