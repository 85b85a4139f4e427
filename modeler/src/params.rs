//! Modeler parameters: one serde struct, every field with its range and default.
//! Out-of-range values are errors naming the parameter and its range.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{name} = {value} is out of range: {range}")]
pub struct ParamError {
    pub name: &'static str,
    pub value: String,
    pub range: &'static str,
}

/// Parameters of a procedural cloud. Lengths are in units of the cloud box
/// [-0.5, 0.5]^3: the hierarchy is scaled to fit the box (with `margin`) after it is
/// grown, so sizes are relative.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CloudParams {
    /// Seed of the hierarchy and of every noise (any u64). Default 1.
    pub seed: u64,
    /// Root spheres, 1 ..= 8. Default 1.
    pub roots: u32,
    /// Root sphere radius before fitting, 0.05 ..= 0.5. Default 0.3.
    pub root_radius: f32,
    /// Horizontal spread of the root centres, 0 ..= 1. Default 0.25.
    pub root_spread: f32,
    /// Levels of children below the roots, 0 ..= 4. Default 2.
    pub levels: u32,
    /// Children per sphere, 0 ..= 10. Default 4.
    pub children: u32,
    /// Child radius / parent radius, 0.2 ..= 0.9. Default 0.55.
    pub radius_ratio: f32,
    /// Preference for children on the upper side, 0 ..= 2. Default 0.6.
    pub upward_bias: f32,
    /// Preference for children pointing away from the cloud's centre, 0 ..= 2. Default 0.5.
    pub outward_bias: f32,
    /// Flat base: 0 = none, 1 = cut at the roots' centres (cumulus-like). 0 ..= 1.
    /// Default 0.5.
    pub flatten_base: f32,
    /// Smooth-union width between spheres, 0 ..= 0.2. Default 0.04.
    pub blend: f32,
    /// Width over which density falls from 1 to 0 inside the boundary,
    /// 0.002 ..= 0.3. Default 0.04.
    pub falloff: f32,
    /// Boundary displacement amplitude, 0 ..= 0.2. Default 0.03.
    pub displacement: f32,
    /// Displacement noise base frequency (cycles per unit), 0.5 ..= 64. Default 6.
    pub frequency: f32,
    /// fBm octaves, 1 ..= 8. Default 4.
    pub octaves: u32,
    /// Frequency ratio between octaves, 1.5 ..= 3. Default 2.
    pub lacunarity: f32,
    /// Amplitude ratio between octaves, 0.2 ..= 0.8. Default 0.5.
    pub gain: f32,
    /// Mix of Worley (cellular, billowy) into the Perlin displacement, 0 ..= 1.
    /// Default 0.3.
    pub worley: f32,
    /// Domain warp ("advection") strength, 0 ..= 0.2. Default 0.
    pub advection: f32,
    /// Domain warp frequency, 0.5 ..= 32. Default 3.
    pub advection_frequency: f32,
    /// Interior noise: 0 = homogeneous, 1 = density fully modulated, 0 ..= 1. Default 0.
    pub interior: f32,
    /// Interior noise frequency, 0.5 ..= 64. Default 8.
    pub interior_frequency: f32,
    /// Empty border kept around the cloud inside the box, 0 ..= 0.2. Default 0.04.
    pub margin: f32,
}

impl Default for CloudParams {
    fn default() -> Self {
        CloudParams {
            seed: 1,
            roots: 1,
            root_radius: 0.3,
            root_spread: 0.25,
            levels: 2,
            children: 4,
            radius_ratio: 0.55,
            upward_bias: 0.6,
            outward_bias: 0.5,
            flatten_base: 0.5,
            blend: 0.04,
            falloff: 0.04,
            displacement: 0.03,
            frequency: 6.0,
            octaves: 4,
            lacunarity: 2.0,
            gain: 0.5,
            worley: 0.3,
            advection: 0.0,
            advection_frequency: 3.0,
            interior: 0.0,
            interior_frequency: 8.0,
            margin: 0.04,
        }
    }
}

fn check_f(name: &'static str, v: f32, lo: f32, hi: f32, range: &'static str) -> Result<(), ParamError> {
    if v.is_finite() && v >= lo && v <= hi { Ok(()) } else { Err(ParamError { name, value: v.to_string(), range }) }
}

fn check_u(name: &'static str, v: u32, lo: u32, hi: u32, range: &'static str) -> Result<(), ParamError> {
    if v >= lo && v <= hi { Ok(()) } else { Err(ParamError { name, value: v.to_string(), range }) }
}

impl CloudParams {
    /// A random cloud: every parameter drawn over its range from `seed` (uniformly,
    /// frequencies log-uniformly), with the hierarchy kept to at most 3 levels of at
    /// most 6 children (about 2,000 spheres at the most, so a cloud builds in well
    /// under a second) and the noise amplitudes drawn from zero up, so smooth and hard
    /// clouds, wispy and homogeneous ones all occur. The same seed gives the same
    /// parameters on any machine.
    pub fn random(seed: u64) -> CloudParams {
        let mut rng = engine::Rng::new(seed, 0x636c_6f75_64, 0); // "cloud"
        let mut u = move || rng.uniform();
        let lin = |lo: f32, hi: f32, u: f32| lo + (hi - lo) * u;
        let log = |lo: f32, hi: f32, u: f32| (lo.ln() + (hi.ln() - lo.ln()) * u).exp();
        let int = |lo: u32, hi: u32, u: f32| (lo + ((hi - lo + 1) as f32 * u) as u32).min(hi);
        CloudParams {
            seed: seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 16,
            roots: int(1, 8, u()),
            root_radius: lin(0.1, 0.5, u()),
            root_spread: lin(0.0, 1.0, u()),
            levels: int(0, 3, u()),
            children: int(0, 6, u()),
            radius_ratio: lin(0.3, 0.8, u()),
            upward_bias: lin(0.0, 2.0, u()),
            outward_bias: lin(0.0, 2.0, u()),
            flatten_base: lin(0.0, 1.0, u()),
            blend: lin(0.0, 0.2, u()),
            falloff: log(0.002, 0.3, u()),
            displacement: lin(0.0, 0.12, u()) * u(),
            frequency: log(1.0, 32.0, u()),
            octaves: int(1, 6, u()),
            lacunarity: lin(1.5, 3.0, u()),
            gain: lin(0.2, 0.8, u()),
            worley: lin(0.0, 1.0, u()),
            advection: lin(0.0, 0.2, u()) * u(),
            advection_frequency: log(0.5, 16.0, u()),
            interior: lin(0.0, 1.0, u()) * u(),
            interior_frequency: log(1.0, 32.0, u()),
            margin: lin(0.02, 0.1, u()),
        }
    }

    pub fn validate(&self) -> Result<(), ParamError> {
        check_u("roots", self.roots, 1, 8, "1 ..= 8")?;
        check_f("root_radius", self.root_radius, 0.05, 0.5, "0.05 ..= 0.5")?;
        check_f("root_spread", self.root_spread, 0.0, 1.0, "0 ..= 1")?;
        check_u("levels", self.levels, 0, 4, "0 ..= 4")?;
        check_u("children", self.children, 0, 10, "0 ..= 10")?;
        check_f("radius_ratio", self.radius_ratio, 0.2, 0.9, "0.2 ..= 0.9")?;
        check_f("upward_bias", self.upward_bias, 0.0, 2.0, "0 ..= 2")?;
        check_f("outward_bias", self.outward_bias, 0.0, 2.0, "0 ..= 2")?;
        check_f("flatten_base", self.flatten_base, 0.0, 1.0, "0 ..= 1")?;
        check_f("blend", self.blend, 0.0, 0.2, "0 ..= 0.2")?;
        check_f("falloff", self.falloff, 0.002, 0.3, "0.002 ..= 0.3")?;
        check_f("displacement", self.displacement, 0.0, 0.2, "0 ..= 0.2")?;
        check_f("frequency", self.frequency, 0.5, 64.0, "0.5 ..= 64")?;
        check_u("octaves", self.octaves, 1, 8, "1 ..= 8")?;
        check_f("lacunarity", self.lacunarity, 1.5, 3.0, "1.5 ..= 3")?;
        check_f("gain", self.gain, 0.2, 0.8, "0.2 ..= 0.8")?;
        check_f("worley", self.worley, 0.0, 1.0, "0 ..= 1")?;
        check_f("advection", self.advection, 0.0, 0.2, "0 ..= 0.2")?;
        check_f("advection_frequency", self.advection_frequency, 0.5, 32.0, "0.5 ..= 32")?;
        check_f("interior", self.interior, 0.0, 1.0, "0 ..= 1")?;
        check_f("interior_frequency", self.interior_frequency, 0.5, 64.0, "0.5 ..= 64")?;
        check_f("margin", self.margin, 0.0, 0.2, "0 ..= 0.2")?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random clouds are valid, reproducible, and cover the ranges.
    #[test]
    fn random_clouds_are_valid_and_reproducible() {
        let all: Vec<CloudParams> = (0..500).map(CloudParams::random).collect();
        for (i, p) in all.iter().enumerate() {
            p.validate().unwrap_or_else(|e| panic!("seed {i}: {e}"));
            assert_eq!(*p, CloudParams::random(i as u64));
        }
        let span = |f: &dyn Fn(&CloudParams) -> f32| {
            let v: Vec<f32> = all.iter().map(f).collect();
            (v.iter().copied().fold(f32::INFINITY, f32::min), v.iter().copied().fold(f32::NEG_INFINITY, f32::max))
        };
        // Each parameter spreads over most of its drawn range.
        let (lo, hi) = span(&|p| p.falloff);
        assert!(lo < 0.004 && hi > 0.2, "falloff {lo}..{hi}");
        let (lo, hi) = span(&|p| p.roots as f32);
        assert!(lo == 1.0 && hi == 8.0, "roots {lo}..{hi}");
        let (lo, hi) = span(&|p| p.interior);
        assert!(lo < 0.01 && hi > 0.8, "interior {lo}..{hi}");
        let (lo, hi) = span(&|p| p.levels as f32);
        assert!(lo == 0.0 && hi == 3.0, "levels {lo}..{hi}");
        assert_ne!(all[0], all[1]);
    }
}
