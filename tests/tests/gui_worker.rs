//! The window's render worker, without a window: scenes go in over the channel,
//! finished passes come out, a change abandons the old render, and a scene that
//! cannot be built shows up as an error message, not a crash.

use app::gui::worker::WorkerHandle;
use app::scene::SceneFile;
use std::time::{Duration, Instant};

fn small_scene(rho: f32) -> SceneFile {
    let mut s = SceneFile::from_toml_str(
        "[grid]\nbuiltin = \"cumulus\"\nresolution = 24\n[camera]\nwidth = 24\nheight = 16\n",
        "t",
    )
    .unwrap();
    s.medium.rho = rho;
    s
}

fn wait_for(mut done: impl FnMut() -> bool) {
    let start = Instant::now();
    while !done() {
        assert!(start.elapsed() < Duration::from_secs(60), "worker did not answer");
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn worker_renders_restarts_and_reports_errors() {
    let worker = WorkerHandle::start(|| {});
    let g1 = worker.render(&small_scene(10.0), false);
    wait_for(|| {
        worker.mailbox.lock().unwrap().latest.as_ref().is_some_and(|p| p.generation == g1 && p.film.spp() >= 3)
    });
    let first = worker.mailbox.lock().unwrap().latest.clone().unwrap();
    assert_eq!((first.film.width(), first.film.height()), (24, 16));
    assert!(first.samples_per_sec > 0.0 && first.noise.is_finite());

    // A change: the new generation replaces the old and starts from zero samples.
    // (Coarse while dragging: 64^3 is built at 48^3, and the image says so.)
    let mut s2 = small_scene(30.0);
    s2.grid.resolution = 64;
    let g2 = worker.render(&s2, true);
    assert!(g2 > g1);
    wait_for(|| worker.mailbox.lock().unwrap().latest.as_ref().is_some_and(|p| p.generation == g2));
    let second = worker.mailbox.lock().unwrap().latest.clone().unwrap();
    assert!(second.coarse);
    assert!(second.film.spp() >= 1);

    // A scene whose cloud cannot be loaded: an error naming the file, no crash, and
    // the worker keeps serving.
    let mut bad = small_scene(10.0);
    bad.grid.builtin = None;
    bad.grid.file = Some("/nonexistent/cloud.vdb".into());
    let g3 = worker.render(&bad, false);
    wait_for(|| worker.mailbox.lock().unwrap().error.as_ref().is_some_and(|(g, _)| *g == g3));
    let msg = worker.mailbox.lock().unwrap().error.clone().unwrap().1;
    assert!(msg.contains("/nonexistent/cloud.vdb"), "{msg}");
    let g4 = worker.render(&small_scene(5.0), false);
    wait_for(|| worker.mailbox.lock().unwrap().latest.as_ref().is_some_and(|p| p.generation == g4));
}

/// Compare mode: the path-traced reference of the same scene and k accumulates next to
/// the prediction, with its own seed; without compare, or in reference mode, there is
/// no second render.
#[test]
fn compare_mode_renders_the_reference_alongside() {
    let worker = WorkerHandle::start(|| {});
    let mut s = small_scene(10.0);
    s.render.mode = "predict".into();
    s.k = 2;
    let g = worker.render_with(&s, false, false, true, app::gui::worker::RenderTarget::Unlimited);
    let done = |g: u64| {
        move |w: &WorkerHandle| {
            w.mailbox.lock().unwrap().latest.as_ref().is_some_and(|p| {
                p.generation == g && p.film.spp() >= 3 && p.reference.as_ref().is_some_and(|r| r.spp() >= 3)
            })
        }
    };
    wait_for(|| done(g)(&worker));
    let p = worker.mailbox.lock().unwrap().latest.clone().unwrap();
    let r = p.reference.clone().unwrap();
    assert_eq!((r.width(), r.height()), (p.film.width(), p.film.height()));
    assert!(r.average(engine::Buffer::High) > 0.0 && p.film.average(engine::Buffer::High) > 0.0);
    assert!(r.sums(engine::Buffer::Full) != p.film.sums(engine::Buffer::Full), "two different estimators");
    for (mode, compare) in [("predict", false), ("reference", true)] {
        s.render.mode = mode.into();
        let g = worker.render_with(&s, false, false, compare, app::gui::worker::RenderTarget::Unlimited);
        wait_for(|| {
            worker.mailbox.lock().unwrap().latest.as_ref().is_some_and(|p| p.generation == g && p.film.spp() >= 2)
        });
        assert!(worker.mailbox.lock().unwrap().latest.as_ref().unwrap().reference.is_none(), "{mode} {compare}");
    }
}

/// What the worker shows for generation `g` until the scene's own render takes over:
/// each change of which preview stands in (None: the render itself), with the noise of
/// the image at that moment.
fn shown_until_handoff(worker: &WorkerHandle, g: u64) -> Vec<(Option<&'static str>, f64)> {
    let mut seen: Vec<(Option<&'static str>, f64)> = vec![];
    let start = Instant::now();
    loop {
        let p = worker.mailbox.lock().unwrap().latest.clone();
        if let Some(p) = p.filter(|p| p.generation == g) {
            let which = p.standing_in.map(|(w, _)| w);
            if seen.last().is_none_or(|(w, _)| *w != which) {
                seen.push((which, p.noise));
            }
            if which.is_none() {
                return seen;
            }
        }
        assert!(start.elapsed() < Duration::from_secs(60), "no hand-off: {seen:?}");
        std::thread::sleep(Duration::from_micros(200));
    }
}

/// After a change the instant preview comes first (the learned one on a coarse
/// lattice, then at its own resolution),
/// and the scene's own render takes over only once its noise is below the hand-off
/// level: no image between the change and the preview, and no grainy one after it.
/// While a slider is dragged, the coarse one alone stands in; in compare mode, nothing.
#[test]
fn the_preview_stands_in_until_the_render_is_clean() {
    use app::gui::worker::{FIRST_LOOK, HANDOFF_NOISE};
    let worker = WorkerHandle::start(|| {});
    let mut s = small_scene(10.0);
    s.render.mode = "predict".into();
    let seen = shown_until_handoff(&worker, worker.render(&s, false));
    let order: Vec<_> = seen.iter().map(|(w, _)| *w).collect();
    assert_eq!(order, [Some(FIRST_LOOK), Some("learned"), None], "{seen:?}");
    let (_, handed) = seen.last().unwrap();
    assert!(*handed <= HANDOFF_NOISE, "the render took over at {handed} noise");

    s.medium.rho = 12.0;
    let seen = shown_until_handoff(&worker, worker.render(&s, true));
    let order: Vec<_> = seen.iter().map(|(w, _)| *w).collect();
    assert_eq!(order, [Some(FIRST_LOOK), None], "{seen:?}");

    let g = worker.render_with(&s, false, false, true, app::gui::worker::RenderTarget::Unlimited);
    wait_for(|| worker.mailbox.lock().unwrap().latest.as_ref().is_some_and(|p| p.generation == g));
    assert!(worker.mailbox.lock().unwrap().latest.as_ref().unwrap().standing_in.is_none());
}
