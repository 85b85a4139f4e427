//! The render worker: owns the renderer on its own thread, takes scene descriptions
//! from the UI over a channel, and publishes finished passes. Nothing renders on the
//! UI thread. Every change bumps the shared generation counter, so the pass under way
//! stops at its next tile, and the worker starts over with the new snapshot.
//!
//! After every change the window shows the instant preview first: the learned
//! preview on a coarse lattice and depth field (a quarter-resolution pass, then full
//! resolution; tens of milliseconds), then, unless a slider is being dragged, the
//! learned preview at its own resolution, refined for a few passes. The
//! scene's own render (path tracing or prediction) accumulates meanwhile and takes
//! over once its relative noise is below [`HANDOFF_NOISE`], so no grainy frame comes
//! between a change and the preview. A scene in preview mode refines its own preview.

use crate::scene::{PredictorCache, SceneFile};
use engine::{Buffer, Cancel, DensityGrid, Film, PassOutcome, RenderControl, Renderer, Scene};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What the UI asks for.
pub enum Command {
    /// Render this scene; `coarse` builds the cloud at a low resolution (a slider is
    /// being dragged).
    Render {
        scene: Box<SceneFile>,
        coarse: bool,
        /// The pointer is down (a slider or the view is being dragged): the coarse
        /// first look only, not the full learned preview (its lattice and depth field
        /// would hold the next change up).
        dragging: bool,
        generation: u64,
        /// Also render the path-traced reference of the same scene and k, a pass of
        /// each in turn (only when the scene is in prediction mode).
        compare: bool,
        /// When the render stops.
        target: RenderTarget,
    },
    /// A new target for the render under way (or finished): it goes on from the
    /// samples it has, or stops at once if it is already there.
    SetTarget(RenderTarget),
    Quit,
}

/// When a render is finished: never (it refines until the next change), at a number
/// of samples per pixel, or after a number of seconds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RenderTarget {
    Unlimited,
    Spp(u32),
    Seconds(f64),
}

impl RenderTarget {
    /// How far a render of `spp` samples per pixel after `secs` seconds is, 0 ..= 1;
    /// None without a target.
    pub fn progress(self, spp: u32, secs: f64) -> Option<f64> {
        match self {
            RenderTarget::Unlimited => None,
            RenderTarget::Spp(n) => Some((spp as f64 / n.max(1) as f64).min(1.0)),
            RenderTarget::Seconds(t) => Some((secs / t.max(1e-3)).min(1.0)),
        }
    }
}

/// The latest finished pass, for the UI.
#[derive(Clone)]
pub struct Published {
    pub generation: u64,
    pub film: Arc<Film>,
    pub render_secs: f64,
    /// Camera samples per second over this render.
    pub samples_per_sec: f64,
    /// Relative standard error of the full image over the cloud's pixels
    /// ([`engine::Film::cloud_noise`]); infinite below 2 spp, where it is not known.
    pub noise: f64,
    /// The cloud was built below the scene's resolution because a cloud slider is
    /// being dragged.
    pub coarse: bool,
    /// The integrator mode the film was rendered in (prediction falls back to path
    /// tracing when the model cannot be loaded).
    pub mode: engine::Mode,
    /// The film is the instant preview (the scene's own mode, or standing in).
    pub is_preview: bool,
    /// In compare mode: the path-traced reference (same scene, same k, its own seed),
    /// accumulating alongside `film`.
    pub reference: Option<Arc<Film>>,
    /// `film` is the instant preview standing in for the scene's own render: which
    /// preview ([`FIRST_LOOK`], "learned") and the relative noise the render under it has
    /// reached so far (None before its first pass).
    pub standing_in: Option<(&'static str, Option<f64>)>,
    /// The reference's noise in compare mode, as `noise`.
    pub reference_noise: Option<f64>,
    /// How far the render is toward its target (None without one).
    pub progress: Option<f64>,
    /// The render reached its target and stopped.
    pub done: bool,
}

/// The scene's own render replaces the preview once its relative noise is below this
/// (the 5 % of a preview in docs/conventions.md).
pub const HANDOFF_NOISE: f64 = 0.05;

/// Passes of the preview refined while the scene's render catches up; after them,
/// every pass goes to the render.
pub const PREVIEW_PASSES: u32 = 8;

/// The instant preview of a job, shown until the render is clean.
struct Standing {
    renderer: Renderer,
    which: &'static str,
    passes: u32,
    /// The learned preview's scene, built after the octave preview's first pass.
    learned: Option<Box<SceneFile>>,
}

/// A render under way: the scene's renderer and, in compare mode, the reference's.
struct Job {
    main: Renderer,
    reference: Option<Renderer>,
    generation: u64,
    start: Instant,
    /// The cloud is built below the scene's resolution.
    coarse_grid: bool,
    target: RenderTarget,
    /// When the target was reached: nothing more is rendered until a change or a new
    /// target.
    done: Option<Instant>,
    /// Prediction with a coarse depth field while the full one was not built yet:
    /// after the first pass the full field is built and the render starts over with it.
    upgrade: Option<Box<SceneFile>>,
    /// The preview standing in for `main` (None once `main` is shown).
    standing: Option<Standing>,
}

/// The preview of `file` with the higher orders by `which` ("octaves" or "learned"),
/// its fields at `nodes` (see [`SceneFile::integrator_cached`]); their builds stop when
/// `cancel` asks.
fn preview_renderer(
    file: &SceneFile,
    scene: Arc<Scene>,
    which: &str,
    nodes: u32,
    cache: &mut PredictorCache,
    cancel: Cancel,
) -> Result<Renderer, String> {
    let mut f = file.clone();
    f.render.mode = "preview".into();
    f.render.preview = which.into();
    let setup = f.integrator_cached(&scene, nodes, cache, cancel).map_err(|e| e.to_string())?;
    Renderer::new(scene, setup.integrator).map_err(|e| e.to_string())
}

/// Lattice nodes per axis of the first look after a change.
pub const FIRST_LOOK_LATTICE: u32 = 12;

/// At most this many lattice nodes per axis for the learned preview that stands in
/// while the scene's own render converges. A finer lattice (filled as the marches
/// read it; at the time measured, one node per voxel) makes its first passes' tiles heavy enough
/// that a change waits for them: `nimbus bench latency` read 20 - 60 ms more for every
/// kind of change at 128 than at 48. The stand-in is replaced by the render anyway;
/// a scene whose own render is the preview keeps its lattice.
pub const STAND_IN_LATTICE: u32 = 48;

/// Depth-field nodes per axis of the first look.
pub const FIRST_LOOK_FIELD: u32 = 16;

/// What the status bar calls the first look.
pub const FIRST_LOOK: &str = "learned, coarse";

/// Depth-field nodes per axis while a slider moves or before the full field is ready
/// (a few tens of milliseconds to build, against about a second for the full field).
pub const COARSE_FIELD_NODES: u32 = 24;

/// Builds the renderers of `scene` on `grid`: the scene's own and, in compare mode
/// with prediction, the path-traced reference (its own seed). Returns them with the
/// model's fallback warning, if any. The model's fields stop building when `cancel`
/// asks (a newer change): the worker then moves on to that change at once.
fn build_job(
    file: &SceneFile,
    scene: Arc<Scene>,
    nodes: u32,
    compare: bool,
    cache: &mut PredictorCache,
    cancel: Cancel,
) -> Result<(Renderer, Option<Renderer>, Option<String>), String> {
    let setup = file.integrator_cached(&scene, nodes, cache, cancel).map_err(|e| e.to_string())?;
    let predicting = matches!(setup.integrator.settings().mode, engine::Mode::Predict { .. });
    let reference = if compare && predicting {
        let mut rs = file.clone();
        rs.render.mode = "reference".into();
        rs.seed = rs.seed.wrapping_add(1);
        // BDPT's prediction splits the buffers at 2k + 1: the reference must too.
        rs.k = setup.integrator.high_order_start();
        let integ = rs.integrator_with(None).map_err(|e| e.to_string())?;
        Some(Renderer::new(scene.clone(), integ).map_err(|e| e.to_string())?)
    } else {
        None
    };
    let warning = crate::scene::density_warning(scene.medium.grid()).or(setup.warning);
    let r = Renderer::new(scene, setup.integrator).map_err(|e| e.to_string())?;
    Ok((r, reference, warning))
}

/// Shared between the worker and the UI.
#[derive(Default)]
pub struct Mailbox {
    pub latest: Option<Published>,
    pub error: Option<(u64, String)>,
    /// Set while a cloud is being rebuilt.
    pub building: bool,
    /// Films of earlier publications, for the worker's next copies ([`copy_film`]).
    spare: Vec<Arc<Film>>,
}

/// Films kept for reuse: a publication's film and reference.
const SPARE_FILMS: usize = 2;

impl Mailbox {
    /// Makes `p` the latest publication; the films it replaces are kept for
    /// [`copy_film`].
    fn publish(&mut self, p: Published) {
        if let Some(old) = self.latest.replace(p) {
            self.spare.push(old.film);
            self.spare.extend(old.reference);
            let excess = self.spare.len().saturating_sub(SPARE_FILMS);
            self.spare.drain(..excess);
        }
    }
}

/// A copy of `r`'s film to publish: into a film of an earlier publication that no one
/// holds any more where there is one (a 256x256 film is 12 MiB, and a copy allocated
/// per pass came back as page faults, one core idle while they were served), else
/// newly allocated.
fn copy_film(mailbox: &Mutex<Mailbox>, r: &Renderer) -> Arc<Film> {
    // Only the worker reaches the spares, so a count of one cannot rise again once
    // the lock is released.
    let free = {
        let mut mb = mailbox.lock().unwrap();
        mb.spare.iter().position(|f| Arc::strong_count(f) == 1).map(|i| mb.spare.swap_remove(i))
    };
    if let Some(mut film) = free {
        if let Some(f) = Arc::get_mut(&mut film) {
            r.snapshot_into(f);
            return film;
        }
    }
    Arc::new(r.snapshot())
}

/// Resolution used for the cloud while a slider moves.
pub const COARSE_RESOLUTION: u32 = 48;

pub fn spawn(
    rx: Receiver<Command>,
    control: Arc<RenderControl>,
    mailbox: Arc<Mutex<Mailbox>>,
    wake: impl Fn() + Send + 'static,
) -> std::thread::JoinHandle<()> {
    std::thread::Builder::new()
        .name("nimbus-render-worker".into())
        .spawn(move || run(rx, control, mailbox, wake))
        .expect("cannot start the render worker")
}

/// The relative noise of `film`'s full image; infinite below two samples per pixel,
/// where the variance is not known yet (and would read as 0, handing the view over to
/// a one-sample image).
fn relative_noise(film: &Film) -> f64 {
    if film.spp() < 2 { f64::INFINITY } else { film.cloud_noise(Buffer::Full) }
}

/// The relative noise of `r`'s film, read in place (no copy of the buffers).
fn film_noise(r: &Renderer) -> f64 {
    relative_noise(&r.film_handle().read().unwrap_or_else(|e| e.into_inner()))
}

fn run(rx: Receiver<Command>, control: Arc<RenderControl>, mailbox: Arc<Mutex<Mailbox>>, wake: impl Fn()) {
    // The last cloud built, keyed by its description, so camera or light changes do
    // not rebuild it.
    let mut cache: Option<(String, Arc<DensityGrid>)> = None;
    let mut job: Option<Job> = None;
    // The last model bound to a cloud and sun, so camera changes do not rebuild its
    // depth field.
    let mut predictors = PredictorCache::default();
    loop {
        // Take the newest command; block only when idle.
        let mut next = None;
        let mut retarget = None;
        loop {
            // A finished job waits like no job.
            let busy = job.as_ref().is_some_and(|j| j.done.is_none());
            let cmd = if busy || next.is_some() || retarget.is_some() {
                match rx.try_recv() {
                    Ok(c) => c,
                    Err(_) => break,
                }
            } else {
                match rx.recv_timeout(Duration::from_millis(200)) {
                    Ok(c) => c,
                    Err(RecvTimeoutError::Timeout) => continue,
                    Err(RecvTimeoutError::Disconnected) => return,
                }
            };
            match cmd {
                Command::Quit => return,
                c @ Command::Render { .. } => next = Some(c),
                Command::SetTarget(t) => retarget = Some(t),
            }
        }
        if let (Some(t), Some(j), None) = (retarget, &mut job, &next) {
            j.target = t;
            if let Some(at) = j.done {
                // Render time leaves the idle time out (a seconds target counts on);
                // a target already reached keeps the render finished.
                let secs = (at - j.start).as_secs_f64();
                if t.progress(j.main.spp(), secs).is_none_or(|p| p < 1.0) {
                    j.start += at.elapsed();
                    j.done = None;
                }
            }
        }
        if let Some(Command::Render { mut scene, coarse, dragging, generation, compare, target }) = next {
            job = None;
            let coarse_grid = coarse && scene.grid.resolution > COARSE_RESOLUTION;
            if coarse {
                scene.grid.resolution = scene.grid.resolution.min(COARSE_RESOLUTION);
            }
            let key = format!(
                "{:?}|{}",
                scene.grid,
                scene.base_dir.as_ref().map(|d| d.display().to_string()).unwrap_or_default()
            );
            let grid = match &cache {
                Some((k, g)) if *k == key => Ok(g.clone()),
                _ => {
                    mailbox.lock().unwrap().building = true;
                    wake();
                    let g = scene.build_grid().map(Arc::new);
                    mailbox.lock().unwrap().building = false;
                    if let Ok(g) = &g {
                        cache = Some((key, g.clone()));
                    }
                    g
                }
            };
            // The full depth field if it is cached (camera, k, p changes), else a coarse
            // one now and the full one after the first pass.
            let full_nodes = models::global::depth_field::DEFAULT_MAX_NODES;
            let mut upgrade = None;
            let start = Instant::now();
            let mut standing = None;
            let built = grid.map_err(|e| e.to_string()).and_then(|g| {
                let built = Arc::new(scene.build_scene(Some(g)).map_err(|e| e.to_string())?);
                // The instant preview first, before the render's own set-up (not in
                // compare mode, where the two estimates themselves are the point, nor
                // for a preview scene whose own render is the octaves).
                let own = (scene.render.mode == "preview").then(|| scene.render.preview.clone());
                let comparing = compare && scene.render.mode == "predict";
                if !comparing && own.as_deref() != Some("octaves") {
                    // The learned preview on a coarse lattice and depth field (tens of
                    // milliseconds): near the render's brightness from the first
                    // frame, where the octaves at their default constants are several
                    // times too dark (docs/evaluation.md).
                    let mut first = (*scene).clone();
                    first.render.preview_nodes = Some(FIRST_LOOK_LATTICE);
                    let quick = preview_renderer(
                        &first,
                        built.clone(),
                        "learned",
                        FIRST_LOOK_FIELD,
                        &mut predictors,
                        Cancel::on(&control, generation),
                    );
                    if let Ok(pr) = quick {
                        // A first look at a quarter of the resolution (a few ms), then
                        // the full one in the loop.
                        if let Some(film) = quarter_pass(&pr, &control, generation) {
                            let which = Some((FIRST_LOOK, None));
                            publish_film(&mailbox, generation, Arc::new(film), &pr, which, start, coarse_grid);
                            wake();
                        }
                        // The learned preview follows unless a slider is moving or it
                        // is the scene's own render anyway.
                        let learned = (!dragging && own.is_none()).then(|| scene.clone());
                        standing = Some(Standing { renderer: pr, which: FIRST_LOOK, passes: 0, learned });
                    }
                }
                // (The point-to-point model of BDPT prediction has no depth field.)
                let nodes = if coarse || dragging || scene.render.mode != "predict" || scene.render.integrator == "bdpt"
                {
                    COARSE_FIELD_NODES
                } else if predictors.has(&scene, &built, full_nodes) {
                    full_nodes
                } else {
                    upgrade = Some(scene.clone());
                    COARSE_FIELD_NODES
                };
                build_job(&scene, built, nodes, compare, &mut predictors, Cancel::on(&control, generation))
            });
            match built {
                Ok((r, reference, warning)) => {
                    mailbox.lock().unwrap().error = warning.map(|w| (generation, w));
                    job = Some(Job {
                        main: r,
                        reference,
                        generation,
                        start,
                        coarse_grid,
                        target,
                        done: None,
                        upgrade,
                        standing,
                    });
                }
                // A set-up cut short by a newer change: that change is next.
                Err(_) if control.should_abort(generation) => {}
                Err(e) => {
                    mailbox.lock().unwrap().error = Some((generation, e));
                    wake();
                }
            }
            continue;
        }
        let Some(j) = &mut job else { continue };
        if j.done.is_some() {
            continue;
        }
        if control.generation() != j.generation {
            job = None; // a newer command is on its way
            continue;
        }
        if let Some(st) = &mut j.standing {
            if st.passes >= 1 && st.learned.is_some() {
                // The full learned preview replaces the first look after its first pass
                // (its lattice is built once for this cloud, sun and camera).
                let mut file = st.learned.take().expect("checked");
                file.render.preview_nodes =
                    Some(file.render.preview_nodes.unwrap_or(STAND_IN_LATTICE).min(STAND_IN_LATTICE));
                let full = models::global::depth_field::DEFAULT_MAX_NODES;
                let cancel = Cancel::on(&control, j.generation);
                if let Ok(r) = preview_renderer(&file, j.main.scene().clone(), "learned", full, &mut predictors, cancel)
                {
                    if control.generation() != j.generation {
                        continue;
                    }
                    (st.renderer, st.which, st.passes) = (r, "learned", 0);
                }
            }
            if st.passes < PREVIEW_PASSES {
                if st.renderer.render_pass(&control, j.generation) != PassOutcome::Completed {
                    continue;
                }
                st.passes += 1;
                let under = Some(film_noise(&j.main)).filter(|n| n.is_finite());
                publish_preview(&mailbox, j.generation, &st.renderer, st.which, under, j.start, j.coarse_grid);
                wake();
            }
        }
        if j.main.render_pass(&control, j.generation) != PassOutcome::Completed {
            continue;
        }
        if let Some(scene) = j.upgrade.take() {
            // The coarse field's image is on screen; build the full field and start over.
            let built = j.main.scene().clone();
            let compare = j.reference.is_some();
            let (full, cancel) = (models::global::depth_field::DEFAULT_MAX_NODES, Cancel::on(&control, j.generation));
            if let Ok((r, reference, _)) = build_job(&scene, built, full, compare, &mut predictors, cancel) {
                if control.generation() == j.generation {
                    (j.main, j.reference, j.start) = (r, reference, Instant::now());
                    continue;
                }
            }
        }
        if let Some(r) = &mut j.reference {
            if r.render_pass(&control, j.generation) != PassOutcome::Completed {
                continue;
            }
        }
        let noise = film_noise(&j.main);
        let secs = j.start.elapsed().as_secs_f64();
        let spp = j.main.spp();
        let progress = j.target.progress(spp, secs);
        let done = progress.is_some_and(|p| p >= 1.0);
        if let Some(st) = &j.standing {
            // At its target the render is shown whatever its noise: it is what was asked for.
            if noise > HANDOFF_NOISE && !done {
                // The preview stays on screen; once it is no longer refined, say how
                // far the render under it is.
                if st.passes >= PREVIEW_PASSES {
                    if let Some(p) = mailbox.lock().unwrap().latest.as_mut().filter(|p| p.generation == j.generation) {
                        p.standing_in = p.standing_in.map(|(which, _)| (which, Some(noise)));
                    }
                    wake();
                }
                continue;
            }
            j.standing = None;
        }
        let film = copy_film(&mailbox, &j.main);
        // Both renders' camera samples in compare mode.
        let passes = film.spp() as f64 * if j.reference.is_some() { 2.0 } else { 1.0 };
        let published = Published {
            generation: j.generation,
            samples_per_sec: passes * film.pixel_count() as f64 / secs.max(1e-9),
            noise,
            render_secs: secs,
            film,
            coarse: j.coarse_grid,
            mode: j.main.integrator().settings().mode,
            is_preview: is_preview(&j.main),
            reference_noise: j.reference.as_ref().map(film_noise),
            reference: j.reference.as_ref().map(|r| copy_film(&mailbox, r)),
            standing_in: None,
            progress,
            done,
        };
        mailbox.lock().unwrap().publish(published);
        wake();
        if done {
            // Finished: idle until the next change or a new target, keeping the film.
            if let Some(j) = &mut job {
                j.done = Some(Instant::now());
            }
        }
    }
}

/// Publishes the preview `r` as the image standing in for the render.
fn publish_preview(
    mailbox: &Mutex<Mailbox>,
    generation: u64,
    r: &Renderer,
    which: &'static str,
    under: Option<f64>,
    start: Instant,
    coarse: bool,
) {
    publish_film(mailbox, generation, copy_film(mailbox, r), r, Some((which, under)), start, coarse);
}

/// One pass of `full`'s scene at a quarter of its resolution (None if the image is
/// already small, or the pass was cancelled).
fn quarter_pass(full: &Renderer, control: &RenderControl, generation: u64) -> Option<Film> {
    let cam = full.scene().camera;
    if cam.width() < 128 || cam.height() < 128 {
        return None;
    }
    let small = cam.with_resolution(cam.width() / 4, cam.height() / 4).ok()?;
    let scene = engine::Scene { camera: small, ..(**full.scene()).clone() };
    let mut r = Renderer::new(Arc::new(scene), full.integrator().clone()).ok()?;
    (r.render_pass(control, generation) == PassOutcome::Completed).then(|| r.snapshot())
}

/// Publishes `film`, rendered by `r`'s integrator.
fn publish_film(
    mailbox: &Mutex<Mailbox>,
    generation: u64,
    film: Arc<Film>,
    r: &Renderer,
    standing_in: Option<(&'static str, Option<f64>)>,
    start: Instant,
    coarse: bool,
) {
    let secs = start.elapsed().as_secs_f64();
    mailbox.lock().unwrap().publish(Published {
        generation,
        samples_per_sec: film.spp() as f64 * film.pixel_count() as f64 / secs.max(1e-9),
        noise: relative_noise(&film),
        render_secs: secs,
        film,
        coarse,
        mode: r.integrator().settings().mode,
        is_preview: is_preview(r),
        reference: None,
        standing_in,
        reference_noise: None,
        progress: None,
        done: false,
    });
}

fn is_preview(r: &Renderer) -> bool {
    matches!(r.integrator().technique(), engine::integrator::Technique::Preview)
}

/// The UI's handle on the worker.
pub struct WorkerHandle {
    pub tx: Sender<Command>,
    pub control: Arc<RenderControl>,
    pub mailbox: Arc<Mutex<Mailbox>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl WorkerHandle {
    pub fn start(wake: impl Fn() + Send + 'static) -> Self {
        let (tx, rx) = std::sync::mpsc::channel();
        let control = Arc::new(RenderControl::new());
        let mailbox = Arc::new(Mutex::new(Mailbox::default()));
        let thread = spawn(rx, control.clone(), mailbox.clone(), wake);
        WorkerHandle { tx, control, mailbox, thread: Some(thread) }
    }

    /// Asks for a new render; the pass under way is abandoned.
    pub fn render(&self, scene: &SceneFile, coarse: bool) -> u64 {
        self.render_with(scene, coarse, coarse, false, RenderTarget::Unlimited)
    }

    /// [`WorkerHandle::render`], with the cloud coarse (`coarse`) and the learned
    /// preview left out (`dragging`) as asked, the path-traced reference alongside
    /// when `compare` is set and the scene is in prediction mode, until `target`.
    /// Changes the target of the render under way without starting it over.
    pub fn set_target(&self, target: RenderTarget) {
        let _ = self.tx.send(Command::SetTarget(target));
    }

    pub fn render_with(
        &self,
        scene: &SceneFile,
        coarse: bool,
        dragging: bool,
        compare: bool,
        target: RenderTarget,
    ) -> u64 {
        let generation = self.control.bump();
        let scene = Box::new(scene.clone());
        let _ = self.tx.send(Command::Render { scene, coarse, dragging, generation, compare, target });
        generation
    }
}

impl Drop for WorkerHandle {
    fn drop(&mut self) {
        self.control.bump();
        let _ = self.tx.send(Command::Quit);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn renderer() -> Renderer {
        let grid = engine::DensityGrid::from_fn(
            glam::UVec3::splat(8),
            engine::Bounds3::new(glam::Vec3::splat(-0.5), glam::Vec3::splat(0.5)),
            |p| if p.length() < 0.4 { 1.0 } else { 0.0 },
        )
        .unwrap();
        let medium = engine::Medium::new(Arc::new(grid), 10.0, 1.0, engine::PhaseFunction::Isotropic).unwrap();
        let camera =
            engine::Camera::new(glam::Vec3::new(0.0, 0.0, 3.0), glam::Vec3::ZERO, glam::Vec3::Y, 30.0, 16, 16).unwrap();
        let sun = engine::Sun::new(glam::Vec3::NEG_Y, glam::Vec3::ONE, 0.0).unwrap();
        let scene = engine::Scene { camera, medium, sun: Some(sun), sky: engine::Sky::default() };
        Renderer::new(Arc::new(scene), engine::Integrator::new(Default::default(), None).unwrap()).unwrap()
    }

    fn published(film: Arc<Film>) -> Published {
        Published {
            generation: 0,
            film,
            render_secs: 0.0,
            samples_per_sec: 0.0,
            noise: 0.0,
            coarse: false,
            mode: engine::Mode::Reference,
            is_preview: false,
            reference: None,
            standing_in: None,
            reference_noise: None,
            progress: None,
            done: false,
        }
    }

    /// A published film that no one holds any more receives the next copy in its own
    /// memory; one the viewer still holds is left alone and a new film is made.
    #[test]
    fn copies_reuse_the_films_the_viewer_let_go() {
        let mut r = renderer();
        r.render_pass(&RenderControl::new(), 0);
        let mailbox = Mutex::new(Mailbox::default());
        let first = copy_film(&mailbox, &r);
        let first_ptr = Arc::as_ptr(&first);
        mailbox.lock().unwrap().publish(published(first));
        // Held by the viewer: the next copy is a new film.
        let held = mailbox.lock().unwrap().latest.as_ref().unwrap().film.clone();
        let second = copy_film(&mailbox, &r);
        assert_ne!(Arc::as_ptr(&second), first_ptr);
        mailbox.lock().unwrap().publish(published(second));
        drop(held);
        // The first film, replaced and let go, takes the next copy, equal to the
        // renderer's film.
        r.render_pass(&RenderControl::new(), 0);
        let third = copy_film(&mailbox, &r);
        assert_eq!(Arc::as_ptr(&third), first_ptr);
        let now = r.snapshot();
        assert_eq!(third.spp(), 2);
        assert!(third.sums(Buffer::Full) == now.sums(Buffer::Full));
        assert!(mailbox.lock().unwrap().spare.len() <= SPARE_FILMS);
    }
}
