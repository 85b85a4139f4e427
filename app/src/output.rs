//! Files out: multi-layer EXR of all buffers, tone-mapped PNG, NumPy arrays and
//! Mitsuba volumes. Everything is written atomically: to a temporary file beside the
//! target, then renamed over it, so a crash or Ctrl-C never leaves half a file.

use anyhow::{Context, Result};
use engine::{Buffer, DensityGrid, Film};
use std::path::Path;

/// Runs `write` on a temporary file, then renames it to `path`
/// ([`models::dataset::npy::write_atomically`]); every error names the file once
/// (that helper's own do already).
pub fn write_atomically(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    models::dataset::npy::write_atomically(path, |tmp| {
        write(tmp).with_context(|| format!("cannot write {}", path.display()))
    })
}

/// Creates directory `dir` and its parents, naming it in the error.
pub fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create directory {}", dir.display()))
}

/// Writes bytes atomically (the error names the file).
pub fn write_bytes_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(models::dataset::npy::write_bytes_atomically(path, bytes)?)
}

/// One named RGB layer of an EXR file.
pub struct ExrLayer {
    pub name: String,
    pub rgb: Vec<[f32; 3]>,
}

/// The layers a render writes: full, direct, low, high, and the per-pixel variance of
/// the full estimate.
pub fn film_layers(film: &Film) -> Vec<ExrLayer> {
    let mut layers: Vec<ExrLayer> = [Buffer::Full, Buffer::Direct, Buffer::Low, Buffer::High]
        .iter()
        .map(|b| ExrLayer { name: b.name().into(), rgb: film.mean(*b) })
        .collect();
    layers.push(ExrLayer { name: "variance".into(), rgb: film.variance_of_mean(Buffer::Full) });
    layers
}

/// A single-part EXR whose channels are `layer.R`, `layer.G`, `layer.B` for each layer:
/// the classic OpenEXR multi-layer layout that exrheader, Nuke, Blender and
/// OpenImageIO read. 32-bit float, ZIP compression.
pub fn write_exr(path: &Path, width: u32, height: u32, layers: &[ExrLayer]) -> Result<()> {
    use exr::prelude::*;
    let mut channels: Vec<AnyChannel<FlatSamples>> = Vec::new();
    for layer in layers {
        anyhow::ensure!(layer.rgb.len() == (width * height) as usize, "layer {} has the wrong size", layer.name);
        for (c, suffix) in ["R", "G", "B"].iter().enumerate() {
            let data: Vec<f32> = layer.rgb.iter().map(|p| p[c]).collect();
            channels.push(AnyChannel::new(format!("{}.{suffix}", layer.name).as_str(), FlatSamples::F32(data)));
        }
    }
    let layer = Layer::new(
        (width as usize, height as usize),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    let image = Image::from_layer(layer);
    write_atomically(path, |tmp| image.write().to_file(tmp).map_err(|e| anyhow::anyhow!("EXR encoding failed: {e}")))
}

/// Reads an EXR written by [`write_exr`] back: (width, height, layers by name).
pub fn read_exr(path: &Path) -> Result<(u32, u32, Vec<ExrLayer>)> {
    use exr::prelude::*;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .with_context(|| format!("cannot read EXR {}", path.display()))?;
    let size = image.layer_data.size;
    let mut layers: Vec<ExrLayer> = Vec::new();
    for ch in &image.layer_data.channel_data.list {
        let full = ch.name.to_string();
        let (name, comp) = full.rsplit_once('.').unwrap_or(("", full.as_str()));
        let c = match comp {
            "R" => 0,
            "G" => 1,
            "B" => 2,
            _ => continue,
        };
        let idx = match layers.iter().position(|l| l.name == name) {
            Some(i) => i,
            None => {
                layers.push(ExrLayer { name: name.to_string(), rgb: vec![[0.0; 3]; size.area()] });
                layers.len() - 1
            }
        };
        for (i, v) in ch.sample_data.values_as_f32().enumerate() {
            layers[idx].rgb[i][c] = v;
        }
    }
    Ok((size.width() as u32, size.height() as u32, layers))
}

/// How linear radiance becomes display values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ToneMap {
    /// Exposure, clamp, sRGB transfer curve.
    Clamp,
    /// Exposure, then a filmic shoulder (Narkowicz's ACES fit), then sRGB.
    Filmic,
}

impl ToneMap {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "clamp" => Some(ToneMap::Clamp),
            "filmic" => Some(ToneMap::Filmic),
            _ => None,
        }
    }

    #[inline]
    pub fn apply(&self, linear: f32, exposure_ev: f32) -> u8 {
        let x = (linear * exposure_ev.exp2()).max(0.0);
        let y = match self {
            ToneMap::Clamp => x.min(1.0),
            ToneMap::Filmic => ((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0),
        };
        let s = if y <= 0.003_130_8 { 12.92 * y } else { 1.055 * y.powf(1.0 / 2.4) - 0.055 };
        (s * 255.0 + 0.5).clamp(0.0, 255.0) as u8
    }

    /// Tone-mapped 8-bit RGB pixels.
    pub fn to_rgb8(&self, rgb: &[[f32; 3]], exposure_ev: f32) -> Vec<[u8; 3]> {
        rgb.iter().map(|p| p.map(|v| self.apply(v, exposure_ev))).collect()
    }

    /// Display RGBA8 pixels of a linear image.
    pub fn to_rgba8(&self, rgb: &[[f32; 3]], exposure_ev: f32) -> Vec<u8> {
        let mut out = Vec::with_capacity(rgb.len() * 4);
        for p in rgb {
            out.extend_from_slice(&[
                self.apply(p[0], exposure_ev),
                self.apply(p[1], exposure_ev),
                self.apply(p[2], exposure_ev),
                255,
            ]);
        }
        out
    }
}

/// Writes a tone-mapped PNG.
pub fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    rgb: &[[f32; 3]],
    tone: ToneMap,
    exposure_ev: f32,
) -> Result<()> {
    let rgba = tone.to_rgba8(rgb, exposure_ev);
    let img = image::RgbaImage::from_raw(width, height, rgba).context("image size mismatch")?;
    write_atomically(path, |tmp| img.save_with_format(tmp, image::ImageFormat::Png).map_err(Into::into))
}

pub use models::dataset::npy::npy_bytes_f32;

/// Writes an (height, width, 3) float32 image as .npy.
pub fn write_npy_image(path: &Path, width: u32, height: u32, rgb: &[[f32; 3]]) -> Result<()> {
    let flat: Vec<f32> = rgb.iter().flatten().copied().collect();
    write_bytes_atomically(path, &npy_bytes_f32(&[height as usize, width as usize, 3], &flat))
}

/// Mitsuba's binary grid volume (.vol, version 3, float32, one channel). The grid is
/// padded with one voxel of zeros on every side, so that Mitsuba's clamp-to-edge
/// lookup agrees with our zero-outside lookup; the bounding box grows to match.
pub fn mitsuba_vol_bytes(grid: &DensityGrid) -> Vec<u8> {
    let n = grid.dims();
    let (px, py, pz) = (n.x + 2, n.y + 2, n.z + 2);
    let b = grid.bounds();
    let vs = grid.voxel_size();
    let (lo, hi) = (b.min - vs, b.max + vs);
    let mut out = Vec::with_capacity(48 + 4 * (px * py * pz) as usize);
    out.extend_from_slice(b"VOL");
    out.push(3);
    for v in [1i32, px as i32, py as i32, pz as i32, 1] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for v in [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for z in 0..pz {
        for y in 0..py {
            for x in 0..px {
                let inside = x >= 1 && y >= 1 && z >= 1 && x <= n.x && y <= n.y && z <= n.z;
                let v = if inside { grid.voxel(x - 1, y - 1, z - 1) } else { 0.0 };
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tone_map_is_monotone_and_bounded() {
        for t in [ToneMap::Clamp, ToneMap::Filmic] {
            assert_eq!(t.apply(0.0, 0.0), 0);
            assert_eq!(t.apply(1e9, 0.0), 255);
            let mut last = 0;
            for i in 0..100 {
                let v = t.apply(i as f32 * 0.05, 0.0);
                assert!(v >= last);
                last = v;
            }
        }
    }

    #[test]
    fn atomic_write_leaves_no_temporary_on_failure() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().to_path_buf();
        let target = dir.join("x.bin");
        std::fs::write(&target, b"old").unwrap();
        let r = write_atomically(&target, |tmp| {
            std::fs::write(tmp, b"half")?;
            anyhow::bail!("simulated failure")
        });
        assert!(r.is_err());
        assert_eq!(std::fs::read(&target).unwrap(), b"old", "old file intact");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "temporary removed");
        write_bytes_atomically(&target, b"new").unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
    }
}
