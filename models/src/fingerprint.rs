//! Fingerprints of model files: what an evaluation's render cache keys a model by.

/// A stable 64-bit fingerprint (FNV-1a) of byte strings, each followed by its length
/// so that the split between them counts: what an evaluation's render cache keys a
/// model by, so a retrained model never reuses another's renders.
pub fn fingerprint(parts: &[&[u8]]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut eat = |b: u8| {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    };
    for p in parts {
        p.iter().copied().for_each(&mut eat);
        (p.len() as u64).to_le_bytes().into_iter().for_each(&mut eat);
    }
    h
}

/// [`fingerprint`] of a model's weights file and its sidecar (same name, .json).
pub fn model_file_fingerprint(weights: &std::path::Path) -> std::io::Result<u64> {
    let read = |p: &std::path::Path| {
        std::fs::read(p).map_err(|e| std::io::Error::new(e.kind(), format!("{}: {e}", p.display())))
    };
    Ok(fingerprint(&[&read(weights)?, &read(&weights.with_extension("json"))?]))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Same bytes, same fingerprint; one changed byte or a moved split, another; a
    /// model file and its sidecar are both read.
    #[test]
    fn fingerprints_follow_the_bytes() {
        assert_eq!(fingerprint(&[b"abc", b"def"]), fingerprint(&[b"abc", b"def"]));
        assert_ne!(fingerprint(&[b"abc", b"def"]), fingerprint(&[b"abc", b"deg"]));
        assert_ne!(fingerprint(&[b"abc", b"def"]), fingerprint(&[b"abcd", b"ef"]));
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().to_path_buf();
        let w = dir.join("m.safetensors");
        std::fs::write(&w, b"weights").unwrap();
        assert!(model_file_fingerprint(&w).unwrap_err().to_string().contains("m.json"));
        std::fs::write(dir.join("m.json"), b"{}").unwrap();
        let a = model_file_fingerprint(&w).unwrap();
        std::fs::write(dir.join("m.json"), b"{ }").unwrap();
        assert_ne!(a, model_file_fingerprint(&w).unwrap());
        assert_eq!(a, fingerprint(&[b"weights", b"{}"]));
    }
}
