//! Ground truth for the point-to-point model (thesis 6.3): per data point, emitter
//! and sensor at the ends of two k-segment walks entering the cloud from outside, the
//! transport T between them to a requested accuracy (confidence-interval stopping),
//! and the density features of `rotations` random rotations of the local frame about
//! the emitter-sensor axis (the thesis reused each T 50 times this way; its isotropic
//! media make T independent of the rotation).
//!
//! The files, chunks, shards, resume and merge are those of [`crate::dataset`]
//! (format `nimbus-p2p-dataset`): once complete `features.npy` [rows, 352] and
//! `targets.npy` [rows, 5]. Point i is a pure function of (seed, i): the same bytes
//! whatever the thread count or sharding.

use super::features::{P2pFeatures, pyramid_for};
use super::frame::LocalFrame;
use super::pyramid::DensityPyramid;
use crate::dataset::chunks;
use crate::dataset::manifest::{DataSpec, DatagenError, Manifest, Shard, setting};
use crate::dataset::stopping::Stopping;
use engine::integrator::p2p::{P2pSettings, sample_query_end, sample_transport};
use engine::{DensityGrid, Medium, P2pQuery, PhaseFunction, Rng};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

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
        Stopping::validate(self.max_rel_error, self.confidence, self.min_samples, self.max_samples)
    }
    pub fn rows(&self) -> u64 {
        self.points * self.rotations as u64
    }
    /// Largest emitter-sensor distance the pyramid serves: the cloud's diagonal.
    fn pyramid(&self, grid: &DensityGrid) -> DensityPyramid {
        pyramid_for(grid, &self.features, grid.bounds().extent().length())
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
    let set = P2pSettings::default();
    let stop = Stopping::new(spec.max_rel_error, spec.confidence, spec.min_samples, spec.max_samples);
    let w = stop.estimate(64, || sample_transport(medium, &q, &set, &mut rng) as f64);
    let dist = (q.sensor - q.emitter).length();
    let n_f = spec.n_features();
    let mut rows = vec![0.0f32; spec.rotations as usize * (n_f + 5)];
    for row in rows.chunks_exact_mut(n_f + 5) {
        let frame =
            LocalFrame::new(q.emitter, q.sensor, std::f32::consts::TAU * rng.uniform()).expect("distinct points");
        spec.features.write(pyramid, spec.rho, spec.albedo, &frame, &mut row[..n_f]);
        row[n_f..].copy_from_slice(&[
            w.mean as f32,
            w.std_error as f32,
            w.samples as f32,
            dist,
            (w.mean * (dist as f64).powi(2)) as f32,
        ]);
    }
    (rows, w.samples)
}

/// Generates (or resumes) this shard's chunks in `dir` from the cloud `grid` (see
/// [`chunks::generate`]); a complete unsharded run ends with features.npy and
/// targets.npy.
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
    let prepare = || {
        let phase = PhaseFunction::henyey_greenstein(spec.g).map_err(|e| setting("--g", e))?;
        let medium =
            Medium::new(grid.clone(), spec.rho, spec.albedo, phase).map_err(|e| setting("--rho", e.to_string()))?;
        Ok((medium, spec.pyramid(&grid)))
    };
    chunks::generate(spec, shard, dir, code_version, progress, cancel, prepare, |(medium, pyramid), i| {
        generate_point(spec, medium, pyramid, i)
    })
}

/// The point-to-point data set.
pub type P2pManifest = Manifest<P2pSpec>;

/// The point-to-point data set has no manifest fields of its own.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct P2pHeader {}

impl DataSpec for P2pSpec {
    const FORMAT: &'static str = "nimbus-p2p-dataset";
    const FORMAT_VERSION: u32 = 1;
    const WHAT: &'static str = "a point-to-point data set";
    /// Per row: T in world units, its standard error, the samples it took, the
    /// emitter-sensor distance D, and T in the local frame (D^2 T, the scale-free
    /// target).
    const TARGET_COLUMNS: [&'static str; 5] = ["T", "std_error", "samples", "distance", "T_local"];
    type Header = P2pHeader;
    fn validate(&self) -> Result<(), DatagenError> {
        Self::validate(self)
    }
    fn header(&self) -> P2pHeader {
        P2pHeader {}
    }
    fn points(&self) -> u64 {
        self.points
    }
    fn chunk_size(&self) -> u64 {
        self.chunk_size
    }
    fn rows_per_point(&self) -> u64 {
        self.rotations as u64
    }
    fn n_features(&self) -> usize {
        self.features.len()
    }
    /// The shards' own counts (each point's rows repeat its sample count).
    fn merged_path_samples(manifests: &[Manifest<Self>], _: &[f32]) -> u64 {
        manifests.iter().map(|m| m.counts.path_samples).sum()
    }
}
