//! The point-to-point networks: the evaluator reproduces candle's forward pass, the
//! residual network has the thesis's block structure, and it learns a function of
//! the per-level densities.

use candle_core::{Device, Tensor};
use engine::Rng;
use models::p2p::features::P2pFeatures;
use models::p2p::net::{P2pArch, P2pNetwork, P2pScratch};

fn rows(n: usize, len: usize, rng: &mut Rng) -> Vec<f32> {
    (0..n * len).map(|_| 3.0 * rng.uniform()).collect()
}

#[test]
fn evaluator_matches_candle() {
    let spec = P2pFeatures::default();
    let mut rng = Rng::new(1, 0, 0);
    // Scratch that outlives one network and meets another (a render thread's does):
    // the narrow residual network first, then the wide one, then the MLP.
    let (mut shared, mut shared_batch) = (P2pScratch::default(), Default::default());
    for arch in [P2pArch::Residual { width: 16, layers: 2 }, P2pArch::default(), P2pArch::Mlp { hidden: vec![400, 32] }]
    {
        let net = P2pNetwork::new(&spec, arch.clone(), 7, &Device::Cpu).unwrap();
        let x = rows(8, spec.len(), &mut rng);
        let want: Vec<f32> = net
            .forward(&Tensor::from_vec(x.clone(), (8, spec.len()), &Device::Cpu).unwrap())
            .unwrap()
            .to_vec1()
            .unwrap();
        let eval = net.evaluator().unwrap();
        let mut scratch = eval.scratch();
        let single: Vec<f32> = x.chunks(spec.len()).map(|r| eval.forward(r, &mut scratch)).collect();
        let portable: Vec<f32> = x.chunks(spec.len()).map(|r| eval.forward_portable(r, &mut scratch)).collect();
        // Batched, with a group that is not full (8 rows as 5 + 3 would be; here 8
        // and then 3 of them again).
        let mut batch = Default::default();
        let mut got = vec![0.0; 8];
        eval.forward_batch(&x, &mut got, &mut batch);
        let mut tail = vec![0.0; 3];
        eval.forward_batch(&x[..3 * spec.len()], &mut tail, &mut batch);
        let reused: Vec<f32> = x.chunks(spec.len()).map(|r| eval.forward(r, &mut shared)).collect();
        let mut reused_batch = vec![0.0; 8];
        eval.forward_batch(&x, &mut reused_batch, &mut shared_batch);
        // The portable batch kernel, 7 rows (a group that is not a multiple of four).
        let mut portable_batch = vec![0.0; 7];
        eval.forward_batch_portable(&x[..7 * spec.len()], &mut portable_batch, &mut Default::default());
        for (i, w) in want.iter().enumerate() {
            for g in [single[i], portable[i], got[i], reused[i], reused_batch[i]]
                .into_iter()
                .chain(tail.get(i).copied())
                .chain(portable_batch.get(i).copied())
            {
                assert!((g - w).abs() <= 1e-4 * (1.0 + w.abs()), "{arch:?} row {i}: {g} vs {w}");
            }
        }
    }
}

/// Figure 6.4 with the defaults: 9 blocks (4 local levels of 54 densities, 5 global
/// of 27), 3 layers of 200 each, residual inputs of 200 from the second block on,
/// phi_D into the last block, one linear output.
#[test]
fn residual_network_has_the_thesis_structure() {
    let spec = P2pFeatures::default();
    let net = P2pNetwork::new(&spec, P2pArch::default(), 1, &Device::Cpu).unwrap();
    let layer = |i: usize, o: usize| i * o + o;
    let mut expected = 0;
    for (b, s) in spec.slices().iter().enumerate() {
        let input = s.len + if b > 0 { 200 } else { 0 } + if b == 8 { 1 } else { 0 };
        expected += layer(input, 200) + 2 * layer(200, 200);
    }
    expected += layer(200, 1);
    assert_eq!(net.parameters(), expected);
    assert_eq!(net.n_inputs(), 352);
}

/// A target that depends on every level's mean density (and phi_D) is learned to a
/// test error below a tenth of its variance.
#[test]
fn residual_network_learns_level_densities() {
    let spec = P2pFeatures::default();
    let slices = spec.slices();
    let mut rng = Rng::new(2, 0, 0);
    let make = |n: usize, rng: &mut Rng| {
        let mut x = vec![0.0f32; n * spec.len()];
        let mut y = vec![0.0f32; n];
        for r in 0..n {
            let row = &mut x[r * spec.len()..(r + 1) * spec.len()];
            let mut t = 0.0;
            for (b, s) in slices.iter().enumerate() {
                let level = 2.0 * rng.uniform();
                for v in &mut row[s.start..s.start + s.len] {
                    *v = level * (0.8 + 0.4 * rng.uniform());
                }
                t += level * (1.0 + b as f32) / 9.0;
            }
            row[spec.len() - 1] = rng.uniform();
            y[r] = (1.0 + t).ln() + 0.3 * row[spec.len() - 1];
        }
        (x, y)
    };
    let (x, y) = make(3000, &mut rng);
    let (xt, yt) = make(500, &mut rng);
    let net = P2pNetwork::new(&spec, P2pArch::Residual { width: 32, layers: 2 }, 3, &Device::Cpu).unwrap();
    let history = net.fit(&x, &y, 30, 50, 2e-3, 4).unwrap();
    assert!(history.last().unwrap() < &history[0], "{history:?}");
    let eval = net.evaluator().unwrap();
    let mut s = eval.scratch();
    let mean = yt.iter().sum::<f32>() / yt.len() as f32;
    let var = yt.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / yt.len() as f32;
    let mse = (0..yt.len())
        .map(|r| (eval.forward(&xt[r * spec.len()..(r + 1) * spec.len()], &mut s) - yt[r]).powi(2))
        .sum::<f32>()
        / yt.len() as f32;
    println!("test mse {mse:.5}, target variance {var:.5}");
    assert!(mse < 0.1 * var, "test mse {mse} vs variance {var}");
}
