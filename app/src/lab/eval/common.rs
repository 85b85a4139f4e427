//! What both evaluations share: renders tracked pass by pass (time to preview), the
//! render cache's files (image stacks as .npy, JSON), and image sheets.

use crate::metrics::{Image, PREVIEW_RMSE, relative_rmse};
use crate::output::write_bytes_atomically;
use anyhow::{Result, bail};
use engine::{Buffer, Film, Integrator, PassOutcome, RenderControl, Renderer, Scene};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// What a tracked render returns.
pub(crate) struct Tracked {
    pub film: Film,
    /// Seconds spent rendering passes (the RMSE checks are not counted).
    pub seconds: f64,
    /// Render seconds until the image first came within 5 % relative RMSE.
    pub preview_secs: Option<f64>,
    /// (render seconds, relative RMSE) after passes 1, 2, 3, 4, 6, 8, 11, ... (about
    /// 30 % apart) and the last: the convergence curve, with a reference.
    pub curve: Vec<(f64, f64)>,
}

/// Renders up to `spp` passes; with a reference, checks the relative RMSE after
/// passes about 30 % apart (and every pass until the first preview) and, if
/// `stop_at_preview`, stops once it is within [`PREVIEW_RMSE`].
pub(crate) fn render_tracked(
    scene: Arc<Scene>,
    integrator: Integrator,
    spp: u32,
    control: &RenderControl,
    reference: Option<(&Image, &[bool])>,
    stop_at_preview: bool,
    mut on_pass: impl FnMut(u32),
) -> Result<Tracked> {
    let mut r = Renderer::new(scene, integrator)?;
    let generation = control.generation();
    let (mut seconds, mut preview_secs, mut curve, mut next_point) = (0.0f64, None, vec![], 1u32);
    for done in 1..=spp {
        let t = Instant::now();
        if r.render_pass(control, generation) == PassOutcome::Cancelled {
            bail!("stopped; finished renders are cached and a rerun resumes from them");
        }
        seconds += t.elapsed().as_secs_f64();
        on_pass(done);
        let Some((reference, mask)) = reference else { continue };
        if preview_secs.is_none() || done >= next_point || done == spp {
            let film = r.film_handle();
            let img = film.read().unwrap_or_else(|e| e.into_inner()).mean(Buffer::Full);
            let rmse = relative_rmse(&img, reference, mask);
            let on_curve = done >= next_point || done == spp;
            if on_curve {
                next_point = (next_point as f64 * 1.3).ceil() as u32;
            }
            let reached = preview_secs.is_none() && rmse <= PREVIEW_RMSE;
            if reached {
                preview_secs = Some(seconds);
            }
            // A run that stops at the preview ends its curve there.
            if on_curve || (reached && stop_at_preview) {
                curve.push((seconds, rmse));
            }
            if reached && stop_at_preview {
                break;
            }
        }
    }
    Ok(Tracked { film: r.snapshot(), seconds, preview_secs, curve })
}

/// An image stack (layers of the same size) as one (h, w, 3 n) .npy file.
pub(crate) fn image_npy(img: &[Vec<[f32; 3]>], w: u32, h: u32) -> Vec<u8> {
    let mut flat = Vec::with_capacity(img.len() * (w * h * 3) as usize);
    for i in 0..(w * h) as usize {
        for layer in img {
            flat.extend_from_slice(&layer[i]);
        }
    }
    models::dataset::npy::npy_bytes_f32(&[h as usize, w as usize, 3 * img.len()], &flat)
}

/// Reads an (h, w, 3 n) image stack back as n layers.
pub(crate) fn read_image_npy(path: &Path, w: u32, h: u32, n: usize) -> Result<Vec<Vec<[f32; 3]>>> {
    let (shape, data) = models::dataset::npy::read_f32(path)?;
    if shape != [h as usize, w as usize, 3 * n] {
        bail!("{}: shape {shape:?}, expected [{h}, {w}, {}]", path.display(), 3 * n);
    }
    let mut layers = vec![Vec::with_capacity((w * h) as usize); n];
    for px in data.chunks_exact(3 * n) {
        for (l, layer) in layers.iter_mut().enumerate() {
            layer.push([px[3 * l], px[3 * l + 1], px[3 * l + 2]]);
        }
    }
    Ok(layers)
}

/// Writes `v` as pretty JSON, atomically.
pub(crate) fn write_json(path: &Path, v: &impl Serialize) -> Result<()> {
    Ok(write_bytes_atomically(path, serde_json::to_string_pretty(v)?.as_bytes())?)
}

/// Reads JSON written by [`write_json`]; None if missing or unreadable.
pub(crate) fn read_json<T: for<'a> Deserialize<'a>>(path: &Path) -> Option<T> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// A grid of equally sized image tiles on a dark ground, 4 px apart.
pub(crate) struct TileSheet {
    image: image::RgbImage,
    w: u32,
    h: u32,
}

impl TileSheet {
    const GAP: u32 = 4;

    pub(crate) fn new(w: u32, h: u32, cols: u32, rows: u32) -> Self {
        let (sw, sh) = (cols * (w + Self::GAP) - Self::GAP, rows * (h + Self::GAP));
        TileSheet { image: image::RgbImage::from_pixel(sw.max(1), sh.max(1), image::Rgb([40, 40, 40])), w, h }
    }

    /// Puts a w x h tile (row-major pixels) at column `col`, row `row`.
    pub(crate) fn put(&mut self, col: u32, row: u32, tile: &[[u8; 3]]) {
        let (ox, oy) = (col * (self.w + Self::GAP), row * (self.h + Self::GAP));
        for y in 0..self.h {
            for x in 0..self.w {
                self.image.put_pixel(ox + x, oy + y, image::Rgb(tile[(y * self.w + x) as usize]));
            }
        }
    }

    /// Writes the sheet as a PNG, atomically.
    pub(crate) fn save(&self, path: &Path) -> Result<()> {
        let mut bytes = std::io::Cursor::new(Vec::new());
        self.image.write_to(&mut bytes, image::ImageFormat::Png)?;
        write_bytes_atomically(path, &bytes.into_inner())?;
        Ok(())
    }
}

/// A CSV table declared column by column, so that each header stands beside the value
/// it names.
pub(crate) struct Csv<'a, T> {
    columns: Vec<(&'static str, Box<dyn Fn(&T) -> String + 'a>)>,
}

impl<'a, T> Csv<'a, T> {
    pub(crate) fn new() -> Self {
        Csv { columns: Vec::new() }
    }

    /// Adds the column `name`, whose cell in a row is `cell(row)`.
    pub(crate) fn col(mut self, name: &'static str, cell: impl Fn(&T) -> String + 'a) -> Self {
        self.columns.push((name, Box::new(cell)));
        self
    }

    /// The header line and one line per row.
    pub(crate) fn render(&self, rows: &[T]) -> String {
        let mut out = self.columns.iter().map(|(name, _)| *name).collect::<Vec<_>>().join(",");
        out.push('\n');
        for row in rows {
            out += &self.columns.iter().map(|(_, cell)| cell(row)).collect::<Vec<_>>().join(",");
            out.push('\n');
        }
        out
    }
}

/// An optional number as a CSV cell: empty when absent.
pub(crate) fn opt_cell(v: Option<f64>) -> String {
    v.map(|v| v.to_string()).unwrap_or_default()
}

/// The figures of merit of one (scene, config, rho, k) cell.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CellResult {
    pub scene: String,
    pub config: String,
    pub rho: f32,
    pub k: u32,
    pub p: f32,
    pub spp_ref: u32,
    pub spp: u32,
    pub size: u32,
    /// Absolute bias (docs/conventions.md).
    pub bias: f64,
    /// bias / mean reference over the same pixels.
    pub rel_bias: f64,
    /// The bias that noise alone would show (both images' variances, after the
    /// downscale), relative: bias values near it are not resolved.
    pub rel_noise_floor: f64,
    pub ttuv_ref: f64,
    pub ttuv_pred: f64,
    pub speedup: f64,
    pub secs_ref: f64,
    pub secs_pred: f64,
    /// Seconds to build the model's depth field for this cloud and sun (once per
    /// configuration; not part of TTUV).
    pub secs_field: f64,
    /// Seconds of the automatic-p pilot passes (0 without --auto-p; not part of TTUV).
    pub secs_pilot: f64,
    pub preview_secs_pred: Option<f64>,
    pub preview_secs_ref: Option<f64>,
    /// The prediction's relative RMSE once its noise is gone (its bias part; see
    /// `relative_rmse_less`): at or above `PREVIEW_RMSE` it never previews.
    #[serde(default)]
    pub rmse_floor: Option<f64>,
    /// Seconds to preview projected from TTUV and the floor (variance falls as 1/t):
    /// TTUV / (mean^2 (0.05^2 - floor^2)); None when the floor is at or above 5 %.
    #[serde(default)]
    pub preview_projected_pred: Option<f64>,
    /// The same projection for path tracing (floor 0: it is unbiased), a check on the
    /// measured `preview_secs_ref`.
    #[serde(default)]
    pub preview_projected_ref: Option<f64>,
    /// The reference's own relative noise (`reference_noise`).
    #[serde(default)]
    pub ref_noise: Option<f64>,
    /// The prediction's (seconds, relative RMSE) curve.
    #[serde(default)]
    pub curve: Vec<(f64, f64)>,
}
