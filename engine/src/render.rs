//! Progressive rendering: one pass is one sample per pixel, rendered in parallel over
//! tiles with rayon and then added to the film in pixel order, so an image depends only
//! on (seed, pass, pixel), never on the thread count or scheduling.
//!
//! A pass checks its [`RenderControl`] before every row of every tile and is
//! abandoned (never half-added) when the generation moves on or a stop is requested,
//! so it stops within the time of one row of samples; the medium's extinction cap
//! bounds that time whatever the grid holds. The film sits behind a lock that is only held while a
//! finished pass is added, so other threads can take a snapshot at any time.

use crate::control::RenderControl;
use crate::film::Film;
use crate::integrator::base::PathSample;
use crate::integrator::{Integrator, IntegratorError};
use crate::rng::Rng;
use crate::scene::Scene;
use glam::Vec2;
use rayon::prelude::*;
use std::sync::{Arc, RwLock};

/// Edge length of a square tile, in pixels.
pub const TILE_SIZE: u32 = 16;

/// The stream family of the preview's per-pixel rotations of its pass sequence:
/// above every pass index (< 2^32) and apart from BDPT's light pools.
pub const PREVIEW_SHIFT: u64 = 0x4841_4c54 << 32; // "HALT"

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PassOutcome {
    Completed,
    Cancelled,
}

/// Renders passes of one scene into one film.
pub struct Renderer {
    scene: Arc<Scene>,
    integrator: Integrator,
    film: Arc<RwLock<Film>>,
    tiles: Vec<(u32, u32, u32, u32)>,
}

impl Renderer {
    pub fn new(scene: Arc<Scene>, integrator: Integrator) -> Result<Self, IntegratorError> {
        integrator.check_scene(&scene)?;
        let (w, h) = (scene.camera.width(), scene.camera.height());
        let mut tiles = Vec::new();
        for y0 in (0..h).step_by(TILE_SIZE as usize) {
            for x0 in (0..w).step_by(TILE_SIZE as usize) {
                tiles.push((x0, y0, (x0 + TILE_SIZE).min(w), (y0 + TILE_SIZE).min(h)));
            }
        }
        Ok(Renderer { film: Arc::new(RwLock::new(Film::new(w, h))), scene, integrator, tiles })
    }

    pub fn scene(&self) -> &Arc<Scene> {
        &self.scene
    }
    pub fn integrator(&self) -> &Integrator {
        &self.integrator
    }

    /// The film, for readers on other threads.
    pub fn film_handle(&self) -> Arc<RwLock<Film>> {
        self.film.clone()
    }

    /// A copy of the current buffers.
    pub fn snapshot(&self) -> Film {
        self.film.read().unwrap_or_else(|e| e.into_inner()).clone()
    }

    pub fn spp(&self) -> u32 {
        self.film.read().unwrap_or_else(|e| e.into_inner()).spp()
    }

    /// Renders the next pass (one sample per pixel) unless `control` says stop.
    pub fn render_pass(&mut self, control: &RenderControl, generation: u64) -> PassOutcome {
        self.render_passes(1, control, generation)
    }

    /// How many passes [`Renderer::render_passes`] should take at once so that both
    /// cores stay busy to the end of a batch: about 1024 tiles of work, at most 16
    /// passes (a 256x256 image: 4 passes; 1024x1024: 1).
    pub fn passes_per_batch(&self) -> u32 {
        (1024 / self.tiles.len().max(1) as u32).clamp(1, 16)
    }

    /// Renders the next `count` passes as one parallel batch (the tiles of all of them
    /// are one pool of work, so no core waits at a barrier between passes for the
    /// slowest tile) and adds them to the film in pass order: the same image as
    /// `count` single passes, bit for bit. All or nothing: a stop or a scene change
    /// abandons the whole batch.
    pub fn render_passes(&mut self, count: u32, control: &RenderControl, generation: u64) -> PassOutcome {
        let first = self.spp();
        let Some(passes) = self.render_passes_samples(first, count.max(1), control, generation) else {
            return PassOutcome::Cancelled;
        };
        self.film.write().unwrap_or_else(|e| e.into_inner()).add_passes(&passes);
        PassOutcome::Completed
    }

    /// Renders pass number `pass` and returns its samples in pixel order, or None if
    /// cancelled.
    pub fn render_pass_samples(&self, pass: u32, control: &RenderControl, generation: u64) -> Option<Vec<PathSample>> {
        self.render_passes_samples(pass, 1, control, generation).map(|mut v| v.remove(0))
    }

    /// Renders passes `first .. first + count`, each in pixel order, or None if
    /// cancelled.
    pub fn render_passes_samples(
        &self,
        first: u32,
        count: u32,
        control: &RenderControl,
        generation: u64,
    ) -> Option<Vec<Vec<PathSample>>> {
        let camera = &self.scene.camera;
        let (w, h) = (camera.width(), camera.height());
        // BDPT's prediction mode: each pass's samples share one pool of light subpath
        // candidates.
        let pools: Vec<_> = (0..count).map(|i| self.integrator.light_pool(&self.scene, first + i, w * h)).collect();
        let nt = self.tiles.len();
        let tiles: Vec<Vec<PathSample>> = (0..count as usize * nt)
            .into_par_iter()
            .map(|i| {
                let (p, t) = (i / nt, i % nt);
                self.render_tile(first + p as u32, self.tiles[t], pools[p].as_ref(), control, generation)
            })
            .collect::<Option<Vec<_>>>()?;
        // Each pass in pixel order, assembled by bands of one tile row in parallel (the
        // tiles are in row-major order, a band's tiles consecutive).
        let band = (TILE_SIZE * w) as usize;
        let tiles_per_band = w.div_ceil(TILE_SIZE) as usize;
        let out = tiles
            .par_chunks(nt)
            .map(|pass_tiles| {
                let mut samples = vec![PathSample::default(); (w * h) as usize];
                samples.par_chunks_mut(band).zip(pass_tiles.par_chunks(tiles_per_band)).enumerate().for_each(
                    |(b, (dst, band_tiles))| {
                        let first = b * tiles_per_band;
                        for (&(x0, y0, x1, _), tile) in self.tiles[first..].iter().zip(band_tiles) {
                            let tw = (x1 - x0) as usize;
                            for (row, chunk) in tile.chunks(tw).enumerate() {
                                let start = (y0 as usize - b * TILE_SIZE as usize + row) * w as usize + x0 as usize;
                                dst[start..start + tw].copy_from_slice(chunk);
                            }
                        }
                    },
                );
                samples
            })
            .collect();
        Some(out)
    }

    /// One tile of one pass, rows in order; None if cancelled. Pixel samples use the
    /// stream (seed, pass, pixel), the preview's per-pixel rotation (seed,
    /// [`PREVIEW_SHIFT`], pixel).
    fn render_tile(
        &self,
        pass: u32,
        (x0, y0, x1, y1): (u32, u32, u32, u32),
        pool: Option<&crate::integrator::bdpt::LightPool>,
        control: &RenderControl,
        generation: u64,
    ) -> Option<Vec<PathSample>> {
        let camera = &self.scene.camera;
        let w = camera.width();
        let seed = self.integrator.settings().seed;
        let mut out = Vec::with_capacity(((x1 - x0) * (y1 - y0)) as usize);
        // The preview's three dimensions (pixel position, march offset) follow a
        // Halton sequence over the passes, rotated per pixel: its passes tile each
        // pixel and each march step evenly, so its image settles faster than with
        // independent samples (its integrand is smooth apart from edges).
        let preview = self.integrator.active_preview();
        // BDPT's predictions are evaluated per tile, in one batch.
        let mut deferred = Vec::new();
        for y in y0..y1 {
            // Checked per row, so a stop acts within one row of samples.
            if control.should_abort(generation) {
                return None;
            }
            for x in x0..x1 {
                let pixel = y as u64 * w as u64 + x as u64;
                if let Some(p) = preview {
                    let mut shift = Rng::new(seed, PREVIEW_SHIFT, pixel);
                    let shift = [shift.uniform_f64(), shift.uniform_f64(), shift.uniform_f64()];
                    let [ux, uy, offset] = crate::sampling::halton_point(pass, shift);
                    let (o, d) = camera.generate_ray(x, y, Vec2::new(ux, uy));
                    out.push(p.trace_with_offset(&self.scene, o, d, offset));
                    continue;
                }
                let mut rng = Rng::new(seed, pass as u64, pixel);
                let (o, d) = camera.generate_ray(x, y, Vec2::new(rng.uniform(), rng.uniform()));
                let first = deferred.len();
                out.push(self.integrator.trace_deferring(&self.scene, o, d, &mut rng, pool, Some(&mut deferred)));
                for p in &mut deferred[first..] {
                    p.owner = (out.len() - 1) as u32;
                }
            }
        }
        self.integrator.resolve_deferred(&self.scene, &mut deferred, &mut out);
        Some(out)
    }
}
