//! The scene parser and everything it builds: any text must give a scene or an error.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(mut scene) = app::scene::SceneFile::from_toml_str(text, "fuzz.toml") else { return };
    if scene.validate().is_err() {
        return;
    }
    // Keep each run small: tiny grids, no files, tiny images.
    scene.grid.resolution = scene.grid.resolution.min(12);
    scene.grid.file = None;
    if scene.grid.builtin.is_none() && scene.grid.preset.is_none() && scene.grid.params.is_none() {
        scene.grid.builtin = Some("sphere".into());
    }
    scene.camera.width = scene.camera.width.min(4);
    scene.camera.height = scene.camera.height.min(4);
    if let Ok(s) = scene.build_scene(None) {
        let _ = scene.integrator(&s, 4);
        let _ = s.camera.generate_ray(0, 0, glam::Vec2::splat(0.5));
    }
});
