//! The cloud-aware model's data generator: clouds like the renderer's (the modeler's
//! presets and random [`CloudParams`]), each under a random sun with random rho,
//! albedo and g; query points where the renderer asks (the k-th scattering vertex of
//! camera paths from random views); the multiple-scattering part of the in-scattered
//! radiance there by path tracing in the grid; and the stencil features of
//! [`super::features`].
//!
//! One chunk is one cloud (a "case", made once per chunk by
//! [`chunks::generate_by_chunk`]): chunk c's cloud, sun and medium are a pure
//! function of (seed, c), and point i's query and ground truth of (seed, i), so the
//! data are the same bytes for any thread or shard count. Files, resume, shards and
//! merge are those of [`crate::dataset`].
//!
//! targets.npy columns: L_ms (orders >= 2 counted from the point, for a sun of unit
//! radiance; the mean of `samples` paths), its standard error, the path count, the
//! first path's estimate alone (an unbiased one-path target, for the comparison of
//! precise and cheap targets), and the vertex index k of the query.

use super::features::{CloudField, N_FEATURES, STORED_FEATURES, expand_stored_rows};
use crate::dataset::chunks;
use crate::dataset::manifest::{DataSpec, DatagenError, Manifest, Shard, check_range, setting};
use crate::dataset::npy;
use engine::rng::mix64;
use engine::{Camera, FreeFlight, Integrator, Medium, PhaseFunction, RenderSettings, Rng, Scene, Sky, Sun};
use glam::Vec3;
use modeler::CloudParams;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

fn uniform_power() -> f32 {
    1.0
}

/// Presets kept out of every training set: the held-out clouds the model is judged on
/// (with the random held-out clouds of [`held_out_cloud`]).
pub const HELD_OUT_PRESETS: [&str; 3] = ["set-10", "set-11", "set-12"];

/// Every setting of a data set; stored in the manifest, compared on resume and merge.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CloudSpec {
    pub points: u64,
    /// Points per cloud (one chunk per cloud).
    pub points_per_cloud: u64,
    /// Voxels per axis of each cloud.
    pub resolution: u32,
    /// Presets among the clouds (cycled), none of [`HELD_OUT_PRESETS`].
    pub presets: Vec<String>,
    /// Every n-th cloud is a preset (0: none); the others are random [`CloudParams`].
    pub preset_every: u64,
    /// Density scale rho, log-uniform in [min, max].
    pub rho: [f32; 2],
    /// Albedo range [min, max], drawn as max - (max - min) u^3: toward max, where
    /// artists work and where multiple scattering changes fastest.
    pub albedo: [f32; 2],
    /// Henyey-Greenstein g range [min, max], drawn as min + (max - min) (1 - u^g_power)
    /// (u uniform): uniform for 1, toward max for larger powers (clouds scatter forward, g near
    /// 0.85, where multiple scattering is most peaked and hardest to learn).
    pub g: [f32; 2],
    /// See `g`.
    #[serde(default = "uniform_power")]
    pub g_power: f32,
    /// Paths per point.
    pub samples: u64,
    /// Probabilities of the query being the 1st, 2nd, 3rd scattering vertex of its
    /// camera path (they sum to 1).
    pub vertex_weights: [f32; 3],
    /// Sun-field nodes per axis at most.
    pub field_nodes: u32,
    pub seed: u64,
    /// Views at a fixed angle to the sun: the cosine between the direction from the
    /// cloud to the camera and the direction to the sun (1 frontlit, -1 backlit), the
    /// azimuth random; None: views from anywhere.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub view_sun_cos: Option<f32>,
    /// Without `view_sun_cos`: the fraction of views drawn within about 15 degrees of
    /// the sun's axis, half in front of the cloud and half behind it (frontlit and
    /// backlit, where the camera's path and the sun's light run together and a
    /// uniform view rarely lands); the others are uniform.
    #[serde(default)]
    pub aligned_views: f32,
    /// A held-out set: the clouds are [`HELD_OUT_PRESETS`] (every `preset_every`-th)
    /// and [`held_out_cloud`]s, never those of a training set; `presets` is unused.
    #[serde(default)]
    pub held_out: bool,
    /// The direction the sun's light travels, the same for every cloud (as a scene
    /// file's `sun.direction`; normalized); None: a uniformly random sun per cloud.
    /// With `view_sun_cos`, reproduces a fixed lighting, such as the evaluation's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun: Option<[f32; 3]>,
}

impl Default for CloudSpec {
    fn default() -> Self {
        CloudSpec {
            points: 51_200,
            points_per_cloud: 256,
            resolution: 64,
            presets: modeler::PRESET_NAMES
                .iter()
                .filter(|n| !HELD_OUT_PRESETS.contains(n))
                .map(|s| s.to_string())
                .collect(),
            preset_every: 4,
            rho: [5.0, 320.0],
            albedo: [0.9, 1.0],
            g: [0.0, 0.9],
            g_power: 1.0,
            samples: 16,
            vertex_weights: [0.5, 0.3, 0.2],
            field_nodes: 128,
            seed: 1,
            view_sun_cos: None,
            aligned_views: 0.3,
            held_out: false,
            sun: None,
        }
    }
}

impl CloudSpec {
    /// The cloud (chunk) of point `i`.
    pub fn cloud_of(&self, i: u64) -> u64 {
        i / self.points_per_cloud
    }

    /// Checks every setting; the error names the command-line flag.
    pub fn validate(&self) -> Result<(), DatagenError> {
        if self.points == 0 {
            return Err(setting("--points", "must be at least 1"));
        }
        if self.points_per_cloud == 0 {
            return Err(setting("--points-per-cloud", "must be at least 1"));
        }
        if !(8..=256).contains(&self.resolution) {
            return Err(setting("--resolution", format!("{} must lie in 8 ..= 256", self.resolution)));
        }
        for p in &self.presets {
            if HELD_OUT_PRESETS.contains(&p.as_str()) {
                return Err(setting("--presets", format!("{p} is a held-out cloud and never trained on")));
            }
            if modeler::preset(p).is_none() {
                return Err(setting(
                    "--presets",
                    format!("no preset {p:?} (there are {})", modeler::PRESET_NAMES.join(", ")),
                ));
            }
        }
        if self.preset_every > 0 && self.presets.is_empty() && !self.held_out {
            return Err(setting("--preset-every", "needs at least one preset in --presets"));
        }
        check_range("--rho", self.rho, |v| v > 0.0 && v <= 10_000.0, "(0, 10000]")?;
        check_range("--albedo", self.albedo, |v| (0.0..=1.0).contains(&v), "[0, 1]")?;
        check_range("--g", self.g, |v| v > -1.0 && v < 1.0, "(-1, 1)")?;
        if !(self.g_power.is_finite() && (0.1..=10.0).contains(&self.g_power)) {
            return Err(setting("--g-power", format!("{} must lie in 0.1 ..= 10", self.g_power)));
        }
        if !(1..=1_000_000).contains(&self.samples) {
            return Err(setting("--samples", format!("{} must lie in 1 ..= 1000000", self.samples)));
        }
        let w = self.vertex_weights;
        if w.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || (w.iter().sum::<f32>() - 1.0).abs() > 1e-4 {
            return Err(setting("--vertex-weights", format!("{w:?} must be three weights >= 0 that sum to 1")));
        }
        if !(0.0..=1.0).contains(&self.aligned_views) {
            return Err(setting("--aligned-views", format!("{} must lie in [0, 1]", self.aligned_views)));
        }
        if let Some(c) = self.view_sun_cos {
            if !(-1.0..=1.0).contains(&c) {
                return Err(setting("--view-sun-cos", format!("{c} must lie in [-1, 1]")));
            }
        }
        if let Some(d) = self.sun {
            if !(d.iter().all(|v| v.is_finite()) && Vec3::from_array(d).length() > 1e-6) {
                return Err(setting("--sun", format!("{d:?} must be a non-zero finite direction")));
            }
        }
        if !(2..=1024).contains(&self.field_nodes) {
            return Err(setting("--field-nodes", format!("{} must lie in 2 ..= 1024", self.field_nodes)));
        }
        Ok(())
    }

    /// The cloud of case `c`: a preset or random parameters.
    pub fn cloud(&self, c: u64) -> (String, CloudParams) {
        if self.held_out {
            if self.preset_every > 0 && c % self.preset_every == 0 {
                let name = HELD_OUT_PRESETS[((c / self.preset_every) % HELD_OUT_PRESETS.len() as u64) as usize];
                return (name.to_string(), modeler::preset(name).expect("a preset"));
            }
            return (format!("held-out-{c}"), held_out_cloud(c));
        }
        if self.preset_every > 0 && c % self.preset_every == 0 {
            let name = &self.presets[((c / self.preset_every) % self.presets.len() as u64) as usize];
            return (name.clone(), modeler::preset(name).expect("validated"));
        }
        // The top bit is clear for training clouds and set for held-out ones.
        let seed = mix64(mix64(self.seed) ^ c) & !(1 << 63);
        (format!("random-{seed:016x}"), CloudParams::random(seed))
    }
}

/// Random held-out cloud `i`: never drawn by any training set (see [`CloudSpec::cloud`]).
pub fn held_out_cloud(i: u64) -> CloudParams {
    CloudParams::random(mix64(0x6865_6c64_6f75_74 ^ i) | (1 << 63)) // "heldout"
}

/// One cloud under one sun: what the points of a chunk share.
pub struct Case {
    pub name: String,
    pub scene: Scene,
    pub field: CloudField,
    /// Path tracing from the query points.
    pub integrator: Integrator,
}

fn log_lerp(r: [f32; 2], u: f32) -> f32 {
    (r[0].ln() + (r[1].ln() - r[0].ln()) * u).exp()
}

fn lerp(r: [f32; 2], u: f32) -> f32 {
    r[0] + (r[1] - r[0]) * u
}

/// The medium and sun of one case.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CaseMedium {
    pub rho: f32,
    pub albedo: f32,
    pub g: f32,
    /// Unit direction toward the sun.
    pub to_sun: Vec3,
}

/// Case `c`'s rho (log-uniform), albedo and g (toward their maxima as `spec` says) and
/// sun (uniform, or `spec.sun`).
pub fn case_medium(spec: &CloudSpec, c: u64) -> CaseMedium {
    let mut rng = Rng::new(spec.seed, c, 0x6361_7365); // "case"
    let rho = log_lerp(spec.rho, rng.uniform());
    let albedo = spec.albedo[1] - (spec.albedo[1] - spec.albedo[0]) * rng.uniform().powi(3);
    let u = rng.uniform();
    // 1 - (1 - u)^p, written so that p = 1 is u itself, bit for bit.
    let g = lerp(spec.g, if spec.g_power == 1.0 { u } else { 1.0 - (1.0 - u).powf(spec.g_power) });
    let random_to_sun = engine::sampling::sample_uniform_sphere(rng.uniform2());
    let to_sun = spec.sun.map_or(random_to_sun, |d| -Vec3::from_array(d).normalize());
    CaseMedium { rho, albedo, g, to_sun }
}

/// Builds case `c` of `spec`: cloud, rho, albedo, g and a uniformly random sun (or
/// `spec.sun`).
pub fn build_case(spec: &CloudSpec, c: u64) -> Result<Case, DatagenError> {
    let (name, params) = spec.cloud(c);
    let grid = modeler::build_grid(&params, spec.resolution).map_err(|e| setting("--presets", e.to_string()))?;
    let CaseMedium { rho, albedo, g, to_sun } = case_medium(spec, c);
    let phase = PhaseFunction::henyey_greenstein(g).map_err(|e| setting("--g", e))?;
    let medium = Medium::new(Arc::new(grid), rho, albedo, phase).map_err(|e| setting("--rho", e.to_string()))?;
    let sun = Sun::new(-to_sun, Vec3::ONE, 0.0).expect("a unit direction");
    let camera = Camera::new(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 30.0, 1, 1).expect("valid camera");
    let field = CloudField::build(&medium, &sun, spec.field_nodes);
    let integrator = Integrator::new(RenderSettings::default(), None).expect("path tracing");
    Ok(Case { name, scene: Scene { medium, sun: Some(sun), sky: Sky::default(), camera }, field, integrator })
}

/// A query like the renderer's: a camera ray from a random view toward the cloud,
/// followed by delta tracking to its `vertex`-th scattering event; the query direction
/// points back along the path. The rays are those of a distant camera that sees the
/// whole cloud: parallel to the view direction and uniform over the disc that the
/// box's bounding sphere casts on the image, so every pixel of the cloud is as likely
/// as in an image, its silhouette's fringe as much as its centre (rays aimed at points
/// near the centre, as a first version drew them, reach the outer fifth of a round
/// cloud's disc about a fifth as often as its pixels do). Paths that miss or leave
/// first are drawn again (at most 1024 times; a cloud too thin for that gets a uniform
/// point of its box). `view`, if given, is (direction to the sun, cosine): the view
/// direction then makes that cosine with the sun's.
pub fn camera_path_query(medium: &Medium, vertex: u32, view: Option<(Vec3, f32)>, rng: &mut Rng) -> (Vec3, Vec3) {
    let b = medium.bounds();
    let (c, r) = (b.center(), 0.5 * b.extent().length());
    for _ in 0..1024 {
        let dir = match view {
            None => engine::sampling::sample_uniform_sphere(rng.uniform2()),
            Some((to_sun, cos)) => {
                let phi = std::f32::consts::TAU * rng.uniform();
                let sin = (1.0 - cos * cos).max(0.0).sqrt();
                engine::sampling::local_to_world(Vec3::new(sin * phi.cos(), sin * phi.sin(), cos), to_sun)
            }
        };
        let (t, s) = engine::sampling::coordinate_system(dir);
        let offset = engine::sampling::sample_uniform_disk(rng.uniform2()) * r;
        let eye = c + dir * (2.0 * r) + t * offset.x + s * offset.y;
        let d = -dir;
        let FreeFlight::Collision { t } = medium.sample_free_flight(eye, d, f32::INFINITY, rng) else { continue };
        let (mut x, mut wo) = (eye + d * t, -d);
        let mut reached = true;
        for _ in 1..vertex {
            match medium.scatter(x, wo, rng) {
                Ok(next) => (x, wo) = next,
                Err(_) => {
                    reached = false;
                    break;
                }
            }
        }
        if reached {
            return (x, wo);
        }
    }
    let u = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform());
    (b.min + u * b.extent(), engine::sampling::sample_uniform_sphere(rng.uniform2()))
}

/// One data point's row (features, then the 5 targets) and its path count.
pub fn generate_point(spec: &CloudSpec, case: &Case, index: u64) -> (Vec<f32>, u64) {
    let mut rng = Rng::new(spec.seed, index, 0x636c_6f75_6470); // "cloudp"
    let u = rng.uniform();
    let w = spec.vertex_weights;
    let vertex = if u < w[0] {
        1
    } else if u < w[0] + w[1] {
        2
    } else {
        3
    };
    let to_sun = -case.scene.sun.expect("a sun").direction();
    let view = match spec.view_sun_cos {
        Some(cos) => Some((to_sun, cos)),
        None if rng.uniform() < spec.aligned_views => {
            let (u, side) = (rng.uniform(), rng.uniform());
            let cos = 1.0 - 0.035 * u * u;
            Some((to_sun, if side < 0.5 { cos } else { -cos }))
        }
        None => None,
    };
    let (x, wo) = camera_path_query(&case.scene.medium, vertex, view, &mut rng);
    let integrator = &case.integrator;
    let (mut sum, mut sq, mut first) = (0.0f64, 0.0f64, 0.0f64);
    for s in 0..spec.samples {
        let v = integrator.multiple_scattered_radiance(&case.scene, x, wo, &mut rng).x as f64;
        let v = if v.is_finite() { v } else { 0.0 };
        if s == 0 {
            first = v;
        }
        sum += v;
        sq += v * v;
    }
    let n = spec.samples as f64;
    let mean = sum / n;
    let std_error = if spec.samples > 1 { ((sq / n - mean * mean).max(0.0) / (n - 1.0)).sqrt() } else { 0.0 };
    // The derived features are computed on loading ([`CloudDataset::read_rows`]).
    let mut row = vec![0.0f32; STORED_FEATURES];
    let m = &case.scene.medium;
    case.field.stored_features(m.albedo(), m.phase().mean_cosine(), x, wo, &mut row);
    row.extend_from_slice(&[mean as f32, std_error as f32, n as f32, first as f32, vertex as f32]);
    (row, spec.samples)
}

/// The cloud data set.
pub type CloudManifest = Manifest<CloudSpec>;

/// The cloud data set's own manifest fields.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CloudHeader {
    pub feature_names: Vec<String>,
}

impl DataSpec for CloudSpec {
    const FORMAT: &'static str = "nimbus-cloud-dataset";
    const FORMAT_VERSION: u32 = 6;
    const WHAT: &'static str = "a cloud data set";
    const TARGET_COLUMNS: [&'static str; 5] = ["L_ms", "std_error", "samples", "L_ms_one_path", "vertex"];
    type Header = CloudHeader;
    fn validate(&self) -> Result<(), DatagenError> {
        Self::validate(self)
    }
    fn header(&self) -> CloudHeader {
        CloudHeader { feature_names: super::features::stored_feature_names() }
    }
    fn points(&self) -> u64 {
        self.points
    }
    fn chunk_size(&self) -> u64 {
        self.points_per_cloud
    }
    fn rows_per_point(&self) -> u64 {
        1
    }
    fn n_features(&self) -> usize {
        STORED_FEATURES
    }
    fn merged_path_samples(_: &[Manifest<Self>], targets: &[f32]) -> u64 {
        targets.chunks_exact(5).map(|t| t[2] as u64).sum()
    }
}

/// Generates (or resumes) this shard's chunks in `dir` (see [`chunks::generate`]).
pub fn generate(
    spec: &CloudSpec,
    shard: Shard,
    dir: &Path,
    code_version: &str,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
) -> Result<CloudManifest, DatagenError> {
    spec.validate()?;
    chunks::generate_by_chunk(
        spec,
        shard,
        dir,
        code_version,
        progress,
        cancel,
        || Ok(()),
        |_, c| build_case(spec, c),
        |_, case, i| generate_point(spec, case, i),
    )
}

/// A data set loaded for training: rows, targets and which cloud each row comes from.
pub struct CloudDataset {
    pub manifest: CloudManifest,
    /// Row-major [n, N_FEATURES]: the stored features and the derived ones.
    pub features: Vec<f32>,
    /// Row-major [n, 5] (TARGET_COLUMNS).
    pub targets: Vec<f32>,
}

impl CloudDataset {
    pub fn load(dir: &Path) -> Result<CloudDataset, DatagenError> {
        let manifest = Self::manifest_of(dir)?;
        // Reserved for the rows spread to N_FEATURES, so that the spreading does not
        // reallocate.
        let rows = Self::rows_of(dir, &manifest)?;
        let (mut features, mut targets) = (Vec::with_capacity(rows * N_FEATURES), Vec::with_capacity(rows * 5));
        Self::read_rows(dir, &manifest, &mut features, &mut targets)?;
        Ok(CloudDataset { features, targets, manifest })
    }

    /// The manifest of the complete data set in `dir` (an incomplete one is refused).
    pub fn manifest_of(dir: &Path) -> Result<CloudManifest, DatagenError> {
        let manifest = CloudManifest::load(dir)?;
        if !manifest.complete {
            return Err(DatagenError::File {
                path: dir.join("manifest.json"),
                why: "the data set is not complete: finish generating it (run the same command again) or merge its shards".into(),
            });
        }
        Ok(manifest)
    }

    /// The data set's rows as its manifest counts them, checked against the sizes of
    /// its files, so that a damaged manifest cannot ask for a buffer its files do not
    /// fill.
    pub fn rows_of(dir: &Path, manifest: &CloudManifest) -> Result<usize, DatagenError> {
        let rows = manifest.counts.points as usize;
        for (name, cols) in [("features.npy", STORED_FEATURES), ("targets.npy", 5)] {
            let path = dir.join(name);
            let size = std::fs::metadata(&path)
                .map_err(|e| DatagenError::File { path: path.clone(), why: e.to_string() })?
                .len();
            if rows.checked_mul(4 * cols).is_none_or(|bytes| bytes as u64 > size) {
                return Err(DatagenError::File {
                    path,
                    why: format!("the manifest counts {rows} rows, more than the file's {size} bytes hold"),
                });
            }
        }
        Ok(rows)
    }

    /// Appends the rows of the data set in `dir` (whose manifest is `manifest`) to
    /// `features` (rows of [`N_FEATURES`]: the stored ones with the derived ones
    /// appended in place) and `targets`, streamed from the files: several data sets load
    /// into buffers reserved once for all of them, at the cost of their rows alone.
    pub fn read_rows(
        dir: &Path,
        manifest: &CloudManifest,
        features: &mut Vec<f32>,
        targets: &mut Vec<f32>,
    ) -> Result<(), DatagenError> {
        let rows = manifest.counts.points as usize;
        let (f0, t0) = (features.len(), targets.len());
        let mut read = || -> Result<(), DatagenError> {
            for (name, cols, out) in
                [("features.npy", STORED_FEATURES, &mut *features), ("targets.npy", 5, &mut *targets)]
            {
                let path = dir.join(name);
                let start = out.len();
                let shape = npy::read_f32_into(&path, out)
                    .map_err(|e| DatagenError::File { path: path.clone(), why: e.to_string() })?;
                if shape.len() != 2 || shape[1] != cols || shape[0] != rows {
                    return Err(DatagenError::File {
                        path,
                        why: format!("shape {shape:?}, expected [{rows}, {cols}] (the manifest's {rows} rows)"),
                    });
                }
                debug_assert_eq!(out.len() - start, rows * cols);
            }
            expand_stored_rows(features, f0, rows);
            Ok(())
        };
        let result = read();
        if result.is_err() {
            features.truncate(f0);
            targets.truncate(t0);
        }
        result
    }

    pub fn len(&self) -> usize {
        self.targets.len() / 5
    }

    pub fn is_empty(&self) -> bool {
        self.targets.is_empty()
    }

    /// The cloud (chunk) of row `i`.
    pub fn cloud_of(&self, i: usize) -> u64 {
        self.manifest.settings.cloud_of(i as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::stats::chi2_test;

    /// First vertices of the camera paths land where an image's pixels do: seen along
    /// a fixed axis, the first collisions with an opaque cube are uniform over its
    /// square silhouette, fringe as often as centre (chi-square on a 10 x 10 grid of
    /// the inner 0.9 of the square, away from the half voxel where the trilinear
    /// density falls off).
    #[test]
    fn first_vertices_are_uniform_over_the_silhouette() {
        let n = 16u32;
        let grid = engine::DensityGrid::new(
            glam::UVec3::splat(n),
            vec![1.0; (n * n * n) as usize],
            Vec3::splat(-0.5),
            Vec3::splat(1.0 / n as f32),
        )
        .unwrap();
        let medium = Medium::new(Arc::new(grid), 2000.0, 1.0, PhaseFunction::Isotropic).unwrap();
        let mut rng = Rng::new(3, 0, 0);
        let (bins, half) = (10usize, 0.45f32);
        let mut counts = vec![0.0f64; bins * bins];
        let mut inside = 0u64;
        for _ in 0..200_000 {
            // Viewed from +y (the camera's direction makes cosine 1 with +y).
            let (x, wo) = camera_path_query(&medium, 1, Some((Vec3::Y, 1.0)), &mut rng);
            assert!((wo - Vec3::Y).length() < 1e-5, "the query looks back along the view: {wo}");
            if x.x.abs() < half && x.z.abs() < half {
                let bin = |v: f32| (((v + half) / (2.0 * half)) * bins as f32) as usize;
                counts[bin(x.x).min(bins - 1) * bins + bin(x.z).min(bins - 1)] += 1.0;
                inside += 1;
            }
        }
        let expected = vec![inside as f64 / (bins * bins) as f64; bins * bins];
        let chi = chi2_test(&counts, &expected, 5.0);
        assert!(chi.p_value > 1e-4, "first vertices not uniform over the silhouette: {chi:?}");
        // The inner 0.9 x 0.9 gets its share of the silhouette, which the density's
        // half-voxel falloff widens to 1 + 1/n (opaque there too at this rho); the
        // binomial standard deviation of the share is 0.001.
        let share = inside as f64 / 200_000.0;
        let expected = 0.81 / (1.0 + 1.0 / n as f64).powi(2);
        assert!((share - expected).abs() < 0.005, "share of the inner square {share}, expected {expected}");
    }

    /// g is drawn as min + (max - min) (1 - u^p): ((max - g) / (max - min))^(1 / p) is
    /// uniform (chi-square), for the uniform draw and one skewed toward max.
    #[test]
    fn g_follows_its_power_law() {
        for power in [1.0f32, 2.0] {
            let spec = CloudSpec { g: [0.1, 0.9], g_power: power, ..Default::default() };
            let bins = 20usize;
            let mut counts = vec![0.0f64; bins];
            let n = 20_000u64;
            for c in 0..n {
                let g = case_medium(&spec, c).g;
                assert!((0.1..=0.9).contains(&g), "{g}");
                let w = ((0.9 - g) / 0.8).max(0.0).powf(1.0 / power);
                counts[((w * bins as f32) as usize).min(bins - 1)] += 1.0;
            }
            let chi = chi2_test(&counts, &vec![n as f64 / bins as f64; bins], 5.0);
            assert!(chi.p_value > 1e-4, "g power {power}: {chi:?}");
        }
        // Skewed toward max: the mean is max - (max - min) / (p + 1).
        let spec = CloudSpec { g: [0.0, 0.9], g_power: 2.0, ..Default::default() };
        let mean = (0..20_000).map(|c| case_medium(&spec, c).g as f64).sum::<f64>() / 20_000.0;
        // Standard deviation of g: 0.9 sqrt(1/5 - 1/9) = 0.268; 4 standard errors.
        assert!((mean - 0.6).abs() < 4.0 * 0.268 / 20_000f64.sqrt(), "mean g {mean}");
    }
}
