//! `nimbus eval temporal`: how a turntable flickers. Given the frames of a mode and
//! the path-traced reference frames of the same turntable (`nimbus turntable`), the
//! temporal error is the mean over pixels and frame pairs of
//! |(I_t - I_{t-1}) - (R_t - R_{t-1})| divided by the mean of R: what changes between
//! frames that should not (noise, a model's jumps), measured against what should
//! (the cloud turning). Given the same turntable rendered with several seeds, the
//! static flicker is the per-pixel standard deviation over the seeds divided by the
//! mean, averaged over frames.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct EvalTemporalArgs {
    /// Turntable folders of the mode to judge (one per seed for the flicker; the
    /// temporal error uses each and reports their mean).
    #[arg(long, num_args = 1.., required = true)]
    pub frames: Vec<PathBuf>,
    /// The path-traced reference turntable (same scene, frames and orbit).
    #[arg(long)]
    pub reference: Option<PathBuf>,
}

/// The full image of every frame of a turntable folder, in order; all the frames its
/// manifest names must be there (a stopped turntable is not scored).
pub fn read_frames(dir: &Path) -> Result<Vec<(u32, u32, Vec<f32>)>> {
    let manifest = dir.join("turntable.json");
    let expected = std::fs::read_to_string(&manifest)
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["frames"].as_u64());
    let mut frames = Vec::new();
    for i in 0.. {
        let path = dir.join(format!("{}.exr", crate::cli::turntable::frame_stem(i)));
        if !path.is_file() {
            break;
        }
        let (w, h, layers) = crate::output::read_exr(&path)?;
        let full =
            layers.iter().find(|l| l.name == "full").with_context(|| format!("{}: no full layer", path.display()))?;
        // Luminance as the mean of the channels.
        let lum: Vec<f32> = full.rgb.iter().map(|p| (p[0] + p[1] + p[2]) / 3.0).collect();
        frames.push((w, h, lum));
    }
    if frames.is_empty() {
        bail!("{}: no frames (frame-0000.exr ...)", dir.display());
    }
    if let Some(n) = expected.filter(|n| *n != frames.len() as u64) {
        bail!(
            "{}: {} of its {n} frames are there; finish the turntable (the same command resumes) first",
            dir.display(),
            frames.len()
        );
    }
    if let Some(i) = frames.iter().position(|f| (f.0, f.1) != (frames[0].0, frames[0].1)) {
        bail!("{}: frame {i} is not {} x {} like frame 0", dir.display(), frames[0].0, frames[0].1);
    }
    Ok(frames)
}

/// Mean |(I_t - I_{t-1}) - (R_t - R_{t-1})| / mean(R) over the frame pairs.
pub fn temporal_error(frames: &[Vec<f32>], reference: &[Vec<f32>]) -> f64 {
    let (mut err, mut n) = (0.0f64, 0usize);
    for t in 1..frames.len().min(reference.len()) {
        for p in 0..frames[t].len() {
            let di = frames[t][p] as f64 - frames[t - 1][p] as f64;
            let dr = reference[t][p] as f64 - reference[t - 1][p] as f64;
            err += (di - dr).abs();
            n += 1;
        }
    }
    let mean: f64 = reference.iter().flatten().map(|v| *v as f64).sum::<f64>()
        / reference.iter().map(|f| f.len()).sum::<usize>().max(1) as f64;
    // No light in the reference: the figure means nothing (not "no error").
    if n == 0 || mean <= 0.0 { f64::NAN } else { err / n as f64 / mean }
}

/// The relative bias of docs/conventions.md on luminance, averaged over frames: per
/// frame, the mean over 16 x 16 pixel blocks (with light in the reference) of
/// |block mean of `frames` - block mean of `reference`| over the mean reference block.
pub fn block_bias(frames: &[Vec<f32>], reference: &[Vec<f32>], w: usize, h: usize) -> f64 {
    let mut total = 0.0;
    let n = frames.len().min(reference.len());
    for t in 0..n {
        let (mut err, mut sum, mut blocks) = (0.0f64, 0.0f64, 0usize);
        for by in (0..h).step_by(16) {
            for bx in (0..w).step_by(16) {
                let (mut a, mut b, mut c) = (0.0f64, 0.0f64, 0usize);
                for y in by..(by + 16).min(h) {
                    for x in bx..(bx + 16).min(w) {
                        a += frames[t][y * w + x] as f64;
                        b += reference[t][y * w + x] as f64;
                        c += 1;
                    }
                }
                if b > 0.0 {
                    err += (a - b).abs() / c as f64;
                    sum += b / c as f64;
                    blocks += 1;
                }
            }
        }
        if blocks > 0 && sum > 0.0 {
            total += err / sum;
        }
    }
    if n == 0 { 0.0 } else { total / n as f64 }
}

/// Per-pixel standard deviation over `runs` (the same frames, other seeds) divided
/// by the mean, averaged over frames.
pub fn static_flicker(runs: &[Vec<Vec<f32>>]) -> f64 {
    let s = runs.len();
    if s < 2 {
        return f64::NAN;
    }
    let frames = runs.iter().map(|r| r.len()).min().unwrap_or(0);
    let (mut sum, mut count) = (0.0f64, 0usize);
    for t in 0..frames {
        let (mut sd, mut mean) = (0.0f64, 0.0f64);
        let px = runs[0][t].len();
        for p in 0..px {
            let m = runs.iter().map(|r| r[t][p] as f64).sum::<f64>() / s as f64;
            let v = runs.iter().map(|r| (r[t][p] as f64 - m).powi(2)).sum::<f64>() / (s - 1) as f64;
            sd += v.sqrt();
            mean += m;
        }
        if mean > 0.0 {
            sum += sd / mean;
            count += 1;
        }
    }
    if count == 0 { 0.0 } else { sum / count as f64 }
}

pub fn eval_temporal(args: &EvalTemporalArgs) -> Result<serde_json::Value> {
    let runs: Vec<Vec<(u32, u32, Vec<f32>)>> = args.frames.iter().map(|d| read_frames(d)).collect::<Result<_>>()?;
    let size = (runs[0][0].0, runs[0][0].1);
    for (dir, run) in args.frames.iter().zip(&runs) {
        if run.len() != runs[0].len() || run.iter().any(|f| (f.0, f.1) != size) {
            bail!("{}: not the same frames as {} (count or size)", dir.display(), args.frames[0].display());
        }
    }
    let images: Vec<Vec<Vec<f32>>> = runs.into_iter().map(|r| r.into_iter().map(|f| f.2).collect()).collect();
    let temporal = match &args.reference {
        Some(dir) => {
            let reference = read_frames(dir)?;
            if reference.len() != images[0].len() || reference.iter().any(|f| (f.0, f.1) != size) {
                bail!("{}: not the same frames as {} (count or size)", dir.display(), args.frames[0].display());
            }
            let reference: Vec<Vec<f32>> = reference.into_iter().map(|f| f.2).collect();
            let temporal = images.iter().map(|r| temporal_error(r, &reference)).sum::<f64>() / images.len() as f64;
            let bias = images.iter().map(|r| block_bias(r, &reference, size.0 as usize, size.1 as usize)).sum::<f64>()
                / images.len() as f64;
            Some((temporal, bias))
        }
        None => None,
    };
    let flicker = static_flicker(&images);
    let out = serde_json::json!({
        "frames": images[0].len(),
        "seeds": images.len(),
        "temporal_error": temporal.map(|t| t.0),
        // The relative bias against the reference (16 x 16 blocks, mean over frames
        // and seeds); noise in either adds to it.
        "relative_bias": temporal.map(|t| t.1),
        "static_flicker": flicker.is_finite().then_some(flicker),
    });
    println!("{out}");
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frames equal to the reference have no temporal error; a constant offset
    /// between the two (bias that does not move) has none either; independent noise
    /// of standard deviation s has E|N(0, s sqrt 2)| = 2 s / sqrt(pi) per pixel.
    #[test]
    fn temporal_error_and_flicker_closed_forms() {
        let mut rng = engine::Rng::new(7, 0, 0);
        let reference: Vec<Vec<f32>> =
            (0..20).map(|t| (0..2000).map(|p| 1.0 + 0.3 * ((t + p) % 7) as f32).collect()).collect();
        let mean: f64 = reference.iter().flatten().map(|v| *v as f64).sum::<f64>() / (20.0 * 2000.0);
        assert_eq!(temporal_error(&reference, &reference), 0.0);
        let biased: Vec<Vec<f32>> = reference.iter().map(|f| f.iter().map(|v| v * 1.0 + 0.2).collect()).collect();
        assert!(temporal_error(&biased, &reference) < 1e-6);
        let s = 0.1f64;
        let mut gauss = move || {
            let (u1, u2) = (rng.uniform().max(1e-12) as f64, rng.uniform() as f64);
            (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
        };
        let noisy: Vec<Vec<f32>> =
            reference.iter().map(|f| f.iter().map(|v| (*v as f64 + s * gauss()) as f32).collect()).collect();
        let expect = 2.0 * s / std::f64::consts::PI.sqrt() / mean;
        let got = temporal_error(&noisy, &reference);
        // 19 x 2000 terms: the mean's relative standard error is below 1 %.
        assert!((got - expect).abs() < 0.03 * expect, "{got} vs {expect}");
        // Flicker of 4 seeds of noise s: E[sample sd] = c4(4) s, c4(4) = 0.9213.
        let runs: Vec<Vec<Vec<f32>>> = (0..4)
            .map(|_| reference.iter().map(|f| f.iter().map(|v| (*v as f64 + s * gauss()) as f32).collect()).collect())
            .collect();
        let flicker = static_flicker(&runs);
        let expect = 0.9213 * s / mean;
        assert!((flicker - expect).abs() < 0.03 * expect, "{flicker} vs {expect}");
        assert!(static_flicker(&runs[..1]).is_nan());
        // A 10 % brighter image is 10 % biased, the reference itself not at all.
        let (w, h) = (50, 40);
        let r: Vec<Vec<f32>> = (0..3).map(|t| (0..w * h).map(|p| 1.0 + ((p + t) % 5) as f32).collect()).collect();
        let brighter: Vec<Vec<f32>> = r.iter().map(|f| f.iter().map(|v| v * 1.1).collect()).collect();
        assert!((block_bias(&brighter, &r, w, h) - 0.1).abs() < 1e-6);
        assert_eq!(block_bias(&r, &r, w, h), 0.0);
    }
}
