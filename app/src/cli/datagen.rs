//! `nimbus datagen global|p2p|merge`: training data for the learned models, with
//! progress, Ctrl-C (finished chunks are kept) and resume, by shards.

use super::common::{DatagenRunArgs, cancel_on_ctrl_c, code_version, init_threads, progress_bar};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use models::dataset::{Counts, DataSpec, Shard, parse_range};
use models::global::datagen::{self, GlobalSpec, ShapeKind};
use models::global::directions::DirectionSetKind;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Subcommand, Debug)]
pub enum DatagenCommand {
    /// Ground truth for the global model: random homogeneous convex media lit by a unit
    /// directional light along (0, 0, -1); features + in-scattered radiance per point.
    Global(GlobalArgs),
    /// Join the shard directories of one data set into a complete one.
    Merge(MergeArgs),
    /// Ground truth for the point-to-point model (thesis 6.3), resumable and shardable.
    P2p(P2pArgs),
}

#[derive(Args, Debug)]
pub struct GlobalArgs {
    /// Number of data points.
    #[arg(long, default_value_t = 10_000)]
    pub points: u64,
    /// Extinction sigma_S range, MIN..MAX (or one value).
    #[arg(long, default_value = "1..100")]
    pub sigma: String,
    /// Scattering albedo range.
    #[arg(long, default_value = "1")]
    pub albedo: String,
    /// Henyey-Greenstein g range, inside (-1, 1).
    #[arg(long, default_value = "0..0.9")]
    pub g: String,
    /// Shapes, comma separated: sphere, box, ellipsoid.
    #[arg(long, default_value = "sphere,box,ellipsoid")]
    pub shapes: String,
    /// Keep the shapes axis-aligned (no random rotation).
    #[arg(long)]
    pub no_rotate: bool,
    /// Scale factor range (per axis for boxes and ellipsoids); 1 keeps unit shapes.
    #[arg(long, default_value = "1")]
    pub scale: String,
    /// Directions of the optical-depth features: 4, 16 or 64 (tetrahedron).
    #[arg(long, default_value_t = 64)]
    pub n_dirs: usize,
    /// Direction set: tetrahedron (the thesis's) or fibonacci.
    #[arg(long, default_value = "tetrahedron")]
    pub directions: String,
    /// Maximum relative half-width of the confidence interval of each target.
    #[arg(long, default_value_t = 0.05)]
    pub max_rel_error: f64,
    /// Confidence level of that interval.
    #[arg(long, default_value_t = 0.95)]
    pub confidence: f64,
    #[arg(long, default_value_t = 1000)]
    pub min_samples: u64,
    #[arg(long, default_value_t = 10_000_000)]
    pub max_samples: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Points per chunk file (the unit of resuming and sharding).
    #[arg(long, default_value_t = 200)]
    pub chunk_size: u64,
    /// Fraction of points sampled like the renderer's queries at k = 1 (first collision
    /// of a ray entering the shape, looking back along it); the rest uniform.
    #[arg(long, default_value_t = 0.0)]
    pub first_collision: f32,
    #[command(flatten)]
    pub data: DatagenRunArgs,
}

#[derive(Args, Debug)]
pub struct MergeArgs {
    /// Shard directories.
    #[arg(required = true)]
    pub shards: Vec<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
}

impl GlobalArgs {
    pub fn spec(&self) -> Result<GlobalSpec> {
        let shapes = self
            .shapes
            .split(',')
            .map(|s| {
                ShapeKind::parse(s).with_context(|| format!("--shapes: unknown shape {s:?} (sphere, box, ellipsoid)"))
            })
            .collect::<Result<Vec<_>>>()?;
        let directions = DirectionSetKind::parse(&self.directions)
            .with_context(|| format!("--directions: unknown set {:?} (tetrahedron, fibonacci)", self.directions))?;
        let spec = GlobalSpec {
            points: self.points,
            sigma: parse_range("--sigma", &self.sigma)?,
            albedo: parse_range("--albedo", &self.albedo)?,
            g: parse_range("--g", &self.g)?,
            shapes,
            rotate: !self.no_rotate,
            scale: parse_range("--scale", &self.scale)?,
            n_dirs: self.n_dirs,
            directions,
            max_rel_error: self.max_rel_error,
            confidence: self.confidence,
            min_samples: self.min_samples,
            max_samples: self.max_samples,
            seed: self.seed,
            chunk_size: self.chunk_size,
            first_collision: self.first_collision,
        };
        spec.validate()?;
        Ok(spec)
    }
}

pub fn datagen(cmd: DatagenCommand) -> Result<()> {
    match cmd {
        DatagenCommand::Global(args) => {
            let spec = args.spec()?;
            let run = Run::start(&args.data)?;
            let what = format!("data set: {} points", spec.points);
            run.go(&what, spec.shard_points(run.shard), |progress, cancel| {
                let m = datagen::generate(&spec, run.shard, &args.data.out, &code_version(), progress, cancel)?;
                Ok((m.complete, m.counts))
            })
        }
        DatagenCommand::Merge(args) => {
            let first = args.shards.first().context("name the shard directories")?;
            let text = std::fs::read_to_string(first.join("manifest.json")).unwrap_or_default();
            let points = if text.contains(<models::p2p::P2pSpec as models::dataset::DataSpec>::FORMAT) {
                models::dataset::merge::<models::p2p::P2pSpec>(&args.shards, &args.out)?.counts.points
            } else {
                models::dataset::merge::<GlobalSpec>(&args.shards, &args.out)?.counts.points
            };
            println!("merged {} shards: {points} points into {}", args.shards.len(), args.out.display());
            Ok(())
        }
        DatagenCommand::P2p(args) => datagen_p2p(args),
    }
}

/// One data-generation run: what it announces, its progress bar, Ctrl-C, and its
/// closing line (both generators).
struct Run<'a> {
    args: &'a DatagenRunArgs,
    shard: Shard,
    threads: usize,
}

impl<'a> Run<'a> {
    /// Parses the shard and starts the threads (before anything else runs on them).
    fn start(args: &'a DatagenRunArgs) -> Result<Self> {
        let shard = Shard::parse(&args.shard)?;
        Ok(Run { args, shard, threads: init_threads(args.run.threads)? })
    }

    /// Runs `generate` for the `owned` points of this shard (given the progress
    /// callback and the cancel flag; it returns whether the data set is complete and
    /// the manifest's counts).
    fn go(
        &self,
        what: &str,
        owned: u64,
        generate: impl FnOnce(&(dyn Fn(u64) + Sync), &std::sync::atomic::AtomicBool) -> Result<(bool, Counts)>,
    ) -> Result<()> {
        eprintln!(
            "{what} ({owned} points in shard {}/{}), {} threads, into {}",
            self.shard.index,
            self.shard.count,
            self.threads,
            self.args.out.display()
        );
        let bar = progress_bar(owned, "points", self.args.run.quiet);
        let cancel = cancel_on_ctrl_c("stopping: finished chunks are kept; run the same command again to resume");
        let started = std::time::Instant::now();
        let before = damaged_chunks(&self.args.out);
        let (complete, counts) = generate(&|n| bar.set_position(n), &cancel)?;
        bar.finish_and_clear();
        let damaged = damaged_chunks(&self.args.out).saturating_sub(before);
        if damaged > 0 {
            eprintln!("warning: {damaged} damaged chunk(s) were set aside as chunks/*.npy.damaged and made again");
        }
        println!(
            "{} {owned} points in {:.1} s this run ({:.1} s total), {} path samples; {}",
            if complete { "complete:" } else { "shard done:" },
            started.elapsed().as_secs_f64(),
            counts.seconds,
            counts.path_samples,
            self.args.out.display()
        );
        Ok(())
    }
}

/// Chunks set aside as damaged in `dir`.
fn damaged_chunks(dir: &std::path::Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir.join("chunks")) else { return 0 };
    entries.flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".damaged")).count()
}

/// The cloud of `nimbus datagen p2p --cloud`: a built-in cloud, a modeler preset or a
/// VDB file.
pub fn cloud_grid(name: &str, resolution: u32) -> Result<engine::DensityGrid> {
    if let Some(b) = crate::cloud::Builtin::from_name(name) {
        return Ok(b.grid(resolution));
    }
    if let Some(params) = modeler::preset(name) {
        return Ok(modeler::build_grid(&params, resolution)?);
    }
    if name.ends_with(".vdb") {
        return Ok(modeler::vdb::read_vdb(std::path::Path::new(name), None)?.grid);
    }
    bail!(
        "--cloud {name:?} is neither a built-in cloud ({}), a modeler preset ({}) nor a .vdb file",
        crate::cloud::Builtin::NAMES.join(", "),
        modeler::PRESET_NAMES.join(", ")
    )
}

fn datagen_p2p(args: P2pArgs) -> Result<()> {
    let spec = models::p2p::datagen::P2pSpec {
        points: args.points,
        cloud: args.cloud.clone(),
        resolution: args.resolution,
        rho: args.rho,
        albedo: args.albedo,
        g: args.g,
        k: args.k,
        rotations: args.rotations,
        features: Default::default(),
        max_rel_error: args.max_rel_error,
        confidence: args.confidence,
        min_samples: args.min_samples,
        max_samples: args.max_samples,
        seed: args.seed,
        chunk_size: args.chunk_size,
    };
    spec.validate()?;
    // The threads first: building the cloud already runs on them.
    let run = Run::start(&args.data)?;
    let grid = Arc::new(cloud_grid(&args.cloud, args.resolution)?);
    let what = format!("point-to-point data set: {} points x {} rotations", spec.points, spec.rotations);
    run.go(&what, spec.shard_points(run.shard), |progress, cancel| {
        let m =
            models::p2p::datagen::generate(&spec, grid, run.shard, &args.data.out, &code_version(), progress, cancel)?;
        Ok((m.complete, m.counts))
    })
}

/// `nimbus datagen p2p`: ground truth for the point-to-point model (thesis 6.3).
#[derive(Args, Debug)]
pub struct P2pArgs {
    /// A built-in cloud, a modeler preset (scene-a .. set-12) or a .vdb file.
    #[arg(long, default_value = "scene-a")]
    pub cloud: String,
    /// Voxels per axis of generated clouds.
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
    #[arg(long, default_value_t = 1000)]
    pub points: u64,
    #[arg(long, default_value_t = 25.0)]
    pub rho: f32,
    #[arg(long, default_value_t = 0.99)]
    pub albedo: f32,
    /// Henyey-Greenstein g (the thesis's model: 0).
    #[arg(long, default_value_t = 0.0)]
    pub g: f32,
    /// Segments of the walks that place emitter and sensor.
    #[arg(long, default_value_t = 2)]
    pub k: u32,
    /// Feature rows per point (random rotations about the emitter-sensor axis).
    #[arg(long, default_value_t = 50)]
    pub rotations: u32,
    #[arg(long, default_value_t = 0.1)]
    pub max_rel_error: f64,
    #[arg(long, default_value_t = 0.95)]
    pub confidence: f64,
    #[arg(long, default_value_t = 1000)]
    pub min_samples: u64,
    #[arg(long, default_value_t = 20_000_000)]
    pub max_samples: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long, default_value_t = 20)]
    pub chunk_size: u64,
    #[command(flatten)]
    pub data: DatagenRunArgs,
}
