//! Bad and hostile input through the command line and the renderer: every run ends,
//! stops when asked within a bounded time, says what is wrong (once, naming the file)
//! and exits with an error when the request cannot be honoured.

use app::cli::{Cli, run};
use clap::Parser;
use engine::{Bounds3, DensityGrid, Integrator, Medium, PassOutcome, PhaseFunction, RenderControl, Renderer};
use glam::{UVec3, Vec3};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn nimbus(args: &[&str]) -> anyhow::Result<()> {
    let mut argv = vec!["nimbus"];
    argv.extend_from_slice(args);
    run(Cli::try_parse_from(argv)?)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The error as `nimbus` prints it (the whole chain).
fn message(r: anyhow::Result<()>) -> String {
    format!("{:#}", r.expect_err("the command should have failed"))
}

/// A 16^3 grid of 0.5 with one voxel of `spike`.
fn spike_grid(spike: f32) -> DensityGrid {
    let n = 16u32;
    let mut data = vec![0.5f32; (n * n * n) as usize];
    data[(8 + n * (8 + n * 8)) as usize] = spike;
    DensityGrid::from_bounds(UVec3::splat(n), data, Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5))).unwrap()
}

/// Runs `f` on its own thread and waits at most `limit` for it: a hang fails the test
/// instead of stalling the suite.
fn within<T: Send + 'static>(limit: Duration, what: &str, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(limit).unwrap_or_else(|_| panic!("{what} did not finish within {limit:?}"))
}

/// A VDB with one voxel of 1e30 (and one of the largest float) among 0.5s renders
/// through the CLI in bounded time (it rendered forever before the extinction cap)
/// and warns about the density.
#[test]
fn a_density_spike_renders_and_ends() {
    let dir = tempfile::tempdir().unwrap();
    for (i, spike) in [1e30f32, f32::MAX].into_iter().enumerate() {
        let vdb = dir.path().join(format!("spike{i}.vdb"));
        std::fs::write(&vdb, modeler::vdb::vdb_bytes(&spike_grid(spike), "density").unwrap()).unwrap();
        let grid = modeler::vdb::read_vdb(&vdb, None).unwrap().grid;
        let w = app::scene::density_warning(&grid).expect("a density of 1e30 draws a warning");
        assert!(w.contains("e30") || w.contains("e38"), "{w}");
        let scene = dir.path().join(format!("spike{i}.toml"));
        std::fs::write(&scene, format!("[grid]\nfile = \"{}\"\n[camera]\nwidth = 16\nheight = 16\n", s(&vdb))).unwrap();
        let exr = dir.path().join(format!("spike{i}.exr"));
        let args: Vec<String> =
            ["render", s(&scene), "--spp", "2", "--out", s(&exr), "--quiet"].iter().map(|a| a.to_string()).collect();
        let r = within(Duration::from_secs(120), "a render of the spike", move || {
            nimbus(&args.iter().map(String::as_str).collect::<Vec<_>>()).map_err(|e| e.to_string())
        });
        r.unwrap();
        let (_, _, layers) = app::output::read_exr(&exr).unwrap();
        assert!(layers.iter().all(|l| l.rgb.iter().all(|p| p.iter().all(|v| v.is_finite()))));
    }
    // Ordinary clouds draw no warning.
    assert!(app::scene::density_warning(&spike_grid(0.9)).is_none());
}

/// A stop request is honoured within a row of samples, also inside a pass through
/// the spike: the pass is abandoned (not half-added) well within the stated bound of
/// one second, where a pass of this scene takes several.
#[test]
fn a_stop_acts_within_a_pass() {
    let grid = Arc::new(spike_grid(1e30));
    let medium = Medium::new(grid, 400.0, 1.0, PhaseFunction::HenyeyGreenstein { g: 0.9 }).unwrap();
    let sun = engine::Sun::new(Vec3::new(0.0, -1.0, 0.0), Vec3::ONE, 0.0).unwrap();
    let camera = engine::Camera::new(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 25.0, 256, 256).unwrap();
    let scene = Arc::new(engine::Scene { medium, sun: Some(sun), sky: engine::Sky::default(), camera });
    let integrator = Integrator::new(Default::default(), None).unwrap();
    let mut renderer = Renderer::new(scene, integrator).unwrap();
    let control = Arc::new(RenderControl::new());
    let c = control.clone();
    let stopper = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(300));
        let t = Instant::now();
        c.request_stop();
        t
    });
    let generation = control.generation();
    let (outcome, ended) = within(Duration::from_secs(120), "a stopped pass", move || {
        let outcome = renderer.render_pass(&control, generation);
        (outcome, Instant::now())
    });
    let asked = stopper.join().unwrap();
    // A pass that finished before the request says nothing about the bound.
    if outcome == PassOutcome::Cancelled {
        let latency = ended.saturating_duration_since(asked);
        assert!(latency < Duration::from_secs(1), "the pass stopped {latency:?} after the request");
    }
    assert_eq!(outcome, PassOutcome::Cancelled, "the scene is meant to take longer than 300 ms per pass");
}

/// A model named on the command line that cannot be loaded is an error naming the
/// file (the render does not fall back to path tracing and exit 0).
#[test]
fn an_explicit_model_that_cannot_load_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(&scene, "[grid]\nbuiltin = \"sphere\"\nresolution = 16\n[camera]\nwidth = 8\nheight = 8\n").unwrap();
    let exr = dir.path().join("o.exr");
    let missing = dir.path().join("nope.safetensors");
    for flag in ["--model", "--p2p-model"] {
        let e = message(nimbus(&[
            "render",
            s(&scene),
            "--spp",
            "1",
            "--predict",
            "1",
            flag,
            s(&missing),
            "--out",
            s(&exr),
        ]));
        assert!(e.contains(flag) && e.contains("nope"), "{e}");
    }
    assert!(!exr.exists());
}

/// Bad output settings are refused before rendering: a non-finite exposure, an EXR
/// path that does not end in .exr, a PNG path that does not end in .png.
#[test]
fn bad_output_settings_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(&scene, "[grid]\nbuiltin = \"sphere\"\nresolution = 16\n[camera]\nwidth = 8\nheight = 8\n").unwrap();
    let (exr, png) = (dir.path().join("o.exr"), dir.path().join("o.png"));
    let e = message(nimbus(&["render", s(&scene), "--exposure", "nan", "--out", s(&exr), "--png", s(&png)]));
    assert!(e.contains("--exposure"), "{e}");
    let e = message(nimbus(&["render", s(&scene), "--out", s(&png)]));
    assert!(e.contains("--out") && e.contains(".exr"), "{e}");
    let e = message(nimbus(&["render", s(&scene), "--out", s(&exr), "--png", s(&exr)]));
    assert!(e.contains("--png") && e.contains(".png"), "{e}");
    assert!(!exr.exists() && !png.exists());
}

/// Messages name the file and say each thing once: a missing scene, a VDB given to
/// `nimbus model`, an output directory that cannot be made (mitsuba, train), a
/// damaged data-set chunk.
#[test]
fn messages_name_the_file_once() {
    let dir = tempfile::tempdir().unwrap();
    let once = |e: &str, what: &str| assert_eq!(e.matches(what).count(), 1, "{what:?} should appear once in: {e}");
    let missing = dir.path().join("missing.toml");
    let e = message(nimbus(&["render", s(&missing), "--out", s(&dir.path().join("o.exr"))]));
    assert!(e.contains("missing.toml"), "{e}");
    once(&e, "No such file or directory");

    let vdb = dir.path().join("cloud.vdb");
    std::fs::write(&vdb, modeler::vdb::vdb_bytes(&spike_grid(0.5), "density").unwrap()).unwrap();
    let e = message(nimbus(&["model", s(&vdb), "--res", "8", "--out", s(&dir.path().join("m.vdb"))]));
    assert!(e.contains("cloud.vdb") && e.contains("VDB") && !e.contains("UTF-8"), "{e}");

    // A regular file where a directory should be: nothing can be made below it.
    let blocker = dir.path().join("file");
    std::fs::write(&blocker, b"x").unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(&scene, "[grid]\nbuiltin = \"sphere\"\nresolution = 8\n").unwrap();
    let out = blocker.join("mitsuba");
    let e = message(nimbus(&["mitsuba", s(&scene), "--out", s(&out)]));
    assert!(e.contains(s(&out)), "{e}");

    // A small data set with one of its chunks damaged, merged again; then trained
    // into a directory that cannot be made.
    let data = dir.path().join("data");
    nimbus(&[
        "datagen",
        "global",
        "--points",
        "24",
        "--sigma",
        "1..5",
        "--n-dirs",
        "4",
        "--max-rel-error",
        "0.5",
        "--chunk-size",
        "8",
        "--out",
        s(&data),
        "--quiet",
    ])
    .unwrap();
    let chunk = models::dataset::chunk_path(&data, 0);
    let (shape, mut values) = models::dataset::npy::read_f32(&chunk).unwrap();
    values[3] = f32::NAN;
    models::dataset::npy::write_f32(&chunk, &shape, &values).unwrap();
    let e = message(nimbus(&["datagen", "merge", s(&data), "--out", s(&dir.path().join("merged"))]));
    assert!(e.contains("not finite"), "{e}");
    once(&e, "chunk-000000.npy");
    let complete = data;
    let model = blocker.join("models").join("m");
    let e = message(nimbus(&[
        "train",
        "global",
        s(&complete),
        "--epochs",
        "1",
        "--hidden",
        "4",
        "--out",
        s(&model),
        "--quiet",
    ]));
    assert!(e.contains(s(&blocker)), "{e}");
}
