//! The instant preview in `nimbus eval --preview`: per scene, lighting and density,
//! the learned preview, the octave approximation with its defaults and with its
//! factors fitted to the reference (least squares on the image), each with its
//! set-up time (fields, model, lattice), time to preview (set-up plus render seconds
//! until 5 % relative RMSE against the converged reference), RMSE floor (the error
//! more passes do not remove) and convergence curve.
//!
//! The fit is an oracle baseline: it sees the reference, and its time is not counted.
//! It runs Nelder-Mead over (a, b, c) in (0, 1]^3 with 3 octaves, each trial a
//! preview of a quarter of the resolution (two passes) against the reference boxed
//! down to it.

use super::common::{image_npy, read_image_npy, read_json, render_tracked, write_json};
use crate::metrics::{Image, avg3, downscale, relative_rmse_with_error};
use crate::output::write_bytes_atomically;
use crate::scene::SceneFile;
use anyhow::{Result, bail};
use engine::field::SunTransmittance;
use engine::integrator::preview::{MultipleScattering, Preview};
use engine::{Buffer, InScatterPredictor, Integrator, PassOutcome, RenderControl, RenderSettings, Renderer, Scene};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// One preview technique in one configuration.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PreviewCell {
    pub scene: String,
    pub config: String,
    pub rho: f32,
    pub size: u32,
    /// learned | octaves | octaves fitted
    pub technique: String,
    /// The octave approximation's (N, a, b, c), for the octave rows.
    pub octaves: Option<[f32; 4]>,
    /// Seconds to build what the technique needs before its first pass.
    pub setup_secs: f64,
    /// Set-up plus render seconds until the image is within 5 % relative RMSE (the
    /// median of `preview_secs_runs` when there are several; `setup_secs` and `curve`
    /// are the first run's).
    pub preview_secs: Option<f64>,
    /// With `--preview-repeats N` > 1 and a first run that reached 5 %: every run's
    /// time to 5 % (None: not within the passes), the first run's first.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub preview_secs_runs: Vec<Option<f64>>,
    /// Relative RMSE after the first pass.
    pub rmse_first_pass: f64,
    /// Relative RMSE with the image's own noise subtracted: its bias part.
    pub rmse_floor: f64,
    /// The floor's standard error over the pixels (`metrics::relative_rmse_with_error`):
    /// large where the reference is noisy beside the floor.
    pub rmse_floor_se: f64,
    pub spp: u32,
    /// (set-up + render seconds, relative RMSE).
    pub curve: Vec<(f64, f64)>,
}

/// A bound model and the seconds its fields took to build.
pub type Bound = (Arc<dyn InScatterPredictor>, f64);

/// The preview techniques, in the order of the tables and the sheet.
const TECHNIQUES: [&str; 3] = ["learned", "octaves", "octaves fitted"];

/// The second run of every preview cell (for its floor) uses the scene's seed xor this.
const SECOND_RUN_SEED: u64 = 0x5345_434f_4e44; // "SECOND"

/// Part of every preview cache file's name: the preview's sampling and the floor's
/// measurement as they are now (cells cached by an earlier form, such as one without
/// the floor's standard error, are made again).
const CACHE_FORM: &str = "v4";

/// What the preview cells of one configuration share.
pub struct PreviewJob<'a> {
    pub file: &'a SceneFile,
    pub scene: &'a Arc<Scene>,
    pub reference: &'a Image,
    pub mask: &'a [bool],
    /// The model bound to this cloud and sun for the preview, given the preview's sun
    /// field (which a cloud-aware model reads instead of its own, as the renderer's
    /// preview does).
    pub bound: &'a dyn Fn(&Arc<SunTransmittance>) -> Bound,
    /// The model's field nodes per axis `bound` builds (`--field-nodes`).
    pub field_nodes: u32,
    /// Passes of each preview render.
    pub spp: u32,
    /// Timed runs of each preview that reaches 5 % (`--preview-repeats`).
    pub repeats: u32,
    pub control: &'a RenderControl,
    pub cache: &'a Path,
    /// The configuration's cache key (scene, reference, model) and labels.
    pub key: &'a str,
    pub labels: (&'a str, &'a str, f32),
}

/// The octave approximation's defaults as (N, a, b, c).
fn default_octaves() -> [f32; 4] {
    match MultipleScattering::DEFAULT_OCTAVES {
        MultipleScattering::Octaves { octaves, a, b, c } => [octaves as f32, a, b, c],
        _ => unreachable!("the default octaves are octaves"),
    }
}

impl PreviewJob<'_> {
    /// The three preview cells and their images (from the cache when there; the
    /// fields are built only when something must be rendered).
    pub fn run(&self) -> Result<Vec<(PreviewCell, Vec<[f32; 3]>)>> {
        let cached: Option<Vec<_>> = TECHNIQUES.iter().map(|t| self.cached(t)).collect();
        if let Some(cells) = cached {
            return Ok(cells);
        }
        let (field, field_secs) = self.sun_field();
        // The learned preview: the model bound to the cloud and sun, its lattice for
        // this camera.
        let learned = |field: &Arc<SunTransmittance>| -> Result<(MultipleScattering, f64)> {
            let (bound, bound_secs) = (self.bound)(field);
            let t = Instant::now();
            let lattice = Preview::learned_lattice(
                self.scene,
                field,
                bound,
                self.scene.camera.position(),
                self.file.render.preview_nodes,
            );
            Ok((MultipleScattering::Lattice(Arc::new(lattice)), bound_secs + t.elapsed().as_secs_f64()))
        };
        let fitted_key = self.cache.join(format!("{}_octaves_fit.json", self.key));
        let fitted = match read_json::<[f32; 4]>(&fitted_key) {
            Some(p) => p,
            None => {
                let p = self.fit_octaves(&field)?;
                write_json(&fitted_key, &p)?;
                p
            }
        };
        Ok(vec![
            self.cell(TECHNIQUES[0], None, field_secs, &field, learned)?,
            self.cell(TECHNIQUES[1], Some(default_octaves()), field_secs, &field, |_| {
                Ok((MultipleScattering::DEFAULT_OCTAVES, 0.0))
            })?,
            self.cell(TECHNIQUES[2], Some(fitted), field_secs, &field, |_| Ok((octaves(fitted), 0.0)))?,
        ])
    }

    /// The cache files of `technique`'s cell: (json, npy). The learned preview's name
    /// carries its lattice's nodes per axis and its model's field nodes (other ones,
    /// another image), and "newcloud": its model reads the preview's sun field and its
    /// set-up builds the density pyramid as for a new cloud.
    fn cache_paths(&self, technique: &str) -> (std::path::PathBuf, std::path::PathBuf) {
        let lattice = if technique == TECHNIQUES[0] {
            // The nodes the lattice takes for this cloud, asked for or by default.
            let n = Preview::lattice_nodes(&self.scene.medium, self.file.render.preview_nodes).0;
            let nodes = if n.x == n.y && n.y == n.z { n.x.to_string() } else { format!("{}x{}x{}", n.x, n.y, n.z) };
            format!("_nodes{nodes}_fields{}_newcloud", self.field_nodes)
        } else {
            String::new()
        };
        let runs = if self.repeats > 1 { format!("_runs{}", self.repeats) } else { String::new() };
        let tag =
            format!("{}_preview_{CACHE_FORM}_{}{lattice}_spp{}{runs}", self.key, technique.replace(' ', "_"), self.spp);
        (self.cache.join(format!("{tag}.json")), self.cache.join(format!("{tag}.npy")))
    }

    /// `technique`'s cell and image from the cache, if both are there and readable.
    fn cached(&self, technique: &str) -> Option<(PreviewCell, Vec<[f32; 3]>)> {
        let (json, npy) = self.cache_paths(technique);
        let cell = read_json::<PreviewCell>(&json)?;
        let (w, h) = (self.reference.w, self.reference.h);
        let image = read_image_npy(&npy, w, h, 1).ok()?.into_iter().next()?;
        Some((cell, image))
    }

    /// One technique's cell: rendered (or read from the cache) and measured.
    fn cell(
        &self,
        technique: &str,
        params: Option<[f32; 4]>,
        field_secs: f64,
        field: &Arc<SunTransmittance>,
        multiple: impl Fn(&Arc<SunTransmittance>) -> Result<(MultipleScattering, f64)>,
    ) -> Result<(PreviewCell, Vec<[f32; 3]>)> {
        if let Some(cached) = self.cached(technique) {
            return Ok(cached);
        }
        let (ms, ms_secs) = multiple(field)?;
        let ms2 = ms.clone();
        let setup_secs = field_secs + ms_secs;
        let t = render_tracked(
            self.scene.clone(),
            self.integrator(field, ms)?,
            self.spp,
            self.control,
            Some((self.reference, self.mask)),
            false,
            |_| {},
        )?;
        let full = Image::from_film(&t.film, Buffer::Full);
        // The floor: the error left once the preview's own noise is taken out. Its
        // passes follow a low-discrepancy sequence, so their spread overstates the
        // noise of their mean; a second run with another seed (other rotations of the
        // sequence) measures it without bias: per pixel (I1 - I2)^2 / 4 is the
        // variance of the two runs' average. It is also steadier than a film's
        // per-pixel variance, whose heavy tails make that estimate swing by a point
        // or more from one seed to the next.
        let settings = self.file.settings();
        let other = RenderSettings { seed: settings.seed ^ SECOND_RUN_SEED, ..settings };
        let second = self.integrator_with(other, field, ms2)?;
        let t2 = render_tracked(self.scene.clone(), second, self.spp, self.control, None, false, |_| {})?;
        let second = Image::from_film(&t2.film, Buffer::Full);
        let average: Vec<[f32; 3]> =
            full.mean.iter().zip(&second.mean).map(|(a, b)| std::array::from_fn(|c| 0.5 * (a[c] + b[c]))).collect();
        let var: Vec<[f32; 3]> = full
            .mean
            .iter()
            .zip(&second.mean)
            .map(|(a, b)| std::array::from_fn(|c| 0.25 * (a[c] - b[c]) * (a[c] - b[c])))
            .collect();
        let first_secs = t.preview_secs.map(|s| s + setup_secs);
        let runs = match first_secs {
            Some(_) if self.repeats > 1 => {
                let mut runs = vec![first_secs];
                for _ in 1..self.repeats {
                    runs.push(self.timed_run(&multiple)?);
                }
                runs
            }
            _ => vec![],
        };
        let (label, config, rho) = self.labels;
        let (rmse_floor, rmse_floor_se) = relative_rmse_with_error(&average, self.reference, self.mask, Some(&var));
        let cell = PreviewCell {
            scene: label.into(),
            config: config.into(),
            rho,
            size: self.reference.w,
            technique: technique.into(),
            octaves: params,
            setup_secs,
            preview_secs: if runs.is_empty() { first_secs } else { median_secs(&runs) },
            preview_secs_runs: runs,
            rmse_first_pass: t.curve.first().map_or(f64::INFINITY, |p| p.1),
            rmse_floor,
            rmse_floor_se,
            spp: self.spp,
            curve: t.curve.iter().map(|&(s, r)| (s + setup_secs, r)).collect(),
        };
        let (json, npy) = self.cache_paths(technique);
        let (w, h) = (self.reference.w, self.reference.h);
        write_bytes_atomically(&npy, &image_npy(std::slice::from_ref(&full.mean), w, h))?;
        write_json(&json, &cell)?;
        Ok((cell, full.mean))
    }

    /// The preview's sun field for the scene's cloud and sun, and the seconds it took.
    fn sun_field(&self) -> (Arc<SunTransmittance>, f64) {
        let sun = self.scene.sun.as_ref().expect("evaluation scenes have a sun");
        let t = Instant::now();
        let field = Arc::new(SunTransmittance::build(&self.scene.medium, sun, SunTransmittance::DEFAULT_MAX_NODES));
        (field, t.elapsed().as_secs_f64())
    }

    /// One more timed run of a preview to 5 %: the sun field and `multiple`'s source
    /// built again (for the cloud-aware model a new binding, as for a new cloud), the
    /// render stopped at 5 %. None when it does not get there within the cell's
    /// passes.
    fn timed_run(
        &self,
        multiple: &impl Fn(&Arc<SunTransmittance>) -> Result<(MultipleScattering, f64)>,
    ) -> Result<Option<f64>> {
        let (field, field_secs) = self.sun_field();
        let (ms, ms_secs) = multiple(&field)?;
        let integrator = self.integrator(&field, ms)?;
        let run = render_tracked(
            self.scene.clone(),
            integrator,
            self.spp,
            self.control,
            Some((self.reference, self.mask)),
            true,
            |_| {},
        )?;
        Ok(run.preview_secs.map(|s| s + field_secs + ms_secs))
    }

    /// The preview integrator for the field and a source of the higher orders.
    fn integrator(&self, field: &Arc<SunTransmittance>, multiple: MultipleScattering) -> Result<Integrator> {
        self.integrator_with(self.file.settings(), field, multiple)
    }

    /// [`PreviewJob::integrator`] with other render settings (another seed).
    fn integrator_with(
        &self,
        settings: RenderSettings,
        field: &Arc<SunTransmittance>,
        multiple: MultipleScattering,
    ) -> Result<Integrator> {
        let preview = Preview::new(field.clone(), multiple, Preview::default_step(&self.scene.medium))
            .map_err(anyhow::Error::msg)?;
        Ok(Integrator::preview(settings, Arc::new(preview))?)
    }

    /// (N, a, b, c) with N the default's, minimizing the squared error against the
    /// reference over the lit pixels, at a quarter of the resolution (Nelder-Mead
    /// from the defaults). An error if the run is stopped, so that no fit of empty
    /// images is cached.
    fn fit_octaves(&self, field: &Arc<SunTransmittance>) -> Result<[f32; 4]> {
        let f = 4u32.min(self.reference.w).max(1);
        let (w, h) = (self.reference.w.div_ceil(f), self.reference.h.div_ceil(f));
        let cam = &self.scene.camera;
        let small = Arc::new(Scene { camera: cam.with_resolution(w, h)?, ..(**self.scene).clone() });
        // The reference boxed down to the small image.
        let target: Vec<f64> = downscale(self.reference, f).0.iter().map(|p| p.iter().sum::<f64>() / 3.0).collect();
        let [n, a0, b0, c0] = default_octaves();
        let generation = self.control.generation();
        let loss = |p: &[f64; 3]| -> f64 {
            let [a, b, c] = p.map(|v| v.clamp(0.01, 1.0) as f32);
            let Ok(integrator) = self.integrator(field, octaves([n, a, b, c])) else { return f64::INFINITY };
            let Ok(mut r) = Renderer::new(small.clone(), integrator) else { return f64::INFINITY };
            for _ in 0..2 {
                if r.render_pass(self.control, generation) == PassOutcome::Cancelled {
                    return f64::INFINITY;
                }
            }
            let img = r.snapshot().mean(Buffer::Full);
            img.iter().zip(&target).filter(|(_, t)| **t > 0.0).map(|(p, t)| (avg3(p) - t).powi(2)).sum()
        };
        let best = nelder_mead(&loss, [a0, b0, c0].map(f64::from), 0.2, 60);
        if self.control.should_abort(generation) {
            bail!("stopped; finished renders are cached and a rerun resumes from them");
        }
        let [a, b, c] = best.map(|v| v.clamp(0.01, 1.0) as f32);
        Ok([n, a, b, c])
    }
}

/// " (median of N runs: lo - hi s)" for several runs, the runs that never got
/// there counted; empty for one run.
fn runs_range(runs: &[Option<f64>]) -> String {
    if runs.len() < 2 {
        return String::new();
    }
    let reached: Vec<f64> = runs.iter().flatten().copied().collect();
    let lo = reached.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = reached.iter().copied().fold(0.0f64, f64::max);
    let never = runs.len() - reached.len();
    let never = if never > 0 { format!(", {never} never") } else { String::new() };
    format!(" (median of {} runs: {lo:.2} - {hi:.2} s{never})", runs.len())
}

/// The median of runs' times to 5 % (a run that never got there counts as the
/// slowest; for an even count the lower of the two middle runs); None when the
/// median run never got there.
fn median_secs(runs: &[Option<f64>]) -> Option<f64> {
    let mut sorted: Vec<f64> = runs.iter().map(|r| r.unwrap_or(f64::INFINITY)).collect();
    sorted.sort_by(f64::total_cmp);
    sorted.get(sorted.len().saturating_sub(1) / 2).copied().filter(|s| s.is_finite())
}

/// The octave approximation of (N, a, b, c).
fn octaves(p: [f32; 4]) -> MultipleScattering {
    MultipleScattering::Octaves { octaves: p[0] as u32, a: p[1], b: p[2], c: p[3] }
}

/// Nelder-Mead minimization of `f` from `start` (initial simplex `scale` along each
/// axis), at most `evals` evaluations; returns the best point.
fn nelder_mead(f: &dyn Fn(&[f64; 3]) -> f64, start: [f64; 3], scale: f64, evals: usize) -> [f64; 3] {
    let mut simplex: Vec<([f64; 3], f64)> = (0..4)
        .map(|i| {
            let mut p = start;
            if i > 0 {
                p[i - 1] += if p[i - 1] + scale <= 1.0 { scale } else { -scale };
            }
            (p, f(&p))
        })
        .collect();
    let mut used = 4;
    let combine =
        |a: &[f64; 3], b: &[f64; 3], t: f64| -> [f64; 3] { std::array::from_fn(|k| a[k] + t * (b[k] - a[k])) };
    while used < evals {
        simplex.sort_by(|x, y| x.1.total_cmp(&y.1));
        let centroid: [f64; 3] = std::array::from_fn(|k| simplex[..3].iter().map(|s| s.0[k]).sum::<f64>() / 3.0);
        let worst = simplex[3];
        let reflect = combine(&centroid, &worst.0, -1.0);
        let fr = f(&reflect);
        used += 1;
        if fr < simplex[0].1 {
            let expand = combine(&centroid, &worst.0, -2.0);
            let fe = f(&expand);
            used += 1;
            simplex[3] = if fe < fr { (expand, fe) } else { (reflect, fr) };
        } else if fr < simplex[2].1 {
            simplex[3] = (reflect, fr);
        } else {
            let contract = combine(&centroid, &worst.0, 0.5);
            let fc = f(&contract);
            used += 1;
            if fc < worst.1 {
                simplex[3] = (contract, fc);
            } else {
                // Shrink toward the best.
                let best = simplex[0].0;
                for s in simplex.iter_mut().skip(1) {
                    s.0 = combine(&best, &s.0, 0.5);
                    s.1 = f(&s.0);
                    used += 1;
                }
            }
        }
    }
    simplex.sort_by(|x, y| x.1.total_cmp(&y.1));
    simplex[0].0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Nelder-Mead finds the minimum of a smooth bowl inside the unit cube.
    #[test]
    fn nelder_mead_finds_a_bowl_minimum() {
        let f = |p: &[f64; 3]| (p[0] - 0.3).powi(2) + 2.0 * (p[1] - 0.7).powi(2) + 0.5 * (p[2] - 0.15).powi(2);
        let best = nelder_mead(&f, [0.5, 0.5, 0.5], 0.2, 200);
        for (got, want) in best.iter().zip([0.3, 0.7, 0.15]) {
            assert!((got - want).abs() < 1e-3, "{best:?}");
        }
    }

    /// The repeated runs' median counts a run that never reached 5 % as the slowest,
    /// takes the lower middle run of an even count, and the table states the range of
    /// the runs that got there.
    #[test]
    fn repeated_runs_report_their_median_and_range() {
        assert_eq!(median_secs(&[Some(0.9), Some(0.7), Some(0.8)]), Some(0.8));
        assert_eq!(median_secs(&[Some(0.9), Some(0.7), Some(0.8), Some(0.6)]), Some(0.7));
        assert_eq!(median_secs(&[None, Some(0.7), Some(0.8)]), Some(0.8));
        assert_eq!(median_secs(&[None, None, Some(0.8)]), None);
        assert_eq!(median_secs(&[]), None);
        assert_eq!(runs_range(&[Some(0.7)]), "");
        assert_eq!(runs_range(&[Some(0.75), Some(0.7), None]), " (median of 3 runs: 0.70 - 0.75 s, 1 never)");
    }
}

/// Seconds as x for the curves: log10, so a render of minutes and a preview of a
/// fraction of a second share a plot.
fn log_seconds(curve: &[(f64, f64)]) -> Vec<(f64, f64)> {
    curve.iter().map(|&(s, r)| (s.max(1e-3).log10(), r)).collect()
}

/// One configuration's plot of relative RMSE against seconds (path tracing, the
/// predictions, the previews) and its sheet: reference, learned preview, octaves,
/// fitted octaves, and the learned preview's error in false colour (yellow = the
/// reference's lit mean).
pub fn write_group(
    out: &Path,
    key: &str,
    job: &PreviewJob,
    cells: &[(PreviewCell, Vec<[f32; 3]>)],
    path_traced: &[(f64, f64)],
    predictions: &[super::common::CellResult],
) -> Result<()> {
    use models::plot::{PALETTE, Series};
    let mut series =
        vec![Series { label: "path tracing".into(), colour: PALETTE[0], points: log_seconds(path_traced) }];
    for (i, c) in predictions.iter().enumerate().take(3) {
        series.push(Series {
            label: format!("predict k {}", c.k),
            colour: PALETTE[1 + i],
            points: log_seconds(&c.curve),
        });
    }
    for (i, (c, _)) in cells.iter().enumerate() {
        series.push(Series { label: c.technique.clone(), colour: PALETTE[4 + i], points: log_seconds(&c.curve) });
    }
    let plot = models::plot::line_plot_png(key, "log10 seconds", "relative RMSE", &series);
    write_bytes_atomically(&out.join(format!("preview_rmse_{key}.png")), &plot)?;
    let reference = job.reference;
    let (w, h) = (reference.w, reference.h);
    let tone = crate::output::ToneMap::Filmic;
    let mut sheet = super::common::TileSheet::new(w, h, 5, 1);
    sheet.put(0, 0, &tone.to_rgb8(&reference.mean, 0.0));
    for (col, (_, img)) in cells.iter().enumerate() {
        sheet.put(col as u32 + 1, 0, &tone.to_rgb8(img, 0.0));
    }
    if let Some((_, learned)) = cells.first() {
        let scale = crate::metrics::lit_mean(&reference.mean).max(1e-12);
        sheet.put(4, 0, &crate::metrics::error_colours(learned, &reference.mean, scale));
    }
    sheet.save(&out.join(format!("preview_sheet_{key}.png")))
}

/// preview.csv (every cell) and preview.md: per configuration, path tracing's and the
/// best prediction's time to preview beside the previews'.
pub fn write_reports(
    out: &Path,
    predictions: &[super::common::CellResult],
    cells: &[PreviewCell],
    quiet: bool,
) -> Result<()> {
    use super::common::{Csv, opt_cell};
    let csv = Csv::<PreviewCell>::new()
        .col("scene", |c| c.scene.clone())
        .col("config", |c| c.config.clone())
        .col("rho", |c| c.rho.to_string())
        .col("size", |c| c.size.to_string())
        .col("technique", |c| c.technique.clone())
        .col("octaves", |c| c.octaves.map(|p| format!("{} {} {} {}", p[0], p[1], p[2], p[3])).unwrap_or_default())
        .col("setup_secs", |c| format!("{:.3}", c.setup_secs))
        .col("preview_secs", |c| opt_cell(c.preview_secs))
        .col("rmse_first_pass", |c| format!("{:.5}", c.rmse_first_pass))
        .col("rmse_floor", |c| format!("{:.5}", c.rmse_floor))
        .col("spp", |c| c.spp.to_string())
        .col("preview_secs_runs", |c| {
            c.preview_secs_runs
                .iter()
                .map(|r| r.map_or("never".into(), |s| format!("{s:.6}")))
                .collect::<Vec<_>>()
                .join(" ")
        })
        .col("rmse_floor_se", |c| format!("{:.5}", c.rmse_floor_se))
        .render(cells);
    write_bytes_atomically(&out.join("preview.csv"), csv.as_bytes())?;
    let secs = |v: Option<f64>| v.map_or("never".to_string(), |s| format!("{s:.2} s"));
    let mut md = String::from(
        "# nimbus eval --preview: time to preview (5 % relative RMSE against the converged reference)\n\n\
         Cells: time to preview (set-up included for the previews) / RMSE floor (+- its standard error over the pixels, \
         large where the reference is noisy beside the floor). Prediction: the best k.\n\n\
         | scene | config | rho | size | path tracing | prediction | learned preview | octaves (default) | octaves (fitted) | path tracing / learned |\n\
         |---|---|---|---|---|---|---|---|---|---|\n",
    );
    let mut groups: Vec<(&str, &str, f32, u32)> =
        cells.iter().map(|c| (c.scene.as_str(), c.config.as_str(), c.rho, c.size)).collect();
    groups.dedup();
    for (scene, config, rho, size) in groups {
        let here = |t: &str| {
            cells.iter().find(|c| {
                (c.scene.as_str(), c.config.as_str(), c.rho, c.size, c.technique.as_str())
                    == (scene, config, rho, size, t)
            })
        };
        let preds: Vec<_> = predictions
            .iter()
            .filter(|c| (c.scene.as_str(), c.config.as_str(), c.rho, c.size) == (scene, config, rho, size))
            .collect();
        let pt = preds.first().and_then(|c| c.preview_secs_ref);
        let best =
            preds.iter().filter_map(|c| c.preview_secs_pred.map(|s| (s, c.k))).min_by(|a, b| a.0.total_cmp(&b.0));
        let pred_cell = match best {
            Some((s, k)) => format!("{s:.1} s (k {k})"),
            None => format!(
                "never (floor {:.1} %)",
                100.0 * preds.iter().filter_map(|c| c.rmse_floor).fold(f64::INFINITY, f64::min)
            ),
        };
        let cell = |t: &str| {
            here(t).map_or("-".to_string(), |c| {
                let fit = c
                    .octaves
                    .filter(|_| t == "octaves fitted")
                    .map(|p| format!(", a {:.2} b {:.2} c {:.2}", p[1], p[2], p[3]))
                    .unwrap_or_default();
                format!(
                    "{}{} / {:.1} % (+- {:.1}){fit}",
                    secs(c.preview_secs),
                    runs_range(&c.preview_secs_runs),
                    100.0 * c.rmse_floor,
                    100.0 * c.rmse_floor_se
                )
            })
        };
        let ratio = match (pt, here("learned").and_then(|c| c.preview_secs)) {
            (Some(a), Some(b)) => format!("{:.0}x", a / b),
            _ => "-".into(),
        };
        md += &format!(
            "| {scene} | {config} | {rho} | {size} | {} | {pred_cell} | {} | {} | {} | {ratio} |\n",
            secs(pt),
            cell("learned"),
            cell("octaves"),
            cell("octaves fitted")
        );
    }
    write_bytes_atomically(&out.join("preview.md"), md.as_bytes())?;
    if !quiet {
        println!("{md}");
    }
    Ok(())
}
