//! `nimbus eval p2p` end to end on a small study (scene A backlit, 32x32, k = 1, 2,
//! the shipped model as "single" and, by its file, as "multi"): tables and sheets
//! are written, the prediction lands near BDPT's high orders, with light subpath
//! candidates too, a rerun resumes from the cache, and a missing model is named.

use app::cli::common::{BdptPredictionArgs, RunArgs};
use app::lab::eval::p2p::{EvalP2pArgs, P2pCell, eval_p2p};
use std::path::PathBuf;

fn shipped() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../assets/models/p2p.safetensors")
}

fn args(out: PathBuf) -> EvalP2pArgs {
    EvalP2pArgs {
        configs: vec!["backlit".into()],
        k: vec![1, 2],
        size: 32,
        spp_ref: 2048,
        spp: 1024,
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

/// The network's answer has the right scale: a wrong 1/D^2, a missing beam area or a
/// double-counted segment is off by a factor of 2 or more (relative bias >= 1), where
/// the model's own bias is a few percent (docs/point-to-point.md); up to
/// `MODEL_BIAS` passes. The relative bias (`app::metrics::bias`) averages |N(b, s)|
/// over the image's 16x16 blocks; by the triangle inequality its expectation is at
/// most |b| + E|N(0, s)|, the noise floor f, and over n blocks its standard deviation
/// about f sqrt(pi / 2 - 1) / sqrt(n). The bound adds z of those at family-wise
/// alpha = 0.01 over the `tests` cells, and the test first asks that the bound can
/// fail on a factor-2 error (enough samples for the floor).
const MODEL_BIAS: f64 = 0.25;

fn assert_right_scale(c: &P2pCell, size: u32, tests: usize, what: &str) {
    let blocks = (size.div_ceil(16) as f64).powi(2);
    let z = engine::stats::z_bound(0.01, tests);
    let bound = MODEL_BIAS + c.rel_noise_floor * (1.0 + z * (std::f64::consts::FRAC_PI_2 - 1.0).sqrt() / blocks.sqrt());
    assert!(bound < 1.0, "{what}: noise floor {} too high to tell a factor of 2 (bound {bound})", c.rel_noise_floor);
    assert!(
        c.rel_bias < bound,
        "{what}: relative bias {} above {bound} (noise floor {})",
        c.rel_bias,
        c.rel_noise_floor
    );
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
        assert_right_scale(c, a.size, 6, &format!("{} k {}", c.model, c.k));
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
        assert_right_scale(c, m4.size, 6, &format!("4 candidates, k {}", c.k));
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
