//! The `nimbus render` command end to end: scene file in, EXR and PNG out, and the
//! errors a user sees for bad input.

use app::cli::{Cli, run};
use app::output::read_exr;
use clap::Parser;
use std::path::Path;

/// A fresh directory, removed with the returned guard.
fn temp_dir(_name: &str) -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

fn nimbus(args: &[&str]) -> anyhow::Result<()> {
    let mut argv = vec!["nimbus"];
    argv.extend_from_slice(args);
    run(Cli::try_parse_from(argv)?)
}

const SCENE: &str = r#"
seed = 3
k = 2
[grid]
builtin = "cumulus"
resolution = 24
[medium]
rho = 15.0
[sky]
radiance = 0.05
[camera]
preset = "toplit"
width = 24
height = 16
"#;

#[test]
fn render_writes_layered_exr_and_png() {
    let guard = temp_dir("render");
    let dir = guard.path().to_path_buf();
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, SCENE).unwrap();
    let (exr, png) = (dir.join("out.exr"), dir.join("out.png"));
    nimbus(&["render", s(&scene), "--spp", "4", "--out", s(&exr), "--png", s(&png), "--quiet"]).unwrap();

    let (w, h, layers) = read_exr(&exr).unwrap();
    assert_eq!((w, h), (24, 16));
    let layer = |n: &str| &layers.iter().find(|l| l.name == n).unwrap_or_else(|| panic!("no layer {n}")).rgb;
    let (full, direct, low, high, var) =
        (layer("full"), layer("direct"), layer("low"), layer("high"), layer("variance"));
    for i in 0..full.len() {
        for c in 0..3 {
            assert!(full[i][c].is_finite() && var[i][c] >= 0.0);
            let sum = direct[i][c] + low[i][c] + high[i][c];
            assert!((sum - full[i][c]).abs() <= 1e-5 * full[i][c].max(1e-3));
        }
    }
    // The sky shows around the cloud, the cloud scatters light.
    assert!((full[0][0] - 0.05).abs() < 1e-6, "corner sees the sky: {:?}", full[0]);
    assert!(high.iter().any(|p| p[0] > 0.0) && low.iter().any(|p| p[0] > 0.0));
    let png_bytes = std::fs::read(&png).unwrap();
    assert_eq!(&png_bytes[..8], b"\x89PNG\r\n\x1a\n");
    // No temporaries left behind.
    let names: Vec<String> =
        std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");

    // OpenEXR's own tools read it (CI installs them; elsewhere the check is skipped).
    match std::process::Command::new("exrheader").arg(&exr).output() {
        Ok(out) => {
            let text = String::from_utf8_lossy(&out.stdout);
            assert!(out.status.success(), "exrheader failed: {text}");
            for ch in ["full.R", "low.G", "high.B", "direct.R", "variance.R"] {
                assert!(text.contains(ch), "exrheader does not list {ch}:\n{text}");
            }
        }
        Err(_) => assert!(std::env::var_os("CI").is_none(), "CI must install exrheader (Debian package openexr)"),
    }
}

#[test]
fn bad_input_gives_clear_messages() {
    let guard = temp_dir("bad");
    let dir = guard.path().to_path_buf();
    let out = dir.join("x.exr");
    let missing = dir.join("nope.toml");
    let e = nimbus(&["render", s(&missing), "--out", s(&out)]).unwrap_err();
    assert!(format!("{e:#}").contains("nope.toml"), "{e:#}");

    let bad_key = dir.join("bad_key.toml");
    std::fs::write(&bad_key, "[grid]\nbuiltin = \"cumulus\"\n[medium]\nrhoo = 3\n").unwrap();
    let e = format!("{:#}", nimbus(&["render", s(&bad_key), "--out", s(&out)]).unwrap_err());
    assert!(e.contains("rhoo") && e.contains("bad_key.toml"), "{e}");

    let bad_range = dir.join("bad_range.toml");
    std::fs::write(&bad_range, "[grid]\nbuiltin = \"cumulus\"\n[medium]\nalbedo = 2\n").unwrap();
    let e = format!("{:#}", nimbus(&["render", s(&bad_range), "--out", s(&out)]).unwrap_err());
    assert!(e.contains("medium.albedo = 2 is out of range: 0 ..= 1"), "{e}");

    // A BDPT prediction option out of range is named (here before any rendering).
    let ok = dir.join("ok.toml");
    std::fs::write(&ok, "[grid]\nbuiltin = \"sphere\"\nresolution = 16\n[camera]\nwidth = 8\nheight = 8\n").unwrap();
    let e = format!(
        "{:#}",
        nimbus(&[
            "render",
            s(&ok),
            "--integrator",
            "bdpt",
            "--predict",
            "1",
            "--extension-samples",
            "0",
            "--spp",
            "1",
            "--out",
            s(&out)
        ])
        .unwrap_err()
    );
    assert!(e.contains("extension_samples") || e.contains("extension samples"), "{e}");

    let garbage = dir.join("garbage.toml");
    std::fs::write(&garbage, [0xffu8, 0xfe, 0x00, 0x12]).unwrap();
    assert!(nimbus(&["render", s(&garbage), "--out", s(&out)]).is_err());
    assert!(!out.exists(), "nothing written on error");
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A scene can take its cloud from a VDB file next to it; `nimbus model` writes one.
#[test]
fn vdb_cloud_round_trip_through_the_cli() {
    let guard = temp_dir("vdb");
    let dir = guard.path().to_path_buf();
    let vdb = dir.join("cloud.vdb");
    nimbus(&["model", "scene-a", "--res", "24", "--out", s(&vdb)]).unwrap();
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, "[grid]\nfile = \"cloud.vdb\"\n[medium]\nrho = 10.0\n[camera]\nwidth = 16\nheight = 16\n")
        .unwrap();
    let exr = dir.join("out.exr");
    nimbus(&["render", s(&scene), "--spp", "2", "--out", s(&exr), "--quiet"]).unwrap();
    let (_, _, layers) = read_exr(&exr).unwrap();
    assert!(layers.iter().find(|l| l.name == "full").unwrap().rgb.iter().any(|p| p[0] > 0.0));

    // A VDB written by OpenVDB with 16-bit half floats (blosc) renders; a damaged one is
    // refused with the file and the reason.
    let half = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../modeler/tests/data/vdb/half_float.vdb");
    let cloud = |file: &Path| {
        format!("[grid]\nfile = \"{}\"\n[medium]\nrho = 10.0\n[camera]\nwidth = 16\nheight = 16\n", file.display())
    };
    std::fs::write(&scene, cloud(&half)).unwrap();
    nimbus(&["render", s(&scene), "--spp", "2", "--out", s(&exr), "--quiet"]).unwrap();
    let (_, _, layers) = read_exr(&exr).unwrap();
    assert!(layers.iter().find(|l| l.name == "full").unwrap().rgb.iter().any(|p| p[0] > 0.0));
    let bytes = std::fs::read(&half).unwrap();
    let broken = dir.join("broken.vdb");
    std::fs::write(&broken, &bytes[..bytes.len() / 2]).unwrap();
    std::fs::write(&scene, cloud(&broken)).unwrap();
    let e = format!("{:#}", nimbus(&["render", s(&scene), "--out", s(&exr), "--quiet"]).unwrap_err());
    assert!(e.contains("broken.vdb") && e.contains("corrupt"), "{e}");
    // Other formats by extension; unknown ones are named.
    nimbus(&["model", "set-03", "--res", "16", "--out", s(&dir.join("c.vol"))]).unwrap();
    nimbus(&["model", "set-03", "--res", "16", "--out", s(&dir.join("c.raw"))]).unwrap();
    assert!(dir.join("c.json").exists());
    let e = format!("{:#}", nimbus(&["model", "set-03", "--out", s(&dir.join("c.obj"))]).unwrap_err());
    assert!(e.contains("c.obj") && e.contains(".vdb"), "{e}");
    let e = format!("{:#}", nimbus(&["model", "scene-q", "--out", s(&vdb)]).unwrap_err());
    assert!(e.contains("scene-q") && e.contains("scene-a"), "{e}");
}

/// `nimbus bench memory` samples resident memory while the window's worker
/// accumulates, and writes its table; nonsense durations are refused.
#[test]
fn memory_bench_writes_its_samples() {
    let guard = temp_dir("memory");
    let dir = guard.path().to_path_buf();
    nimbus(&["bench", "memory", "--seconds", "2", "--interval", "0.5", "--size", "16", "--out", s(&dir)]).unwrap();
    let csv = std::fs::read_to_string(dir.join("memory.csv")).unwrap();
    let rows: Vec<Vec<f64>> = csv.lines().skip(1).map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
    assert!(rows.len() >= 4, "{csv}");
    assert!(rows.iter().all(|r| r[1] > 1.0), "resident memory must be positive: {csv}");
    assert!(rows.windows(2).all(|w| w[1][0] > w[0][0]), "times must increase: {csv}");
    assert!(dir.join("memory.png").exists());
    let e = format!("{:#}", nimbus(&["bench", "memory", "--seconds", "0"]).unwrap_err());
    assert!(e.contains("positive"), "{e}");
}

/// `--preview` renders the instant preview (learned and octaves) into the same
/// layered EXR; `--time-limit` stops a render after its seconds and still writes the
/// finished passes; bad values are refused.
#[test]
fn preview_and_time_limit() {
    let guard = temp_dir("preview");
    let dir = guard.path().to_path_buf();
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, SCENE.replace("radiance = 0.05", "radiance = 0.0")).unwrap();
    for which in ["learned", "octaves"] {
        let exr = dir.join(format!("{which}.exr"));
        nimbus(&["render", s(&scene), "--preview", which, "--spp", "2", "--out", s(&exr), "--quiet"]).unwrap();
        let (_, _, layers) = read_exr(&exr).unwrap();
        let layer = |n: &str| layers.iter().find(|l| l.name == n).unwrap().rgb.clone();
        let (low, high) = (layer("low"), layer("high"));
        assert!(low.iter().any(|p| p[0] > 0.0), "{which}: single scattering");
        assert!(high.iter().any(|p| p[0] > 0.0), "{which}: the higher orders");
    }
    let e = format!(
        "{:#}",
        nimbus(&["render", s(&scene), "--preview", "guess", "--out", s(&dir.join("x.exr"))]).unwrap_err()
    );
    assert!(e.contains("render.preview") && e.contains("octaves"), "{e}");
    let exr = dir.join("timed.exr");
    let t = std::time::Instant::now();
    nimbus(&["render", s(&scene), "--time-limit", "1.5", "--out", s(&exr), "--quiet"]).unwrap();
    let took = t.elapsed().as_secs_f64();
    assert!(exr.exists() && took < 30.0, "a 1.5 s time limit took {took:.1} s");
    let e = format!("{:#}", nimbus(&["render", s(&scene), "--time-limit=-1", "--out", s(&exr)]).unwrap_err());
    assert!(e.contains("--time-limit"), "{e}");
}

/// `nimbus turntable`: N frames as EXR + PNG and an animated PNG; the camera turns
/// (the frames differ) while the sun stays; a stopped run resumes keeping the frames
/// written, and gives the same frames as an uninterrupted one; a folder holding
/// another turntable is refused; `nimbus eval temporal` reads the frames back (a
/// turntable against itself has no temporal error).
#[test]
fn turntable_writes_frames_resumes_and_refuses_other_settings() {
    let guard = temp_dir("turntable");
    let dir = guard.path().to_path_buf();
    let scene = dir.join("scene.toml");
    // (Not the built-in cumulus under a sun overhead: it looks the same from every side.)
    let text = SCENE.replace("builtin = \"cumulus\"", "preset = \"scene-b\"") + "[sun]\ndirection = [0.6, -1.0, 0.3]\n";
    std::fs::write(&scene, text).unwrap();
    let out = dir.join("turn");
    let args = ["turntable", s(&scene), "--frames", "4", "--spp", "2", "--out", s(&out), "--quiet"];
    nimbus(&args).unwrap();
    let frame = |i: u32, ext: &str| out.join(format!("frame-{i:04}.{ext}"));
    for i in 0..4 {
        assert!(frame(i, "exr").is_file() && frame(i, "png").is_file(), "frame {i}");
    }
    let anim = std::fs::read(out.join("turntable.png")).unwrap();
    let actl = anim.windows(4).position(|w| w == b"acTL").expect("an animated PNG (acTL chunk)");
    assert_eq!(u32::from_be_bytes(anim[actl + 4..actl + 8].try_into().unwrap()), 4, "4 frames in the animation");
    let full = |i: u32| read_exr(&frame(i, "exr")).unwrap().2.into_iter().find(|l| l.name == "full").unwrap().rgb;
    let first: Vec<_> = (0..4).map(full).collect();
    assert!(first[0] != first[1], "the camera did not turn");

    // A stopped run (frames 1 and 2 missing) resumes: frame 0 is kept as it was, the
    // missing ones are made again, bit for bit the same.
    let kept = std::fs::metadata(frame(0, "exr")).unwrap().modified().unwrap();
    std::fs::remove_file(frame(1, "png")).unwrap();
    std::fs::remove_file(frame(2, "exr")).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(20));
    nimbus(&args).unwrap();
    assert_eq!(std::fs::metadata(frame(0, "exr")).unwrap().modified().unwrap(), kept, "frame 0 was rewritten");
    for i in 0..4 {
        assert!(full(i) == first[i as usize], "frame {i} differs after the resume");
    }

    // Other settings into the same folder are refused, naming it.
    let e = nimbus(&["turntable", s(&scene), "--frames", "5", "--spp", "2", "--out", s(&out), "--quiet"])
        .unwrap_err()
        .to_string();
    assert!(e.contains("another turntable") && e.contains(s(&out)), "{e}");
    let e = nimbus(&["turntable", s(&scene), "--orbit", "moon", "--out", s(&dir.join("x")), "--quiet"])
        .unwrap_err()
        .to_string();
    assert!(e.contains("--orbit"), "{e}");

    // The sun turning instead: the camera stays, the light moves.
    let sun = dir.join("sun");
    nimbus(&[
        "turntable",
        s(&scene),
        "--frames",
        "2",
        "--spp",
        "2",
        "--orbit",
        "sun",
        "--degrees",
        "180",
        "--out",
        s(&sun),
        "--quiet",
    ])
    .unwrap();
    let high = |f: &str| read_exr(&sun.join(f)).unwrap().2.into_iter().find(|l| l.name == "high").unwrap().rgb;
    assert!(high("frame-0000.exr") != high("frame-0001.exr"), "the sun did not turn");

    let t = app::lab::eval::temporal::eval_temporal(&app::lab::eval::temporal::EvalTemporalArgs {
        frames: vec![out.clone()],
        reference: Some(out.clone()),
    })
    .unwrap();
    assert_eq!(t["temporal_error"].as_f64(), Some(0.0));
    assert_eq!(t["frames"].as_u64(), Some(4));

    // A stopped turntable is not scored, and frames without a manifest are not
    // adopted.
    std::fs::remove_file(frame(3, "exr")).unwrap();
    let e = app::lab::eval::temporal::eval_temporal(&app::lab::eval::temporal::EvalTemporalArgs {
        frames: vec![out.clone()],
        reference: None,
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("3 of its 4 frames"), "{e}");
    std::fs::remove_file(out.join("turntable.json")).unwrap();
    let e = nimbus(&args).unwrap_err().to_string();
    assert!(e.contains("no turntable.json"), "{e}");
}

/// `nimbus datagen cloud` with a fixed sun and view, then `nimbus eval cloud-points`:
/// every point is a first vertex lit from that sun, and the reported bias is the sum
/// of the model's predictions over the sum of the targets, recomputed here row by row.
#[test]
fn cloud_points_reports_a_models_bias_on_a_fixed_lighting() {
    use app::lab::eval::cloud_points::{EvalCloudPointsArgs, eval_cloud_points};
    use models::cloud::datagen::CloudDataset;
    use models::cloud::features::N_FEATURES;
    let guard = temp_dir("cloud-points");
    let data = guard.path().join("points");
    let d = data.to_str().unwrap();
    nimbus(&[
        "datagen",
        "cloud",
        "--points",
        "24",
        "--points-per-cloud",
        "8",
        "--resolution",
        "16",
        "--samples",
        "2",
        "--presets",
        "scene-a",
        "--preset-every",
        "1",
        "--rho",
        "20..20",
        "--sun",
        "0,-1,0",
        "--view-sun-cos",
        "0",
        "--vertex-weights",
        "1,0,0",
        "--quiet",
        "--out",
        d,
    ])
    .unwrap();
    let ds = CloudDataset::load(&data).unwrap();
    assert_eq!(ds.manifest.settings.sun, Some([0.0, -1.0, 0.0]));
    let rows =
        eval_cloud_points(&EvalCloudPointsArgs { data: vec![data.clone()], model: vec![], ensemble: false }).unwrap();
    assert_eq!(rows.len(), 1);
    let r = &rows[0];
    assert_eq!(r.all.points, 24);
    assert_eq!(r.by_vertex[0].as_ref().unwrap().points, 24);
    assert!(r.by_vertex[1].is_none() && r.by_vertex[2].is_none());
    let model = models::cloud::CloudModel::shipped().unwrap();
    let mut scratch = model.mlp.scratch();
    let (mut sp, mut st) = (0.0f64, 0.0f64);
    for (f, t) in ds.features.chunks_exact(N_FEATURES).zip(ds.targets.chunks_exact(5)) {
        sp += model.predict_features(f, &mut scratch) as f64;
        st += t[0] as f64;
    }
    assert!(st > 0.0);
    assert!((r.all.bias - (sp / st - 1.0)).abs() < 1e-9, "{} vs {}", r.all.bias, sp / st - 1.0);
    // A bad sun is refused, naming the flag.
    let e = nimbus(&["datagen", "cloud", "--points", "8", "--sun", "0,0", "--out", d]).unwrap_err();
    assert!(e.to_string().contains("--sun"), "{e}");

    // Distillation from the shipped model: the sidecar names the teacher by its
    // fingerprint; a teacher that does not exist is refused, naming the flag.
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/models/cloud.safetensors");
    let out = guard.path().join("student");
    let train = |teacher: &str| {
        nimbus(&[
            "train",
            "cloud",
            d,
            "--teacher",
            teacher,
            "--epochs",
            "1",
            "--hidden",
            "8",
            "--batch",
            "8",
            "--refit-output",
            "2",
            "--quiet",
            "--out",
            out.to_str().unwrap(),
        ])
    };
    train(shipped.to_str().unwrap()).unwrap();
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.with_extension("json")).unwrap()).unwrap();
    let fp = models::fingerprint::model_file_fingerprint(&shipped).unwrap();
    assert_eq!(side["training"]["teachers"], serde_json::json!([format!("{fp:016x}")]));
    // The shipped model and the student, each alone and averaged (--ensemble): the
    // ensemble's bias is that of the mean of the two predictions, recomputed here.
    let student = out.with_extension("safetensors");
    let rows = eval_cloud_points(&EvalCloudPointsArgs {
        data: vec![data.clone()],
        model: vec![shipped.clone(), student.clone()],
        ensemble: true,
    })
    .unwrap();
    assert_eq!(rows.len(), 3);
    assert_eq!(rows[2].model, "ensemble of 2");
    let student_model = models::cloud::CloudModel::load(&student).unwrap();
    let mut scratch2 = student_model.mlp.scratch();
    let (mut sp, mut sq) = (0.0f64, 0.0f64);
    for (f, t) in ds.features.chunks_exact(N_FEATURES).zip(ds.targets.chunks_exact(5)) {
        let a = model.predict_features(f, &mut scratch) as f64;
        let b = student_model.predict_features(f, &mut scratch2) as f64;
        sp += 0.5 * (a + b);
        sq += (0.5 * (a + b) - t[0] as f64).powi(2) - (t[1] as f64).powi(2);
    }
    let mean_t = st / ds.len() as f64;
    assert!((rows[2].all.bias - (sp / st - 1.0)).abs() < 1e-9, "{} vs {}", rows[2].all.bias, sp / st - 1.0);
    let rmse = (sq.max(0.0) / ds.len() as f64).sqrt() / mean_t;
    assert!((rows[2].all.point_rmse - rmse).abs() < 1e-9 * rmse.max(1.0), "{} vs {rmse}", rows[2].all.point_rmse);
    assert!((rows[0].all.bias - r.all.bias).abs() < 1e-12, "the shipped model's row is its own");
    let e = train(guard.path().join("none.safetensors").to_str().unwrap()).unwrap_err();
    assert!(format!("{e:#}").contains("--teacher"), "{e:#}");
    let o = out.to_str().unwrap();
    let args = ["train", "cloud", d, "--teacher", shipped.to_str().unwrap(), "--target", "one-path", "--out", o];
    let e = nimbus(&args).unwrap_err();
    assert!(e.to_string().contains("--teacher"), "{e}");
}
