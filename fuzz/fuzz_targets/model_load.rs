//! The model loaders, both models: any weights bytes and sidecar text give a model
//! that predicts without panicking, or an error. Input: one byte choosing the model,
//! two bytes of sidecar length (little-endian), the sidecar, then the weights.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, rest)) = data.split_first() else { return };
    let Some((len, rest)) = rest.split_first_chunk::<2>() else { return };
    let len = (u16::from_le_bytes(*len) as usize).min(rest.len());
    let (sidecar, weights) = rest.split_at(len);
    let sidecar = String::from_utf8_lossy(sidecar);
    if kind % 2 == 0 {
        if let Ok(m) = models::global::GlobalModel::from_bytes(weights, &sidecar, Path::new("fuzz.safetensors")) {
            let raw = vec![0.5f32; m.sidecar.features.names.len()];
            let _ = m.predict_features(&raw, &mut m.mlp.scratch());
        }
    } else if let Ok(m) = models::p2p::P2pModel::from_bytes(weights, &sidecar, Path::new("fuzz.safetensors")) {
        let raw = vec![0.5f32; m.sidecar.features.len()];
        let _ = m.predict_features(&raw, 0.3, &mut Vec::new(), &mut Default::default());
    }
});
