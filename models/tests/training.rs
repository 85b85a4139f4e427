//! Training, model files and the fast evaluator of the global model.

use candle_core::{Device, Tensor};
use engine::InScatterPredictor;
use engine::Rng;
use models::dataset::Shard;
use models::global::GlobalSpec;
use models::global::directions::DirectionSetKind;
use models::global::model::{
    FeatureLayout, GlobalModel, TargetKind, predicted_l_i, single_scattering, single_scattering_phase, transform_target,
};
use models::global::train::{Network, Quiet, TrainConfig, TrainData, train};
use models::nn::Optimizer;
use models::nn::fit::StopAfterEpochs;
use models::nn::{Activation, Kernel};
use std::sync::atomic::AtomicBool;

/// A fresh directory, removed with the returned guard.
fn temp(_name: &str) -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

/// A synthetic data set whose transformed target is a known smooth function of the
/// features: ln(1 + L / p) = f(x).
fn smooth_data(n: usize, seed: u64) -> (TrainData, impl Fn(&[f32]) -> f32) {
    let layout = FeatureLayout::current(DirectionSetKind::Tetrahedron, 4);
    let f = |x: &[f32]| 1.5 + 0.5 * (1.5 * x[4]).sin() + 0.3 * x[2].cos() * x[5] / 4.0 - 0.2 * x[1] * x[6] / 4.0;
    let mut rng = Rng::new(seed, 1, 2);
    let mut features = vec![];
    let mut l_i = vec![];
    for _ in 0..n {
        let row = [
            1.0,
            rng.uniform() * 0.9,
            rng.uniform() * std::f32::consts::PI,
            rng.uniform() * std::f32::consts::TAU,
            -4.0 * rng.uniform(),
            -4.0 * rng.uniform(),
            -4.0 * rng.uniform(),
            -4.0 * rng.uniform(),
        ];
        l_i.push(single_scattering_phase(&row) * f(&row).exp_m1());
        features.extend_from_slice(&row);
    }
    (TrainData { layout, features, l_i, sources: vec![format!("synthetic-{seed}")] }, f)
}

#[test]
fn training_recovers_a_known_smooth_function() {
    let (data, _) = smooth_data(6000, 1);
    let cfg =
        TrainConfig { hidden: vec![32, 16], epochs: 40, batch: 100, lr: 3e-3, lr_decay: 0.95, ..Default::default() };
    let guard = temp("smooth");
    let dir = guard.path().to_path_buf();
    let (_, report) = train(&data, &cfg, &dir.join("m"), false, "test", "test", &Quiet).unwrap();
    // The standardized target has variance 1; a recovered function leaves a few per cent.
    assert!(report.test_mse < 0.02 * report.test_target_variance, "{report:?}");
    assert!(report.rel_error_median < 0.05, "{report:?}");
    assert_eq!(report.dropped_points, 0);
    let h = &report.history;
    assert!(h.last().unwrap().test_mse < 0.2 * h[0].test_mse, "the loss falls");
    assert!(dir.join("m.loss.csv").exists() && dir.join("m.loss.png").exists());
}

#[test]
fn sgd_with_momentum_also_learns() {
    let (data, _) = smooth_data(3000, 2);
    let cfg = TrainConfig {
        hidden: vec![32, 16],
        epochs: 15,
        batch: 100,
        optimizer: Optimizer::Sgd { momentum: 0.9 },
        lr: 0.02,
        activation: Activation::Tanh,
        ..Default::default()
    };
    let guard = temp("sgd");
    let dir = guard.path().to_path_buf();
    let (_, report) = train(&data, &cfg, &dir.join("m"), false, "test", "test", &Quiet).unwrap();
    assert!(report.test_mse < 0.25 * report.test_target_variance, "{report:?}");
}

/// A tiny ground-truth data set made by the generator itself trains to a test error
/// well below the variance of its targets.
#[test]
fn a_generated_data_set_trains() {
    let guard = temp("gen");
    let dir = guard.path().to_path_buf();
    let spec = GlobalSpec {
        points: 1500,
        sigma: [0.5, 8.0],
        g: [0.0, 0.8],
        n_dirs: 16,
        max_rel_error: 0.15,
        min_samples: 128,
        chunk_size: 250,
        seed: 3,
        ..Default::default()
    };
    models::global::datagen::generate(&spec, Shard::ALL, &dir.join("data"), "test", &|_| {}, &AtomicBool::new(false))
        .unwrap();
    let data = TrainData::load(&[dir.join("data")]).unwrap();
    assert_eq!(data.n_features(), 20);
    let cfg =
        TrainConfig { hidden: vec![64, 32], epochs: 30, batch: 50, lr: 2e-3, lr_decay: 0.95, ..Default::default() };
    let (model, report) = train(&data, &cfg, &dir.join("m"), false, "test", "test", &Quiet).unwrap();
    assert!(report.test_mse < 0.25 * report.test_target_variance, "{report:?}");
    assert_eq!(model.sidecar.features.n_dirs, 16);
    // A data set of another layout is refused by name.
    let other = GlobalSpec { n_dirs: 4, points: 10, chunk_size: 10, ..spec.clone() };
    models::global::datagen::generate(&other, Shard::ALL, &dir.join("data4"), "test", &|_| {}, &AtomicBool::new(false))
        .unwrap();
    let e = TrainData::load(&[dir.join("data"), dir.join("data4")]).err().unwrap().to_string();
    assert!(e.contains("4 tetrahedron directions") && e.contains("16 tetrahedron"), "{e}");
}

#[test]
fn fast_evaluator_matches_candle_and_files_round_trip() {
    let dev = Device::Cpu;
    let widths = [68, 200, 100, 1];
    for act in [Activation::Relu, Activation::Tanh, Activation::Silu] {
        let net = Network::glorot(&widths, act, 5, &dev).unwrap();
        // Non-zero biases so that they are tested too.
        let mut rng = Rng::new(9, 0, 0);
        for (_, b) in &net.params {
            let n = b.as_tensor().dims1().unwrap();
            let v: Vec<f32> = (0..n).map(|_| rng.uniform() - 0.5).collect();
            b.set(&Tensor::from_vec(v, n, &dev).unwrap()).unwrap();
        }
        let mlp = net.to_mlp().unwrap();
        let mut scratch = mlp.scratch();
        let n = 256;
        let xs: Vec<f32> = (0..n * 68).map(|_| 4.0 * rng.uniform() - 2.0).collect();
        let candle: Vec<f32> =
            net.forward(&Tensor::from_slice(&xs, (n, 68), &dev).unwrap()).unwrap().to_vec1().unwrap();
        let mut batch = vec![0.0; n];
        mlp.forward_batch(&xs, &mut batch, &mut scratch);
        for i in 0..n {
            let one = mlp.forward(&xs[i * 68..(i + 1) * 68], &mut scratch);
            assert_eq!(one, batch[i]);
            let tol = 1e-5 * candle[i].abs().max(1.0);
            assert!((one - candle[i]).abs() <= tol, "{act:?} row {i}: {one} vs {}", candle[i]);
            // The portable path (CPUs without AVX2) agrees too.
            let portable = mlp.forward_portable(&xs[i * 68..(i + 1) * 68], &mut scratch);
            assert!((portable - candle[i]).abs() <= tol, "{act:?} row {i}: portable {portable} vs {}", candle[i]);
        }
    }
}

#[test]
fn every_layer_kernel_gives_the_portable_bits() {
    // Widths that exercise every register blocking: a layer narrower than one vector
    // block, one that fills a 128-output block, 192 (a partial AVX-512 block), 300
    // (past the 256 outputs of one AVX-512 pass, with a remainder) and an odd input
    // count.
    let dev = Device::Cpu;
    let widths = [451, 192, 300, 128, 7, 1];
    let net = Network::glorot(&widths, Activation::Relu, 3, &dev).unwrap();
    let mut rng = Rng::new(21, 0, 0);
    for (_, b) in &net.params {
        let n = b.as_tensor().dims1().unwrap();
        let v: Vec<f32> = (0..n).map(|_| 0.2 * rng.uniform() - 0.05).collect();
        b.set(&Tensor::from_vec(v, n, &dev).unwrap()).unwrap();
    }
    let mlp = net.to_mlp().unwrap();
    let mut scratch = mlp.scratch();
    let n = 64;
    let xs: Vec<f32> = (0..n * 451).map(|_| 4.0 * rng.uniform() - 2.0).collect();
    let candle: Vec<f32> = net.forward(&Tensor::from_slice(&xs, (n, 451), &dev).unwrap()).unwrap().to_vec1().unwrap();
    let kernels = [Kernel::Portable, Kernel::Avx2, Kernel::Avx512];
    assert!(Kernel::best().available());
    let mut nonzero = 0;
    for (i, row) in xs.chunks_exact(451).enumerate() {
        let portable = mlp.forward_with_kernel(Kernel::Portable, row, &mut scratch).unwrap();
        assert!(
            (portable - candle[i]).abs() <= 1e-4 * candle[i].abs().max(1.0),
            "row {i}: {portable} vs {}",
            candle[i]
        );
        nonzero += usize::from(portable != 0.0);
        for k in kernels {
            if let Some(y) = mlp.forward_with_kernel(k, row, &mut scratch) {
                assert_eq!(y.to_bits(), portable.to_bits(), "{} row {i}: {y} vs portable {portable}", k.name());
            }
        }
        assert_eq!(mlp.forward(row, &mut scratch).to_bits(), portable.to_bits());
    }
    // The rows are not all cut off by the ReLUs (the comparison would be empty).
    assert!(nonzero > n / 2, "{nonzero} of {n} outputs are non-zero");
}

#[test]
fn save_load_predicts_identically_and_bad_files_are_refused() {
    let (data, _) = smooth_data(800, 3);
    let cfg = TrainConfig { hidden: vec![16, 8], epochs: 2, ..Default::default() };
    let guard = temp("files");
    let dir = guard.path().to_path_buf();
    let out = dir.join("m");
    let (model, _) = train(&data, &cfg, &out, false, "test", "test", &Quiet).unwrap();
    let loaded = GlobalModel::load(&dir.join("m.safetensors")).unwrap();
    let (mut s1, mut s2) = (model.mlp.scratch(), loaded.mlp.scratch());
    for row in data.features.chunks_exact(8).take(100) {
        assert_eq!(model.predict_features(row, &mut s1).to_bits(), loaded.predict_features(row, &mut s2).to_bits());
    }
    let weights = std::fs::read(dir.join("m.safetensors")).unwrap();
    let sidecar = std::fs::read_to_string(dir.join("m.json")).unwrap();
    let load_err = |w: &[u8], s: &str| {
        std::fs::write(dir.join("bad.safetensors"), w).unwrap();
        std::fs::write(dir.join("bad.json"), s).unwrap();
        GlobalModel::load(&dir.join("bad.safetensors")).err().expect("refused").to_string()
    };
    // Truncated and corrupted weights.
    let e = load_err(&weights[..weights.len() / 2], &sidecar);
    assert!(e.contains("bad.safetensors"), "{e}");
    let mut flipped = weights.clone();
    flipped[3] ^= 0x55;
    assert!(load_err(&flipped, &sidecar).contains("bad.safetensors"));
    // A weight replaced by NaN.
    let mut nan = weights.clone();
    let end = nan.len();
    nan[end - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    assert!(load_err(&nan, &sidecar).contains("non-finite"));
    // Sidecar of another layout / architecture.
    let e = load_err(&weights, &sidecar.replace("\"tau_hat_4\"", "\"tau_4\""));
    assert!(e.contains("feature names"), "{e}");
    let e = load_err(&weights, &sidecar.replacen("16,", "17,", 1));
    assert!(e.contains("shape"), "{e}");
    let e = load_err(&weights, "{ not json");
    assert!(e.contains("bad.json"), "{e}");
}

#[test]
fn an_interrupted_training_resumes_to_the_same_weights() {
    let (data, _) = smooth_data(1000, 4);
    let cfg = TrainConfig { hidden: vec![16, 8], epochs: 4, batch: 100, ..Default::default() };
    let guard = temp("resume");
    let dir = guard.path().to_path_buf();
    let (full, _) = train(&data, &cfg, &dir.join("a"), false, "test", "test", &Quiet).unwrap();
    let stop = StopAfterEpochs::new(2);
    let e = train(&data, &cfg, &dir.join("b"), false, "test", "test", &stop).err().unwrap();
    assert!(e.to_string().contains("--resume"), "{e}");
    let (resumed, report) = train(&data, &cfg, &dir.join("b"), true, "test", "test", &Quiet).unwrap();
    assert_eq!(report.history.len(), 4);
    // The model and checkpoint files have the permissions of any other new file
    // (not the 0600 of a temporary-file library), and no temporary is left.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = |p: &std::path::Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        std::fs::write(dir.join("plain"), b"x").unwrap();
        let plain = mode(&dir.join("plain"));
        for f in ["b.safetensors", "b.json", "b.checkpoint/state.safetensors"] {
            assert_eq!(mode(&dir.join(f)), plain, "{f}");
        }
        for d in [dir.clone(), dir.join("b.checkpoint")] {
            let left: Vec<_> = std::fs::read_dir(&d)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with('.'))
                .collect();
            assert!(left.is_empty(), "temporaries left in {}: {left:?}", d.display());
        }
    }
    let (mut s1, mut s2) = (full.mlp.scratch(), resumed.mlp.scratch());
    for row in data.features.chunks_exact(8).take(50) {
        let (a, b) = (full.predict_features(row, &mut s1), resumed.predict_features(row, &mut s2));
        assert!((a - b).abs() <= 1e-5 * a.abs().max(1e-3), "{a} vs {b}");
    }
}

/// The multiple-scattering target: a data set whose L_i is exact single scattering
/// plus a known smooth multiple-scattering part trains to that part, the model file
/// says what it predicts (so the renderer adds single scattering by NEE), and the
/// training report's relative error is of L_i with single scattering added back.
#[test]
fn multiple_scattering_target_trains_and_round_trips() {
    let (mut data, f) = smooth_data(6000, 3);
    let n_f = data.n_features();
    for i in 0..data.len() {
        let row = &data.features[i * n_f..(i + 1) * n_f];
        let ms = f(row).exp_m1() / (4.0 * std::f32::consts::PI);
        data.l_i[i] = single_scattering(row) + ms;
        // The transform recovers f exactly (up to f32 rounding).
        let y = transform_target(TargetKind::Multiple, row, data.l_i[i]);
        assert!((y - f(row)).abs() < 1e-3 * f(row).abs().max(1.0), "{y} vs {}", f(row));
        assert!((predicted_l_i(TargetKind::Multiple, row, y) - data.l_i[i]).abs() <= 1e-4 * data.l_i[i].max(1e-3));
    }
    let cfg = TrainConfig {
        hidden: vec![32, 16],
        epochs: 40,
        batch: 100,
        lr: 3e-3,
        lr_decay: 0.95,
        target: TargetKind::Multiple,
        ..Default::default()
    };
    let guard = temp("multiple");
    let dir = guard.path().to_path_buf();
    let (_, report) = train(&data, &cfg, &dir.join("m"), false, "test", "test", &Quiet).unwrap();
    assert!(report.test_mse < 0.02 * report.test_target_variance, "{report:?}");
    assert!(report.rel_error_median < 0.05, "{report:?}");
    let model = GlobalModel::load(&dir.join("m.safetensors")).unwrap();
    assert_eq!(model.target(), TargetKind::Multiple);
    assert!(!model.predicts_single_scattering());
}
