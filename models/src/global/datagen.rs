//! The global model's data generator (thesis section 5.3): random homogeneous convex
//! media, a uniform query point and direction in each, the in-scattered radiance there
//! by path tracing to a requested confidence, and the feature vector.
//!
//! The data set's files, chunks, shards, resume and merge are those of
//! [`crate::dataset`]: point i is a pure function of (seed, i), whatever the thread
//! count or sharding. `features.npy` is float32 [N, 4 + n_D] (albedo, g, theta, phi,
//! tau_hat_1 .. tau_hat_nD, thesis eqs. 5.6-5.7), `targets.npy` float32 [N, 5].
//!
//! targets.npy columns: L_i (the estimate), its standard error, the sample count, the
//! medium's sigma_S, the shape (0 sphere, 1 box, 2 ellipsoid). The target
//! transformations (thesis eqs. 5.8-5.9) belong to the trainer.

use super::directions::DirectionSetKind;
use super::features::FeatureExtractor;
use super::ground_truth::{ConvexMedium, Shape, Stopping, estimate_in_scattered};
use crate::dataset::chunks;
use crate::dataset::manifest::{DataSpec, DatagenError, Manifest, Shard, check_range, setting};
use crate::dataset::npy;
use engine::{PhaseFunction, Rng};
use glam::{Mat3, Quat, Vec3};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::atomic::AtomicBool;

/// The light of the data generator: radiance 1 travelling along (0, 0, -1) (thesis 5.3).
pub const OMEGA_L: Vec3 = Vec3::new(0.0, 0.0, -1.0);

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

impl GlobalSpec {
    /// Checks every setting; the error names the command-line flag.
    pub fn validate(&self) -> Result<(), DatagenError> {
        if self.points == 0 {
            return Err(setting("--points", "must be at least 1"));
        }
        check_range("--sigma", self.sigma, |v| v > 0.0 && v <= 10_000.0, "(0, 10000]")?;
        check_range("--albedo", self.albedo, |v| (0.0..=1.0).contains(&v), "[0, 1]")?;
        check_range("--g", self.g, |v| v > -1.0 && v < 1.0, "(-1, 1)")?;
        check_range("--scale", self.scale, |v| v >= 0.01 && v <= 100.0, "[0.01, 100]")?;
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
        Stopping::validate(self.max_rel_error, self.confidence, self.min_samples, self.max_samples)?;
        if self.chunk_size == 0 {
            return Err(setting("--chunk-size", "must be at least 1"));
        }
        Ok(())
    }

    pub fn stopping(&self) -> Stopping {
        Stopping::new(self.max_rel_error, self.confidence, self.min_samples, self.max_samples)
    }

    /// The feature names, in order.
    pub fn feature_names(&self) -> Vec<String> {
        super::model::FeatureLayout::current(self.directions, self.n_dirs).names
    }
}

/// The global model's data set: the manifest adds the light direction and the
/// feature names.
pub type GlobalManifest = Manifest<GlobalSpec>;

/// The global data set's own manifest fields.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct GlobalHeader {
    pub light_direction: [f32; 3],
    pub feature_names: Vec<String>,
}

impl DataSpec for GlobalSpec {
    const FORMAT: &'static str = "nimbus-global-dataset";
    const FORMAT_VERSION: u32 = 1;
    const WHAT: &'static str = "a Nimbus data-set manifest";
    const TARGET_COLUMNS: [&'static str; 5] = ["L_i", "std_error", "samples", "sigma_s", "shape"];
    type Header = GlobalHeader;
    fn validate(&self) -> Result<(), DatagenError> {
        Self::validate(self)
    }
    fn header(&self) -> GlobalHeader {
        GlobalHeader { light_direction: OMEGA_L.to_array(), feature_names: self.feature_names() }
    }
    fn points(&self) -> u64 {
        self.points
    }
    fn chunk_size(&self) -> u64 {
        self.chunk_size
    }
    fn rows_per_point(&self) -> u64 {
        1
    }
    fn n_features(&self) -> usize {
        4 + self.n_dirs
    }
    /// The sample counts stored with the points (column `samples`).
    fn merged_path_samples(_: &[Manifest<Self>], targets: &[f32]) -> u64 {
        targets.chunks_exact(5).map(|t| t[2] as u64).sum()
    }
}

/// Generates (or resumes) this shard's chunks in `dir` (see [`chunks::generate`]).
pub fn generate(
    spec: &GlobalSpec,
    shard: Shard,
    dir: &Path,
    code_version: &str,
    progress: &(dyn Fn(u64) + Sync),
    cancel: &AtomicBool,
) -> Result<GlobalManifest, DatagenError> {
    spec.validate()?;
    let prepare = || Ok(FeatureExtractor::with_set(spec.directions, spec.n_dirs).expect("validated"));
    chunks::generate(spec, shard, dir, code_version, progress, cancel, prepare, |fe, i| {
        let p = generate_point(spec, fe, i);
        let mut row = p.features.clone();
        row.extend_from_slice(&p.targets());
        (row, p.samples)
    })
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

/// A loaded, complete data set.
pub struct Dataset {
    pub manifest: GlobalManifest,
    /// Row-major [n, n_features].
    pub features: Vec<f32>,
    /// Row-major [n, 5] (TARGET_COLUMNS).
    pub targets: Vec<f32>,
}

impl Dataset {
    pub fn load(dir: &Path) -> Result<Dataset, DatagenError> {
        let manifest = GlobalManifest::load(dir)?;
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
    use crate::dataset::chunks::{chunk_path, merge};
    use crate::dataset::manifest::parse_range;
    use std::path::PathBuf;

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

    fn run(spec: &GlobalSpec, shard: Shard, dir: &Path, threads: usize) -> Result<GlobalManifest, DatagenError> {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| generate(spec, shard, dir, "test", &|_| {}, &AtomicBool::new(false)))
    }

    fn files(dir: &Path) -> (Vec<u8>, Vec<u8>) {
        (std::fs::read(dir.join("features.npy")).unwrap(), std::fs::read(dir.join("targets.npy")).unwrap())
    }

    #[test]
    fn same_data_whatever_threads_shards_and_interruptions() {
        let root = tempfile::tempdir().unwrap();
        let temp_dir = |name: &str| root.path().join(name);
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
        assert!(merge::<GlobalSpec>(&shards[..2], &merged).unwrap_err().to_string().contains("missing"));
        merge::<GlobalSpec>(&shards, &merged).unwrap();
        assert_eq!(files(&merged), reference, "sharding changed the data");
        // A shard given twice is refused.
        let dup = vec![shards[0].clone(), shards[1].clone(), shards[2].clone(), shards[0].clone()];
        assert!(merge::<GlobalSpec>(&dup, &temp_dir("dup")).unwrap_err().to_string().contains("also in"));

        // Interrupted: chunks 1 and 3 lost, a stray temporary left; the resumed run is
        // identical.
        let resumed = temp_dir("resumed");
        run(&spec, Shard { index: 0, count: 1 }, &resumed, 2).unwrap();
        for f in ["features.npy", "targets.npy"] {
            std::fs::remove_file(resumed.join(f)).unwrap();
        }
        let mut m = GlobalManifest::load(&resumed).unwrap();
        m.complete = false;
        m.save(&resumed).unwrap();
        std::fs::remove_file(chunk_path(&resumed, 1)).unwrap();
        std::fs::remove_file(chunk_path(&resumed, 3)).unwrap();
        std::fs::write(resumed.join("chunks").join(".chunk-000001.npy.1.x.tmp"), b"half").unwrap();
        let m = run(&spec, Shard::ALL, &resumed, 2).unwrap();
        assert!(m.complete);
        assert_eq!(files(&resumed), reference, "resuming changed the data");

        // A well-formed chunk holding a NaN: merge refuses it, naming the chunk and
        // the row; a resumed run sets it aside and makes it again.
        let (shape, mut data) = npy::read_f32(&chunk_path(&resumed, 2)).unwrap();
        data[7 + shape[1]] = f32::NAN;
        npy::write_f32(&chunk_path(&resumed, 2), &shape, &data).unwrap();
        let e = merge::<GlobalSpec>(std::slice::from_ref(&resumed), &temp_dir("nan")).unwrap_err().to_string();
        assert!(e.contains("chunk-000002.npy") && e.contains("row 1") && e.contains("not finite"), "{e}");
        let mut m = GlobalManifest::load(&resumed).unwrap();
        m.complete = false;
        m.save(&resumed).unwrap();
        run(&spec, Shard::ALL, &resumed, 2).unwrap();
        assert_eq!(files(&resumed), reference, "the damaged chunk was not made again");
        assert!(crate::dataset::chunks::damaged_path(&resumed, 2).exists(), "the damaged chunk was not kept aside");

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
    }

    /// A manifest whose settings are invalid (a chunk size of 0 would divide by
    /// zero when chunks are counted; fuzzing the readers asks for this) is refused on
    /// reading, naming the setting.
    #[test]
    fn manifests_with_bad_settings_are_refused() {
        let path = Path::new("m/manifest.json");
        let good = serde_json::to_string(&GlobalManifest::new(&tiny(), None, "test")).unwrap();
        assert!(GlobalManifest::from_json(&good, path).is_ok());
        for (key, bad) in [("\"chunk_size\":5", "\"chunk_size\":0"), ("\"points\":23", "\"points\":0")] {
            assert!(good.contains(key), "{good}");
            let e = GlobalManifest::from_json(&good.replace(key, bad), path).unwrap_err().to_string();
            assert!(e.contains("manifest.json") && e.contains("settings"), "{e}");
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
