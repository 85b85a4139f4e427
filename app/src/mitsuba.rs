//! A Mitsuba 3 scene for the same cloud, sun and camera: `cloud.vol` (the padded grid,
//! see `output::mitsuba_vol_bytes`) and `scene.xml`, so a user can render the cloud in
//! Mitsuba and compare. Conventions matched (checked by bench/mitsuba_compare.py):
//! `gridvolume` maps [0, 1]^3 onto the padded grid's box through `to_world` and looks
//! up cell-centred; `directional.direction` is the direction of travel and its
//! `irradiance` our sun radiance; `perspective` with `fov_axis = y` and `look_at`
//! gives our image orientation; a `box` pixel filter matches our pixel jitter.

use crate::output;
use anyhow::Result;
use engine::Scene;
use std::path::Path;

fn v3(v: glam::Vec3) -> String {
    format!("{:.9}, {:.9}, {:.9}", v.x, v.y, v.z)
}

/// The scene XML referring to `vol_name` beside it.
pub fn scene_xml(scene: &Scene, spp: u32, vol_name: &str) -> String {
    let grid = scene.medium.grid();
    let vs = grid.voxel_size();
    // The exported volume is padded by one voxel on every side.
    let (lo, hi) = (grid.bounds().min - vs, grid.bounds().max + vs);
    let (centre, half) = (0.5 * (lo + hi), 0.5 * (hi - lo));
    let cam = &scene.camera;
    let far = 4.0 * ((cam.position() - centre).length() + (hi - lo).length());
    let phase = match scene.medium.phase() {
        engine::PhaseFunction::Isotropic => "<phase type=\"isotropic\"/>".to_string(),
        engine::PhaseFunction::HenyeyGreenstein { g } => {
            format!("<phase type=\"hg\"><float name=\"g\" value=\"{g}\"/></phase>")
        }
        other => format!(
            "<!-- {other:?} has no Mitsuba equivalent: HG with the same mean cosine -->\n            <phase type=\"hg\"><float name=\"g\" value=\"{}\"/></phase>",
            other.mean_cosine()
        ),
    };
    let sun = scene.sun.map(|s| {
        let e = s.radiance();
        format!(
            "    <emitter type=\"directional\">\n        <vector name=\"direction\" value=\"{}\"/>\n        <rgb name=\"irradiance\" value=\"{}\"/>\n    </emitter>\n",
            v3(s.direction()),
            v3(e)
        )
    });
    // Mitsuba's constant emitter holds a uniform sky; a gradient or a ground is
    // written as the horizon's radiance, and the file says so.
    let sky = (!scene.sky.is_black()).then(|| {
        let s = &scene.sky;
        let note = if s.zenith != s.horizon || s.ground != s.horizon {
            "    <!-- Nimbus's sky has a gradient or a ground: written as its horizon radiance -->\n"
        } else {
            ""
        };
        format!(
            "{note}    <emitter type=\"constant\">\n        <rgb name=\"radiance\" value=\"{}\"/>\n    </emitter>\n",
            v3(s.horizon)
        )
    });
    format!(
        r#"<?xml version="1.0" encoding="utf-8"?>
<!-- Written by Nimbus. Render with: mitsuba -m llvm_ad_rgb scene.xml -->
<scene version="3.0.0">
    <integrator type="volpath">
        <integer name="max_depth" value="-1"/>
    </integrator>
    <sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <string name="fov_axis" value="y"/>
        <float name="near_clip" value="{near}"/>
        <float name="far_clip" value="{far}"/>
        <transform name="to_world">
            <lookat origin="{origin}" target="{target}" up="{up}"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="{spp}"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{w}"/>
            <integer name="height" value="{h}"/>
            <rfilter type="box"/>
            <boolean name="sample_border" value="false"/>
        </film>
    </sensor>
    <medium type="heterogeneous" id="cloud">
        <volume name="sigma_t" type="gridvolume">
            <string name="filename" value="{vol}"/>
            <string name="filter_type" value="trilinear"/>
            <string name="wrap_mode" value="clamp"/>
            <transform name="to_world">
                <scale value="{extent}"/>
                <translate value="{lo}"/>
            </transform>
        </volume>
        <float name="scale" value="{rho}"/>
        <float name="albedo" value="{albedo}"/>
        {phase}
    </medium>
{sun}{sky}    <shape type="cube">
        <transform name="to_world">
            <scale value="{half}"/>
            <translate value="{centre}"/>
        </transform>
        <bsdf type="null"/>
        <ref name="interior" id="cloud"/>
    </shape>
</scene>
"#,
        fov = cam.fov_y_deg(),
        near = far * 1e-6,
        origin = v3(cam.position()),
        target = v3(cam.target()),
        up = v3(cam.up()),
        w = cam.width(),
        h = cam.height(),
        vol = vol_name,
        extent = v3(hi - lo),
        lo = v3(lo),
        rho = scene.medium.rho(),
        albedo = scene.medium.albedo(),
        sun = sun.unwrap_or_default(),
        sky = sky.unwrap_or_default(),
        half = v3(half),
        centre = v3(centre),
    )
}

/// Writes `dir/cloud.vol` and `dir/scene.xml`.
pub fn export(scene: &Scene, spp: u32, dir: &Path) -> Result<()> {
    crate::output::create_dir(dir)?;
    output::write_bytes_atomically(&dir.join("cloud.vol"), &output::mitsuba_vol_bytes(scene.medium.grid()))?;
    output::write_bytes_atomically(&dir.join("scene.xml"), scene_xml(scene, spp, "cloud.vol").as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::SceneFile;

    #[test]
    fn xml_carries_the_scene() {
        let file = SceneFile::from_toml_str(
            "[grid]\nbuiltin = \"sphere\"\nresolution = 8\n[medium]\nrho = 12.5\nalbedo = 0.9\ng = 0.7\n[sun]\ndirection = [0, -1, 0]\nradiance = [1, 2, 3]\n[camera]\nposition = [0, 0, 3]\nwidth = 40\nheight = 30\n",
            "t",
        )
        .unwrap();
        let scene = file.build_scene(None).unwrap();
        let xml = scene_xml(&scene, 77, "cloud.vol");
        for needle in [
            "<medium type=\"heterogeneous\" id=\"cloud\">",
            "<float name=\"scale\" value=\"12.5\"/>",
            "<float name=\"albedo\" value=\"0.9\"/>",
            "<float name=\"g\" value=\"0.7\"/>",
            "<integer name=\"sample_count\" value=\"77\"/>",
            "<integer name=\"width\" value=\"40\"/>",
            "origin=\"0.000000000, 0.000000000, 3.000000000\"",
            "<vector name=\"direction\" value=\"0.000000000, -1.000000000, 0.000000000\"/>",
            "<rgb name=\"irradiance\" value=\"1.000000000, 2.000000000, 3.000000000\"/>",
            // 8 voxels of 1/8 plus one voxel of padding each side: [-0.625, 0.625].
            "<translate value=\"-0.625000000, -0.625000000, -0.625000000\"/>",
            "<scale value=\"1.250000000, 1.250000000, 1.250000000\"/>",
        ] {
            assert!(xml.contains(needle), "missing {needle} in\n{xml}");
        }
        // Well-formed enough: every opened element is closed.
        assert_eq!(xml.matches("<medium").count(), xml.matches("</medium>").count());
        assert_eq!(xml.matches("<sensor").count(), xml.matches("</sensor>").count());
    }
}
