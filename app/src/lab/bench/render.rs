//! `nimbus bench render`: samples per second of the path tracer on a fixed scene, the
//! majorant cell size compared in the same run, peak memory, and the files
//! bench/mitsuba_compare.py needs to render the same scene in Mitsuba 3.

use crate::cli::common::{init_threads, progress_bar, stop_on_ctrl_c};
use crate::output;
use crate::progressive::render_spp;
use crate::scene::SceneFile;
use anyhow::{Result, bail};
use clap::Args;
use engine::{Buffer, RenderControl};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Args, Debug)]
pub struct BenchRenderArgs {
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    #[arg(long)]
    pub threads: Option<usize>,
    /// The cloud: a built-in (cumulus, sphere) or a modeler preset (scene-a, set-05, ...).
    #[arg(long, default_value = "cumulus")]
    pub cloud: String,
    /// Majorant cell edge (voxels) of the measured configuration (default: the
    /// engine's choice for the grid, 8 up to 128^3).
    #[arg(long)]
    pub majorant_cells: Option<u32>,
    /// Also measure these majorant cell edges, as ratios against the first.
    #[arg(long, value_delimiter = ',')]
    pub compare_cells: Vec<u32>,
    /// Grid resolution of the benchmark cloud (128 is the reference setting).
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
    /// Also render the same cloud at these resolutions (per-sample cost as ratios to
    /// the first, grids built one at a time).
    #[arg(long, value_delimiter = ',')]
    pub compare_resolutions: Vec<u32>,
    /// Also render the first resolution's grid in sparse storage (dense vs sparse
    /// lookups, same majorants, same images).
    #[arg(long)]
    pub compare_sparse: bool,
    /// Also render the first configuration without the trackers' control density
    /// (plain delta and ratio tracking, so without the homogeneous blocks either: the
    /// same estimate, other variance and cost).
    #[arg(long)]
    pub compare_control: bool,
    /// Also render the first configuration without the trackers' local balls (every
    /// flight and shadow ray walks the majorant cells by the DDA from its origin: the
    /// same estimate, other cost).
    #[arg(long)]
    pub compare_balls: bool,
    /// Also render each configuration without homogeneous blocks (flights and
    /// shadow rays from a cloud's constant core tracked in closed form: the same
    /// estimate, other cost).
    #[arg(long)]
    pub compare_blocks: bool,
    /// Also render the first configuration with homogeneous blocks of these edges,
    /// in voxels.
    #[arg(long, value_delimiter = ',')]
    pub compare_block_cells: Vec<u32>,
    /// Also render the first configuration with ratio tracking's tentative
    /// collisions at these multiples of the residual majorant (1: plain ratio
    /// tracking; the default is engine::RATIO_TRACKING_OVERSAMPLING): the same
    /// estimate, other variance and cost.
    #[arg(long, value_delimiter = ',')]
    pub compare_oversampling: Vec<f32>,
    /// Also render the first configuration with next event estimation's
    /// shadow-roulette floor at these multiples of the isotropic phase 1 / (4 pi) (1:
    /// every shadow ray toward a direction at or above the isotropic value is cast;
    /// the default follows the phase's peak, engine::medium::SHADOW_ROULETTE_PEAK_FRACTION):
    /// the same estimate, other variance and cost.
    #[arg(long, value_delimiter = ',')]
    pub compare_shadow_floor: Vec<f32>,
    /// Also render every configuration with trilinear lookups in the trackers (eight
    /// voxels per tentative collision instead of one corner drawn by its weight: the
    /// same estimate, other variance and cost).
    #[arg(long)]
    pub compare_lookups: bool,
    /// Also render every sparse configuration with free flights' brick-bounds test
    /// the other way round (on where the grid's size leaves it off, and off where on:
    /// the same images bit for bit, other cost).
    #[arg(long)]
    pub compare_bounds: bool,
    /// Render every configuration this many times, alternating, and report medians.
    #[arg(long, default_value_t = 1)]
    pub rounds: u32,
    /// Write the cloud (Mitsuba .vol), scene.json and nimbus_full.npy here for
    /// bench/mitsuba_compare.py.
    #[arg(long)]
    pub mitsuba_dir: Option<PathBuf>,
}

/// The fixed benchmark scene of `nimbus bench render`.
pub fn bench_scene_file() -> SceneFile {
    bench_scene_for("cumulus").expect("built-in cloud")
}

/// The benchmark scene with another cloud: a built-in or a modeler preset.
pub fn bench_scene_for(cloud: &str) -> Result<SceneFile> {
    let grid = if crate::cloud::Builtin::from_name(cloud).is_some() {
        format!("builtin = \"{cloud}\"")
    } else if modeler::preset(cloud).is_some() {
        format!("preset = \"{cloud}\"")
    } else {
        bail!(
            "--cloud {cloud}: neither a built-in cloud ({}) nor a modeler preset ({})",
            crate::cloud::Builtin::NAMES.join(", "),
            modeler::PRESET_NAMES.join(", ")
        );
    };
    let mut s = SceneFile::from_toml_str(&format!("[grid]\n{grid}\nresolution = 128\n"), "bench")?;
    s.medium.rho = 40.0;
    s.medium.albedo = 1.0;
    s.medium.g = 0.85;
    s.camera.preset = Some("toplit".into());
    s.camera.width = 256;
    s.camera.height = 256;
    s.seed = 1;
    Ok(s)
}

/// CPU seconds (user + system) this process has used (Linux: /proc/self/stat).
pub fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name, which is in parentheses and may hold spaces.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let (utime, stime): (f64, f64) = (f.get(11)?.parse().ok()?, f.get(12)?.parse().ok()?);
    Some((utime + stime) / 100.0)
}

/// Resident set size of this process now (Linux: VmRSS).
pub fn resident_bytes() -> Option<u64> {
    proc_status_bytes("VmRSS:")
}

/// A memory line of /proc/self/status (given in kB), in bytes.
fn proc_status_bytes(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// One configuration's measurement.
#[derive(Clone, Copy)]
struct Measured {
    rate: f64,
    secs: f64,
    cpu_per_wall: Option<f64>,
    efficiency: f64,
    rel_noise: f64,
    mean: f64,
}

fn measure(
    scene: Arc<engine::Scene>,
    file: &SceneFile,
    spp: u32,
    control: &Arc<RenderControl>,
) -> Result<(Measured, crate::progressive::RenderOutcome)> {
    let bar = progress_bar(spp as u64, "spp", false);
    let cpu0 = process_cpu_seconds();
    let outcome = render_spp(scene, file.integrator_with(None)?, spp, control, |d| bar.set_position(d as u64))?;
    let cpu1 = process_cpu_seconds();
    bar.finish_and_clear();
    if outcome.stopped {
        bail!("stopped");
    }
    let rel_noise = outcome.film.relative_noise(Buffer::Full);
    let secs = outcome.render_secs;
    let m = Measured {
        rate: outcome.samples_per_sec(),
        secs,
        cpu_per_wall: cpu0.zip(cpu1).map(|(a, b)| (b - a) / secs.max(1e-9)),
        // 1 / (relative variance x seconds): the figure that equal-variance
        // comparisons need (docs/conventions.md).
        efficiency: 1.0 / (rel_noise * rel_noise * secs).max(1e-30),
        rel_noise,
        mean: outcome.film.average(Buffer::Full),
    };
    Ok((m, outcome))
}

/// Samples per second and efficiency on the fixed scene, per majorant cell size, per
/// grid resolution and storage, with memory.
pub fn bench_render(args: BenchRenderArgs) -> Result<()> {
    let threads = init_threads(args.threads)?;
    let mut file = bench_scene_for(&args.cloud)?;
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    println!(
        "bench render: {} {}^3, rho 40, albedo 1, HG g 0.85, toplit, 256x256, {} spp, {threads} threads",
        args.cloud, args.resolution, args.spp
    );
    let mut results = Vec::new();
    let mut base: Option<Measured> = None;
    let mut report = |label: String, m: Measured, extra: serde_json::Value, results: &mut Vec<serde_json::Value>| {
        let b = *base.get_or_insert(m);
        let (ratio, eff_ratio) = (m.rate / b.rate, m.efficiency / b.efficiency);
        println!(
            "  {label:<34} {:>7.3} Msamples/s ({ratio:.3}x)  efficiency {:.3e} ({eff_ratio:.3}x)  noise {:.4}  mean {:.5}  {:.2} s  cpu/wall {}",
            m.rate / 1e6,
            m.efficiency,
            m.rel_noise,
            m.mean,
            m.secs,
            m.cpu_per_wall.map(|c| format!("{c:.2}")).unwrap_or_else(|| "?".into())
        );
        let mut j = serde_json::json!({"config": label, "samples_per_second": m.rate, "seconds": m.secs,
            "ratio": ratio, "efficiency": m.efficiency, "efficiency_ratio": eff_ratio,
            "relative_noise": m.rel_noise, "mean": m.mean, "cpu_per_wall": m.cpu_per_wall});
        if let (Some(o), Some(e)) = (j.as_object_mut(), extra.as_object()) {
            o.extend(e.clone());
        }
        results.push(j);
    };

    // Every configuration is built first; then the rounds alternate between them, so
    // a slow spell of this shared machine hits all alike, and each reports its median.
    struct Config {
        label: String,
        scene: Arc<engine::Scene>,
        info: serde_json::Value,
        runs: Vec<Measured>,
    }
    let mut configs: Vec<Config> = Vec::new();
    let mut resolutions = vec![args.resolution];
    resolutions.extend(args.compare_resolutions.iter().copied().filter(|r| *r != args.resolution));
    for (ri, &res) in resolutions.iter().enumerate() {
        file.grid.resolution = res;
        let start = std::time::Instant::now();
        let grid = Arc::new(file.build_grid()?);
        let build_secs = start.elapsed().as_secs_f64();
        let default_cells = engine::medium::MajorantGrid::default_cell_voxels(&grid);
        let first_cells = if ri == 0 { args.majorant_cells.unwrap_or(default_cells) } else { default_cells };
        let mut storages = vec![grid.clone()];
        if ri == 0 && args.compare_sparse && !grid.is_sparse() {
            storages.push(Arc::new(grid.to_sparse()));
        }
        let base_scene = file.build_scene(Some(grid.clone()))?;
        for (si, g) in storages.iter().enumerate() {
            let mut cells = vec![first_cells];
            if ri == 0 && si == 0 {
                cells.extend(args.compare_cells.iter().copied().filter(|c| *c != first_cells));
            }
            let bricks = g.stored_bricks();
            let info = serde_json::json!({"resolution": res, "sparse": g.is_sparse(),
                "grid_bytes": g.memory_bytes(), "stored_bricks": bricks, "build_seconds": build_secs,
                "resident_bytes_after_build": resident_bytes()});
            let b = g.brick_dims();
            println!(
                "  {res}^3 {}: grid {:.1} MiB ({} of {} bricks stored), built in {:.2} s, resident {:.1} MiB",
                if g.is_sparse() { "sparse" } else { "dense" },
                g.memory_bytes() as f64 / 1048576.0,
                bricks,
                b.x as u64 * b.y as u64 * b.z as u64,
                build_secs,
                resident_bytes().unwrap_or(0) as f64 / 1048576.0
            );
            for &c in &cells {
                let medium = engine::Medium::with_majorant_cells(
                    g.clone(),
                    file.medium.rho,
                    file.medium.albedo,
                    file.phase(),
                    c,
                )?;
                let label = format!("{res}^3 {} cells {c}", if g.is_sparse() { "sparse" } else { "dense" });
                let mut info = info.clone();
                info["majorant_cells"] = c.into();
                // The measured configuration last, after the baselines asked for
                // (each the same medium tracked another way, tagged in its JSON).
                let mut variants: Vec<(String, engine::Medium, Option<(&str, serde_json::Value)>)> = Vec::new();
                if configs.is_empty() && args.compare_control {
                    let tag = Some(("control", false.into()));
                    variants.push((" no control".into(), medium.clone().without_control(), tag));
                }
                if configs.is_empty() && args.compare_balls {
                    let tag = Some(("balls", false.into()));
                    variants.push((" no balls".into(), medium.clone().without_local_balls(), tag));
                }
                if args.compare_blocks {
                    variants.push((
                        " no blocks".into(),
                        medium.clone().without_blocks(),
                        Some(("blocks", false.into())),
                    ));
                }
                if configs.is_empty() {
                    for &b in &args.compare_block_cells {
                        let tag = Some(("block_cells", b.into()));
                        variants.push((format!(" blocks {b}"), medium.clone().with_block_cells(b), tag));
                    }
                    for &m in &args.compare_oversampling {
                        let tag = Some(("ratio_oversampling", m.into()));
                        variants.push((format!(" oversampling {m}"), medium.clone().with_ratio_oversampling(m), tag));
                    }
                    for &f in &args.compare_shadow_floor {
                        let tag = Some(("shadow_floor", f.into()));
                        let floor = f * engine::sampling::INV_4PI;
                        variants.push((
                            format!(" shadow floor {f}"),
                            medium.clone().with_shadow_roulette_floor(floor),
                            tag,
                        ));
                    }
                }
                if args.compare_lookups {
                    let tag = Some(("lookups", "trilinear".into()));
                    variants.push((" trilinear".into(), medium.clone().with_trilinear_lookups(), tag));
                }
                if args.compare_bounds && g.is_sparse() {
                    let on = !medium.uses_brick_bounds();
                    let suffix = if on { " bounds on" } else { " bounds off" };
                    let tag = Some(("brick_bounds", on.into()));
                    variants.push((suffix.into(), medium.clone().with_brick_bounds(on), tag));
                }
                variants.push((String::new(), medium, None));
                for (suffix, medium, tag) in variants {
                    let mut info = info.clone();
                    if let Some((key, value)) = tag {
                        info[key] = value;
                    }
                    let scene = Arc::new(engine::Scene { medium, ..base_scene.clone() });
                    configs.push(Config { label: format!("{label}{suffix}"), scene, info, runs: Vec::new() });
                }
            }
        }
    }
    let rounds = args.rounds.max(1);
    for round in 0..rounds {
        for (ci, c) in configs.iter_mut().enumerate() {
            let (m, outcome) = measure(c.scene.clone(), &file, args.spp, &control)?;
            c.runs.push(m);
            if let (Some(dir), 0, 0) = (&args.mitsuba_dir, ci, round) {
                write_mitsuba_bundle(dir, &c.scene, &outcome, threads)?;
            }
        }
    }
    println!("  median of {rounds} alternated round(s):");
    for c in configs {
        let mut runs = c.runs.clone();
        runs.sort_by(|a, b| a.rate.total_cmp(&b.rate));
        let mut m = runs[runs.len() / 2];
        let effs: Vec<f64> = {
            let mut e: Vec<f64> = c.runs.iter().map(|r| r.efficiency).collect();
            e.sort_by(f64::total_cmp);
            e
        };
        m.efficiency = effs[effs.len() / 2];
        let mut info = c.info.clone();
        info["rates"] = c.runs.iter().map(|r| r.rate).collect::<Vec<_>>().into();
        report(c.label, m, info, &mut results);
    }
    let peak = peak_resident_bytes();
    if let Some(p) = peak {
        println!("  peak resident memory: {:.1} MiB", p as f64 / 1048576.0);
    }
    println!(
        "{}",
        serde_json::json!({"bench": "render", "cloud": args.cloud, "resolution": args.resolution, "spp": args.spp,
            "threads": threads, "peak_resident_bytes": peak, "results": results})
    );
    Ok(())
}

fn write_mitsuba_bundle(
    dir: &Path,
    scene: &engine::Scene,
    outcome: &crate::progressive::RenderOutcome,
    threads: usize,
) -> Result<()> {
    crate::output::create_dir(dir)?;
    output::write_bytes_atomically(&dir.join("cloud.vol"), &output::mitsuba_vol_bytes(scene.medium.grid()))?;
    let film = &outcome.film;
    output::write_npy_image(&dir.join("nimbus_full.npy"), film.width(), film.height(), &film.mean(Buffer::Full))?;
    let cam = &scene.camera;
    let sun = scene.sun.expect("bench scene has a sun");
    let g = scene.medium.phase().mean_cosine();
    let json = serde_json::json!({
        "resolution": [cam.width(), cam.height()],
        "spp": film.spp(),
        "camera": {"origin": cam.position().to_array(), "target": cam.target().to_array(), "up": cam.up().to_array(), "fov_y_deg": cam.fov_y_deg()},
        "sun": {"direction": sun.direction().to_array(), "irradiance": sun.radiance().to_array()},
        "medium": {"rho": scene.medium.rho(), "albedo": scene.medium.albedo(), "g": g},
        "nimbus": {"spp": film.spp(), "seconds": outcome.render_secs, "samples_per_second": outcome.samples_per_sec(), "threads": threads, "image": "nimbus_full.npy",
            "relative_noise": film.relative_noise(Buffer::Full),
            "efficiency": 1.0 / (film.relative_noise(Buffer::Full).powi(2) * outcome.render_secs).max(1e-30)},
    });
    output::write_bytes_atomically(&dir.join("scene.json"), serde_json::to_string_pretty(&json)?.as_bytes())?;
    eprintln!("wrote cloud.vol, scene.json and nimbus_full.npy to {}", dir.display());
    Ok(())
}

/// Peak resident set size of this process (Linux: VmHWM), if known.
pub fn peak_resident_bytes() -> Option<u64> {
    proc_status_bytes("VmHWM:")
}
