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
    /// The sample buffers of the last batch, kept for the next one (see [`Scratch`]).
    scratch: Scratch,
}

/// A batch's sample buffers: one per tile of every pass, then one per pass in pixel
/// order. The renderer keeps them from batch to batch: allocated anew for each, the
/// few megabytes a batch takes went back to the operating system when freed (the
/// allocator trims its heap) and came back as page faults, 5 % of a render's time at
/// 256x256.
#[derive(Default)]
struct Scratch {
    tiles: Vec<Vec<PathSample>>,
    passes: Vec<Vec<PathSample>>,
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
        Ok(Renderer {
            film: Arc::new(RwLock::new(Film::new(w, h))),
            scene,
            integrator,
            tiles,
            scratch: Scratch::default(),
        })
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

    /// [`Renderer::snapshot`] into `dst`, in the memory `dst` already holds.
    pub fn snapshot_into(&self, dst: &mut Film) {
        dst.copy_from(&self.film.read().unwrap_or_else(|e| e.into_inner()));
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
        let count = count.max(1);
        let mut scratch = std::mem::take(&mut self.scratch);
        let done = self.render_into(first, count, control, generation, &mut scratch);
        if done {
            self.film.write().unwrap_or_else(|e| e.into_inner()).add_passes(&scratch.passes[..count as usize]);
        }
        self.scratch = scratch;
        if done { PassOutcome::Completed } else { PassOutcome::Cancelled }
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
        let count = count.max(1);
        let mut scratch = Scratch::default();
        self.render_into(first, count, control, generation, &mut scratch).then(|| {
            scratch.passes.truncate(count as usize);
            scratch.passes
        })
    }

    /// Renders passes `first .. first + count` into `scratch.passes[..count]`, each in
    /// pixel order, in the memory the buffers already hold; false if cancelled (the
    /// buffers' contents are then undefined).
    fn render_into(
        &self,
        first: u32,
        count: u32,
        control: &RenderControl,
        generation: u64,
        scratch: &mut Scratch,
    ) -> bool {
        let camera = &self.scene.camera;
        let (w, h) = (camera.width(), camera.height());
        // BDPT's prediction mode: each pass's samples share one pool of light subpath
        // candidates.
        let pools: Vec<_> = (0..count).map(|i| self.integrator.light_pool(&self.scene, first + i, w * h)).collect();
        let nt = self.tiles.len();
        let n = count as usize * nt;
        if scratch.tiles.len() < n {
            scratch.tiles.resize_with(n, Vec::new);
        }
        let tiles = &mut scratch.tiles[..n];
        let done = tiles.par_iter_mut().enumerate().all(|(i, out)| {
            let (p, t) = (i / nt, i % nt);
            self.render_tile(first + p as u32, self.tiles[t], pools[p].as_ref(), control, generation, out)
        });
        if !done {
            return false;
        }
        // Each pass in pixel order, assembled by bands of one tile row in parallel (the
        // tiles are in row-major order, a band's tiles consecutive).
        if scratch.passes.len() < count as usize {
            scratch.passes.resize_with(count as usize, Vec::new);
        }
        let band = (TILE_SIZE * w) as usize;
        let tiles_per_band = w.div_ceil(TILE_SIZE) as usize;
        scratch.passes[..count as usize].par_iter_mut().zip(tiles.par_chunks(nt)).for_each(|(samples, pass_tiles)| {
            samples.resize((w * h) as usize, PathSample::default());
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
        });
        true
    }

    /// One tile of one pass into `out` (cleared first), rows in order; false if
    /// cancelled. Pixel samples use the
    /// stream (seed, pass, pixel), the preview's per-pixel rotation (seed,
    /// [`PREVIEW_SHIFT`], pixel).
    fn render_tile(
        &self,
        pass: u32,
        (x0, y0, x1, y1): (u32, u32, u32, u32),
        pool: Option<&crate::integrator::bdpt::LightPool>,
        control: &RenderControl,
        generation: u64,
        out: &mut Vec<PathSample>,
    ) -> bool {
        let camera = &self.scene.camera;
        let w = camera.width();
        let seed = self.integrator.settings().seed;
        out.clear();
        out.reserve(((x1 - x0) * (y1 - y0)) as usize);
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
                return false;
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
        self.integrator.resolve_deferred(&self.scene, &mut deferred, out);
        true
    }
}
