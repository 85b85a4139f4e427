//! Chunk files, shards, resume and merge, for both data generators.
//!
//! Data point i is a pure function of (seed, i), so a data set does not depend on the
//! thread count or on how it was sharded. Points are grouped into chunks of
//! `chunk_size`; chunk c belongs to shard c mod N. Each chunk is one `.npy` file
//! written atomically, so an interrupted run resumes by skipping the chunks that
//! exist, and [`merge`] joins shard directories chunk by chunk in order.
//!
//! Directory layout: `manifest.json`; `chunks/chunk-NNNNNN.npy` (float32 [rows,
//! features + 5]) while generating; once complete `features.npy` [N, features] and
//! `targets.npy` [N, 5].

use super::manifest::{Counts, DataSpec, DatagenError, Manifest, Shard, setting, settings_diff};
use super::npy;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

pub fn chunk_path(dir: &Path, chunk: u64) -> PathBuf {
    dir.join("chunks").join(format!("chunk-{chunk:06}.npy"))
}

/// Where a damaged chunk is set aside (kept for inspection) before it is made again.
pub fn damaged_path(dir: &Path, chunk: u64) -> PathBuf {
    dir.join("chunks").join(format!("chunk-{chunk:06}.npy.damaged"))
}

/// Chunk `c` of `spec` as read from `path`, if it holds what it should: the shape
/// [points x rows per point, features + 5] and finite values only. The error says
/// what is wrong.
fn read_chunk<S: DataSpec>(spec: &S, c: u64, path: &Path) -> Result<Vec<f32>, String> {
    let cols = spec.n_features() + 5;
    let rows = (spec.chunk_len(c) * spec.rows_per_point()) as usize;
    let (shape, data) = npy::read_f32(path).map_err(|e| e.to_string())?;
    if shape != [rows, cols] {
        return Err(format!("{}: shape {shape:?}, expected [{rows}, {cols}]", path.display()));
    }
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        return Err(format!("{}: row {} column {} is {} (not finite)", path.display(), i / cols, i % cols, data[i]));
    }
    Ok(data)
}

/// Generates (or resumes) this shard's chunks of `spec` in `dir`. `prepare` is
/// called once the manifest says there is work left and gives what the points share
/// (a feature extractor, a medium); `point(&shared, i)` makes data point i's rows
/// (features then the 5 targets, `rows_per_point` rows) and its path samples.
/// `progress` is called with the number of points finished so far (chunks found on
/// disk included) from worker threads; `cancel` stops between points. A complete
/// unsharded run ends with the merged features.npy and targets.npy.
#[allow(clippy::too_many_arguments)]
pub fn generate<S: DataSpec, T: Sync>(
    spec: &S,
    shard: Shard,
    dir: &Path,
    code_version: &str,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
    prepare: impl FnOnce() -> Result<T, DatagenError>,
    point: impl Fn(&T, u64) -> (Vec<f32>, u64) + Sync,
) -> Result<Manifest<S>, DatagenError> {
    generate_by_chunk(spec, shard, dir, code_version, progress, cancel, prepare, |_, _| Ok(()), |t, _, i| point(t, i))
}

/// [`generate`] with state per chunk: `chunk(&shared, c)` makes what chunk c's points
/// share (a cloud, say) before they run, and is dropped with the chunk; an error
/// stops the run before the chunk is written and is returned.
#[allow(clippy::too_many_arguments)]
pub fn generate_by_chunk<S: DataSpec, T: Sync, C: Sync>(
    spec: &S,
    shard: Shard,
    dir: &Path,
    code_version: &str,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
    prepare: impl FnOnce() -> Result<T, DatagenError>,
    chunk: impl Fn(&T, u64) -> Result<C, DatagenError> + Sync,
    point: impl Fn(&T, &C, u64) -> (Vec<f32>, u64) + Sync,
) -> Result<Manifest<S>, DatagenError> {
    let started = std::time::Instant::now();
    let mut manifest = Manifest::open(dir, spec, shard, code_version)?;
    if manifest.complete {
        return Ok(manifest);
    }
    let shared = prepare()?;
    let owned = make_chunks(
        &mut manifest,
        dir,
        shard,
        started,
        progress,
        cancel,
        |c| chunk(&shared, c),
        |state: &C, i| point(&shared, state, i),
    )?;
    if shard == Shard::ALL {
        return merge(&[dir.to_owned()], dir);
    }
    manifest.counts.points = owned;
    manifest.save(dir)?;
    Ok(manifest)
}

/// Makes this shard's missing chunks (see [`write_chunks`]), reporting the points done
/// so far (chunks on disk included) to `progress`, and books the run in the manifest:
/// seconds, path samples, chunks. Returns the shard's point count, or `Cancelled`.
#[allow(clippy::too_many_arguments)]
fn make_chunks<S: DataSpec, C: Sync>(
    manifest: &mut Manifest<S>,
    dir: &Path,
    shard: Shard,
    started: std::time::Instant,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
    chunk: impl Fn(u64) -> Result<C, DatagenError> + Sync,
    point: impl Fn(&C, u64) -> (Vec<f32>, u64) + Sync,
) -> Result<u64, DatagenError> {
    let spec = manifest.settings.clone();
    let chunks: Vec<u64> = (0..spec.n_chunks()).filter(|&c| shard.owns(c)).collect();
    // Chunks on disk are checked before they count as done: a damaged one (cut
    // short, wrong shape, a value that is not finite) is set aside and made again.
    for &c in &chunks {
        let path = chunk_path(dir, c);
        if path.exists() && read_chunk(&spec, c, &path).is_err() {
            std::fs::rename(&path, damaged_path(dir, c))
                .map_err(|e| DatagenError::File { path: path.clone(), why: format!("cannot set it aside: {e}") })?;
        }
    }
    let todo: Vec<u64> = chunks.iter().copied().filter(|&c| !chunk_path(dir, c).exists()).collect();
    let owned: u64 = chunks.iter().map(|&c| spec.chunk_len(c)).sum();
    let done = AtomicU64::new(owned - todo.iter().map(|&c| spec.chunk_len(c)).sum::<u64>());
    progress(done.load(Ordering::Relaxed));
    let cols = spec.n_features() + 5;
    let (finished, samples) = write_chunks(dir, &todo, &spec, cols, cancel, chunk, |state, i| {
        let out = point(state, i);
        progress(done.fetch_add(1, Ordering::Relaxed) + 1);
        out
    })?;
    let counts = &mut manifest.counts;
    counts.seconds += started.elapsed().as_secs_f64();
    counts.path_samples += samples;
    counts.chunks = (chunks.len() - todo.len() + finished) as u64;
    let done_chunks = counts.chunks as usize;
    manifest.save(dir)?;
    if finished < todo.len() {
        return Err(DatagenError::Cancelled { done: done_chunks, total: chunks.len() });
    }
    Ok(owned)
}

/// Makes the chunks `todo` in parallel (points in parallel within a chunk): `point(i)`
/// gives data point i's rows (`cols` values each) and its path samples; each chunk is
/// written atomically once all its points are done. Stops between points once
/// `cancel` is set. Returns (chunks written, path samples of the points made).
#[allow(clippy::too_many_arguments)]
fn write_chunks<S: DataSpec, C: Sync>(
    dir: &Path,
    todo: &[u64],
    spec: &S,
    cols: usize,
    cancel: &AtomicBool,
    chunk: impl Fn(u64) -> Result<C, DatagenError> + Sync,
    point: impl Fn(&C, u64) -> (Vec<f32>, u64) + Sync,
) -> Result<(usize, u64), DatagenError> {
    let samples = AtomicU64::new(0);
    // A chunk whose state cannot be made stops the others too.
    let failed = AtomicBool::new(false);
    let stopped = || cancel.load(Ordering::Relaxed) || failed.load(Ordering::Relaxed);
    let results: Vec<Result<bool, DatagenError>> = todo
        .par_iter()
        .map(|&c| {
            if stopped() {
                return Ok(false);
            }
            let state = chunk(c).inspect_err(|_| failed.store(true, Ordering::Relaxed))?;
            let first = c * spec.chunk_size();
            let points: Option<Vec<Vec<f32>>> = (first..first + spec.chunk_len(c))
                .into_par_iter()
                .map(|i| {
                    if stopped() {
                        return None;
                    }
                    let (rows, n) = point(&state, i);
                    samples.fetch_add(n, Ordering::Relaxed);
                    Some(rows)
                })
                .collect();
            let Some(points) = points else { return Ok(false) };
            let rows = points.concat();
            npy::write_f32(&chunk_path(dir, c), &[rows.len() / cols, cols], &rows)?;
            Ok(true)
        })
        .collect();
    let mut finished = 0;
    for r in results {
        finished += r? as usize;
    }
    Ok((finished, samples.load(Ordering::Relaxed)))
}

/// Joins the chunks of one or more shard directories (or one complete unsharded run)
/// into `out`: features.npy, targets.npy and a manifest. Refuses shards made with
/// different settings, and missing or duplicated chunks.
pub fn merge<S: DataSpec>(dirs: &[PathBuf], out: &Path) -> Result<Manifest<S>, DatagenError> {
    let manifests: Vec<Manifest<S>> = dirs.iter().map(|d| Manifest::load(d)).collect::<Result<_, _>>()?;
    let Some(first) = manifests.first() else {
        return Err(setting("merge", "needs at least one directory"));
    };
    let spec = first.settings.clone();
    for (m, d) in manifests.iter().zip(dirs).skip(1) {
        if let Some(diff) = settings_diff(&spec, &m.settings) {
            return Err(DatagenError::Mismatch { dir: d.clone(), diff });
        }
    }
    let n_f = spec.n_features();
    let mut owner: Vec<Option<usize>> = vec![None; spec.n_chunks() as usize];
    for (k, d) in dirs.iter().enumerate() {
        for c in 0..spec.n_chunks() {
            if chunk_path(d, c).exists() {
                if let Some(j) = owner[c as usize] {
                    return Err(DatagenError::File {
                        path: chunk_path(d, c),
                        why: format!("chunk {c} is also in {}", dirs[j].display()),
                    });
                }
                owner[c as usize] = Some(k);
            }
        }
    }
    if let Some(c) = owner.iter().position(Option::is_none) {
        let missing = owner.iter().filter(|o| o.is_none()).count();
        return Err(DatagenError::File {
            path: chunk_path(&dirs[0], c as u64),
            why: format!(
                "{missing} of {} chunks are missing (first: chunk {c}); finish every shard first",
                owner.len()
            ),
        });
    }
    let n_rows = (spec.points() * spec.rows_per_point()) as usize;
    let mut features = Vec::with_capacity(n_rows * n_f);
    let mut targets = Vec::with_capacity(n_rows * 5);
    for (c, k) in owner.iter().enumerate() {
        let path = chunk_path(&dirs[k.unwrap()], c as u64);
        let data = read_chunk(&spec, c as u64, &path).map_err(|why| DatagenError::Chunk { why })?;
        for row in data.chunks_exact(n_f + 5) {
            features.extend_from_slice(&row[..n_f]);
            targets.extend_from_slice(&row[n_f..]);
        }
    }
    npy::write_f32(&out.join("features.npy"), &[n_rows, n_f], &features)?;
    npy::write_f32(&out.join("targets.npy"), &[n_rows, 5], &targets)?;
    let mut m = Manifest::new(&spec, None, &first.code_version);
    m.complete = true;
    m.counts = Counts {
        points: spec.points(),
        chunks: spec.n_chunks(),
        path_samples: S::merged_path_samples(&manifests, &targets),
        seconds: manifests.iter().map(|m| m.counts.seconds).sum(),
    };
    m.save(out)?;
    Ok(m)
}
