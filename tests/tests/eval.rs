//! The evaluation pipeline end to end on a small study (scene A, toplit, rho 20,
//! 96x96 pixels): tables, plots and sheets are written, relative bias falls from k = 1
//! to k = 4 by more than the two estimates' noise explains, prediction at k = 1 has a
//! lower TTUV than path tracing, path tracing reaches a preview and the prediction's
//! RMSE floor falls with k, and a rerun resumes from the cache.

use app::cli::common::RunArgs;
use app::lab::eval::global::{EvalArgs, eval};

/// The study of `small_evaluation_runs_end_to_end`, written to `out`.
fn small_study(out: std::path::PathBuf) -> EvalArgs {
    EvalArgs {
        scenes: vec!["A".into()],
        configs: vec!["toplit".into()],
        rho: vec![20.0],
        k: vec![1, 4],
        size: 96,
        // The reference's own variance is subtracted from the preview's squared error
        // (`relative_rmse`); its pooled estimate scatters by several per cent under
        // the path tracer's heavy tails (g = 0.85). At 4,096 spp (9 % noise per pixel)
        // 5 % of it is 0.0004 against the 0.0025 of a 5 % preview; at 1,024 spp it was
        // 0.0016, and whether path tracing reached 5 % depended on the reference's seed.
        spp_ref: 4096,
        spp: 512,
        p: 0.25,
        auto_p: false,
        res: 64,
        field_nodes: 33,
        model: None,
        // The thesis's model, whose bias on this cloud falls with k.
        predictor: "global".into(),
        preview: true,
        // Path tracing needs about 14,000 spp here (9 % relative noise per pixel at
        // 4,096 spp, toplit, g = 0.85).
        preview_spp: Some(32_768),
        preview_passes: 8,
        preview_repeats: 1,
        preview_nodes: None,
        prediction_lattice: None,
        first_vertex: None,
        sky: false,
        out,
        run: RunArgs { threads: None, quiet: true },
    }
}

#[test]
fn small_evaluation_runs_end_to_end() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().to_path_buf();
    let args = small_study(out.clone());
    let r = eval(&args).unwrap();
    assert_eq!(r.len(), 2);
    let (k1, k4) = (&r[0], &r[1]);
    assert_eq!((k1.k, k4.k), (1, 4));
    eprintln!(
        "relative bias k=1 {:.4} (floor {:.4}), k=4 {:.4} (floor {:.4}); speedup k=1 {:.1}x",
        k1.rel_bias, k1.rel_noise_floor, k4.rel_bias, k4.rel_noise_floor, k1.speedup
    );
    for c in &r {
        assert!(c.rel_bias.is_finite() && c.rel_noise_floor > 0.0 && c.ttuv_pred > 0.0, "{c:?}");
    }
    // Noise moves a measured bias up by at most its noise floor (|x| <= E|x + N| <=
    // |x| + E|N|), so the true fall is at least m1 - floor1 - m4 in expectation. A
    // measured bias is a mean over n independent 16x16 blocks, so it scatters around
    // its expectation by at most sd(N) / sqrt(n) = floor sqrt(pi / 2) / sqrt(n): a
    // fall larger than floor1 plus 4 standard deviations of the difference is not noise.
    let blocks = (args.size.div_ceil(16) as f64).powi(2);
    let sd = (std::f64::consts::PI / 2.0).sqrt() * k1.rel_noise_floor.hypot(k4.rel_noise_floor) / blocks.sqrt();
    assert!(
        k1.rel_bias - k4.rel_bias > k1.rel_noise_floor + 4.0 * sd,
        "relative bias k=1 {} (floor {}), k=4 {} (floor {}), sd of the difference {sd}",
        k1.rel_bias,
        k1.rel_noise_floor,
        k4.rel_bias,
        k4.rel_noise_floor
    );
    assert!(k1.speedup > 1.0, "prediction at k = 1 must beat path tracing in TTUV: {k1:?}");
    for f in ["results.md", "results.csv", "bias_A.png", "speedup_A.png", "sheet_A_toplit_rho20_96px_res64.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let md = std::fs::read_to_string(out.join("results.md")).unwrap();
    assert!(md.contains("| toplit | 20 |") && md.contains("(9.2x)"), "{md}");
    // Time to preview: path tracing (unbiased) gets there, the reference's own noise
    // subtracted; the prediction's RMSE floor (its bias part) falls with k as its bias
    // does.
    assert!(k1.preview_secs_ref.is_some_and(|s| s > 0.0), "{k1:?}");
    assert!(md.contains("Time to preview"), "{md}");
    let (f1, f4) = (k1.rmse_floor.unwrap(), k4.rmse_floor.unwrap());
    assert!(f1.is_finite() && f4 < f1, "RMSE floor k=1 {f1}, k=4 {f4}");
    // The instant previews: the learned one, the octaves with their defaults and
    // fitted to the reference; a fit does no worse than the defaults it starts
    // from; every preview's first pass is already within a few times its floor (it
    // is nearly noise-free); curves, sheet and tables written.
    let csv = std::fs::read_to_string(out.join("preview.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 3, "{csv}");
    let floor = |t: &str| rows.iter().find(|r| r[4] == t).unwrap()[9].parse::<f64>().unwrap();
    let first = |t: &str| rows.iter().find(|r| r[4] == t).unwrap()[8].parse::<f64>().unwrap();
    assert!(floor("octaves fitted") <= floor("octaves") + 1e-4, "{csv}");
    for t in ["learned", "octaves", "octaves fitted"] {
        assert!(floor(t).is_finite() && first(t) < 2.0 * floor(t) + 0.05, "{t}: {csv}");
    }
    for f in ["preview.md", "preview_rmse_A_toplit_rho20_96px_res64.png", "preview_sheet_A_toplit_rho20_96px_res64.png"]
    {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // A rerun finds every render in the cache: the same numbers (to the last digit
    // JSON keeps; a re-render would differ in timing and therefore in TTUV).
    let again = eval(&args).unwrap();
    let same = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs();
    assert!(same(again[0].ttuv_pred, k1.ttuv_pred) && same(again[1].bias, k4.bias), "{again:?}");
}

/// `--preview-repeats 3`: a preview that reaches 5 % (the learned one on scene A
/// frontlit, whose floor is a few per cent; against a reference of 4,096 spp, so that
/// the floor's estimate scatters by about a point, not two) is timed three times, each run from a new
/// cloud's set-up and stopped at 5 %, and its time is their median; the previews that
/// do not (the octaves, tens of per cent off) are timed once. The runs' images are the
/// same (same seed), so each reaches 5 % at the same pass and only the seconds differ.
#[test]
fn repeated_preview_runs_report_their_median() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().to_path_buf();
    let args = EvalArgs {
        configs: vec!["frontlit".into()],
        rho: vec![40.0],
        k: vec![1],
        size: 64,
        spp_ref: 4096,
        spp: 8,
        predictor: "cloud".into(),
        preview_spp: Some(8),
        preview_passes: 16,
        preview_repeats: 3,
        ..small_study(out.clone())
    };
    eval(&args).unwrap();
    let csv = std::fs::read_to_string(out.join("preview.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 3, "{csv}");
    let row = |t: &str| rows.iter().find(|r| r[4] == t).unwrap();
    let learned = row("learned");
    let runs: Vec<f64> = learned[11].split(' ').map(|s| s.parse().unwrap()).collect();
    assert_eq!(runs.len(), 3, "the learned preview reaches 5 % and is timed three times: {csv}");
    let mut sorted = runs.clone();
    sorted.sort_by(f64::total_cmp);
    let secs: f64 = learned[7].parse().unwrap();
    assert!((secs - sorted[1]).abs() < 1e-3, "its time is the median run's: {csv}");
    assert!(runs.iter().all(|s| *s > 0.0 && s.is_finite()), "{csv}");
    // Each run was timed on its own (set up and rendered again): their microseconds
    // differ.
    assert!(runs[0] != runs[1] && runs[1] != runs[2], "three separate runs: {csv}");
    for t in ["octaves", "octaves fitted"] {
        assert!(row(t)[7].is_empty() && row(t)[11].is_empty(), "{t} never reaches 5 %, timed once: {csv}");
    }
    let md = std::fs::read_to_string(out.join("preview.md")).unwrap();
    assert!(md.contains("(median of 3 runs: "), "{md}");
    // A preview's floor, first pass and time are measured against the reference: a
    // reference of other samples measures all three previews again, rather than
    // reading cells measured against the first one from the cache.
    let cached_previews = || {
        std::fs::read_dir(out.join("cache"))
            .unwrap()
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .filter(|n| n.contains("_preview_") && n.ends_with(".json"))
            .count()
    };
    assert_eq!(cached_previews(), 3);
    eval(&EvalArgs { spp_ref: 256, ..args }).unwrap();
    assert_eq!(cached_previews(), 6, "the previews measured against the second reference are cells of their own");
}
