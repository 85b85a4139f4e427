//! `nimbus model` (a procedural cloud to .vdb, .vol or .raw) and `nimbus sheet` (a
//! contact sheet of the modeler's presets).

use super::common::{init_threads, progress_bar};
use crate::output::{self, ToneMap};
use crate::progressive::render_spp;
use crate::scene::SceneFile;
use anyhow::{Context, Result, bail};
use clap::Args;
use engine::{Buffer, DensityGrid, RenderControl};
use modeler::CloudParams;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct ModelArgs {
    /// A preset name (scene-a, scene-b, scene-c, set-01 .. set-12) or a TOML file of
    /// modeler parameters.
    pub source: String,
    /// Voxels per axis.
    #[arg(long, default_value_t = 128)]
    pub res: u32,
    /// Override the seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Output: NAME.vdb (OpenVDB), NAME.vol (Mitsuba grid volume) or NAME.raw (+ NAME.json).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args, Debug)]
pub struct SheetArgs {
    #[arg(long)]
    pub out: PathBuf,
    /// Samples per pixel per cloud.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Edge of each tile in pixels.
    #[arg(long, default_value_t = 192)]
    pub tile: u32,
    /// Grid resolution of each cloud.
    #[arg(long, default_value_t = 96)]
    pub res: u32,
    /// Density scale.
    #[arg(long, default_value_t = 20.0)]
    pub rho: f32,
}

/// Modeler parameters from a preset name or a TOML file.
pub fn load_params(source: &str) -> Result<CloudParams> {
    if let Some(p) = modeler::preset(source) {
        return Ok(p);
    }
    let path = Path::new(source);
    if !path.exists() {
        bail!("'{source}' is neither a preset ({}) nor an existing parameter file", modeler::PRESET_NAMES.join(", "));
    }
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {source}"))?;
    let text = match String::from_utf8(bytes) {
        Ok(text) => text,
        Err(e) => {
            // OpenVDB files begin with the magic number 0x56444220 (little-endian).
            let vdb = e.as_bytes().starts_with(&[0x20, 0x42, 0x44, 0x56]);
            bail!(
                "{source} is not a TOML file of modeler parameters ({}); give a preset ({}) or a TOML file",
                if vdb { "it is a VDB file, which a scene uses as [grid] file = ..." } else { "it is binary" },
                modeler::PRESET_NAMES.join(", ")
            );
        }
    };
    let params: CloudParams =
        toml::from_str(&text).map_err(|e| anyhow::anyhow!("{source}: {}", e.to_string().trim()))?;
    params.validate().with_context(|| format!("{source}"))?;
    Ok(params)
}

pub fn model(args: ModelArgs) -> Result<()> {
    let mut params = load_params(&args.source)?;
    if let Some(seed) = args.seed {
        params.seed = seed;
    }
    let start = Instant::now();
    let grid = modeler::build_grid(&params, args.res)?;
    let build_secs = start.elapsed().as_secs_f64();
    write_grid(&grid, &args.out)?;
    println!(
        "{}",
        serde_json::json!({"source": args.source, "resolution": args.res, "build_seconds": build_secs, "out": args.out})
    );
    Ok(())
}

/// Writes a grid by extension: .vdb (OpenVDB), .vol (Mitsuba), .raw (+ .json sidecar).
pub fn write_grid(grid: &DensityGrid, out: &Path) -> Result<()> {
    match out.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref() {
        Some("vol") => output::write_bytes_atomically(out, &output::mitsuba_vol_bytes(grid)),
        Some("raw") => {
            let data: Vec<u8> = grid.to_dense_vec().iter().flat_map(|v| v.to_le_bytes()).collect();
            output::write_bytes_atomically(out, &data)?;
            let b = grid.bounds();
            let json = serde_json::json!({
                "format": "float32 little-endian, x fastest, then y, then z",
                "dims": grid.dims().to_array(),
                "bounds_min": b.min.to_array(),
                "bounds_max": b.max.to_array(),
                "voxel_size": grid.voxel_size().to_array(),
                "cell_centred": true,
                "max_value": grid.max_value(),
            });
            output::write_bytes_atomically(&out.with_extension("json"), serde_json::to_string_pretty(&json)?.as_bytes())
        }
        Some("vdb") => output::write_bytes_atomically(out, &modeler::vdb::vdb_bytes(grid, "density")?),
        _ => bail!("{}: unknown cloud format; use .vdb, .vol or .raw", out.display()),
    }
}

pub fn sheet(args: SheetArgs) -> Result<()> {
    init_threads(None)?;
    let names = modeler::PRESET_NAMES;
    let cols = 5u32;
    let rows = (names.len() as u32).div_ceil(cols);
    let (tw, th) = (args.tile, args.tile);
    let mut sheet = image::RgbaImage::new(cols * tw, rows * th);
    let control = RenderControl::new();
    let bar = progress_bar(names.len() as u64, "clouds", false);
    for (i, name) in names.iter().enumerate() {
        let mut file = SceneFile::from_toml_str(&format!("[grid]\npreset = \"{name}\"\n"), "sheet")?;
        file.grid.resolution = args.res;
        file.medium.rho = args.rho;
        file.sun.direction = [0.4, -1.0, -0.3];
        file.camera.preset = Some("toplit".into());
        file.camera.fov_y_deg = 24.0;
        (file.camera.width, file.camera.height) = (tw, th);
        file.seed = i as u64;
        let scene = Arc::new(file.build_scene(None)?);
        let out = render_spp(scene, file.integrator_with(None)?, args.spp, &control, |_| {})?;
        let rgba = ToneMap::Filmic.to_rgba8(&out.film.mean(Buffer::Full), 0.5);
        let tile = image::RgbaImage::from_raw(tw, th, rgba).context("tile size")?;
        image::imageops::overlay(&mut sheet, &tile, ((i as u32 % cols) * tw) as i64, ((i as u32 / cols) * th) as i64);
        bar.inc(1);
    }
    bar.finish_and_clear();
    output::write_atomically(&args.out, |tmp| {
        sheet.save_with_format(tmp, image::ImageFormat::Png).map_err(Into::into)
    })?;
    println!("wrote {} ({} clouds: {})", args.out.display(), names.len(), names.join(", "));
    Ok(())
}
