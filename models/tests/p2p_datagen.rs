//! The point-to-point data generator: the same bytes for 1 and 2 threads, a run
//! stopped after its first chunk resumes to the same bytes, shards merge to the
//! unsharded data set, settings are checked on resume, every row is consistent, and
//! the data set trains a model that loads and predicts.

use engine::{Bounds3, DensityGrid};
use glam::{UVec3, Vec3};
use models::dataset::Shard;
use models::p2p::datagen::{P2pSpec, generate};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

fn cloud() -> Arc<DensityGrid> {
    let b = Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5));
    Arc::new(
        DensityGrid::from_fn(UVec3::splat(24), b, |p| {
            (1.0 - (p.length() / 0.45).powi(2)).max(0.0) * (1.0 + 0.5 * (7.0 * p.x).sin())
        })
        .unwrap(),
    )
}

fn spec() -> P2pSpec {
    P2pSpec {
        points: 7,
        cloud: "test blob".into(),
        resolution: 24,
        rho: 6.0,
        albedo: 0.9,
        g: 0.0,
        k: 2,
        rotations: 3,
        max_rel_error: 0.3,
        min_samples: 200,
        max_samples: 200_000,
        seed: 5,
        chunk_size: 2,
        ..Default::default()
    }
}

/// A fresh directory `name` below `root`.
fn dir(root: &tempfile::TempDir, name: &str) -> PathBuf {
    root.path().join(name)
}

fn bytes(d: &Path) -> (Vec<u8>, Vec<u8>) {
    (std::fs::read(d.join("features.npy")).unwrap(), std::fs::read(d.join("targets.npy")).unwrap())
}

fn run(s: &P2pSpec, shard: Shard, d: &Path, threads: usize, cancel: &AtomicBool) -> Result<(), String> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    pool.install(|| generate(s, cloud(), shard, d, "test", &|_| {}, cancel)).map(|_| ()).map_err(|e| e.to_string())
}

#[test]
fn deterministic_resumable_and_shardable() {
    let s = spec();
    let never = AtomicBool::new(false);
    let root = tempfile::tempdir().unwrap();
    let dir = |name| dir(&root, name);
    let (a, b) = (dir("a"), dir("b"));
    run(&s, Shard::ALL, &a, 1, &never).unwrap();
    run(&s, Shard::ALL, &b, 2, &never).unwrap();
    assert_eq!(bytes(&a), bytes(&b), "1 and 2 threads differ");

    // Rows: 352 features and 5 targets; T > 0, T_local = D^2 T, the rotations of one
    // point share their targets but not all their features.
    let (shape, t) = models::dataset::npy::read_f32(&a.join("targets.npy")).unwrap();
    assert_eq!(shape, [21, 5]);
    let (fshape, f) = models::dataset::npy::read_f32(&a.join("features.npy")).unwrap();
    assert_eq!(fshape, [21, 352]);
    for r in t.chunks(5) {
        assert!(r[0] > 0.0 && r[1] >= 0.0 && r[2] >= 200.0 && r[3] > 0.0, "{r:?}");
        assert!((r[4] - r[3] * r[3] * r[0]).abs() <= 1e-4 * r[4].abs(), "{r:?}");
    }
    assert_eq!(t[0..5], t[5..10]);
    assert_ne!(f[0..351], f[352..703], "rotations give different feature rows");

    // Stopped after the first chunk, then resumed: the same bytes.
    let c = dir("c");
    let cancel = AtomicBool::new(false);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let stopped = pool.install(|| {
        generate(
            &s,
            cloud(),
            Shard::ALL,
            &c,
            "test",
            &|n| {
                if n >= 2 {
                    cancel.store(true, Ordering::Relaxed)
                }
            },
            &cancel,
        )
    });
    assert!(stopped.is_err(), "the run should have been cancelled");
    assert!(models::dataset::chunk_path(&c, 0).exists());
    run(&s, Shard::ALL, &c, 2, &never).unwrap();
    assert_eq!(bytes(&a), bytes(&c), "resumed run differs");

    // Two shards merged.
    let (s0, s1, m) = (dir("s0"), dir("s1"), dir("m"));
    run(&s, Shard { index: 0, count: 2 }, &s0, 1, &never).unwrap();
    run(&s, Shard { index: 1, count: 2 }, &s1, 1, &never).unwrap();
    std::fs::create_dir_all(&m).unwrap();
    models::dataset::merge::<P2pSpec>(&[s0.clone(), s1.clone()], &m).unwrap();
    assert_eq!(bytes(&a), bytes(&m), "merged shards differ");

    // Other settings in the same directory are refused, naming the flag.
    let e = run(&P2pSpec { rho: 7.0, ..s.clone() }, Shard::ALL, &a, 1, &never).unwrap_err();
    assert!(e.contains("--rho"), "{e}");
    // The data set trains (a small residual network), the model files load, predict
    // finite positive transport for every row, and broken files are refused by name.
    let out = a.join("model/m");
    let cfg = models::p2p::train::P2pTrainConfig {
        arch: models::p2p::net::P2pArch::Residual { width: 16, layers: 2 },
        epochs: 3,
        batch: 4,
        lr_decay: 0.5,
        test_fraction: 0.3,
        ..Default::default()
    };
    let side = models::p2p::train::train(&[a.clone()], &cfg, &out, false, &never, &|_, _| {}).unwrap();
    // Stopped after 1 epoch and resumed: the same weights as the straight run.
    let out2 = a.join("model2/m");
    let stop = AtomicBool::new(false);
    let e =
        models::p2p::train::train(&[a.clone()], &cfg, &out2, false, &stop, &|_, _| stop.store(true, Ordering::Relaxed))
            .unwrap_err();
    assert!(e.contains("--resume"), "{e}");
    models::p2p::train::train(&[a.clone()], &cfg, &out2, true, &never, &|_, _| {}).unwrap();
    assert_eq!(
        std::fs::read(a.join("model/m.safetensors")).unwrap(),
        std::fs::read(a.join("model2/m.safetensors")).unwrap(),
        "resumed training differs"
    );
    // A checkpoint of other settings is refused, the learning-rate decay included.
    for other in [
        models::p2p::train::P2pTrainConfig { lr: 0.5, ..cfg.clone() },
        models::p2p::train::P2pTrainConfig { lr_decay: 1.0, ..cfg.clone() },
    ] {
        let e = models::p2p::train::train(&[a.clone()], &other, &out2, true, &never, &|_, _| {}).unwrap_err();
        assert!(e.contains("other settings"), "{e}");
    }
    // The decay is applied (with a constant rate the second and third epochs train
    // other weights) and recorded in the sidecar.
    let out3 = a.join("model3/m");
    let constant = models::p2p::train::P2pTrainConfig { lr_decay: 1.0, ..cfg.clone() };
    models::p2p::train::train(&[a.clone()], &constant, &out3, false, &never, &|_, _| {}).unwrap();
    assert_ne!(
        std::fs::read(a.join("model/m.safetensors")).unwrap(),
        std::fs::read(a.join("model3/m.safetensors")).unwrap(),
        "--lr-decay changed nothing"
    );
    assert_eq!(side.lr_decay, 0.5);
    // The first epoch trains at the full rate: one epoch with decay 0.5 is one at 1.
    let one = |decay: f64, name: &str| {
        let cfg1 = models::p2p::train::P2pTrainConfig { epochs: 1, lr_decay: decay, ..cfg.clone() };
        let o = a.join(format!("{name}/m"));
        models::p2p::train::train(&[a.clone()], &cfg1, &o, false, &never, &|_, _| {}).unwrap();
        std::fs::read(a.join(format!("{name}/m.safetensors"))).unwrap()
    };
    assert_eq!(one(0.5, "model4"), one(1.0, "model5"), "the first epoch is decayed");
    let bad = models::p2p::train::P2pTrainConfig { lr_decay: 0.0, ..cfg.clone() };
    let e = models::p2p::train::train(&[a.clone()], &bad, &a.join("model6/m"), false, &never, &|_, _| {}).unwrap_err();
    assert!(e.contains("decay"), "{e}");
    for (bad, flag) in [
        (models::p2p::train::P2pTrainConfig { epochs: 0, ..cfg.clone() }, "--epochs"),
        (models::p2p::train::P2pTrainConfig { lr: f64::NAN, ..cfg.clone() }, "--lr"),
        (models::p2p::train::P2pTrainConfig { lr_decay: 1.5, ..cfg.clone() }, "--lr-decay"),
    ] {
        let e = bad.validate().unwrap_err();
        assert!(e.starts_with(flag), "{e}");
    }
    assert!(side.test_mse.is_finite() && side.feature_mean.len() == 352);
    let weights = a.join("model/m.safetensors");
    for ext in ["json", "loss.csv", "loss.png"] {
        assert!(a.join(format!("model/m.{ext}")).exists(), "{ext}");
    }
    let model = models::p2p::model::P2pModel::load(&weights).unwrap();
    let mut input = vec![];
    let mut scratch = Default::default();
    for (row, tr) in f.chunks(352).zip(t.chunks(5)) {
        let p = model.predict_features(row, tr[3], &mut input, &mut scratch);
        assert!(p.is_finite() && p > 0.0, "{p}");
    }
    std::fs::write(a.join("model/m.json"), "{}").unwrap();
    let e = models::p2p::model::P2pModel::load(&weights).err().unwrap();
    assert!(e.contains("m.json"), "{e}");
    std::fs::write(&weights, b"junk").unwrap();
    let e = models::p2p::model::P2pModel::load(&weights).err().unwrap();
    assert!(e.contains("m.json") || e.contains("m.safetensors"), "{e}");
}
