//! The global model's data generator (thesis section 5.3): random homogeneous convex
//! media, a uniform query point and direction in each, the in-scattered radiance there
//! by path tracing to a requested confidence, and the feature vector.
//!
//! Reproducibility and scale-out: data point i is a pure function of (seed, i), so the
//! data set does not depend on the thread count or on how it was sharded. Points are
//! grouped into chunks of `chunk_size`; chunk c belongs to shard c mod N. Each chunk is
//! one `.npy` file written atomically, so an interrupted run resumes by skipping the
//! chunks that exist, and `merge` joins shard directories chunk by chunk in order.
//!
//! Directory layout (see the README's data-set section):
//! - `manifest.json`: settings, code version, counts;
//! - `chunks/chunk-NNNNNN.npy`: float32 [points, features + 5] during generation;
//! - `features.npy` float32 [N, 4 + n_D] and `targets.npy` float32 [N, 5] once complete.
//!
//! targets.npy columns: L_i (the estimate), its standard error, the sample count, the
//! medium's sigma_S, the shape (0 sphere, 1 box, 2 ellipsoid). The target
//! transformations (thesis eqs. 5.8-5.9) belong to the trainer.

use crate::directions::DirectionSetKind;
use crate::features::FeatureExtractor;
use crate::ground_truth::{ConvexMedium, Shape, Stopping, estimate_in_scattered};
use crate::npy;
use engine::{PhaseFunction, Rng};
use glam::{Mat3, Quat, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// The light of the data generator: radiance 1 travelling along (0, 0, -1) (thesis 5.3).
pub const OMEGA_L: Vec3 = Vec3::new(0.0, 0.0, -1.0);

/// Columns of targets.npy.
pub const TARGET_COLUMNS: [&str; 5] = ["L_i", "std_error", "samples", "sigma_s", "shape"];

/// Manifest format tag and version.
pub const FORMAT: &str = "nimbus-global-dataset";
pub const FORMAT_VERSION: u32 = 1;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ShapeKind {
    Sphere,
    Box,
    /// A sphere scaled independently along its three axes.
    Ellipsoid,
}

impl ShapeKind {
    pub fn parse(s: &str) -> Option<Self> {
        match s.trim() {
            "sphere" => Some(ShapeKind::Sphere),
            "box" => Some(ShapeKind::Box),
            "ellipsoid" => Some(ShapeKind::Ellipsoid),
            _ => None,
        }
    }

    fn id(self) -> f32 {
        match self {
            ShapeKind::Sphere => 0.0,
            ShapeKind::Box => 1.0,
            ShapeKind::Ellipsoid => 2.0,
        }
    }
}

/// Every setting of a data set; stored in the manifest, compared on resume and merge.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GlobalSpec {
    pub points: u64,
    /// Extinction sigma_S, uniform in [min, max].
    pub sigma: [f32; 2],
    pub albedo: [f32; 2],
    /// Henyey-Greenstein g.
    pub g: [f32; 2],
    pub shapes: Vec<ShapeKind>,
    /// Uniformly random rotation of each shape.
    pub rotate: bool,
    /// Scale factor, uniform in [min, max]: one factor for spheres, one per axis for
    /// boxes and ellipsoids. [1, 1] keeps the unit shapes.
    pub scale: [f32; 2],
    pub n_dirs: usize,
    pub directions: DirectionSetKind,
    pub max_rel_error: f64,
    pub confidence: f64,
    pub min_samples: u64,
    pub max_samples: u64,
    pub seed: u64,
    pub chunk_size: u64,
    /// Fraction of points sampled like the renderer's queries at k = 1: the first
    /// collision of a ray entering the shape, query direction back along the ray (near
    /// the surface, looking out). The rest are uniform in the volume with a uniform
    /// direction (the thesis's sampling). 0 in data sets made before the option.
    #[serde(default)]
    pub first_collision: f32,
}

impl Default for GlobalSpec {
    fn default() -> Self {
        GlobalSpec {
            points: 10_000,
            sigma: [1.0, 100.0],
            albedo: [1.0, 1.0],
            g: [0.0, 0.9],
            shapes: vec![ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Ellipsoid],
            rotate: true,
            scale: [1.0, 1.0],
            n_dirs: 64,
            directions: DirectionSetKind::Tetrahedron,
            max_rel_error: 0.05,
            confidence: 0.95,
            min_samples: 1000,
            max_samples: 10_000_000,
            seed: 1,
            chunk_size: 200,
            first_collision: 0.0,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DatagenError {
    #[error("{flag}: {why}")]
    Setting { flag: &'static str, why: String },
    #[error("{0}")]
    Npy(#[from] npy::NpyError),
    #[error("{path}: {why}")]
    File { path: PathBuf, why: String },
    #[error("{dir} already holds a data set made with other settings: {diff}; use another --out or the same settings")]
    Mismatch { dir: PathBuf, diff: String },
    #[error("cancelled; {done} of {total} chunks are on disk, run the same command again to resume")]
    Cancelled { done: usize, total: usize },
}

pub(crate) fn setting(flag: &'static str, why: impl Into<String>) -> DatagenError {
    DatagenError::Setting { flag, why: why.into() }
}

/// Parses "MIN..MAX" or a single value.
pub fn parse_range(flag: &'static str, s: &str) -> Result<[f32; 2], DatagenError> {
    let parse = |t: &str| {
        t.trim()
            .parse::<f32>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| setting(flag, format!("{t:?} is not a number")))
    };
    let r = match s.split_once("..") {
        Some((a, b)) => [parse(a)?, parse(b)?],
        None => [parse(s)?; 2],
    };
    if r[0] > r[1] {
        return Err(setting(flag, format!("{s} is an empty range (MIN > MAX)")));
    }
    Ok(r)
}

impl GlobalSpec {
    /// Checks every setting; the error names the command-line flag.
    pub fn validate(&self) -> Result<(), DatagenError> {
        if self.points == 0 {
            return Err(setting("--points", "must be at least 1"));
        }
        let check = |flag: &'static str, r: [f32; 2], ok: &dyn Fn(f32) -> bool, what: &str| {
            if !(r[0] <= r[1]) {
                Err(setting(flag, format!("{}..{} is an empty range", r[0], r[1])))
            } else if !ok(r[0]) || !ok(r[1]) {
                Err(setting(flag, format!("{}..{} must lie in {what}", r[0], r[1])))
            } else {
                Ok(())
            }
        };
        check("--sigma", self.sigma, &|v| v > 0.0 && v <= 10_000.0, "(0, 10000]")?;
        check("--albedo", self.albedo, &|v| (0.0..=1.0).contains(&v), "[0, 1]")?;
        check("--g", self.g, &|v| v > -1.0 && v < 1.0, "(-1, 1)")?;
        check("--scale", self.scale, &|v| v >= 0.01 && v <= 100.0, "[0.01, 100]")?;
        if !(0.0..=1.0).contains(&self.first_collision) {
            return Err(setting("--first-collision", format!("{} must lie in [0, 1]", self.first_collision)));
        }
        if self.shapes.is_empty() {
            return Err(setting("--shapes", "needs at least one of sphere, box, ellipsoid"));
        }
        if self.directions.directions(self.n_dirs).is_none() {
            return Err(setting(
                "--n-dirs",
                format!(
                    "{} is not offered by the {} set (tetrahedron: 4, 16, 64; fibonacci: 4..=256)",
                    self.n_dirs,
                    self.directions.name()
                ),
            ));
        }
        if !(self.max_rel_error > 0.0 && self.max_rel_error < 1.0) {
            return Err(setting("--max-rel-error", format!("{} must lie in (0, 1)", self.max_rel_error)));
        }
        if !(self.confidence > 0.0 && self.confidence < 1.0) {
            return Err(setting("--confidence", format!("{} must lie in (0, 1)", self.confidence)));
        }
        if self.min_samples == 0 || self.min_samples > self.max_samples {
            return Err(setting("--min-samples", "must be at least 1 and at most --max-samples"));
        }
        if self.chunk_size == 0 {
            return Err(setting("--chunk-size", "must be at least 1"));
        }
        Ok(())
    }

    pub fn n_features(&self) -> usize {
        4 + self.n_dirs
    }

    pub fn n_chunks(&self) -> u64 {
        chunk_count(self.points, self.chunk_size)
    }

    pub fn stopping(&self) -> Stopping {
        Stopping {
            max_rel_error: self.max_rel_error,
            z: engine::stats::normal_quantile(0.5 + 0.5 * self.confidence),
            min_samples: self.min_samples,
            max_samples: self.max_samples,
        }
    }

    /// The feature names, in order.
    pub fn feature_names(&self) -> Vec<String> {
        crate::global::FeatureLayout::current(self.directions, self.n_dirs).names
    }

    /// Points in chunk `c` (the last chunk may be short).
    pub fn chunk_len(&self, c: u64) -> u64 {
        chunk_len(self.points, self.chunk_size, c)
    }

    /// Points that `shard` makes.
    pub fn shard_points(&self, shard: Shard) -> u64 {
        shard_points(self.points, self.chunk_size, shard)
    }
}

/// Chunks of `chunk_size` points that hold `points` (both data generators).
pub fn chunk_count(points: u64, chunk_size: u64) -> u64 {
    points.div_ceil(chunk_size)
}

/// Points in chunk `c` (the last chunk may be short).
pub fn chunk_len(points: u64, chunk_size: u64, c: u64) -> u64 {
    (points - c * chunk_size).min(chunk_size)
}

/// Points that `shard` makes (it owns chunks c with c mod N == i).
pub fn shard_points(points: u64, chunk_size: u64, shard: Shard) -> u64 {
    (0..chunk_count(points, chunk_size)).filter(|&c| shard.owns(c)).map(|c| chunk_len(points, chunk_size, c)).sum()
}

/// One data point.
#[derive(Clone, Debug, PartialEq)]
pub struct DataPoint {
    pub features: Vec<f32>,
    pub l_i: f64,
    pub std_error: f64,
    pub samples: u64,
    pub sigma: f32,
    pub shape: ShapeKind,
}

impl DataPoint {
    fn targets(&self) -> [f32; 5] {
        [self.l_i as f32, self.std_error as f32, self.samples as f32, self.sigma, self.shape.id()]
    }
}

/// A uniformly distributed rotation (Shoemake's quaternion from three uniforms).
fn random_rotation(rng: &mut Rng) -> Mat3 {
    let (u1, u2, u3) = (rng.uniform(), rng.uniform(), rng.uniform());
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    let tau = std::f32::consts::TAU;
    let q = Quat::from_xyzw(a * (tau * u2).sin(), a * (tau * u2).cos(), b * (tau * u3).sin(), b * (tau * u3).cos());
    Mat3::from_quat(q.normalize())
}

fn lerp(r: [f32; 2], u: f32) -> f32 {
    r[0] + (r[1] - r[0]) * u
}

/// The random medium, query point and direction of data point `index`: a pure function
/// of (seed, index).
pub fn sample_setup(spec: &GlobalSpec, index: u64) -> (ConvexMedium, ShapeKind, Vec3, Vec3, Rng) {
    let mut rng = Rng::new(spec.seed, index, 0x6461_7461_6765_6e); // "datagen"
    let sigma = lerp(spec.sigma, rng.uniform());
    let albedo = lerp(spec.albedo, rng.uniform());
    let g = lerp(spec.g, rng.uniform());
    let kind = spec.shapes[((rng.uniform() * spec.shapes.len() as f32) as usize).min(spec.shapes.len() - 1)];
    let rotation = if spec.rotate { random_rotation(&mut rng) } else { Mat3::IDENTITY };
    let s = [lerp(spec.scale, rng.uniform()), lerp(spec.scale, rng.uniform()), lerp(spec.scale, rng.uniform())];
    let (shape, scale) = match kind {
        ShapeKind::Sphere => (Shape::Sphere, Vec3::splat(s[0])),
        ShapeKind::Box => (Shape::Box, Vec3::from(s)),
        ShapeKind::Ellipsoid => (Shape::Sphere, Vec3::from(s)),
    };
    let phase = PhaseFunction::HenyeyGreenstein { g };
    let medium = ConvexMedium::new(shape, rotation * Mat3::from_diagonal(scale), sigma, albedo, phase)
        .expect("validated settings give a valid medium");
    // No extra random number unless the option is on: older data sets stay reproducible.
    let (x, wo) = if spec.first_collision > 0.0 && rng.uniform() < spec.first_collision {
        first_collision_query(&medium, &mut rng)
    } else {
        (medium.sample_inside(&mut rng), engine::sampling::sample_uniform_sphere(rng.uniform2()))
    };
    (medium, kind, x, wo, rng)
}

/// A query like the renderer's at k = 1: a ray through a uniform interior point along a
/// uniform direction enters the shape; its first collision (exact free flight) is the
/// point and the direction back along the ray the query direction. Rays that pass
/// through without colliding are drawn again.
fn first_collision_query(medium: &ConvexMedium, rng: &mut Rng) -> (Vec3, Vec3) {
    loop {
        let p0 = medium.sample_inside(rng);
        let d = engine::sampling::sample_uniform_sphere(rng.uniform2());
        let entry = p0 - d * medium.exit_distance(p0, -d);
        let chord = medium.exit_distance(entry, d);
        let t = engine::sampling::sample_exponential(rng.uniform(), medium.sigma_t);
        if t < chord {
            return (entry + d * t, -d);
        }
    }
}

/// Generates data point `index`.
pub fn generate_point(spec: &GlobalSpec, fe: &FeatureExtractor, index: u64) -> DataPoint {
    let (medium, kind, x, wo, mut rng) = sample_setup(spec, index);
    let est = estimate_in_scattered(&medium, OMEGA_L, x, wo, &spec.stopping(), &mut rng);
    let g = medium.phase.mean_cosine();
    let mut features = vec![0.0; fe.len()];
    fe.extract_with(medium.albedo, g, OMEGA_L, wo, |d| medium.sigma_t * medium.exit_distance(x, d), &mut features);
    DataPoint {
        features,
        l_i: est.mean,
        std_error: est.std_error,
        samples: est.samples,
        sigma: medium.sigma_t,
        shape: kind,
    }
}

/// Which part of the data set a run makes: chunks c with c mod count == index.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: u64,
    pub count: u64,
}

impl Shard {
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// "i/N".
    pub fn parse(s: &str) -> Result<Shard, DatagenError> {
        let bad = || setting("--shard", format!("{s:?} is not i/N with 0 <= i < N"));
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let (index, count) = (i.trim().parse::<u64>().map_err(|_| bad())?, n.trim().parse::<u64>().map_err(|_| bad())?);
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }

    pub fn owns(&self, chunk: u64) -> bool {
        chunk % self.count == self.index
    }
}

/// manifest.json
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub format_version: u32,
    /// Nimbus version and commit that made the data.
    pub code_version: String,
    pub settings: GlobalSpec,
    /// The part of the data set in this directory (absent once merged / complete).
    pub shard: Option<Shard>,
    pub light_direction: [f32; 3],
    pub feature_names: Vec<String>,
    pub target_columns: Vec<String>,
    /// Set once features.npy and targets.npy hold the whole data set.
    pub complete: bool,
    pub counts: Counts,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Counts {
    pub points: u64,
    pub chunks: u64,
    pub path_samples: u64,
    /// Wall-clock seconds of generation summed over runs (resumes and shards).
    pub seconds: f64,
}

impl Manifest {
    pub fn new(spec: &GlobalSpec, shard: Option<Shard>, code_version: &str) -> Self {
        Manifest {
            format: FORMAT.into(),
            format_version: FORMAT_VERSION,
            code_version: code_version.into(),
            settings: spec.clone(),
            shard,
            light_direction: OMEGA_L.to_array(),
            feature_names: spec.feature_names(),
            target_columns: TARGET_COLUMNS.iter().map(|s| s.to_string()).collect(),
            complete: false,
            counts: Counts::default(),
        }
    }

    pub fn load(dir: &Path) -> Result<Manifest, DatagenError> {
        load_manifest(dir, FORMAT, FORMAT_VERSION, "a Nimbus data-set manifest", |m: &Manifest| {
            (m.format.clone(), m.format_version)
        })
    }

    pub fn save(&self, dir: &Path) -> Result<(), DatagenError> {
        save_manifest(dir, self)
    }
}

/// Reads `dir/manifest.json` as a `T` and checks its format and version (`what`
/// names the kind of file in the error). Shared by both data generators.
pub(crate) fn load_manifest<T: serde::de::DeserializeOwned>(
    dir: &Path,
    format: &str,
    version: u32,
    what: &str,
    format_of: impl Fn(&T) -> (String, u32),
) -> Result<T, DatagenError> {
    let path = dir.join("manifest.json");
    let text =
        std::fs::read_to_string(&path).map_err(|e| DatagenError::File { path: path.clone(), why: e.to_string() })?;
    let m: T = serde_json::from_str(&text)
        .map_err(|e| DatagenError::File { path: path.clone(), why: format!("not {what}: {e}") })?;
    let (f, v) = format_of(&m);
    if f != format || v != version {
        return Err(DatagenError::File { path, why: format!("format {f} v{v} is not {format} v{version}") });
    }
    Ok(m)
}

/// Writes `dir/manifest.json` atomically.
pub(crate) fn save_manifest<T: Serialize>(dir: &Path, m: &T) -> Result<(), DatagenError> {
    let path = dir.join("manifest.json");
    let text = serde_json::to_string_pretty(m).expect("manifest serializes");
    npy::write_bytes_atomically(&path, text.as_bytes()).map_err(|e| DatagenError::File { path, why: e.to_string() })
}

/// What the two data generators' manifests share: settings compared on resume, the
/// shard, completion and counts, and reading and writing.
pub(crate) trait DataManifest: Sized {
    type Spec: Serialize;
    fn create(spec: &Self::Spec, shard: Option<Shard>, code_version: &str) -> Self;
    fn read(dir: &Path) -> Result<Self, DatagenError>;
    fn write(&self, dir: &Path) -> Result<(), DatagenError>;
    fn spec(&self) -> &Self::Spec;
    fn shard(&self) -> Option<Shard>;
    fn counts_mut(&mut self) -> &mut Counts;
}

/// Opens `dir`'s manifest to resume it (refusing other settings or another shard,
/// naming the flags), or creates it.
pub(crate) fn open_manifest<M: DataManifest>(
    dir: &Path,
    spec: &M::Spec,
    shard: Shard,
    code_version: &str,
) -> Result<M, DatagenError> {
    let shard = (shard != Shard::ALL).then_some(shard);
    if !dir.join("manifest.json").exists() {
        let m = M::create(spec, shard, code_version);
        m.write(dir)?;
        return Ok(m);
    }
    let m = M::read(dir)?;
    if let Some(diff) = settings_diff(m.spec(), spec) {
        return Err(DatagenError::Mismatch { dir: dir.to_owned(), diff });
    }
    if m.shard() != shard {
        return Err(DatagenError::Mismatch {
            dir: dir.to_owned(),
            diff: format!("--shard was {:?}, now {:?}", m.shard(), shard),
        });
    }
    Ok(m)
}

/// How a data set is cut into chunks.
pub(crate) struct Chunking<'a> {
    pub n_chunks: u64,
    pub chunk_size: u64,
    pub chunk_len: &'a (dyn Fn(u64) -> u64 + Sync),
    /// Values per row.
    pub cols: usize,
}

/// Makes this shard's missing chunks (see [`write_chunks`]), reporting the points done
/// so far (chunks on disk included) to `progress`, and books the run in the manifest:
/// seconds, path samples, chunks. Returns the shard's point count, or `Cancelled`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn make_chunks<M: DataManifest>(
    manifest: &mut M,
    dir: &Path,
    chunking: &Chunking,
    shard: Shard,
    started: std::time::Instant,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
    point: impl Fn(u64) -> (Vec<f32>, u64) + Sync,
) -> Result<u64, DatagenError> {
    let chunks: Vec<u64> = (0..chunking.n_chunks).filter(|&c| shard.owns(c)).collect();
    let todo: Vec<u64> = chunks.iter().copied().filter(|&c| !chunk_path(dir, c).exists()).collect();
    let owned: u64 = chunks.iter().map(|&c| (chunking.chunk_len)(c)).sum();
    let done = std::sync::atomic::AtomicU64::new(owned - todo.iter().map(|&c| (chunking.chunk_len)(c)).sum::<u64>());
    progress(done.load(Ordering::Relaxed));
    let (finished, samples) =
        write_chunks(dir, &todo, chunking.chunk_size, chunking.chunk_len, chunking.cols, cancel, |i| {
            let out = point(i);
            progress(done.fetch_add(1, Ordering::Relaxed) + 1);
            out
        })?;
    let counts = manifest.counts_mut();
    counts.seconds += started.elapsed().as_secs_f64();
    counts.path_samples += samples;
    counts.chunks = (chunks.len() - todo.len() + finished) as u64;
    let done_chunks = counts.chunks as usize;
    manifest.write(dir)?;
    if finished < todo.len() {
        return Err(DatagenError::Cancelled { done: done_chunks, total: chunks.len() });
    }
    Ok(owned)
}

impl DataManifest for Manifest {
    type Spec = GlobalSpec;
    fn create(spec: &GlobalSpec, shard: Option<Shard>, code_version: &str) -> Self {
        Manifest::new(spec, shard, code_version)
    }
    fn read(dir: &Path) -> Result<Self, DatagenError> {
        Manifest::load(dir)
    }
    fn write(&self, dir: &Path) -> Result<(), DatagenError> {
        self.save(dir)
    }
    fn spec(&self) -> &GlobalSpec {
        &self.settings
    }
    fn shard(&self) -> Option<Shard> {
        self.shard
    }
    fn counts_mut(&mut self) -> &mut Counts {
        &mut self.counts
    }
}

/// The settings that differ, as "--flag was A, now B".
pub fn settings_diff<T: Serialize>(old: &T, new: &T) -> Option<String> {
    let (a, b) = (serde_json::to_value(old).unwrap(), serde_json::to_value(new).unwrap());
    let (a, b) = (a.as_object().unwrap(), b.as_object().unwrap());
    let diffs: Vec<String> = b
        .iter()
        .filter(|(k, v)| a.get(*k) != Some(*v))
        .map(|(k, v)| format!("--{} was {}, now {}", k.replace('_', "-"), a.get(k).cloned().unwrap_or_default(), v))
        .collect();
    (!diffs.is_empty()).then(|| diffs.join("; "))
}

pub fn chunk_path(dir: &Path, chunk: u64) -> PathBuf {
    dir.join("chunks").join(format!("chunk-{chunk:06}.npy"))
}

/// Generates (or resumes) this shard's chunks in `dir`. `progress` is called with the
/// number of points finished so far (chunks found on disk included) from worker
/// threads; `cancel` stops between points. A complete unsharded run ends with the
/// merged features.npy and targets.npy.
pub fn generate(
    spec: &GlobalSpec,
    shard: Shard,
    dir: &Path,
    code_version: &str,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
) -> Result<Manifest, DatagenError> {
    spec.validate()?;
    let started = std::time::Instant::now();
    let mut manifest: Manifest = open_manifest(dir, spec, shard, code_version)?;
    if manifest.complete {
        return Ok(manifest);
    }
    let fe = FeatureExtractor::with_set(spec.directions, spec.n_dirs).expect("validated");
    let chunking = Chunking {
        n_chunks: spec.n_chunks(),
        chunk_size: spec.chunk_size,
        chunk_len: &|c| spec.chunk_len(c),
        cols: spec.n_features() + 5,
    };
    let owned = make_chunks(&mut manifest, dir, &chunking, shard, started, progress, cancel, |i| {
        let p = generate_point(spec, &fe, i);
        let mut row = p.features.clone();
        row.extend_from_slice(&p.targets());
        (row, p.samples)
    })?;
    if shard == Shard::ALL {
        return merge(&[dir.to_owned()], dir);
    }
    manifest.counts.points = owned;
    manifest.save(dir)?;
    Ok(manifest)
}

/// Makes the chunks `todo` in parallel (points in parallel within a chunk): `point(i)`
/// gives data point i's rows (`cols` values each) and its path samples; each chunk is
/// written atomically once all its points are done. Stops between points once
/// `cancel` is set. Returns (chunks written, path samples of the points made). Shared
/// by the global and the point-to-point generators.
pub(crate) fn write_chunks(
    dir: &Path,
    todo: &[u64],
    chunk_size: u64,
    chunk_len: impl Fn(u64) -> u64 + Sync,
    cols: usize,
    cancel: &AtomicBool,
    point: impl Fn(u64) -> (Vec<f32>, u64) + Sync,
) -> Result<(usize, u64), DatagenError> {
    let samples = std::sync::atomic::AtomicU64::new(0);
    let results: Vec<Result<bool, DatagenError>> = todo
        .par_iter()
        .map(|&c| {
            let first = c * chunk_size;
            let points: Option<Vec<Vec<f32>>> = (first..first + chunk_len(c))
                .into_par_iter()
                .map(|i| {
                    if cancel.load(Ordering::Relaxed) {
                        return None;
                    }
                    let (rows, n) = point(i);
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
pub fn merge(dirs: &[PathBuf], out: &Path) -> Result<Manifest, DatagenError> {
    let manifests: Vec<Manifest> = dirs.iter().map(|d| Manifest::load(d)).collect::<Result<_, _>>()?;
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
    let mut features = Vec::with_capacity(spec.points as usize * n_f);
    let mut targets = Vec::with_capacity(spec.points as usize * 5);
    let mut samples = 0u64;
    for (c, k) in owner.iter().enumerate() {
        let path = chunk_path(&dirs[k.unwrap()], c as u64);
        let (shape, data) = npy::read_f32(&path)?;
        let expect = spec.chunk_len(c as u64) as usize;
        if shape != [expect, n_f + 5] {
            return Err(DatagenError::File { path, why: format!("shape {shape:?}, expected [{expect}, {}]", n_f + 5) });
        }
        for row in data.chunks_exact(n_f + 5) {
            features.extend_from_slice(&row[..n_f]);
            targets.extend_from_slice(&row[n_f..]);
            samples += row[n_f + 2] as u64;
        }
    }
    let n = spec.points as usize;
    npy::write_f32(&out.join("features.npy"), &[n, n_f], &features)?;
    npy::write_f32(&out.join("targets.npy"), &[n, 5], &targets)?;
    let mut m = Manifest::new(&spec, None, &first.code_version);
    m.complete = true;
    m.counts = Counts {
        points: spec.points,
        chunks: spec.n_chunks(),
        path_samples: samples,
        seconds: manifests.iter().map(|m| m.counts.seconds).sum(),
    };
    m.save(out)?;
    Ok(m)
}

/// A loaded, complete data set.
pub struct Dataset {
    pub manifest: Manifest,
    /// Row-major [n, n_features].
    pub features: Vec<f32>,
    /// Row-major [n, 5] (TARGET_COLUMNS).
    pub targets: Vec<f32>,
}

impl Dataset {
    pub fn load(dir: &Path) -> Result<Dataset, DatagenError> {
        let manifest = Manifest::load(dir)?;
        if !manifest.complete {
            return Err(DatagenError::File {
                path: dir.join("manifest.json"),
                why: "the data set is not complete: finish generating it (run the same command again) or merge its shards".into(),
            });
        }
        let n_f = manifest.settings.n_features();
        let n = manifest.counts.points as usize;
        let (fs, features) = npy::read_f32(&dir.join("features.npy"))?;
        let (ts, targets) = npy::read_f32(&dir.join("targets.npy"))?;
        if fs != [n, n_f] || ts != [n, 5] {
            return Err(DatagenError::File {
                path: dir.to_owned(),
                why: format!("features {fs:?} / targets {ts:?} do not match the manifest ({n} points, {n_f} features)"),
            });
        }
        Ok(Dataset { manifest, features, targets })
    }

    pub fn len(&self) -> usize {
        self.manifest.counts.points as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn n_features(&self) -> usize {
        self.manifest.settings.n_features()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> GlobalSpec {
        GlobalSpec {
            points: 23,
            sigma: [0.5, 4.0],
            albedo: [0.5, 1.0],
            g: [-0.3, 0.9],
            scale: [0.5, 1.5],
            n_dirs: 16,
            max_rel_error: 0.3,
            min_samples: 64,
            chunk_size: 5,
            seed: 7,
            ..Default::default()
        }
    }

    fn temp_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("nimbus-datagen-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    fn run(spec: &GlobalSpec, shard: Shard, dir: &Path, threads: usize) -> Result<Manifest, DatagenError> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| generate(spec, shard, dir, "test", &|_| {}, &AtomicBool::new(false)))
    }

    fn files(dir: &Path) -> (Vec<u8>, Vec<u8>) {
        (std::fs::read(dir.join("features.npy")).unwrap(), std::fs::read(dir.join("targets.npy")).unwrap())
    }

    #[test]
    fn same_data_whatever_threads_shards_and_interruptions() {
        let spec = tiny();
        let one = temp_dir("one");
        let m = run(&spec, Shard::ALL, &one, 1).unwrap();
        assert!(m.complete);
        assert_eq!(m.counts.points, 23);
        let reference = files(&one);

        let two = temp_dir("two");
        run(&spec, Shard::ALL, &two, 2).unwrap();
        assert_eq!(files(&two), reference, "thread count changed the data");

        // Three shards on different thread counts, merged.
        let shards: Vec<PathBuf> = (0..3).map(|i| temp_dir(&format!("shard{i}"))).collect();
        for (i, d) in shards.iter().enumerate() {
            let m = run(&spec, Shard { index: i as u64, count: 3 }, d, 1 + i % 2).unwrap();
            assert!(!m.complete);
        }
        let merged = temp_dir("merged");
        assert!(merge(&shards[..2], &merged).unwrap_err().to_string().contains("missing"));
        merge(&shards, &merged).unwrap();
        assert_eq!(files(&merged), reference, "sharding changed the data");
        // A shard given twice is refused.
        let dup = vec![shards[0].clone(), shards[1].clone(), shards[2].clone(), shards[0].clone()];
        assert!(merge(&dup, &temp_dir("dup")).unwrap_err().to_string().contains("also in"));

        // Interrupted: chunks 1 and 3 lost, a stray temporary left; the resumed run is
        // identical.
        let resumed = temp_dir("resumed");
        run(&spec, Shard { index: 0, count: 1 }, &resumed, 2).unwrap();
        for f in ["features.npy", "targets.npy"] {
            std::fs::remove_file(resumed.join(f)).unwrap();
        }
        let mut m = Manifest::load(&resumed).unwrap();
        m.complete = false;
        m.save(&resumed).unwrap();
        std::fs::remove_file(chunk_path(&resumed, 1)).unwrap();
        std::fs::remove_file(chunk_path(&resumed, 3)).unwrap();
        std::fs::write(resumed.join("chunks").join(".chunk-000001.npy.1.x.tmp"), b"half").unwrap();
        let m = run(&spec, Shard::ALL, &resumed, 2).unwrap();
        assert!(m.complete);
        assert_eq!(files(&resumed), reference, "resuming changed the data");

        // A cancelled run says how far it got and keeps what it has.
        let cancelled = temp_dir("cancelled");
        let flag = AtomicBool::new(true);
        let e = generate(&spec, Shard::ALL, &cancelled, "test", &|_| {}, &flag).unwrap_err();
        assert!(e.to_string().contains("resume"), "{e}");

        // Other settings in the same directory are refused, naming the flag.
        let other = GlobalSpec { g: [0.0, 0.5], ..spec.clone() };
        let e = run(&other, Shard::ALL, &cancelled, 1).unwrap_err().to_string();
        assert!(e.contains("--g was"), "{e}");

        let data = Dataset::load(&one).unwrap();
        assert_eq!(data.len(), 23);
        for row in data.targets.chunks_exact(5) {
            assert!(row[0] > 0.0 && row[1] >= 0.0 && row[2] >= 64.0 && row[3] >= 0.5 && row[3] <= 4.0);
        }
        for row in data.features.chunks_exact(20) {
            assert!(row[4..].iter().all(|t| *t <= 0.0 && t.is_finite()));
        }
        for d in [one, two, merged, resumed, cancelled].iter().chain(&shards) {
            let _ = std::fs::remove_dir_all(d);
        }
    }

    #[test]
    fn bad_settings_name_their_flag() {
        let cases: [(GlobalSpec, &str); 7] = [
            (GlobalSpec { g: [0.0, 1.0], ..tiny() }, "--g"),
            (GlobalSpec { sigma: [5.0, 1.0], ..tiny() }, "--sigma"),
            (GlobalSpec { albedo: [0.0, 1.5], ..tiny() }, "--albedo"),
            (GlobalSpec { shapes: vec![], ..tiny() }, "--shapes"),
            (GlobalSpec { n_dirs: 32, ..tiny() }, "--n-dirs"),
            (GlobalSpec { confidence: 1.0, ..tiny() }, "--confidence"),
            (GlobalSpec { points: 0, ..tiny() }, "--points"),
        ];
        for (spec, flag) in cases {
            let e = spec.validate().unwrap_err().to_string();
            assert!(e.starts_with(flag), "{e}");
        }
        assert!(parse_range("--sigma", "3..1").unwrap_err().to_string().contains("empty"));
        assert_eq!(parse_range("--g", "0..0.9").unwrap(), [0.0, 0.9]);
        assert_eq!(parse_range("--albedo", "1").unwrap(), [1.0, 1.0]);
        assert!(Shard::parse("3/3").is_err() && Shard::parse("x").is_err());
        assert_eq!(Shard::parse("1/4").unwrap(), Shard { index: 1, count: 4 });
        assert_eq!(ShapeKind::parse("cone"), None);
    }

    /// Points are spread as specified: shapes in equal shares, query points inside.
    #[test]
    fn setups_cover_the_specified_distribution() {
        let spec = GlobalSpec { points: 3000, scale: [0.5, 1.5], ..Default::default() };
        let mut counts = [0.0f64; 3];
        let mut sigma_mean = 0.0;
        for i in 0..3000 {
            let (m, kind, x, wo, _) = sample_setup(&spec, i);
            assert!(m.contains(x));
            assert!((wo.length() - 1.0).abs() < 1e-5);
            counts[kind.id() as usize] += 1.0;
            sigma_mean += m.sigma_t as f64 / 3000.0;
        }
        let chi = engine::stats::chi2_test(&counts, &[1000.0; 3], 5.0);
        assert!(chi.p_value > 0.01, "{counts:?}");
        // Mean of U[1, 100] is 50.5, standard error 28.6 / sqrt(3000) = 0.52.
        assert!((sigma_mean - 50.5).abs() < 4.0 * 0.52, "{sigma_mean}");
    }
}
