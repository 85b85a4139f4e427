//! Ground truth for the point-to-point model (thesis 6.3): per data point, emitter
//! and sensor at the ends of two k-segment walks entering the cloud from outside, the
//! transport T between them to a requested accuracy (confidence-interval stopping),
//! and the density features of `rotations` random rotations of the local frame about
//! the emitter-sensor axis (the thesis reused each T 50 times this way; its isotropic
//! media make T independent of the rotation).
//!
//! The layout follows the global data generator: `manifest.json` (format
//! `nimbus-p2p-dataset`), chunks of `chunk_size` points written atomically as
//! `chunks/chunk-NNNNNN.npy` (so a stopped run resumes), shards by chunk index, and
//! once complete `features.npy` [rows, 352] and `targets.npy` [rows, 5]. Point i is a
//! pure function of (seed, i): the same bytes whatever the thread count or sharding.

use crate::datagen::{
    Chunking, Counts, DataManifest, DatagenError, Shard, chunk_path, load_manifest, make_chunks, open_manifest,
    save_manifest, setting, settings_diff,
};
use crate::density_features::{DensityPyramid, LocalFrame, P2pFeatures, pyramid_for};
use crate::npy;
use engine::p2p::{P2pQuery, P2pSettings, sample_query_end, sample_transport};
use engine::stats::Welford;
use engine::{DensityGrid, Medium, PhaseFunction, Rng};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

pub const FORMAT: &str = "nimbus-p2p-dataset";
pub const FORMAT_VERSION: u32 = 1;
/// Per row: T in world units, its standard error, the samples it took, the
/// emitter-sensor distance D, and T in the local frame (D^2 T, the scale-free target).
pub const TARGET_COLUMNS: [&str; 5] = ["T", "std_error", "samples", "distance", "T_local"];

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct P2pSpec {
    pub points: u64,
    /// The cloud, as the command line named it (preset, built-in or file): compared on
    /// resume; the grid itself is passed in.
    pub cloud: String,
    pub resolution: u32,
    pub rho: f32,
    pub albedo: f32,
    pub g: f32,
    /// Segments of the walks that place emitter and sensor.
    pub k: u32,
    pub rotations: u32,
    pub features: P2pFeatures,
    pub max_rel_error: f64,
    pub confidence: f64,
    pub min_samples: u64,
    pub max_samples: u64,
    pub seed: u64,
    pub chunk_size: u64,
}

impl Default for P2pSpec {
    fn default() -> Self {
        P2pSpec {
            points: 1000,
            cloud: "scene-a".into(),
            resolution: 128,
            rho: 25.0,
            albedo: 0.99,
            g: 0.0,
            k: 2,
            rotations: 50,
            features: P2pFeatures::default(),
            max_rel_error: 0.1,
            confidence: 0.95,
            min_samples: 1000,
            max_samples: 20_000_000,
            seed: 1,
            chunk_size: 20,
        }
    }
}

impl P2pSpec {
    pub fn validate(&self) -> Result<(), DatagenError> {
        if self.points == 0 {
            return Err(setting("--points", "must be at least 1"));
        }
        if !(self.rho.is_finite() && self.rho > 0.0) {
            return Err(setting("--rho", format!("must be positive, got {}", self.rho)));
        }
        if !(0.0..=1.0).contains(&self.albedo) {
            return Err(setting("--albedo", format!("must lie in [0, 1], got {}", self.albedo)));
        }
        if !(self.g > -1.0 && self.g < 1.0) {
            return Err(setting("--g", format!("must lie in (-1, 1), got {}", self.g)));
        }
        if self.k == 0 || self.rotations == 0 || self.chunk_size == 0 {
            return Err(setting("--k / --rotations / --chunk-size", "must be at least 1"));
        }
        if !(self.max_rel_error > 0.0 && self.confidence > 0.0 && self.confidence < 1.0) {
            return Err(setting("--max-rel-error / --confidence", "must be positive (confidence below 1)"));
        }
        Ok(())
    }
    pub fn n_chunks(&self) -> u64 {
        crate::datagen::chunk_count(self.points, self.chunk_size)
    }
    pub fn chunk_len(&self, c: u64) -> u64 {
        crate::datagen::chunk_len(self.points, self.chunk_size, c)
    }
    /// Points that `shard` makes.
    pub fn shard_points(&self, shard: Shard) -> u64 {
        crate::datagen::shard_points(self.points, self.chunk_size, shard)
    }
    pub fn rows(&self) -> u64 {
        self.points * self.rotations as u64
    }
    pub fn n_features(&self) -> usize {
        self.features.len()
    }
    /// Largest emitter-sensor distance the pyramid serves: the cloud's diagonal.
    fn pyramid(&self, grid: &DensityGrid) -> DensityPyramid {
        pyramid_for(grid, &self.features, grid.bounds().extent().length())
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct P2pManifest {
    pub format: String,
    pub format_version: u32,
    pub code_version: String,
    pub settings: P2pSpec,
    pub shard: Option<Shard>,
    pub target_columns: Vec<String>,
    pub complete: bool,
    pub counts: Counts,
}

impl P2pManifest {
    fn new(spec: &P2pSpec, shard: Option<Shard>, code_version: &str) -> Self {
        P2pManifest {
            format: FORMAT.into(),
            format_version: FORMAT_VERSION,
            code_version: code_version.into(),
            settings: spec.clone(),
            shard,
            target_columns: TARGET_COLUMNS.iter().map(|s| s.to_string()).collect(),
            complete: false,
            counts: Counts::default(),
        }
    }

    pub fn load(dir: &Path) -> Result<Self, DatagenError> {
        load_manifest(dir, FORMAT, FORMAT_VERSION, "a point-to-point data set", |m: &P2pManifest| {
            (m.format.clone(), m.format_version)
        })
    }

    fn save(&self, dir: &Path) -> Result<(), DatagenError> {
        save_manifest(dir, self)
    }
}

/// The rows of data point `index`: `rotations` rows of features + targets.
pub fn generate_point(spec: &P2pSpec, medium: &Medium, pyramid: &DensityPyramid, index: u64) -> (Vec<f32>, u64) {
    let mut rng = Rng::new(spec.seed, index, 0x7032_7064_6174_61); // "p2pdata"
    let q = loop {
        let e = sample_query_end(medium, spec.k, &mut rng);
        let s = sample_query_end(medium, spec.k, &mut rng);
        if let (Some((e, we)), Some((s, ws))) = (e, s) {
            if (e - s).length() > 1e-4 {
                break P2pQuery { emitter: e, omega_e: we, sensor: s, omega_s: ws };
            }
        }
    };
    let z = engine::stats::normal_quantile(0.5 + 0.5 * spec.confidence);
    let set = P2pSettings::default();
    let mut w = Welford::default();
    loop {
        for _ in 0..64 {
            w.add(sample_transport(medium, &q, &set, &mut rng) as f64);
        }
        let done = w.n >= spec.min_samples && w.mean > 0.0 && z * w.std_error() <= spec.max_rel_error * w.mean;
        if done || w.n >= spec.max_samples {
            break;
        }
    }
    let dist = (q.sensor - q.emitter).length();
    let n_f = spec.n_features();
    let mut rows = vec![0.0f32; spec.rotations as usize * (n_f + 5)];
    for row in rows.chunks_exact_mut(n_f + 5) {
        let frame =
            LocalFrame::new(q.emitter, q.sensor, std::f32::consts::TAU * rng.uniform()).expect("distinct points");
        spec.features.write(pyramid, spec.rho, spec.albedo, &frame, &mut row[..n_f]);
        row[n_f..].copy_from_slice(&[
            w.mean as f32,
            w.std_error() as f32,
            w.n as f32,
            dist,
            (w.mean * (dist as f64).powi(2)) as f32,
        ]);
    }
    (rows, w.n)
}

/// Generates (or resumes) this shard's chunks in `dir` from the cloud `grid`; a
/// complete unsharded run ends with features.npy and targets.npy.
pub fn generate(
    spec: &P2pSpec,
    grid: Arc<DensityGrid>,
    shard: Shard,
    dir: &Path,
    code_version: &str,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
) -> Result<P2pManifest, DatagenError> {
    spec.validate()?;
    let started = std::time::Instant::now();
    let mut manifest: P2pManifest = open_manifest(dir, spec, shard, code_version)?;
    if manifest.complete {
        return Ok(manifest);
    }
    let phase = PhaseFunction::henyey_greenstein(spec.g).map_err(|e| setting("--g", e))?;
    let medium =
        Medium::new(grid.clone(), spec.rho, spec.albedo, phase).map_err(|e| setting("--rho", e.to_string()))?;
    let pyramid = spec.pyramid(&grid);
    let chunking = Chunking {
        n_chunks: spec.n_chunks(),
        chunk_size: spec.chunk_size,
        chunk_len: &|c| spec.chunk_len(c),
        cols: spec.n_features() + 5,
    };
    let owned = make_chunks(&mut manifest, dir, &chunking, shard, started, progress, cancel, |i| {
        generate_point(spec, &medium, &pyramid, i)
    })?;
    if shard == Shard::ALL {
        return merge(&[dir.to_owned()], dir);
    }
    manifest.counts.points = owned;
    manifest.save(dir)?;
    Ok(manifest)
}

impl DataManifest for P2pManifest {
    type Spec = P2pSpec;
    fn create(spec: &P2pSpec, shard: Option<Shard>, code_version: &str) -> Self {
        P2pManifest::new(spec, shard, code_version)
    }
    fn read(dir: &Path) -> Result<Self, DatagenError> {
        P2pManifest::load(dir)
    }
    fn write(&self, dir: &Path) -> Result<(), DatagenError> {
        self.save(dir)
    }
    fn spec(&self) -> &P2pSpec {
        &self.settings
    }
    fn shard(&self) -> Option<Shard> {
        self.shard
    }
    fn counts_mut(&mut self) -> &mut Counts {
        &mut self.counts
    }
}

/// Joins the chunks of shard directories (or one unsharded run) into `out`.
pub fn merge(dirs: &[PathBuf], out: &Path) -> Result<P2pManifest, DatagenError> {
    let manifests: Vec<P2pManifest> = dirs.iter().map(|d| P2pManifest::load(d)).collect::<Result<_, _>>()?;
    let first = manifests.first().ok_or_else(|| setting("merge", "needs at least one directory"))?;
    let spec = first.settings.clone();
    for (m, d) in manifests.iter().zip(dirs).skip(1) {
        if let Some(x) = settings_diff(&spec, &m.settings) {
            return Err(DatagenError::Mismatch { dir: d.clone(), diff: x });
        }
    }
    let n_f = spec.n_features();
    let (mut features, mut targets) = (vec![], vec![]);
    for c in 0..spec.n_chunks() {
        let found: Vec<&PathBuf> = dirs.iter().filter(|d| chunk_path(d, c).exists()).collect();
        if found.len() != 1 {
            return Err(DatagenError::File {
                path: chunk_path(&dirs[0], c),
                why: format!("chunk {c} is in {} of the directories (must be exactly one)", found.len()),
            });
        }
        let path = chunk_path(found[0], c);
        let (shape, data) = npy::read_f32(&path)?;
        let rows = (spec.chunk_len(c) * spec.rotations as u64) as usize;
        if shape != [rows, n_f + 5] {
            return Err(DatagenError::File { path, why: format!("shape {shape:?}, expected [{rows}, {}]", n_f + 5) });
        }
        for row in data.chunks_exact(n_f + 5) {
            features.extend_from_slice(&row[..n_f]);
            targets.extend_from_slice(&row[n_f..]);
        }
    }
    let rows = spec.rows() as usize;
    npy::write_f32(&out.join("features.npy"), &[rows, n_f], &features)?;
    npy::write_f32(&out.join("targets.npy"), &[rows, 5], &targets)?;
    let mut m = P2pManifest::new(&spec, None, &first.code_version);
    m.complete = true;
    m.counts = Counts {
        points: spec.points,
        chunks: spec.n_chunks(),
        path_samples: manifests.iter().map(|m| m.counts.path_samples).sum(),
        seconds: manifests.iter().map(|m| m.counts.seconds).sum(),
    };
    m.save(out)?;
    Ok(m)
}
