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

/// What [`auto_p`] measured and chose.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct AutoP {
    /// The chosen prediction probability.
    pub p: f32,
    /// Mean over lit pixels of the per-sample variance with p = 1 (V1) and of the
    /// second moment of the predicted contribution (B).
    pub v1: f64,
    pub b: f64,
    /// Seconds per pass without predictions (c0) and of the predictions in a pass at
    /// p = 1 (c1).
    pub c0: f64,
    pub c1: f64,
}

/// Chooses the prediction probability p that minimizes TTUV (the thesis, section 5.4,
/// proposes choosing p this way). With X = L + H (low orders plus the predicted
/// contribution), rouletting H with probability p gives per-sample variance
/// V(p) = V1 + B (1/p - 1) with V1 = Var(X) at p = 1 and B = E[H^2], and cost per pass
/// C(p) = c0 + p c1. TTUV is proportional to V(p) C(p) = (A + B/p)(c0 + p c1) with
/// A = V1 - B, whose minimum is at p* = sqrt(B c0 / (A c1)), clamped to [0.05, 1]
/// (p = 1 when A <= 0). V1 and B come from `pilot_spp` passes at p = 1, c0 and c1
/// from those passes' time and as many at p = 0.1 (pixel means over lit pixels; the
/// pilot uses its own seed and is discarded).
pub fn auto_p(
    scene: Arc<Scene>,
    settings: engine::RenderSettings,
    predictor: Arc<dyn engine::InScatterPredictor>,
    pilot_spp: u32,
    control: &RenderControl,
) -> Result<AutoP, engine::integrator::IntegratorError> {
    use engine::{Buffer, Mode};
    let pilot = |p: f32| {
        let s = engine::RenderSettings { seed: settings.seed ^ 0x5eed_a070, mode: Mode::Predict { p }, ..settings };
        render_spp(scene.clone(), Integrator::new(s, Some(predictor.clone()))?, pilot_spp.max(2), control, |_| {})
    };
    let full = pilot(1.0)?;
    let few = pilot(0.1)?;
    let n = full.film.spp() as f64;
    let (mean, var) = (full.film.mean(Buffer::Full), full.film.variance_of_mean(Buffer::Full));
    let (hmean, hvar) = (full.film.mean(Buffer::High), full.film.variance_of_mean(Buffer::High));
    let (mut v1, mut b, mut lit) = (0.0f64, 0.0f64, 0usize);
    for i in 0..mean.len() {
        if mean[i].iter().sum::<f32>() <= 0.0 {
            continue;
        }
        lit += 1;
        for c in 0..3 {
            v1 += var[i][c] as f64 * n / 3.0;
            // E[H^2] = sample variance (n - 1) / n + mean^2
            b += (hvar[i][c] as f64 * (n - 1.0) + (hmean[i][c] as f64).powi(2)) / 3.0;
        }
    }
    let lit = lit.max(1) as f64;
    let (v1, b) = (v1 / lit, b / lit);
    let (t1, t01) = (full.render_secs / n, few.render_secs / few.film.spp().max(1) as f64);
    let c1 = ((t1 - t01) / 0.9).max(1e-9);
    let c0 = (t1 - c1).max(1e-9);
    let a = v1 - b;
    let p = if a <= 0.0 { 1.0 } else { ((b * c0) / (a * c1)).sqrt().clamp(0.05, 1.0) as f32 };
    Ok(AutoP { p, v1, b, c0, c1 })
}
