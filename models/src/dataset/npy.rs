//! NumPy `.npy` files (format version 1.0, little-endian float32, C order): what the
//! data generator writes, the trainer reads, and every Python user can open with
//! `numpy.load`. Also the atomic file write used for every file the models write.

use std::io::Write;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    /// (The I/O error is part of the message, not a source, so that an error chain
    /// does not print it twice.)
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
    /// A failed write (the error names the file).
    #[error("{0}")]
    Write(std::io::Error),
    #[error("{path}: not a float32 .npy file we can read: {why}")]
    Format { path: PathBuf, why: String },
}

/// A temporary path beside `path` (same directory, so the rename is atomic), unique per
/// process and thread.
fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let thread = format!("{:?}", std::thread::current().id()).replace(|c: char| !c.is_ascii_alphanumeric(), "");
    path.with_file_name(format!(".{name}.{}.{thread}.tmp", std::process::id()))
}

/// Removes temporaries of `path` left by processes that no longer run (killed
/// mid-write): `.NAME.<pid>.<thread>.tmp` beside it whose pid has no `/proc` entry.
/// Where `/proc` is missing nothing can be told dead, and nothing is removed.
fn remove_stale_temporaries(path: &Path) {
    let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else { return };
    let dir = if dir.as_os_str().is_empty() { Path::new(".") } else { dir };
    if !Path::new("/proc/self").exists() {
        return;
    }
    let prefix = format!(".{}.", name.to_string_lossy());
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let file = entry.file_name();
        let Some(rest) = file.to_str().and_then(|f| f.strip_prefix(&prefix)).and_then(|r| r.strip_suffix(".tmp"))
        else {
            continue;
        };
        let Some(pid) = rest.split('.').next().and_then(|p| p.parse::<u32>().ok()) else { continue };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// `e` with what failed and on which path in its message (the kind kept).
fn named(what: &str, path: &Path, e: std::io::Error) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("{what} {}: {e}", path.display()))
}

/// Runs `write` on a temporary path beside `path`, then renames it over `path`: a crash
/// or Ctrl-C never leaves half a file, and the old file survives a failed write. Every
/// file Nimbus writes goes through here. Temporaries of `path` that a killed process
/// left are removed first.
pub fn write_atomically<E: From<std::io::Error>>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), E> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| {
            std::io::Error::new(
                e.kind(),
                format!("cannot write {}: cannot create directory {}: {e}", path.display(), dir.display()),
            )
        })?;
    }
    remove_stale_temporaries(path);
    let tmp = temp_path(path);
    let result =
        write(&tmp).and_then(|_| std::fs::rename(&tmp, path).map_err(|e| E::from(named("cannot write", path, e))));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes `bytes` atomically (synced before the rename).
pub fn write_bytes_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomically(path, |tmp| {
        let mut f = std::fs::File::create(tmp).map_err(|e| named("cannot write", path, e))?;
        f.write_all(bytes).and_then(|_| f.sync_all()).map_err(|e| named("cannot write", path, e))
    })
}

/// The bytes of a float32 `.npy` file of the given shape.
pub fn npy_bytes_f32(shape: &[usize], data: &[f32]) -> Vec<u8> {
    assert_eq!(shape.iter().product::<usize>(), data.len());
    let shape_str = match shape.len() {
        1 => format!("({},)", shape[0]),
        _ => format!("({})", shape.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_str}, }}");
    // Pad so that the data starts at a multiple of 64 bytes (magic 6 + version 2 + len 2).
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + 4 * data.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Writes a float32 array atomically.
pub fn write_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<(), NpyError> {
    write_bytes_atomically(path, &npy_bytes_f32(shape, data)).map_err(NpyError::Write)
}

/// Where a `.npy` file's header text starts and where it ends (the data's start),
/// from the file's first 12 bytes (version 1.0 needs 10).
fn header_span(prefix: &[u8]) -> Result<(usize, usize), String> {
    if prefix.len() < 10 || &prefix[..6] != b"\x93NUMPY" {
        return Err("missing the \\x93NUMPY magic".into());
    }
    let (header_start, header_len): (usize, usize) = match prefix[6] {
        1 => (10, u16::from_le_bytes([prefix[8], prefix[9]]) as usize),
        2 | 3 if prefix.len() >= 12 => (12, u32::from_le_bytes(prefix[8..12].try_into().unwrap()) as usize),
        v => return Err(format!("format version {v} is not supported")),
    };
    Ok((header_start, header_start + header_len))
}

/// A float32 `.npy` header: the array's shape, where its data starts and how many
/// values it holds. `bytes` is the file's start (at least through the header).
fn parse_header(bytes: &[u8]) -> Result<(Vec<usize>, usize, usize), String> {
    let (header_start, data_start) = header_span(bytes)?;
    if data_start > bytes.len() {
        return Err("header runs past the end".into());
    }
    let header = std::str::from_utf8(&bytes[header_start..data_start]).map_err(|_| "header is not text")?;
    let field = |key: &str| -> Result<&str, String> {
        let at = header.find(&format!("'{key}'")).ok_or(format!("header has no '{key}'"))?;
        Ok(header[at + key.len() + 2..].trim_start().trim_start_matches(':').trim_start())
    };
    if !field("descr")?.starts_with("'<f4'") {
        return Err(format!("dtype is not little-endian float32 ('<f4'): {header}"));
    }
    if !field("fortran_order")?.starts_with("False") {
        return Err("Fortran order is not supported".into());
    }
    let shape_text = field("shape")?.strip_prefix('(').ok_or("the shape is not a tuple")?;
    let close = shape_text.find(')').ok_or("unterminated shape")?;
    let shape: Vec<usize> = shape_text[..close]
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("bad shape entry {s:?}")))
        .collect::<Result<_, _>>()?;
    let count = shape.iter().try_fold(1usize, |a, &b| a.checked_mul(b)).ok_or("shape overflows")?;
    Ok((shape, data_start, count))
}

/// The error for a payload of `have` bytes where `shape` needs `count` values.
fn payload_mismatch(shape: &[usize], count: usize, have: u64) -> String {
    format!("shape {shape:?} needs {} bytes of data, the file has {have}", count as u64 * 4)
}

/// Parses a float32 `.npy` file: its shape and data.
pub fn parse_f32(bytes: &[u8]) -> Result<(Vec<usize>, Vec<f32>), String> {
    let (shape, data_start, count) = parse_header(bytes)?;
    let payload = &bytes[data_start..];
    if count.checked_mul(4) != Some(payload.len()) {
        return Err(payload_mismatch(&shape, count, payload.len() as u64));
    }
    let data = payload.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
    Ok((shape, data))
}

/// Reads a float32 `.npy` file onto the end of `out` and returns its shape. The file
/// is streamed in blocks, so reading costs the array's own memory and no copy of the
/// file: data sets of several gigabytes load into one buffer reserved for all of them.
/// On an error `out` is left as it was.
pub fn read_f32_into(path: &Path, out: &mut Vec<f32>) -> Result<Vec<usize>, NpyError> {
    use std::io::{Read, Seek};
    let io = |error| NpyError::Io { path: path.to_owned(), error };
    let format = |why| NpyError::Format { path: path.to_owned(), why };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let size = file.metadata().map_err(io)?.len();
    // The header: its length is in the first 12 bytes.
    let mut head = vec![0u8; 12.min(size as usize)];
    file.read_exact(&mut head).map_err(io)?;
    let (_, header_end) = header_span(&head).map_err(format)?;
    let have = head.len();
    head.resize(header_end.min(size as usize), 0);
    if head.len() > have {
        file.read_exact(&mut head[have..]).map_err(io)?;
    }
    let (shape, data_start, count) = parse_header(&head).map_err(format)?;
    let payload = size - data_start as u64;
    if (count as u64).checked_mul(4) != Some(payload) {
        return Err(format(payload_mismatch(&shape, count, payload)));
    }
    // (A header shorter than the 12 bytes read leaves the file past the data's start.)
    file.seek(std::io::SeekFrom::Start(data_start as u64)).map_err(io)?;
    let start = out.len();
    out.reserve(count);
    let mut block = vec![0u8; 1 << 20];
    let mut left = count;
    while left > 0 {
        let n = left.min(block.len() / 4);
        if let Err(e) = file.read_exact(&mut block[..4 * n]) {
            out.truncate(start);
            return Err(io(e));
        }
        out.extend(block[..4 * n].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())));
        left -= n;
    }
    Ok(shape)
}

/// Reads a float32 `.npy` file.
pub fn read_f32(path: &Path) -> Result<(Vec<usize>, Vec<f32>), NpyError> {
    let mut data = vec![];
    let shape = read_f32_into(path, &mut data)?;
    Ok((shape, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Headers the fuzzer found: a shape that is not a tuple (`'shape': )12, 25)`)
    /// is refused, not sliced out of range.
    #[test]
    fn fuzz_regressions_are_refused() {
        let bytes = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/fuzz_npy_shape.npy")).unwrap();
        let e = parse_f32(&bytes).unwrap_err();
        assert!(e.contains("tuple"), "{e}");
    }

    /// Streaming a file onto a buffer gives what parsing its bytes gives, appended
    /// after what the buffer held, across block boundaries (2^18 values per block);
    /// a file whose payload is short or long, or whose header is cut, is refused
    /// with the buffer unchanged.
    #[test]
    fn read_into_appends_what_parse_reads() {
        let dir = tempfile::tempdir().unwrap();
        let n = (1 << 18) + 1000;
        let data: Vec<f32> = (0..n).map(|i| (i as f32).sin() * 1e3 + i as f32).collect();
        let bytes = npy_bytes_f32(&[n / 4, 4], &data);
        let path = dir.path().join("a.npy");
        std::fs::write(&path, &bytes).unwrap();
        let mut out = vec![7.0f32, -1.0];
        let shape = read_f32_into(&path, &mut out).unwrap();
        assert_eq!(shape, vec![n / 4, 4]);
        let (parsed_shape, parsed) = parse_f32(&bytes).unwrap();
        assert_eq!(parsed_shape, shape);
        assert_eq!(&out[..2], &[7.0, -1.0]);
        assert!(out[2..].iter().zip(&parsed).all(|(a, b)| a.to_bits() == b.to_bits()) && out.len() == n + 2);
        // A version 2.0 header (4-byte length) reads the same.
        let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        let mut v2 = b"\x93NUMPY\x02\x00".to_vec();
        v2.extend_from_slice(&(header_len as u32).to_le_bytes());
        v2.extend_from_slice(&bytes[10..]);
        std::fs::write(&path, &v2).unwrap();
        assert_eq!(read_f32(&path).unwrap().1.len(), n);
        for bad in [&bytes[..bytes.len() - 4], &[&bytes[..], &[0u8; 4][..]].concat()[..], &bytes[..40], &bytes[..5]] {
            std::fs::write(&path, bad).unwrap();
            let before = out.clone();
            let e = read_f32_into(&path, &mut out).unwrap_err();
            assert!(matches!(e, NpyError::Format { .. }), "{e}");
            assert_eq!(out.len(), before.len());
        }
    }

    /// A temporary left by a killed process (a pid that does not run) is removed by
    /// the next write of the same file; one of a live process, and other files' ones,
    /// are kept; the written file has the permissions of any new file (0644 under
    /// the usual umask 022, never 0600).
    #[test]
    fn stale_temporaries_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("chunk.npy");
        // Linux pids stay below 2^22.
        let stale = dir.path().join(".chunk.npy.4194399.ThreadId2.tmp");
        let live = dir.path().join(format!(".chunk.npy.{}.ThreadId7.tmp", std::process::id()));
        let other = dir.path().join(".other.npy.4194399.ThreadId2.tmp");
        for f in [&stale, &live, &other] {
            std::fs::write(f, b"half").unwrap();
        }
        write_bytes_atomically(&target, b"data").unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"data");
        if Path::new("/proc/self").exists() {
            assert!(!stale.exists(), "the dead process's temporary is still there");
        }
        assert!(live.exists() && other.exists());
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let reference = dir.path().join("plain");
            std::fs::write(&reference, b"x").unwrap();
            let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode(&target), mode(&reference), "an atomic write's mode differs from a plain file's");
        }
    }

    #[test]
    fn round_trip_and_alignment() {
        let b = npy_bytes_f32(&[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, -6.5]);
        let header_len = u16::from_le_bytes([b[8], b[9]]) as usize;
        assert_eq!((10 + header_len) % 64, 0);
        let (shape, data) = parse_f32(&b).unwrap();
        assert_eq!(shape, vec![2, 3]);
        assert_eq!(data, vec![1.0, 2.0, 3.0, 4.0, 5.0, -6.5]);
        let (shape, _) = parse_f32(&npy_bytes_f32(&[4], &[0.0; 4])).unwrap();
        assert_eq!(shape, vec![4]);
    }

    #[test]
    fn bad_files_are_refused_with_a_reason() {
        let good = npy_bytes_f32(&[2, 2], &[1.0; 4]);
        assert!(parse_f32(&good[..good.len() - 1]).unwrap_err().contains("needs 16 bytes"));
        assert!(parse_f32(b"hello").unwrap_err().contains("magic"));
        let mut f8 = good.clone();
        let at = f8.windows(3).position(|w| w == b"<f4").unwrap();
        f8[at + 2] = b'8';
        assert!(parse_f32(&f8).unwrap_err().contains("float32"));
        for cut in 0..good.len() {
            let _ = parse_f32(&good[..cut]); // never panics
        }
    }
}
