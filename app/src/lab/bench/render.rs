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
    /// Majorant cell edge (voxels) of the measured configuration.
    #[arg(long, default_value_t = engine::medium::MajorantGrid::DEFAULT_CELL_VOXELS)]
    pub majorant_cells: u32,
    /// Also measure these majorant cell edges, as ratios against the first.
    #[arg(long, value_delimiter = ',')]
    pub compare_cells: Vec<u32>,
    /// Grid resolution of the benchmark cloud (128 is the reference setting; 256 and
    /// 512 check memory).
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
    /// Write the cloud (Mitsuba .vol), scene.json and nimbus_full.npy here for
    /// bench/mitsuba_compare.py.
    #[arg(long)]
    pub mitsuba_dir: Option<PathBuf>,
}

/// The fixed benchmark scene of `nimbus bench render`.
pub fn bench_scene_file() -> SceneFile {
    let mut s = SceneFile::from_toml_str("[grid]\nbuiltin = \"cumulus\"\nresolution = 128\n", "bench").expect("valid");
    s.medium.rho = 40.0;
    s.medium.albedo = 1.0;
    s.medium.g = 0.85;
    s.camera.preset = Some("toplit".into());
    s.camera.width = 256;
    s.camera.height = 256;
    s.seed = 1;
    s
}

/// Samples per second on the fixed scene, per majorant cell size, with peak memory.
pub fn bench_render(args: BenchRenderArgs) -> Result<()> {
    let threads = init_threads(args.threads)?;
    let mut file = bench_scene_file();
    file.grid.resolution = args.resolution;
    let grid = Arc::new(file.build_grid()?);
    let control = Arc::new(RenderControl::new());
    stop_on_ctrl_c(&control);
    let mut cells = vec![args.majorant_cells];
    cells.extend(args.compare_cells.iter().copied().filter(|c| *c != args.majorant_cells));
    println!(
        "bench render: cumulus {}^3, rho 40, albedo 1, HG g 0.85, toplit, 256x256, {} spp, {threads} threads",
        args.resolution, args.spp
    );
    let mut base_rate = None;
    let mut results = Vec::new();
    let base = file.build_scene(Some(grid.clone()))?;
    for &c in &cells {
        let medium =
            engine::Medium::with_majorant_cells(grid.clone(), file.medium.rho, file.medium.albedo, file.phase(), c)?;
        let scene = Arc::new(engine::Scene { medium, ..base.clone() });
        let bar = progress_bar(args.spp as u64, "spp", false);
        let outcome =
            render_spp(scene.clone(), file.integrator_with(None)?, args.spp, &control, |d| bar.set_position(d as u64))?;
        bar.finish_and_clear();
        if outcome.stopped {
            bail!("stopped");
        }
        let rate = outcome.samples_per_sec();
        let ratio = rate / *base_rate.get_or_insert(rate);
        println!(
            "  majorant cells {c:>2} voxels: {:>8.3} Msamples/s  ({:.3}x)  {:.2} s",
            rate / 1e6,
            ratio,
            outcome.render_secs
        );
        results.push(serde_json::json!({"majorant_cells": c, "samples_per_second": rate, "seconds": outcome.render_secs, "ratio": ratio}));
        if let (Some(dir), true) = (&args.mitsuba_dir, c == args.majorant_cells) {
            write_mitsuba_bundle(dir, &scene, &outcome, threads)?;
        }
    }
    let peak = peak_resident_bytes();
    if let Some(p) = peak {
        println!(
            "  peak resident memory: {:.1} MiB (density grid {:.1} MiB)",
            p as f64 / 1048576.0,
            grid.memory_bytes() as f64 / 1048576.0
        );
    }
    println!(
        "{}",
        serde_json::json!({"bench": "render", "resolution": args.resolution, "spp": args.spp,
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
        "nimbus": {"spp": film.spp(), "seconds": outcome.render_secs, "samples_per_second": outcome.samples_per_sec(), "threads": threads, "image": "nimbus_full.npy"},
    });
    output::write_bytes_atomically(&dir.join("scene.json"), serde_json::to_string_pretty(&json)?.as_bytes())?;
    eprintln!("wrote cloud.vol, scene.json and nimbus_full.npy to {}", dir.display());
    Ok(())
}

/// Peak resident set size of this process (Linux: VmHWM), if known.
pub fn peak_resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}
