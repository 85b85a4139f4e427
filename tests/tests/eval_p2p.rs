//! `nimbus eval p2p` end to end on a small study (scene A backlit, 32x32, k = 1, 2,
//! the shipped model as "single" and, by its file, as "multi"): tables and sheets
//! are written, the prediction lands near BDPT's high orders, with light subpath
//! candidates too, a rerun resumes from the cache, and a missing model is named.

use app::cli::common::{BdptPredictionArgs, RunArgs};
use app::lab::eval::p2p::{EvalP2pArgs, eval_p2p};
use std::path::PathBuf;

fn shipped() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../assets/models/p2p.safetensors")
}

fn args(out: PathBuf) -> EvalP2pArgs {
    EvalP2pArgs {
        configs: vec!["backlit".into()],
        k: vec![1, 2],
        size: 32,
        spp_ref: 512,
        spp: 256,
        p: 1.0,
        bdpt: BdptPredictionArgs { r: Some(0.08), candidates: Some(1), extension_samples: None },
        cloud: "scene-a".into(),
        res: 64,
        model: None,
        multi_model: Some(shipped()),
        also: vec![],
        out,
        run: RunArgs { threads: None, quiet: true },
    }
}

#[test]
fn small_p2p_evaluation_runs_end_to_end() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().to_path_buf();
    let a = args(out.clone());
    let cells = eval_p2p(&a).unwrap();
    assert_eq!(cells.len(), 4);
    for c in &cells {
        eprintln!("{c:?}");
        assert!(c.mae.is_finite() && c.ttuv_pred_high > 0.0 && c.ttuv_bdpt_high > 0.0 && c.ttuv_pt_full > 0.0, "{c:?}");
        // The network's answer has the right scale: a wrong 1/D^2, a missing beam
        // area or a double-counted segment would be off by far more than this.
        assert!(c.rel_bias < 0.6, "relative bias {} (noise floor {})", c.rel_bias, c.rel_noise_floor);
    }
    // The same model twice, under two names, on the same scene: same images.
    assert_eq!(cells[0].mae, cells[1].mae);
    for f in ["p2p.md", "p2p.csv", "sheets/backlit.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let md = std::fs::read_to_string(out.join("p2p.md")).unwrap();
    assert!(md.contains("| backlit | single | 1 |") && md.contains("| 7.9x |"), "{md}");
    let again = eval_p2p(&a).unwrap();
    // A rerun reads every render from the cache: the same numbers (to the digits JSON
    // keeps of the timings; a re-render would differ in timing by far more).
    for (x, y) in cells.iter().zip(&again) {
        assert_eq!(x.mae, y.mae);
        for (a, b) in [(x.ttuv_pred_high, y.ttuv_pred_high), (x.speedup, y.speedup)] {
            assert!((a - b).abs() <= 1e-12 * a.abs(), "{a} vs {b}");
        }
    }
    // Light subpath candidates: their own renders (the references reused), the same
    // answer within the same tolerance.
    let mut m4 = args(out.clone());
    m4.k = vec![1];
    m4.bdpt.candidates = Some(4);
    let resampled = eval_p2p(&m4).unwrap();
    assert_eq!(resampled.len(), 2);
    for c in &resampled {
        assert!(c.rel_bias < 0.6, "4 candidates: relative bias {} (noise floor {})", c.rel_bias, c.rel_noise_floor);
        assert!(c.variance_ratio > 0.0 && c.secs_estimated > 0.0, "{c:?}");
        assert!(c.secs_free > 0.0 && c.free_ceiling.is_finite() && c.free_ceiling > 0.0, "{c:?}");
    }
    assert!(resampled[0].ttuv_pred_high != cells[0].ttuv_pred_high);
    // Prediction renders are cached under their candidates and extension samples.
    let names: Vec<String> = std::fs::read_dir(out.join("cache"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    let x = format!("_pool4_x{}_", engine::integrator::bdpt::Prediction::DEFAULT_EXTENSION_SAMPLES);
    assert!(names.iter().any(|n| n.contains("_estimated_") && n.contains(&x)), "{names:?}");
    // The reference is shared: read back from the cache here, so equal to the digit
    // its timing survives JSON (serde_json's default float parser may miss the last
    // bit), where a re-render would differ in timing by far more.
    let (a, b) = (resampled[0].ttuv_bdpt_high, cells[0].ttuv_bdpt_high);
    assert!((a - b).abs() <= 1e-12 * a.abs(), "the reference is shared: {a} vs {b}");
    let mut bad = args(out.clone());
    bad.multi_model = Some(out.join("no-such-model.safetensors"));
    let e = format!("{:#}", eval_p2p(&bad).unwrap_err());
    assert!(e.contains("no-such-model"), "{e}");
}
