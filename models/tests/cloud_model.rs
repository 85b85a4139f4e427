//! The cloud-aware model's pipeline on a small data set: the generator gives the same
//! bytes for 1 and 2 threads, after a stop and resume, and as merged shards; refuses
//! changed settings and held-out clouds in training; every row is consistent with its
//! cloud and vertex; training resumes to the same weights; the fast evaluator agrees
//! with candle; the model files round-trip and broken ones are refused; fine-tuning
//! starts from a model and keeps its standardization; rows weighted by their targets'
//! predicted noise train, resume and are recorded; and the bound predictor answers
//! through the engine's trait.

use models::cloud::datagen::{CloudDataset, CloudSpec, HELD_OUT_PRESETS, build_case, generate};
use models::cloud::features::N_FEATURES;
use models::cloud::train::{CloudTrainConfig, CloudTrainData, train};
use models::cloud::{BoundCloudModel, CloudModel};
use models::dataset::{DataSpec, Shard};
use models::nn::fit::{Quiet, StopAfterEpochs};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

fn spec() -> CloudSpec {
    CloudSpec {
        points: 40,
        points_per_cloud: 8,
        resolution: 16,
        presets: vec!["scene-b".into()],
        preset_every: 3,
        rho: [5.0, 40.0],
        samples: 4,
        field_nodes: 24,
        seed: 9,
        ..Default::default()
    }
}

fn bytes(d: &Path) -> (Vec<u8>, Vec<u8>) {
    (std::fs::read(d.join("features.npy")).unwrap(), std::fs::read(d.join("targets.npy")).unwrap())
}

fn run(s: &CloudSpec, shard: Shard, d: &Path, threads: usize, cancel: &AtomicBool) -> Result<(), String> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    pool.install(|| generate(s, shard, d, "test", &|_| {}, cancel)).map(|_| ()).map_err(|e| e.to_string())
}

#[test]
fn generator_is_deterministic_resumable_and_shardable() {
    let s = spec();
    let never = AtomicBool::new(false);
    let root = tempfile::tempdir().unwrap();
    let dir = |n: &str| -> PathBuf { root.path().join(n) };
    run(&s, Shard::ALL, &dir("a"), 1, &never).unwrap();
    run(&s, Shard::ALL, &dir("b"), 2, &never).unwrap();
    assert_eq!(bytes(&dir("a")), bytes(&dir("b")), "1 and 2 threads differ");

    let ds = CloudDataset::load(&dir("a")).unwrap();
    assert_eq!(ds.len(), 40);
    assert_eq!(ds.features.len(), 40 * N_FEATURES);
    for (i, t) in ds.targets.chunks_exact(5).enumerate() {
        // Mean >= 0, a standard error, the path count, one path's value, a vertex 1..3.
        assert!(t[0] >= 0.0 && t[1] >= 0.0 && t[2] == 4.0 && t[3] >= 0.0, "row {i}: {t:?}");
        assert!((1.0..=3.0).contains(&t[4]) && t[4].fract() == 0.0, "row {i}: {t:?}");
        let f = &ds.features[i * N_FEATURES..(i + 1) * N_FEATURES];
        assert!(f.iter().all(|v| v.is_finite()), "row {i}");
        // One medium per cloud: the albedo and g features are shared within a chunk.
        let first = &ds.features[(i / 8) * 8 * N_FEATURES..][..2];
        assert_eq!(&f[..2], first, "row {i}");
    }
    assert_ne!(ds.features[..2], ds.features[8 * N_FEATURES..8 * N_FEATURES + 2], "clouds 0 and 1 share a medium");

    // Stopped after the first chunk, resumed: the same bytes.
    let cancel = AtomicBool::new(false);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let stopped = pool.install(|| {
        generate(
            &s,
            Shard::ALL,
            &dir("c"),
            "test",
            &|n| {
                if n >= 8 {
                    cancel.store(true, Ordering::Relaxed)
                }
            },
            &cancel,
        )
    });
    assert!(stopped.is_err(), "the run should have been cancelled");
    assert!(models::dataset::chunk_path(&dir("c"), 0).exists());
    run(&s, Shard::ALL, &dir("c"), 2, &never).unwrap();
    assert_eq!(bytes(&dir("a")), bytes(&dir("c")), "resumed run differs");

    // Two shards merged.
    run(&s, Shard { index: 0, count: 2 }, &dir("s0"), 2, &never).unwrap();
    run(&s, Shard { index: 1, count: 2 }, &dir("s1"), 1, &never).unwrap();
    std::fs::create_dir_all(dir("m")).unwrap();
    models::dataset::merge::<CloudSpec>(&[dir("s0"), dir("s1")], &dir("m")).unwrap();
    assert_eq!(bytes(&dir("a")), bytes(&dir("m")), "merged shards differ");

    // Changed settings in the same directory, held-out presets and bad ranges are
    // refused, naming the flag.
    let e = run(&CloudSpec { samples: 5, ..s.clone() }, Shard::ALL, &dir("a"), 1, &never).unwrap_err();
    assert!(e.contains("samples"), "{e}");
    let e = CloudSpec { presets: vec![HELD_OUT_PRESETS[0].into()], ..s.clone() }.validate().unwrap_err();
    assert!(e.to_string().contains("--presets") && e.to_string().contains("held-out"), "{e}");
    let e = CloudSpec { vertex_weights: [0.5, 0.5, 0.5], ..s.clone() }.validate().unwrap_err();
    assert!(e.to_string().contains("--vertex-weights"), "{e}");
    let e = CloudSpec { g_power: 0.0, ..s.clone() }.validate().unwrap_err();
    assert!(e.to_string().contains("--g-power"), "{e}");
    let e = CloudSpec { sun: Some([0.0, 0.0, 0.0]), ..s.clone() }.validate().unwrap_err();
    assert!(e.to_string().contains("--sun"), "{e}");

    // A fixed sun lights every cloud from that direction; the rest of each case (rho,
    // albedo, g) is drawn as without it.
    let fixed = CloudSpec { sun: Some([0.0, -2.0, 0.0]), ..s.clone() };
    for c in 0..3 {
        let (a, b) = (build_case(&s, c).unwrap(), build_case(&fixed, c).unwrap());
        assert_eq!(b.scene.sun.unwrap().direction(), glam::Vec3::NEG_Y, "case {c}");
        assert_ne!(a.scene.sun.unwrap().direction(), glam::Vec3::NEG_Y, "case {c}");
        assert_eq!(a.scene.medium.rho(), b.scene.medium.rho(), "case {c}");
        assert_eq!(a.scene.medium.albedo(), b.scene.medium.albedo(), "case {c}");
    }

    // A held-out set draws other clouds and is refused as training data.
    let h = CloudSpec { held_out: true, presets: vec![], ..s.clone() };
    run(&h, Shard::ALL, &dir("h"), 2, &never).unwrap();
    for c in 0..h.n_chunks() {
        assert_ne!(h.cloud(c).1, s.cloud(c).1, "cloud {c} of the held-out set is a training cloud");
    }
    let e = CloudTrainData::load(&[dir("h")]).err().unwrap();
    assert!(e.to_string().contains("held-out"), "{e}");
}

/// A small training set (96 points of 12 clouds) in a fresh directory, and the
/// configuration of a small network for it.
struct Small {
    s: CloudSpec,
    root: tempfile::TempDir,
    data_dir: PathBuf,
    data: CloudTrainData,
    cfg: CloudTrainConfig,
}

/// Trains `data` into `out`, stopped after 2 epochs; the run's error.
fn train_stopped(data: &CloudTrainData, cfg: &CloudTrainConfig, out: &Path) -> models::nn::fit::TrainError {
    let stop = StopAfterEpochs::new(2);
    train(data.clone(), None, cfg, out, false, "test", "test", &stop).err().expect("a stopped run is an error")
}

/// `dir`/a.safetensors and `dir`/b.safetensors hold the same bytes.
fn assert_same_weights(dir: &Path, what: &str) {
    let read = |name: &str| std::fs::read(dir.join(name)).unwrap();
    assert_eq!(read("a.safetensors"), read("b.safetensors"), "{what}");
}

fn small_training_set() -> Small {
    let s = CloudSpec { points: 96, points_per_cloud: 8, ..spec() };
    let root = tempfile::tempdir().unwrap();
    let data_dir = root.path().join("data");
    run(&s, Shard::ALL, &data_dir, 2, &AtomicBool::new(false)).unwrap();
    let data = CloudTrainData::load(std::slice::from_ref(&data_dir)).unwrap();
    let mut cfg = CloudTrainConfig { test_fraction: 0.25, ..Default::default() };
    (cfg.schedule.hidden, cfg.schedule.epochs, cfg.schedule.batch) = (vec![16, 8], 4, 16);
    Small { s, root, data_dir, data, cfg }
}

#[test]
fn training_resumes_and_the_model_round_trips() {
    let Small { s, root, data, cfg, .. } = small_training_set();
    let (full, report) =
        train(data.clone(), None, &cfg, &root.path().join("a"), false, "test", "test", &Quiet).unwrap();
    // The test split holds out whole clouds: 3 of 12.
    assert_eq!(report.test.clouds, 3);
    assert_eq!(report.test.points + report.train_points, 96);
    assert!(report.test.bias.is_finite() && report.test.bias_std_error > 0.0, "{:?}", report.test);
    // Stopped after 2 epochs, resumed: the same weights as the straight run.
    let e = train_stopped(&data, &cfg, &root.path().join("b"));
    assert!(e.to_string().contains("--resume"), "{e}");
    train(data.clone(), None, &cfg, &root.path().join("b"), true, "test", "test", &Quiet).unwrap();
    assert_same_weights(root.path(), "resumed training differs");
    // The fast evaluator against candle on the same weights, and the loaded model
    // against the one returned.
    let weights = root.path().join("a.safetensors");
    let loaded = CloudModel::load(&weights).unwrap();
    let tensors = candle_core::safetensors::load(&weights, &candle_core::Device::Cpu).unwrap();
    let side = &loaded.sidecar;
    let (mut s1, mut s2) = (loaded.mlp.scratch(), full.mlp.scratch());
    for row in data.features.chunks_exact(N_FEATURES).take(20) {
        let x: Vec<f32> =
            row.iter().enumerate().map(|(k, v)| (v - side.feature_mean[k]) / side.feature_std[k]).collect();
        let mut h = candle_core::Tensor::from_vec(x, (1, N_FEATURES), &candle_core::Device::Cpu).unwrap();
        for l in 0..3 {
            let w = &tensors[&format!("layers.{l}.weight")];
            let b = &tensors[&format!("layers.{l}.bias")];
            h = h.matmul(&w.t().unwrap()).unwrap().broadcast_add(b).unwrap();
            if l < 2 {
                h = h.relu().unwrap();
            }
        }
        let o: f32 = h.flatten_all().unwrap().to_vec1::<f32>().unwrap()[0];
        let want = loaded.untransform(o);
        let got = loaded.predict_features(row, &mut s1);
        assert!((got - want).abs() <= 1e-4 * want.abs().max(1e-4), "{got} vs candle {want}");
        assert_eq!(got, full.predict_features(row, &mut s2));
    }
    // Broken sidecars are refused, naming the problem.
    let text = std::fs::read_to_string(root.path().join("a.json")).unwrap();
    let bytes = std::fs::read(&weights).unwrap();
    let err = |json: &str| CloudModel::from_bytes(&bytes, json, Path::new("bad.safetensors")).unwrap_err().to_string();
    assert!(err(&text.replace("\"cos_theta\"", "\"angle\"")).contains("features"));
    assert!(err(&text.replace("nimbus-cloud-model", "nimbus-global-model")).contains("format"));
    assert!(err("{ not json").contains("bad.json"));
    assert!(err(&text.replacen("\"hidden\": [\n    16", "\"hidden\": [\n    17", 1)).contains("shape"));

    // Bound to a cloud and sun, the model answers the engine's trait: multiple
    // scattering only, finite and non-negative, and the same as its own features.
    let case = models::cloud::datagen::build_case(&s, 1).unwrap();
    let medium = &case.scene.medium;
    let sun = case.scene.sun.unwrap();
    let bound = BoundCloudModel::new(Arc::new(loaded.clone()), medium, &sun, 24);
    use engine::InScatterPredictor;
    assert!(!bound.predicts_single_scattering());
    let mut feat = vec![0.0; N_FEATURES];
    let mut rng = engine::Rng::new(1, 2, 3);
    for _ in 0..20 {
        let (x, wo) = models::cloud::datagen::camera_path_query(medium, 1, None, &mut rng);
        let v = bound.predict(medium, &sun, x, wo);
        bound.field().features(medium.albedo(), medium.phase().mean_cosine(), x, wo, &mut feat);
        assert!(v.is_finite() && v >= 0.0);
        assert_eq!(v, loaded.predict_features(&feat, &mut s1));
    }
    // A batch (37 points: two full batches of the network's rows and a tail of 5, and
    // a lone point) gives each point the bits of a single prediction.
    let queries: Vec<_> =
        (0..37).map(|_| models::cloud::datagen::camera_path_query(medium, 1, None, &mut rng)).collect();
    let (xs, ws): (Vec<_>, Vec<_>) = queries.iter().copied().unzip();
    for n in [37, 1] {
        let mut many = vec![f32::NAN; n];
        bound.predict_many(medium, &sun, &xs[..n], &ws[..n], &mut many);
        for (i, &(x, wo)) in queries[..n].iter().enumerate() {
            assert_eq!(many[i].to_bits(), bound.predict(medium, &sun, x, wo).to_bits(), "point {i} of {n}");
        }
    }
}

/// A network of the stored features alone (the models before the derived coupling)
/// reads the first STORED_FEATURES values of the vector and loads as it was saved; the
/// coupling's network reads them all; other lengths are refused.
#[test]
fn models_read_the_stored_features_or_all() {
    use models::cloud::features::DerivedInputs;
    use models::cloud::features::STORED_FEATURES;
    let Small { root, data, cfg, .. } = small_training_set();
    let plain = CloudTrainConfig { derived: DerivedInputs::None, ..cfg.clone() };
    let (model, _) = train(data.clone(), None, &plain, &root.path().join("p"), false, "test", "test", &Quiet).unwrap();
    assert_eq!(model.inputs(), STORED_FEATURES);
    assert_eq!(model.sidecar.feature_names.len(), STORED_FEATURES);
    let (coupled, _) = train(data.clone(), None, &cfg, &root.path().join("c"), false, "test", "test", &Quiet).unwrap();
    assert_eq!(coupled.inputs(), N_FEATURES);
    // The stored-only network ignores the derived values: changing them changes nothing;
    // the coupled one reads them. One scratch serves both, in either order.
    let mut s = model.mlp.scratch();
    let mut moved = 0;
    for row in data.features.chunks_exact(N_FEATURES).take(10) {
        let mut other = row.to_vec();
        other[STORED_FEATURES..].iter_mut().for_each(|v| *v += 1.0);
        moved += (coupled.predict_features(row, &mut s) != coupled.predict_features(&other, &mut s)) as usize;
        assert_eq!(model.predict_features(row, &mut s), model.predict_features(&other, &mut s));
    }
    assert!(moved > 0, "the coupled network does not read the derived values");
    // A sidecar naming another length (one short of the stored features) is refused.
    let text = std::fs::read_to_string(root.path().join("p.json")).unwrap();
    let mut side: serde_json::Value = serde_json::from_str(&text).unwrap();
    for key in ["feature_names", "feature_mean", "feature_std"] {
        side[key].as_array_mut().unwrap().truncate(STORED_FEATURES - 1);
    }
    let bytes = std::fs::read(root.path().join("p.safetensors")).unwrap();
    let err = CloudModel::from_bytes(&bytes, &side.to_string(), Path::new("p.safetensors")).unwrap_err();
    assert!(err.to_string().contains("features"), "{err}");
}

/// Distillation: the training targets are exactly 4 pi times the mean of the teachers'
/// predictions at each row, the same for any thread count; the path-traced targets
/// stay for the reports; the teachers are part of the run's identity (a resume with
/// another teacher is refused, with the same one it finishes to the weights of a
/// straight run) and are named in the sidecar.
#[test]
fn distillation_trains_on_the_teachers_mean() {
    let Small { root, data_dir, data, mut cfg, .. } = small_training_set();
    cfg.refit_output = 3;
    let teacher = |seed: u64, name: &str| {
        let c =
            CloudTrainConfig { schedule: models::nn::fit::FitSchedule { seed, ..cfg.schedule.clone() }, ..cfg.clone() };
        train(data.clone(), None, &c, &root.path().join(name), false, "test", "test", &Quiet).unwrap().0
    };
    let (t1, t2) = (teacher(1, "t1"), teacher(2, "t2"));
    let distilled = |threads: usize, teachers: &[&CloudModel], names: &[&str]| {
        let mut d = CloudTrainData::load(std::slice::from_ref(&data_dir)).unwrap();
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| d.distill_from(teachers, names.iter().map(|n| n.to_string()).collect())).unwrap();
        d
    };
    let mut d1 = distilled(1, &[&t1, &t2], &["t1", "t2"]);
    let d3 = distilled(3, &[&t1, &t2], &["t1", "t2"]);
    let y = d1.distilled.as_ref().unwrap().targets.clone();
    assert_eq!(Some(&y), d3.distilled.as_ref().map(|d| &d.targets), "teacher targets depend on the thread count");
    let (mut s1, mut s2) = (t1.mlp.scratch(), t2.mlp.scratch());
    let four_pi = 4.0 * std::f32::consts::PI;
    for (i, row) in data.features.chunks_exact(N_FEATURES).enumerate() {
        let want = (t1.predict_features(row, &mut s1) as f64 + t2.predict_features(row, &mut s2) as f64) / 2.0;
        assert_eq!(y[i], four_pi * want as f32, "row {i}");
    }
    assert_eq!(d1.targets, data.targets, "the path-traced targets must stay for the reports");
    assert!(d1.distill_from(&[], vec![]).is_err(), "no teacher must be refused");

    // Trained on them, stopped and resumed with another teacher: refused; with the
    // same: the straight run's weights. The sidecar names the teachers.
    let (_, report) = train(d1.clone(), None, &cfg, &root.path().join("a"), false, "test", "test", &Quiet).unwrap();
    assert!(report.refit.is_some() && report.test.bias.is_finite());
    train_stopped(&d1, &cfg, &root.path().join("b"));
    let other = distilled(2, &[&t1], &["t1"]);
    let e = train(other.clone(), None, &cfg, &root.path().join("b"), true, "test", "test", &Quiet).err().unwrap();
    assert!(e.to_string().contains("other settings or data"), "{e}");
    train(d1.clone(), None, &cfg, &root.path().join("b"), true, "test", "test", &Quiet).unwrap();
    assert_same_weights(root.path(), "resumed distillation differs");
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.path().join("a.json")).unwrap()).unwrap();
    assert_eq!(side["training"]["teachers"], serde_json::json!(["t1", "t2"]));
    // Trained on the teachers' mean, the student differs from a run on the paths.
    let (plain, _) = train(data.clone(), None, &cfg, &root.path().join("c"), false, "test", "test", &Quiet).unwrap();
    let student = CloudModel::load(&root.path().join("a.safetensors")).unwrap();
    let row = &data.features[..N_FEATURES];
    assert_ne!(
        student.predict_features(row, &mut student.mlp.scratch()),
        plain.predict_features(row, &mut plain.mlp.scratch())
    );
}

/// Two data sets load as one, in order, the second's clouds told apart from the
/// first's; a manifest counting more rows than its files hold is refused before any
/// buffer is reserved for them, and a file cut short is refused after reading.
#[test]
fn data_sets_load_in_order_and_damaged_ones_are_refused() {
    let small = small_training_set();
    let twice = CloudTrainData::load(&[small.data_dir.clone(), small.data_dir.clone()]).unwrap();
    let n = small.data.len();
    assert_eq!(twice.len(), 2 * n);
    assert_eq!(&twice.features[..small.data.features.len()], &small.data.features[..]);
    assert_eq!(&twice.features[small.data.features.len()..], &small.data.features[..]);
    assert_eq!(&twice.targets[5 * n..], &small.data.targets[..]);
    assert_eq!(twice.clouds[n], (1, 0));
    assert_eq!(twice.clouds[n - 1], (0, small.data.clouds[n - 1].1));

    let copy = |name: &str| {
        let d = small.root.path().join(name);
        std::fs::create_dir_all(&d).unwrap();
        for f in ["manifest.json", "features.npy", "targets.npy"] {
            std::fs::copy(small.data_dir.join(f), d.join(f)).unwrap();
        }
        d
    };
    let huge = copy("huge");
    let path = huge.join("manifest.json");
    let mut m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    m["counts"]["points"] = serde_json::json!(1u64 << 50);
    std::fs::write(&path, serde_json::to_string(&m).unwrap()).unwrap();
    let e = CloudTrainData::load(&[huge]).err().unwrap().to_string();
    assert!(e.contains("rows") && e.contains("features.npy"), "{e}");

    let cut = copy("cut");
    let bytes = std::fs::read(cut.join("targets.npy")).unwrap();
    std::fs::write(cut.join("targets.npy"), &bytes[..bytes.len() - 20]).unwrap();
    let e = CloudTrainData::load(&[small.data_dir.clone(), cut]).err().unwrap().to_string();
    assert!(e.contains("targets.npy"), "{e}");
}

/// The recipe's default network is the shipped model's, so `nimbus train cloud` with
/// the documented flags trains a model of the shipped shape.
#[test]
fn the_training_default_is_the_shipped_shape() {
    let shipped = CloudModel::shipped().unwrap();
    assert_eq!(shipped.sidecar.hidden, CloudTrainConfig::default().schedule.hidden);
    assert_eq!(shipped.inputs(), N_FEATURES);
}

/// Fine-tuning: a run started from a model keeps its standardization and, with a
/// learning rate too small to move the weights, returns its predictions; with a real
/// one it moves away from them. A network of another shape is refused naming --init,
/// and the starting model is part of the run's identity (a resume from another model
/// is refused) and named in the sidecar.
#[test]
fn fine_tuning_starts_from_the_model() {
    let Small { root, data_dir, data, cfg, .. } = small_training_set();
    let (base, _) = train(data.clone(), None, &cfg, &root.path().join("base"), false, "test", "test", &Quiet).unwrap();
    let from = |model: &CloudModel, name: &str| {
        let mut d = CloudTrainData::load(std::slice::from_ref(&data_dir)).unwrap();
        d.start_from(model.clone(), name.into());
        d
    };
    let still = CloudTrainConfig {
        schedule: models::nn::fit::FitSchedule { lr: 1e-20, epochs: 1, ..cfg.schedule.clone() },
        ..cfg.clone()
    };
    let (kept, _) =
        train(from(&base, "base"), None, &still, &root.path().join("kept"), false, "test", "test", &Quiet).unwrap();
    assert_eq!(kept.sidecar.feature_mean, base.sidecar.feature_mean);
    assert_eq!(kept.sidecar.feature_std, base.sidecar.feature_std);
    assert_eq!(
        (kept.sidecar.target_mean, kept.sidecar.target_std),
        (base.sidecar.target_mean, base.sidecar.target_std)
    );
    let (mut s1, mut s2) = (base.mlp.scratch(), kept.mlp.scratch());
    for row in data.features.chunks_exact(N_FEATURES) {
        let (a, b) = (base.predict_features(row, &mut s1), kept.predict_features(row, &mut s2));
        assert!((a - b).abs() <= 1e-5 * a.abs().max(1e-6), "{a} vs {b}: a still run moved the model");
    }
    let tuned_cfg = CloudTrainConfig {
        schedule: models::nn::fit::FitSchedule { epochs: 3, ..cfg.schedule.clone() },
        ..cfg.clone()
    };
    let (tuned, _) =
        train(from(&base, "base"), None, &tuned_cfg, &root.path().join("a"), false, "test", "test", &Quiet).unwrap();
    let mut moved = 0usize;
    for row in data.features.chunks_exact(N_FEATURES) {
        moved += (base.predict_features(row, &mut s1) != tuned.predict_features(row, &mut s2)) as usize;
    }
    assert!(moved > 0, "fine-tuning did not move the model");
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.path().join("a.json")).unwrap()).unwrap();
    assert_eq!(side["training"]["init"], serde_json::json!("base"));
    // Stopped and resumed from another starting model: refused; from the same one:
    // the straight run's weights.
    train_stopped(&from(&base, "base"), &tuned_cfg, &root.path().join("b"));
    let e = train(from(&base, "other"), None, &tuned_cfg, &root.path().join("b"), true, "test", "test", &Quiet)
        .err()
        .unwrap();
    assert!(e.to_string().contains("other settings or data"), "{e}");
    train(from(&base, "base"), None, &tuned_cfg, &root.path().join("b"), true, "test", "test", &Quiet).unwrap();
    assert_same_weights(root.path(), "a resumed fine-tuning differs");
    // Another network shape: refused, naming the flag.
    let wide = CloudTrainConfig {
        schedule: models::nn::fit::FitSchedule { hidden: vec![8], ..cfg.schedule.clone() },
        ..cfg.clone()
    };
    let e =
        train(from(&base, "base"), None, &wide, &root.path().join("w"), false, "test", "test", &Quiet).err().unwrap();
    assert!(e.to_string().contains("--init"), "{e}");
}

/// Rows weighted by their targets' predicted noise: the run reports the noise model and
/// records the floor in the sidecar, resumes to the same weights, refuses to resume a
/// run of other weights, and differs from the unweighted run; a set too small for the
/// noise model and a distilled run (whose targets carry no path noise) are refused,
/// naming the flag.
#[test]
fn noise_weighted_training_resumes_and_is_recorded() {
    let Small { root, data, cfg, .. } = small_training_set();
    let weighted = CloudTrainConfig { noise_weights: Some(0.003), ..cfg.clone() };
    let err = train(data.clone(), None, &weighted, &root.path().join("few"), false, "test", "test", &Quiet)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("--noise-weights"), "{err}");
    // Enough rows for the noise model's N_FEATURES + 1 coefficients (four rows each).
    let s = CloudSpec { points: 4000, points_per_cloud: 40, ..spec() };
    let dir = root.path().join("big");
    run(&s, Shard::ALL, &dir, 2, &AtomicBool::new(false)).unwrap();
    let big = CloudTrainData::load(std::slice::from_ref(&dir)).unwrap();
    let (model, report) =
        train(big.clone(), None, &weighted, &root.path().join("a"), false, "test", "test", &Quiet).unwrap();
    let r = report.noise_weights.as_ref().expect("a weighted run reports its noise model");
    assert!(r.fit_rows >= 4 * (N_FEATURES + 1), "{r:?}");
    assert!(r.r_squared.is_finite() && r.weight_quantiles[0] < r.weight_quantiles[2], "{r:?}");
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.path().join("a.json")).unwrap()).unwrap();
    assert_eq!(side["training"]["config"]["noise_weights"].as_f64(), Some(0.003f32 as f64));
    assert!(side["training"]["report"]["noise_weights"]["fit_rows"].is_u64());
    train_stopped(&big, &weighted, &root.path().join("b"));
    let e = train(big.clone(), None, &cfg, &root.path().join("b"), true, "test", "test", &Quiet).err().unwrap();
    assert!(e.to_string().contains("other settings or data"), "{e}");
    train(big.clone(), None, &weighted, &root.path().join("b"), true, "test", "test", &Quiet).unwrap();
    assert_same_weights(root.path(), "resumed weighted training differs");
    let (plain, plain_report) =
        train(big.clone(), None, &cfg, &root.path().join("c"), false, "test", "test", &Quiet).unwrap();
    assert!(plain_report.noise_weights.is_none());
    let row = &big.features[..N_FEATURES];
    assert_ne!(
        model.predict_features(row, &mut model.mlp.scratch()),
        plain.predict_features(row, &mut plain.mlp.scratch())
    );
    let mut distilled = big.clone();
    distilled.distill_from(&[&plain], vec!["plain".into()]).unwrap();
    let e = train(distilled, None, &weighted, &root.path().join("d"), false, "test", "test", &Quiet).err().unwrap();
    assert!(e.to_string().contains("--noise-weights"), "{e}");
}
