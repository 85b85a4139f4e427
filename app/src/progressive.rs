//! Headless progressive rendering to a fixed sample count, shared by `render`,
//! `bench` and the tests.

use engine::{Film, Integrator, PassOutcome, RenderControl, Renderer, Scene};
use std::sync::Arc;
use std::time::Instant;

pub struct RenderOutcome {
    pub film: Film,
    pub render_secs: f64,
    /// True if stopped before reaching the requested spp (the film holds whole passes).
    pub stopped: bool,
}

impl RenderOutcome {
    /// Camera samples per second.
    pub fn samples_per_sec(&self) -> f64 {
        self.film.spp() as f64 * self.film.pixel_count() as f64 / self.render_secs.max(1e-9)
    }
}

/// Renders `spp` passes, calling `on_pass(spp_done)` after each; stops early when
/// `control` asks.
pub fn render_spp(
    scene: Arc<Scene>,
    integrator: Integrator,
    spp: u32,
    control: &RenderControl,
    mut on_pass: impl FnMut(u32),
) -> Result<RenderOutcome, engine::integrator::IntegratorError> {
    let mut renderer = Renderer::new(scene, integrator)?;
    let generation = control.generation();
    let start = Instant::now();
    let mut stopped = false;
    for done in 1..=spp {
        if renderer.render_pass(control, generation) == PassOutcome::Cancelled {
            stopped = true;
            break;
        }
        on_pass(done);
    }
    let render_secs = start.elapsed().as_secs_f64();
    Ok(RenderOutcome { film: renderer.snapshot(), render_secs, stopped })
}
