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

impl CloudParams {
    /// A random cloud: every parameter drawn over its range from `seed` (uniformly,
    /// frequencies log-uniformly), with the hierarchy kept to at most 3 levels of at
    /// most 6 children (about 2,000 spheres at the most, so a cloud builds in well
    /// under a second) and the noise amplitudes drawn from zero up, so smooth and hard
    /// clouds, wispy and homogeneous ones all occur. The same seed gives the same
    /// parameters on any machine.
    pub fn random(seed: u64) -> CloudParams {
        let mut rng = engine::Rng::new(seed, 0x63_6c6f_7564, 0); // "cloud"
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

    /// Checks every parameter against its range in [`PARAMS`].
    pub fn validate(&self) -> Result<(), ParamError> {
        for spec in &PARAMS {
            let v = self.get(spec.name).expect("every spec names a field");
            if !(v.is_finite() && v >= spec.lo && v <= spec.hi) {
                let value = if spec.integer { (v as u32).to_string() } else { v.to_string() };
                return Err(ParamError { name: spec.name, value, range: spec.range });
            }
        }
        Ok(())
    }

    /// The parameter `name` (a field of [`PARAMS`]) as a number; None for other names.
    pub fn get(&self, name: &str) -> Option<f32> {
        let mut copy = self.clone();
        copy.field(name).map(|f| match f {
            Field::Real(v) => *v,
            Field::Count(v) => *v as f32,
        })
    }

    /// Sets the parameter `name` (counts are rounded to the nearest integer, negative
    /// values to 0); false for a name that is not in [`PARAMS`]. Does not check the
    /// range: [`CloudParams::validate`] does.
    pub fn set(&mut self, name: &str, value: f32) -> bool {
        match self.field(name) {
            Some(Field::Real(v)) => *v = value,
            Some(Field::Count(v)) => *v = value.round().max(0.0) as u32,
            None => return false,
        }
        true
    }

    fn field(&mut self, name: &str) -> Option<Field<'_>> {
        use Field::{Count, Real};
        Some(match name {
            "roots" => Count(&mut self.roots),
            "root_radius" => Real(&mut self.root_radius),
            "root_spread" => Real(&mut self.root_spread),
            "levels" => Count(&mut self.levels),
            "children" => Count(&mut self.children),
            "radius_ratio" => Real(&mut self.radius_ratio),
            "upward_bias" => Real(&mut self.upward_bias),
            "outward_bias" => Real(&mut self.outward_bias),
            "flatten_base" => Real(&mut self.flatten_base),
            "blend" => Real(&mut self.blend),
            "falloff" => Real(&mut self.falloff),
            "displacement" => Real(&mut self.displacement),
            "frequency" => Real(&mut self.frequency),
            "octaves" => Count(&mut self.octaves),
            "lacunarity" => Real(&mut self.lacunarity),
            "gain" => Real(&mut self.gain),
            "worley" => Real(&mut self.worley),
            "advection" => Real(&mut self.advection),
            "advection_frequency" => Real(&mut self.advection_frequency),
            "interior" => Real(&mut self.interior),
            "interior_frequency" => Real(&mut self.interior_frequency),
            "margin" => Real(&mut self.margin),
            _ => return None,
        })
    }
}

enum Field<'a> {
    Real(&'a mut f32),
    Count(&'a mut u32),
}

/// The groups the parameters are shown in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Group {
    /// The sphere hierarchy: how many spheres, how big, where.
    Hierarchy,
    /// The union of the spheres: base, blending, the soft edge.
    Shape,
    /// Noise displacement of the boundary.
    Noise,
    /// The domain warp that pulls the surface into wisps.
    Advection,
    /// Density variation inside the cloud, and the border around it.
    Interior,
}

impl Group {
    pub const ALL: [Group; 5] = [Group::Hierarchy, Group::Shape, Group::Noise, Group::Advection, Group::Interior];

    pub fn name(self) -> &'static str {
        match self {
            Group::Hierarchy => "hierarchy",
            Group::Shape => "shape",
            Group::Noise => "noise",
            Group::Advection => "advection",
            Group::Interior => "interior",
        }
    }
}

/// One parameter of [`CloudParams`] (all but the seed): its field name, group, valid
/// range (the one [`CloudParams::validate`] enforces), how a slider should move over
/// it, its unit and a one-line description.
#[derive(Clone, Copy, Debug)]
pub struct ParamSpec {
    pub name: &'static str,
    pub group: Group,
    pub lo: f32,
    pub hi: f32,
    /// The range as error messages print it.
    pub range: &'static str,
    /// A count (roots, levels, children, octaves).
    pub integer: bool,
    /// A slider over a logarithmic scale (frequencies, the falloff width).
    pub log: bool,
    /// The unit, "" for a plain number. Lengths are in box widths: the cloud is fitted
    /// into the box [-0.5, 0.5]^3.
    pub unit: &'static str,
    pub doc: &'static str,
}

const fn spec(
    name: &'static str,
    group: Group,
    (lo, hi, range): (f32, f32, &'static str),
    (integer, log): (bool, bool),
    unit: &'static str,
    doc: &'static str,
) -> ParamSpec {
    ParamSpec { name, group, lo, hi, range, integer, log, unit, doc }
}

const REAL: (bool, bool) = (false, false);
const COUNT: (bool, bool) = (true, false);
const LOG: (bool, bool) = (false, true);
const BOX: &str = "box widths";
const CYCLES: &str = "cycles per box width";

/// Every parameter but the seed, in display order.
pub const PARAMS: [ParamSpec; 22] = {
    use Group::*;
    [
        spec("roots", Hierarchy, (1.0, 8.0, "1 ..= 8"), COUNT, "", "root spheres the cloud grows from"),
        spec(
            "root_radius",
            Hierarchy,
            (0.05, 0.5, "0.05 ..= 0.5"),
            REAL,
            BOX,
            "root sphere radius, before the cloud is fitted to the box",
        ),
        spec(
            "root_spread",
            Hierarchy,
            (0.0, 1.0, "0 ..= 1"),
            REAL,
            BOX,
            "horizontal spread of the root centres: 0 stacks them, 1 lines them up wide",
        ),
        spec(
            "levels",
            Hierarchy,
            (0.0, 4.0, "0 ..= 4"),
            COUNT,
            "",
            "generations of child spheres below the roots (each multiplies the sphere count)",
        ),
        spec("children", Hierarchy, (0.0, 10.0, "0 ..= 10"), COUNT, "", "child spheres on the surface of each sphere"),
        spec(
            "radius_ratio",
            Hierarchy,
            (0.2, 0.9, "0.2 ..= 0.9"),
            REAL,
            "",
            "child radius over parent radius: small gives cauliflower detail, large gives lobes",
        ),
        spec(
            "upward_bias",
            Hierarchy,
            (0.0, 2.0, "0 ..= 2"),
            REAL,
            "",
            "how much children prefer the upper side: towering cumulus at 2",
        ),
        spec(
            "outward_bias",
            Hierarchy,
            (0.0, 2.0, "0 ..= 2"),
            REAL,
            "",
            "how much children point away from the cloud's centre: spread-out clouds at 2",
        ),
        spec(
            "flatten_base",
            Shape,
            (0.0, 1.0, "0 ..= 1"),
            REAL,
            "",
            "flat bottom: 0 none, 1 cut at the roots' centres, as a cumulus base",
        ),
        spec(
            "blend",
            Shape,
            (0.0, 0.2, "0 ..= 0.2"),
            REAL,
            BOX,
            "smooth-union width where spheres meet: 0 leaves creases, larger fills them",
        ),
        spec(
            "falloff",
            Shape,
            (0.002, 0.3, "0.002 ..= 0.3"),
            LOG,
            BOX,
            "depth over which density rises from 0 at the surface to full: hard edges when small, soft when large",
        ),
        spec("displacement", Noise, (0.0, 0.2, "0 ..= 0.2"), REAL, BOX, "how far noise pushes the surface in and out"),
        spec(
            "frequency",
            Noise,
            (0.5, 64.0, "0.5 ..= 64"),
            LOG,
            CYCLES,
            "size of the largest noise bumps: low is big billows, high is fine grain",
        ),
        spec("octaves", Noise, (1.0, 8.0, "1 ..= 8"), COUNT, "", "layers of finer noise added on top of the largest"),
        spec(
            "lacunarity",
            Noise,
            (1.5, 3.0, "1.5 ..= 3"),
            REAL,
            "",
            "frequency ratio from one noise layer to the next",
        ),
        spec(
            "gain",
            Noise,
            (0.2, 0.8, "0.2 ..= 0.8"),
            REAL,
            "",
            "amplitude ratio from one noise layer to the next: high keeps fine detail strong",
        ),
        spec(
            "worley",
            Noise,
            (0.0, 1.0, "0 ..= 1"),
            REAL,
            "",
            "mix of cellular (billowy, cauliflower) noise into the smooth Perlin noise",
        ),
        spec(
            "advection",
            Advection,
            (0.0, 0.2, "0 ..= 0.2"),
            REAL,
            BOX,
            "domain warp strength: drags the surface into wisps, 0 for none",
        ),
        spec("advection_frequency", Advection, (0.5, 32.0, "0.5 ..= 32"), LOG, CYCLES, "size of the warp's swirls"),
        spec(
            "interior",
            Interior,
            (0.0, 1.0, "0 ..= 1"),
            REAL,
            "",
            "density variation inside: 0 homogeneous, 1 fully modulated by noise",
        ),
        spec(
            "interior_frequency",
            Interior,
            (0.5, 64.0, "0.5 ..= 64"),
            LOG,
            CYCLES,
            "size of the interior's density blobs",
        ),
        spec(
            "margin",
            Interior,
            (0.0, 0.2, "0 ..= 0.2"),
            REAL,
            BOX,
            "empty border kept around the cloud inside its box",
        ),
    ]
};

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

    /// The table names every field but the seed, each once; get and set round-trip,
    /// and validate refuses a value just outside each range, naming the parameter.
    #[test]
    fn the_parameter_table_covers_every_field() {
        let names: std::collections::BTreeSet<&str> = PARAMS.iter().map(|s| s.name).collect();
        assert_eq!(names.len(), PARAMS.len(), "a parameter is listed twice");
        let fields = serde_json::to_value(CloudParams::default()).unwrap();
        let fields: std::collections::BTreeSet<&str> =
            fields.as_object().unwrap().keys().map(|k| k.as_str()).filter(|k| *k != "seed").collect();
        assert_eq!(names, fields);
        let d = CloudParams::default();
        for spec in &PARAMS {
            let v = d.get(spec.name).unwrap();
            assert!(v >= spec.lo && v <= spec.hi, "{}: default {v} outside {}", spec.name, spec.range);
            let mut p = d.clone();
            let mid = if spec.integer { ((spec.lo + spec.hi) / 2.0).round() } else { (spec.lo + spec.hi) / 2.0 };
            assert!(p.set(spec.name, mid));
            assert_eq!(p.get(spec.name), Some(mid), "{}", spec.name);
            p.validate().unwrap();
            let step = if spec.integer { 1.0 } else { (spec.hi - spec.lo) * 1e-3 };
            for bad in [spec.hi + step, spec.lo - step, f32::NAN] {
                if spec.integer && bad < 0.0 {
                    continue; // a negative count cannot be stored
                }
                let mut p = d.clone();
                p.set(spec.name, bad);
                if spec.integer && bad.is_nan() {
                    continue; // NaN rounds to 0, which may be in range
                }
                let e = p.validate().expect_err(spec.name);
                assert_eq!(e.name, spec.name);
                assert_eq!(e.range, spec.range);
            }
        }
        assert!(!d.clone().set("seed", 2.0) && d.get("nonsense").is_none());
    }
}
