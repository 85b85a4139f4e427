//! The Nimbus window (eframe/egui with wgpu): a progressive viewport, cloud, medium,
//! light and camera controls, and a status bar. Rendering happens on the worker
//! thread (`worker`); the UI only edits a scene description, sends it, and shows the
//! latest finished pass through one texture.

pub mod worker;

use crate::output::ToneMap;
use crate::scene::{CameraPreset, SceneFile, default_up};
use eframe::egui;
use engine::Buffer;
use glam::Vec3;
use worker::WorkerHandle;

/// The default scene a fresh start shows: the built-in cumulus, lit from above.
pub fn default_scene() -> SceneFile {
    let mut s =
        SceneFile::from_toml_str(include_str!("../../../assets/scenes/cumulus.toml"), "assets/scenes/cumulus.toml")
            .expect("the bundled scene parses");
    s.grid.resolution = 96;
    s.k = 2;
    s
}

/// Orbit camera state: angles around the target, in degrees, and distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Orbit {
    pub yaw_deg: f32,
    pub pitch_deg: f32,
    pub distance: f32,
}

impl Orbit {
    fn from_preset(preset: CameraPreset, sun_direction: Vec3, distance: f32) -> Self {
        let view = preset.view_direction(sun_direction.normalize_or(Vec3::NEG_Y));
        let from = -view; // direction from target to camera
        Orbit {
            yaw_deg: from.x.atan2(from.z).to_degrees(),
            pitch_deg: from.y.clamp(-1.0, 1.0).asin().to_degrees(),
            distance,
        }
    }

    fn position(&self, target: Vec3) -> Vec3 {
        let (yaw, pitch) = (self.yaw_deg.to_radians(), self.pitch_deg.to_radians());
        target + self.distance * Vec3::new(pitch.cos() * yaw.sin(), pitch.sin(), pitch.cos() * yaw.cos())
    }
}

pub struct NimbusApp {
    scene: SceneFile,
    orbit: Orbit,
    sun_elevation_deg: f32,
    sun_azimuth_deg: f32,
    preset_name: String,
    exposure: f32,
    tone: ToneMap,
    view_buffer: Buffer,
    worker: WorkerHandle,
    sent: Option<(SceneFile, bool)>,
    texture: Option<egui::TextureHandle>,
    shown: Option<(u64, u32, f32, Buffer)>,
}

impl NimbusApp {
    pub fn new(ctx: &egui::Context) -> Self {
        let ctx = ctx.clone();
        let worker = WorkerHandle::start(move || ctx.request_repaint());
        let scene = default_scene();
        let sun = Vec3::from_array(scene.sun.direction);
        let mut app = NimbusApp {
            orbit: Orbit::from_preset(CameraPreset::Toplit, sun, scene.camera.distance),
            sun_elevation_deg: (-sun.normalize().y).asin().to_degrees(),
            sun_azimuth_deg: (-sun.x).atan2(-sun.z).to_degrees().rem_euclid(360.0),
            preset_name: "builtin: cumulus".into(),
            scene,
            exposure: 1.0,
            tone: ToneMap::Filmic,
            view_buffer: Buffer::Full,
            worker,
            sent: None,
            texture: None,
            shown: None,
        };
        app.apply_camera();
        app
    }

    pub fn scene(&self) -> &SceneFile {
        &self.scene
    }

    fn apply_camera(&mut self) {
        let target = Vec3::from_array(self.scene.camera.target);
        let pos = self.orbit.position(target);
        self.scene.camera.position = Some(pos.to_array());
        self.scene.camera.up = default_up((target - pos).normalize()).to_array();
        self.scene.camera.preset = None;
    }

    fn apply_sun(&mut self) {
        let (el, az) = (self.sun_elevation_deg.to_radians(), self.sun_azimuth_deg.to_radians());
        let to_sun = Vec3::new(el.cos() * az.sin(), el.sin(), el.cos() * az.cos());
        self.scene.sun.direction = (-to_sun).to_array();
    }

    fn controls(&mut self, ui: &mut egui::Ui) {
        egui::ScrollArea::vertical().show(ui, |ui| {
            ui.heading("Cloud");
            let mut sources: Vec<String> =
                crate::cloud::Builtin::NAMES.iter().map(|n| format!("builtin: {n}")).collect();
            sources.extend(modeler::PRESET_NAMES.iter().map(|n| n.to_string()));
            egui::ComboBox::from_label("shape").selected_text(&self.preset_name).show_ui(ui, |ui| {
                for s in &sources {
                    if ui.selectable_label(*s == self.preset_name, s).clicked() {
                        self.preset_name = s.clone();
                        let g = &mut self.scene.grid;
                        (g.builtin, g.preset, g.params, g.file) = (None, None, None, None);
                        match s.strip_prefix("builtin: ") {
                            Some(b) => g.builtin = Some(b.to_string()),
                            None => g.preset = Some(s.clone()),
                        }
                    }
                }
            });
            ui.add(egui::Slider::new(&mut self.scene.grid.resolution, 32..=256).text("resolution"));

            ui.separator();
            ui.heading("Medium");
            let m = &mut self.scene.medium;
            ui.add(egui::Slider::new(&mut m.rho, 0.5..=400.0).logarithmic(true).text("density rho"));
            ui.add(egui::Slider::new(&mut m.albedo, 0.0..=1.0).text("albedo"));
            egui::ComboBox::from_label("phase").selected_text(&m.phase).show_ui(ui, |ui| {
                for p in ["hg", "isotropic", "rayleigh", "hazy", "murky"] {
                    ui.selectable_value(&mut m.phase, p.to_string(), p);
                }
            });
            if m.phase == "hg" {
                ui.add(egui::Slider::new(&mut m.g, -0.95..=0.95).text("g"));
            }

            ui.separator();
            ui.heading("Light");
            let mut sun_changed =
                ui.add(egui::Slider::new(&mut self.sun_elevation_deg, -89.0..=89.0).text("sun elevation")).changed();
            sun_changed |=
                ui.add(egui::Slider::new(&mut self.sun_azimuth_deg, 0.0..=360.0).text("sun azimuth")).changed();
            if sun_changed {
                self.apply_sun();
            }
            let mut radiance = self.scene.sun.radiance.to_vec3().x;
            if ui.add(egui::Slider::new(&mut radiance, 0.0..=10.0).text("sun radiance")).changed() {
                self.scene.sun.radiance = crate::scene::Rgb::Grey(radiance);
            }
            ui.add(egui::Slider::new(&mut self.scene.sun.angular_radius_deg, 0.0..=10.0).text("sun size (deg)"));
            let mut sky = self.scene.sky.radiance.to_vec3().x;
            if ui.add(egui::Slider::new(&mut sky, 0.0..=2.0).text("sky")).changed() {
                self.scene.sky.radiance = crate::scene::Rgb::Grey(sky);
            }

            ui.separator();
            ui.heading("Camera");
            ui.horizontal(|ui| {
                for (name, preset) in [
                    ("toplit", CameraPreset::Toplit),
                    ("backlit", CameraPreset::Backlit),
                    ("frontlit", CameraPreset::Frontlit),
                ] {
                    if ui
                        .button(name)
                        .on_hover_text("the thesis's lighting configurations, relative to the sun")
                        .clicked()
                    {
                        self.orbit =
                            Orbit::from_preset(preset, Vec3::from_array(self.scene.sun.direction), self.orbit.distance);
                    }
                }
            });
            ui.add(egui::Slider::new(&mut self.orbit.distance, 1.0..=10.0).text("distance"));
            ui.add(egui::Slider::new(&mut self.scene.camera.fov_y_deg, 5.0..=90.0).text("field of view"));
            ui.label("Drag the image to orbit, scroll to zoom.");

            ui.separator();
            ui.heading("Render");
            ui.horizontal(|ui| {
                ui.radio_value(&mut self.scene.render.mode, "reference".to_string(), "path tracing");
                ui.add_enabled(false, egui::RadioButton::new(false, "prediction at bounce k"))
                    .on_disabled_hover_text("needs a trained model: none ships yet (issues 6 and 7)");
            });
            ui.add(egui::Slider::new(&mut self.scene.k, 1..=8).text("k (first high order)"));
            ui.horizontal(|ui| {
                ui.label("show");
                for b in Buffer::ALL {
                    ui.selectable_value(&mut self.view_buffer, b, b.name());
                }
            });
            ui.add(egui::Slider::new(&mut self.exposure, -4.0..=6.0).text("exposure (stops)"));
            ui.horizontal(|ui| {
                ui.selectable_value(&mut self.tone, ToneMap::Filmic, "filmic");
                ui.selectable_value(&mut self.tone, ToneMap::Clamp, "clamp");
            });
            ui.horizontal(|ui| {
                let mut w = self.scene.camera.width;
                ui.add(egui::DragValue::new(&mut w).range(16..=2048).prefix("w "));
                let mut h = self.scene.camera.height;
                ui.add(egui::DragValue::new(&mut h).range(16..=2048).prefix("h "));
                (self.scene.camera.width, self.scene.camera.height) = (w, h);
            });
        });
    }

    fn viewport(&mut self, ui: &mut egui::Ui) {
        let published = self.worker.mailbox.lock().unwrap().latest.clone();
        if let Some(p) = &published {
            let key = (p.generation, p.film.spp(), self.exposure, self.view_buffer);
            if self.shown != Some(key) {
                let rgba = self.tone.to_rgba8(&p.film.mean(self.view_buffer), self.exposure);
                let image = egui::ColorImage::from_rgba_unmultiplied(
                    [p.film.width() as usize, p.film.height() as usize],
                    &rgba,
                );
                match &mut self.texture {
                    Some(t) => t.set(image, egui::TextureOptions::LINEAR),
                    None => {
                        self.texture =
                            Some(ui.ctx().load_texture("nimbus-viewport", image, egui::TextureOptions::LINEAR))
                    }
                }
                self.shown = Some(key);
            }
        }
        let avail = ui.available_size();
        let (rect, response) = ui.allocate_exact_size(avail, egui::Sense::click_and_drag());
        ui.painter().rect_filled(rect, 0.0, egui::Color32::from_gray(12));
        if let Some(t) = &self.texture {
            let size = t.size_vec2();
            let scale = (rect.width() / size.x).min(rect.height() / size.y);
            let shown = egui::Rect::from_center_size(rect.center(), size * scale);
            ui.painter().image(
                t.id(),
                shown,
                egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0)),
                egui::Color32::WHITE,
            );
        }
        if response.dragged() {
            let d = response.drag_delta();
            self.orbit.yaw_deg -= d.x * 0.4;
            self.orbit.pitch_deg = (self.orbit.pitch_deg + d.y * 0.4).clamp(-89.0, 89.0);
        }
        if response.hovered() {
            let scroll = ui.ctx().input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                self.orbit.distance = (self.orbit.distance * (-scroll * 0.002).exp()).clamp(1.0, 10.0);
            }
        }
    }

    fn status(&self, ui: &mut egui::Ui) {
        let mb = self.worker.mailbox.lock().unwrap();
        ui.horizontal(|ui| {
            if let Some(p) = &mb.latest {
                ui.label(format!(
                    "{} spp   {:.1} s   {:.2} M samples/s   noise {:.1} %{}",
                    p.film.spp(),
                    p.render_secs,
                    p.samples_per_sec / 1e6,
                    100.0 * p.noise,
                    if p.coarse { "   (coarse cloud while dragging)" } else { "" }
                ));
            } else {
                ui.label("starting…");
            }
            if mb.building {
                ui.spinner();
                ui.label("building the cloud…");
            }
        });
        if let Some((_, e)) = &mb.error {
            ui.colored_label(egui::Color32::from_rgb(255, 110, 90), e);
        }
    }

    /// Sends the scene to the worker when it changed (coarse while the pointer is down).
    fn sync(&mut self, ctx: &egui::Context) {
        self.apply_camera();
        let dragging = ctx.input(|i| i.pointer.any_down());
        let changed = self.sent.as_ref().is_none_or(|(s, coarse)| *s != self.scene || (*coarse && !dragging));
        if changed {
            if let Err(e) = self.scene.validate() {
                self.worker.mailbox.lock().unwrap().error = Some((0, e.to_string()));
                return;
            }
            let grid_changed = self.sent.as_ref().is_none_or(|(s, _)| s.grid != self.scene.grid);
            let coarse = dragging && grid_changed || dragging && self.sent.as_ref().is_some_and(|(_, c)| *c);
            self.worker.render(&self.scene, coarse);
            self.sent = Some((self.scene.clone(), coarse));
        }
    }
}

impl eframe::App for NimbusApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        egui::Panel::right("controls").resizable(true).default_size(300.0).show(ui, |ui| self.controls(ui));
        egui::Panel::bottom("status").show(ui, |ui| self.status(ui));
        egui::CentralPanel::default().show(ui, |ui| self.viewport(ui));
        let ctx = ui.ctx().clone();
        self.sync(&ctx);
    }
}

/// Opens the window; returns when it is closed.
pub fn run() -> anyhow::Result<()> {
    let options = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default().with_inner_size([1180.0, 760.0]).with_title("Nimbus"),
        ..Default::default()
    };
    eframe::run_native("Nimbus", options, Box::new(|cc| Ok(Box::new(NimbusApp::new(&cc.egui_ctx))))).map_err(|e| {
        anyhow::anyhow!("cannot open the Nimbus window: {e} (the subcommands work without a display: nimbus --help)")
    })
}
