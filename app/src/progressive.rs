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
    // Passes in batches, so no core idles at the end of each pass (same image).
    let batch = renderer.passes_per_batch();
    let mut done = 0;
    while done < spp {
        let n = batch.min(spp - done);
        if renderer.render_passes(n, control, generation) == PassOutcome::Cancelled {
            stopped = true;
            break;
        }
        for _ in 0..n {
            done += 1;
            on_pass(done);
        }
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
/// proposes choosing p this way). Rouletting the predicted contribution H with
/// probability p gives per-sample variance V(p) = V1 + B (1/p - 1), with V1 the variance
/// at p = 1 and B = E[H^2], and cost per pass C(p) = c0 + p c1. TTUV is proportional to
/// V(p) C(p) = (A + B/p)(c0 + p c1) with A = V1 - B, whose minimum is at
/// p* = sqrt(B c0 / (A c1)), clamped to [0.05, 1] (p = 1 when A <= 0). Two pilots of
/// `pilot_spp` passes, at p = 1 and p = 0.1 (after a warm-up pilot at p = 1), give V1 and
/// V(0.1) = V1 + 9 B, so B = (V(0.1) - V1) / 9 (this also holds when the high buffer
/// carries NEE that is not rouletted, as with multiple-scattering models), and the
/// two pass times give c0 and c1. Variances are pixel means over lit pixels; the
/// pilots use their own seed and are discarded.
pub fn auto_p(
    scene: Arc<Scene>,
    integrator: &Integrator,
    pilot_spp: u32,
    control: &RenderControl,
) -> anyhow::Result<AutoP> {
    use engine::{Buffer, Mode};
    let settings = *integrator.settings();
    let pilot = |p: f32, spp: u32| -> anyhow::Result<RenderOutcome> {
        let s = engine::RenderSettings { seed: settings.seed ^ 0x5eed_a070, mode: Mode::Predict { p }, ..settings };
        let out = render_spp(scene.clone(), integrator.with_settings(s)?, spp, control, |_| {})?;
        if out.stopped {
            anyhow::bail!("stopped while choosing p");
        }
        Ok(out)
    };
    let spp = pilot_spp.max(2);
    // Warm-up at p = 1 as long as a pilot: caches, page faults, thread start, and a
    // predictor's lattice filled where the paths read it, so the pilots time the
    // steady state the render spends its passes in.
    pilot(1.0, spp)?;
    let (full, few) = (pilot(1.0, spp)?, pilot(0.1, spp)?);
    // Mean over lit pixels of the per-sample variance (sample variance = variance of
    // the mean times spp).
    let per_sample_variance = |f: &Film| {
        let (mean, var) = (f.mean(Buffer::Full), f.variance_of_mean(Buffer::Full));
        let n = f.spp() as f64;
        let (mut v, mut lit) = (0.0f64, 0usize);
        for (m, s) in mean.iter().zip(&var) {
            if m.iter().sum::<f32>() > 0.0 {
                lit += 1;
                v += s.iter().map(|x| *x as f64).sum::<f64>() * n / 3.0;
            }
        }
        v / lit.max(1) as f64
    };
    let (v1, v01) = (per_sample_variance(&full.film), per_sample_variance(&few.film));
    let b = ((v01 - v1) / 9.0).max(0.0);
    let (t1, t01) = (full.render_secs / spp as f64, few.render_secs / spp as f64);
    let c1 = ((t1 - t01) / 0.9).max(1e-9);
    let c0 = (t1 - c1).max(1e-9);
    let a = v1 - b;
    // No roulette variance: predict as rarely as allowed; all variance from roulette: always.
    let p = if b <= 0.0 {
        0.05
    } else if a <= 0.0 {
        1.0
    } else {
        ((b * c0) / (a * c1)).sqrt().clamp(0.05, 1.0) as f32
    };
    Ok(AutoP { p, v1, b, c0, c1 })
}
