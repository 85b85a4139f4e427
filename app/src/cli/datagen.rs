//! `nimbus datagen global|p2p|cloud|merge`: training data for the learned models, with
//! progress, Ctrl-C (finished chunks are kept) and resume, by shards.

use super::common::{DatagenRunArgs, cancel_on_ctrl_c, code_version, init_threads, progress_bar};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use models::cloud::CloudSpec;
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
    /// Ground truth for the cloud-aware model: the modeler's presets and random clouds
    /// under random suns, queries at camera-path vertices, multiple scattering by path
    /// tracing; one chunk per cloud.
    Cloud(CloudArgs),
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
            let format = models::dataset::manifest::format_of(first);
            let is = |f: &str| format.as_deref() == Some(f);
            let points = if is(<models::p2p::P2pSpec as DataSpec>::FORMAT) {
                models::dataset::merge::<models::p2p::P2pSpec>(&args.shards, &args.out)?.counts.points
            } else if is(<CloudSpec as DataSpec>::FORMAT) {
                models::dataset::merge::<CloudSpec>(&args.shards, &args.out)?.counts.points
            } else {
                models::dataset::merge::<GlobalSpec>(&args.shards, &args.out)?.counts.points
            };
            println!("merged {} shards: {points} points into {}", args.shards.len(), args.out.display());
            Ok(())
        }
        DatagenCommand::P2p(args) => datagen_p2p(args),
        DatagenCommand::Cloud(args) => {
            let spec = args.spec()?;
            let run = Run::start(&args.data)?;
            let what =
                format!("cloud data set: {} points, {} clouds at {}^3", spec.points, spec.n_chunks(), spec.resolution);
            run.go(&what, spec.shard_points(run.shard), |progress, cancel| {
                let m = models::cloud::datagen::generate(
                    &spec,
                    run.shard,
                    &args.data.out,
                    &code_version(),
                    progress,
                    cancel,
                )?;
                Ok((m.complete, m.counts))
            })
        }
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

/// `nimbus datagen cloud`: ground truth for the cloud-aware model.
#[derive(Args, Debug)]
pub struct CloudArgs {
    #[arg(long, default_value_t = 51_200)]
    pub points: u64,
    /// Points per cloud (one chunk, the unit of resuming and sharding, per cloud).
    #[arg(long, default_value_t = 256)]
    pub points_per_cloud: u64,
    /// Voxels per axis of each cloud.
    #[arg(long, default_value_t = 64)]
    pub resolution: u32,
    /// Modeler presets among the clouds, comma separated (set-10 .. set-12 are held
    /// out); "none" for random clouds only.
    #[arg(
        long,
        default_value = "scene-a,scene-b,scene-c,set-01,set-02,set-03,set-04,set-05,set-06,set-07,set-08,set-09"
    )]
    pub presets: String,
    /// Every n-th cloud is a preset (0: none); the others are random.
    #[arg(long, default_value_t = 4)]
    pub preset_every: u64,
    /// Density scale range (log-uniform), MIN..MAX.
    #[arg(long, default_value = "5..320")]
    pub rho: String,
    #[arg(long, default_value = "0.9..1")]
    pub albedo: String,
    /// Henyey-Greenstein g range.
    #[arg(long, default_value = "0..0.9")]
    pub g: String,
    /// g is drawn as MIN + (MAX - MIN) (1 - u^P), u uniform: 1 uniform, larger toward MAX.
    #[arg(long, default_value_t = 1.0)]
    pub g_power: f32,
    /// Paths per point (the target is their mean; the first is also stored alone).
    #[arg(long, default_value_t = 16)]
    pub samples: u64,
    /// Probabilities that a query is a camera path's 1st, 2nd, 3rd scattering vertex.
    #[arg(long, default_value = "0.5,0.3,0.2")]
    pub vertex_weights: String,
    /// Sun-transmittance field nodes per axis at most.
    #[arg(long, default_value_t = 128)]
    pub field_nodes: u32,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Views at a fixed angle to the sun: the cosine between the directions from the
    /// cloud to the camera and to the sun (1 frontlit, -1 backlit); default: any view.
    #[arg(long, allow_hyphen_values = true)]
    pub view_sun_cos: Option<f32>,
    /// Without --view-sun-cos: the fraction of views within about 15 degrees of the
    /// sun's axis (frontlit and backlit); the others are uniform.
    #[arg(long, default_value_t = 0.3)]
    pub aligned_views: f32,
    /// Make a held-out set: the held-out presets (set-10 .. set-12) and random clouds
    /// that no training set draws; --presets is ignored.
    #[arg(long)]
    pub held_out: bool,
    /// The same sun for every cloud: the direction its light travels, X,Y,Z (as a
    /// scene file's sun.direction, e.g. 0,-1,0 from straight above); default: a
    /// random sun per cloud. With --view-sun-cos it reproduces a fixed lighting.
    #[arg(long, allow_hyphen_values = true)]
    pub sun: Option<String>,
    #[command(flatten)]
    pub data: DatagenRunArgs,
}

impl CloudArgs {
    pub fn spec(&self) -> Result<CloudSpec> {
        let presets = match self.presets.trim() {
            _ if self.held_out => vec![],
            "none" | "" => vec![],
            list => list.split(',').map(|s| s.trim().to_string()).collect(),
        };
        let w: Vec<f32> = self
            .vertex_weights
            .split(',')
            .map(|s| s.trim().parse::<f32>().with_context(|| format!("--vertex-weights: {s:?} is not a number")))
            .collect::<Result<_>>()?;
        let vertex_weights: [f32; 3] =
            w.try_into().map_err(|_| anyhow::anyhow!("--vertex-weights: give three weights, such as 0.5,0.3,0.2"))?;
        let spec = CloudSpec {
            points: self.points,
            points_per_cloud: self.points_per_cloud,
            resolution: self.resolution,
            preset_every: if presets.is_empty() && !self.held_out { 0 } else { self.preset_every },
            presets,
            rho: parse_range("--rho", &self.rho)?,
            albedo: parse_range("--albedo", &self.albedo)?,
            g: parse_range("--g", &self.g)?,
            g_power: self.g_power,
            samples: self.samples,
            vertex_weights,
            field_nodes: self.field_nodes,
            seed: self.seed,
            view_sun_cos: self.view_sun_cos,
            aligned_views: self.aligned_views,
            held_out: self.held_out,
            sun: self.sun.as_deref().map(parse_direction).transpose()?,
        };
        spec.validate()?;
        Ok(spec)
    }
}

/// "X,Y,Z" as a direction (checked non-zero by the spec).
fn parse_direction(s: &str) -> Result<[f32; 3]> {
    let v: Vec<f32> = s
        .split(',')
        .map(|c| c.trim().parse::<f32>().with_context(|| format!("--sun: {c:?} is not a number")))
        .collect::<Result<_>>()?;
    v.try_into().map_err(|_| anyhow::anyhow!("--sun: give three components, such as 0,-1,0"))
}
