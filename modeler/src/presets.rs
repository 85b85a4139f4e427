//! Named clouds: the thesis's evaluation scenes A, B, C (appendix A) and a set of
//! twelve clouds from fixed seeds and varied parameters.

use crate::params::CloudParams;

pub const PRESET_NAMES: [&str; 15] = [
    "scene-a", "scene-b", "scene-c", "set-01", "set-02", "set-03", "set-04", "set-05", "set-06", "set-07", "set-08",
    "set-09", "set-10", "set-11", "set-12",
];

/// The parameters of a named preset, or None.
pub fn preset(name: &str) -> Option<CloudParams> {
    let d = CloudParams::default();
    Some(match name {
        // Nearly convex, homogeneous interior, falloff near the surface.
        "scene-a" => CloudParams {
            seed: 11,
            roots: 1,
            levels: 1,
            children: 6,
            radius_ratio: 0.6,
            upward_bias: 0.2,
            outward_bias: 0.0,
            flatten_base: 0.3,
            blend: 0.12,
            falloff: 0.08,
            displacement: 0.015,
            frequency: 4.0,
            octaves: 3,
            worley: 0.0,
            ..d
        },
        // Strongly concave, several lobes, homogeneous interior.
        "scene-b" => CloudParams {
            seed: 23,
            roots: 3,
            root_spread: 0.9,
            levels: 2,
            children: 3,
            radius_ratio: 0.5,
            upward_bias: 0.9,
            outward_bias: 1.2,
            flatten_base: 0.6,
            blend: 0.02,
            falloff: 0.03,
            displacement: 0.02,
            frequency: 7.0,
            worley: 0.4,
            ..d
        },
        // Complex shape, heterogeneous interior.
        "scene-c" => CloudParams {
            seed: 37,
            roots: 2,
            root_spread: 0.6,
            levels: 3,
            children: 4,
            radius_ratio: 0.5,
            upward_bias: 0.7,
            outward_bias: 0.8,
            flatten_base: 0.5,
            blend: 0.03,
            falloff: 0.03,
            displacement: 0.04,
            frequency: 8.0,
            octaves: 5,
            worley: 0.5,
            advection: 0.03,
            advection_frequency: 4.0,
            interior: 0.85,
            interior_frequency: 10.0,
            ..d
        },
        _ => {
            let i: u64 = name.strip_prefix("set-")?.parse().ok().filter(|i| (1..=12).contains(i))?;
            set_member(i)
        }
    })
}

/// Cloud i of the set: fixed seed, parameters walked through their useful ranges so
/// the set spans compact puffs to spread, wispy, heterogeneous clouds.
fn set_member(i: u64) -> CloudParams {
    let t = (i - 1) as f32 / 11.0;
    let cyc = |k: u64, n: u64| ((i * k) % n) as f32 / (n - 1) as f32;
    CloudParams {
        seed: 1000 + i * 7919,
        roots: 1 + ((i * 5) % 4) as u32,
        root_radius: 0.25 + 0.1 * cyc(3, 5),
        root_spread: 0.3 + 0.6 * cyc(7, 4),
        levels: 1 + ((i * 3) % 3) as u32,
        children: 3 + ((i * 7) % 4) as u32,
        radius_ratio: 0.45 + 0.2 * cyc(5, 6),
        upward_bias: 0.3 + 0.8 * cyc(11, 5),
        outward_bias: 0.2 + 1.0 * cyc(13, 4),
        flatten_base: 0.2 + 0.7 * cyc(2, 5),
        blend: 0.02 + 0.06 * cyc(9, 4),
        falloff: 0.02 + 0.06 * cyc(4, 5),
        displacement: 0.01 + 0.04 * t,
        frequency: 4.0 + 6.0 * cyc(6, 5),
        octaves: 3 + ((i * 2) % 3) as u32,
        worley: 0.5 * cyc(8, 3),
        advection: 0.04 * cyc(10, 3),
        interior: if i % 3 == 0 { 0.6 + 0.3 * t } else { 0.0 },
        ..CloudParams::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preset_is_valid_and_unknown_names_are_none() {
        for name in PRESET_NAMES {
            preset(name).unwrap().validate().unwrap_or_else(|e| panic!("{name}: {e}"));
        }
        assert!(preset("set-13").is_none() && preset("set-00").is_none() && preset("scene-d").is_none());
    }
}
