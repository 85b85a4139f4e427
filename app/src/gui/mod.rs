//! The Nimbus window (eframe/egui with wgpu): a progressive viewport, cloud, medium,
//! light and camera controls, and a status bar. Rendering happens on the worker
//! thread (`worker`); the UI only edits a scene description, sends it, and shows the
//! latest finished pass through one texture.

pub mod compare;
pub mod worker;

use crate::output::ToneMap;
use crate::scene::{CameraPreset, SceneFile, default_up};
use compare::{CompareView, Layout};
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

/// What a drag in the viewport moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ViewDrag {
    Orbit,
    /// Shift or the secondary button: the sun's azimuth (horizontal) and elevation.
    Sun,
    /// The divider of the wipe view, grabbed near it.
    Wipe,
}

/// Something the user asked for, applied after the frame's layout.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Action {
    OpenScene,
    OpenVdb,
    /// Open a scene (.toml) or a VDB cloud (.vdb) without a dialog (recent files, tests).
    OpenPath(std::path::PathBuf),
    /// Pick another global model (.safetensors with its .json sidecar) for prediction.
    LoadModel,
    SaveScene,
    ExportExr,
    ExportPng,
    ExportVdb,
    ExportMitsuba,
    Undo,
    Redo,
    Reset,
    /// Write to this path without a dialog (what the dialogs above end in; tests).
    WriteTo(Target, std::path::PathBuf),
}

/// What [`Action::WriteTo`] writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    Scene,
    /// The latest image, every buffer, as multi-layer EXR.
    Exr,
    /// The latest image as shown, tone-mapped.
    Png,
    Vdb,
    /// A folder: cloud.vol and scene.xml.
    Mitsuba,
}

/// Parameter-change history for undo and redo.
#[derive(Default)]
struct History {
    states: Vec<SceneFile>,
    at: usize,
}

impl History {
    /// Records `scene` if it differs from the current state (drops any redo tail).
    fn record(&mut self, scene: &SceneFile) {
        if self.states.get(self.at) == Some(scene) {
            return;
        }
        self.states.truncate(self.at + 1);
        self.states.push(scene.clone());
        self.at = self.states.len() - 1;
        if self.states.len() > 200 {
            self.states.remove(0);
            self.at -= 1;
        }
    }
    fn undo(&mut self) -> Option<SceneFile> {
        (self.at > 0).then(|| {
            self.at -= 1;
            self.states[self.at].clone()
        })
    }
    fn redo(&mut self) -> Option<SceneFile> {
        (self.at + 1 < self.states.len()).then(|| {
            self.at += 1;
            self.states[self.at].clone()
        })
    }
}

const STORAGE_SCENE: &str = "nimbus.scene";
const STORAGE_RECENT: &str = "nimbus.recent";
/// Recent files kept in the File menu.
const RECENT_MAX: usize = 8;

pub struct NimbusApp {
    scene: SceneFile,
    history: History,
    actions: Vec<Action>,
    /// Last message for the user: (text, is_error).
    message: Option<(String, bool)>,
    orbit: Orbit,
    sun_elevation_deg: f32,
    sun_azimuth_deg: f32,
    preset_name: String,
    exposure: f32,
    tone: ToneMap,
    view_buffer: Buffer,
    worker: WorkerHandle,
    /// The last scene sent to the worker, whether coarse, whether in compare mode.
    sent: Option<(SceneFile, bool, bool)>,
    /// Reference and prediction side by side, with the buffer panels.
    compare: bool,
    compare_view: CompareView,
    /// Recently opened scenes and clouds, newest first (persisted).
    recent: Vec<std::path::PathBuf>,
    /// CPU time of the last frame's `ui` and the largest over the last second (ms):
    /// the window's own cost, shown in the status bar (goal: under 16 ms).
    frame_ms: (f32, f32, std::time::Instant),
    texture: Option<egui::TextureHandle>,
    shown: Option<(u64, u32, f32, Buffer, ToneMap)>,
    drag: ViewDrag,
    /// The viewport's area in the last frame.
    view_rect: egui::Rect,
}

impl NimbusApp {
    /// The window's state; the last session's scene is restored from `storage` if it
    /// parses (unsaved work survives a restart), else the default cloud.
    pub fn new(ctx: &egui::Context, storage: Option<&dyn eframe::Storage>) -> Self {
        let ctx = ctx.clone();
        let worker = WorkerHandle::start(move || ctx.request_repaint());
        let restored = storage
            .and_then(|s| s.get_string(STORAGE_SCENE))
            .and_then(|t| SceneFile::from_toml_str(&t, "last session").ok())
            .filter(|s| s.validate().is_ok());
        let mut app = NimbusApp {
            orbit: Orbit { yaw_deg: 0.0, pitch_deg: 0.0, distance: 2.8 },
            sun_elevation_deg: 90.0,
            sun_azimuth_deg: 0.0,
            preset_name: String::new(),
            scene: default_scene(),
            history: History::default(),
            actions: Vec::new(),
            message: None,
            exposure: 1.0,
            tone: ToneMap::Filmic,
            view_buffer: Buffer::Full,
            worker,
            sent: None,
            compare: false,
            compare_view: CompareView::default(),
            frame_ms: (0.0, 0.0, std::time::Instant::now()),
            recent: storage
                .and_then(|s| s.get_string(STORAGE_RECENT))
                .map(|t| t.lines().filter(|l| !l.is_empty()).map(std::path::PathBuf::from).take(RECENT_MAX).collect())
                .unwrap_or_default(),
            texture: None,
            shown: None,
            drag: ViewDrag::Orbit,
            view_rect: egui::Rect::NOTHING,
        };
        app.set_scene(restored.unwrap_or_else(default_scene));
        app.history.record(&app.scene);
        app
    }

    /// Replaces the scene and the controls derived from it (orbit, sun angles, shape).
    pub fn set_scene(&mut self, scene: SceneFile) {
        let sun = Vec3::from_array(scene.sun.direction).normalize_or(Vec3::NEG_Y);
        self.sun_elevation_deg = (-sun.y).clamp(-1.0, 1.0).asin().to_degrees();
        self.sun_azimuth_deg = (-sun.x).atan2(-sun.z).to_degrees().rem_euclid(360.0);
        let target = Vec3::from_array(scene.camera.target);
        self.orbit = match scene.camera.position {
            Some(p) => {
                let from = Vec3::from_array(p) - target;
                let len = from.length().max(1e-3);
                Orbit {
                    yaw_deg: from.x.atan2(from.z).to_degrees(),
                    pitch_deg: (from.y / len).clamp(-1.0, 1.0).asin().to_degrees(),
                    distance: len,
                }
            }
            None => {
                let preset =
                    scene.camera.preset.as_deref().and_then(CameraPreset::from_name).unwrap_or(CameraPreset::Toplit);
                Orbit::from_preset(preset, sun, scene.camera.distance)
            }
        };
        let g = &scene.grid;
        self.preset_name = match (&g.builtin, &g.preset, &g.file) {
            (Some(b), _, _) => format!("builtin: {b}"),
            (_, Some(p), _) => p.clone(),
            (_, _, Some(f)) => format!(
                "file: {}",
                std::path::Path::new(f).file_name().map(|n| n.to_string_lossy()).unwrap_or_default()
            ),
            _ => "custom parameters".into(),
        };
        self.scene = scene;
        self.apply_camera();
    }

    /// Queues an action (menu items, shortcuts, tests).
    pub fn request(&mut self, action: Action) {
        self.actions.push(action);
    }

    /// Turns the side-by-side comparison with path tracing on or off.
    pub fn set_compare(&mut self, on: bool) {
        self.compare = on;
    }

    /// The comparison's numbers: (relative bias, its noise floor), once both renders
    /// have samples.
    pub fn compare_bias(&self) -> Option<(f64, f64)> {
        self.compare_view.bias
    }

    /// How reference and prediction share the viewport in compare mode.
    pub fn set_compare_layout(&mut self, layout: Layout) {
        self.compare_view.layout = layout;
    }

    /// CPU milliseconds of the last frame's `ui` and the most over the last second.
    pub fn frame_ms(&self) -> (f32, f32) {
        (self.frame_ms.0, self.frame_ms.1)
    }

    /// The viewport's area on screen (the image is fitted and centred in it).
    pub fn viewport_rect(&self) -> egui::Rect {
        self.view_rect
    }

    /// The wipe divider, as a fraction of the image width.
    pub fn wipe(&self) -> f32 {
        self.compare_view.wipe
    }

    /// The sun's (elevation, azimuth) in degrees, as the light panel shows them.
    pub fn sun_angles(&self) -> (f32, f32) {
        (self.sun_elevation_deg, self.sun_azimuth_deg)
    }

    pub fn message(&self) -> Option<&(String, bool)> {
        self.message.as_ref()
    }

    /// The latest finished pass the worker published: (generation, spp, mean of the
    /// full image).
    pub fn rendered(&self) -> Option<(u64, u32, f64)> {
        self.worker
            .mailbox
            .lock()
            .unwrap()
            .latest
            .as_ref()
            .map(|p| (p.generation, p.film.spp(), p.film.average(Buffer::Full)))
    }

    fn menu(&mut self, ui: &mut egui::Ui) {
        egui::MenuBar::new().ui(ui, |ui| {
            ui.menu_button("File", |ui| {
                let items = [
                    ("Open scene…  Ctrl+O", Action::OpenScene),
                    ("Open VDB cloud…", Action::OpenVdb),
                    ("Save scene…  Ctrl+S", Action::SaveScene),
                    ("Export image (EXR, all buffers)…  Ctrl+E", Action::ExportExr),
                    ("Export image (PNG)…", Action::ExportPng),
                    ("Export cloud (VDB)…", Action::ExportVdb),
                    ("Export Mitsuba scene…", Action::ExportMitsuba),
                ];
                for (label, action) in items {
                    if ui.button(label).clicked() {
                        self.actions.push(action);
                        ui.close();
                    }
                }
                ui.menu_button("Open recent", |ui| {
                    if self.recent.is_empty() {
                        ui.label("nothing opened yet");
                    }
                    for path in self.recent.clone() {
                        if ui.button(path.display().to_string()).clicked() {
                            self.actions.push(Action::OpenPath(path));
                            ui.close();
                        }
                    }
                });
                ui.separator();
                if ui.button("Load global model…").clicked() {
                    self.actions.push(Action::LoadModel);
                    ui.close();
                }
                ui.separator();
                if ui.button("Quit").clicked() {
                    ui.ctx().send_viewport_cmd(egui::ViewportCommand::Close);
                }
            });
            ui.menu_button("Edit", |ui| {
                for (label, action) in [
                    ("Undo  Ctrl+Z", Action::Undo),
                    ("Redo  Ctrl+Shift+Z", Action::Redo),
                    ("Reset to the default cloud", Action::Reset),
                ] {
                    if ui.button(label).clicked() {
                        self.actions.push(action);
                        ui.close();
                    }
                }
            });
        });
    }

    fn shortcuts(&mut self, ctx: &egui::Context) {
        use egui::{Key, KeyboardShortcut, Modifiers};
        let table = [
            (KeyboardShortcut::new(Modifiers::COMMAND | Modifiers::SHIFT, Key::Z), Action::Redo),
            (KeyboardShortcut::new(Modifiers::COMMAND, Key::Y), Action::Redo),
            (KeyboardShortcut::new(Modifiers::COMMAND, Key::Z), Action::Undo),
            (KeyboardShortcut::new(Modifiers::COMMAND, Key::O), Action::OpenScene),
            (KeyboardShortcut::new(Modifiers::COMMAND, Key::S), Action::SaveScene),
            (KeyboardShortcut::new(Modifiers::COMMAND, Key::E), Action::ExportExr),
        ];
        for (shortcut, action) in table {
            if ctx.input_mut(|i| i.consume_shortcut(&shortcut)) {
                self.actions.push(action);
            }
        }
    }

    fn apply_actions(&mut self) {
        for action in std::mem::take(&mut self.actions) {
            let result = self.apply(action);
            match result {
                Ok(Some(done)) => self.message = Some((done, false)),
                Ok(None) => {}
                Err(e) => self.message = Some((format!("{e:#}"), true)),
            }
        }
    }

    fn apply(&mut self, action: Action) -> anyhow::Result<Option<String>> {
        use anyhow::Context as _;
        let file_dialog = || rfd::FileDialog::new();
        match action {
            Action::Undo => {
                if let Some(s) = self.history.undo() {
                    self.set_scene(s);
                }
                Ok(None)
            }
            Action::Redo => {
                if let Some(s) = self.history.redo() {
                    self.set_scene(s);
                }
                Ok(None)
            }
            Action::Reset => {
                self.set_scene(default_scene());
                Ok(None)
            }
            Action::OpenPath(path) => {
                let is_vdb = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("vdb"));
                if is_vdb { self.open_vdb(path) } else { self.open_scene(path) }
            }
            Action::LoadModel => {
                let Some(path) = file_dialog().add_filter("Nimbus global model", &["safetensors"]).pick_file() else {
                    return Ok(None);
                };
                self.load_model(path)
            }
            Action::OpenScene => {
                let Some(path) = file_dialog().add_filter("Nimbus scene", &["toml"]).pick_file() else {
                    return Ok(None);
                };
                self.open_scene(path)
            }
            Action::OpenVdb => {
                let Some(path) = file_dialog().add_filter("OpenVDB", &["vdb"]).pick_file() else { return Ok(None) };
                self.open_vdb(path)
            }
            Action::SaveScene => {
                let Some(path) =
                    file_dialog().add_filter("Nimbus scene", &["toml"]).set_file_name("scene.toml").save_file()
                else {
                    return Ok(None);
                };
                self.write_to(Target::Scene, &path)
            }
            Action::ExportExr | Action::ExportPng => {
                let (target, ext, name) = if action == Action::ExportExr {
                    (Target::Exr, "exr", "OpenEXR")
                } else {
                    (Target::Png, "png", "PNG")
                };
                // Refuse before asking for a file when there is nothing to write.
                self.worker.mailbox.lock().unwrap().latest.as_ref().context("nothing rendered yet")?;
                let Some(path) =
                    file_dialog().add_filter(name, &[ext]).set_file_name(format!("nimbus.{ext}")).save_file()
                else {
                    return Ok(None);
                };
                self.write_to(target, &path)
            }
            Action::ExportVdb => {
                let Some(path) = file_dialog().add_filter("OpenVDB", &["vdb"]).set_file_name("cloud.vdb").save_file()
                else {
                    return Ok(None);
                };
                self.write_to(Target::Vdb, &path)
            }
            Action::ExportMitsuba => {
                let Some(dir) = file_dialog().pick_folder() else { return Ok(None) };
                self.write_to(Target::Mitsuba, &dir)
            }
            Action::WriteTo(target, path) => self.write_to(target, &path),
        }
    }

    /// Writes the scene, the image or the cloud to `path` (a folder for Mitsuba).
    fn write_to(&mut self, target: Target, path: &std::path::Path) -> anyhow::Result<Option<String>> {
        use anyhow::Context as _;
        let latest_film = || self.worker.mailbox.lock().unwrap().latest.as_ref().map(|p| p.film.clone());
        match target {
            Target::Scene => {
                crate::output::write_bytes_atomically(path, self.scene.to_toml().as_bytes())?;
                Ok(Some(format!("saved {}", path.display())))
            }
            Target::Exr | Target::Png => {
                let film = latest_film().context("nothing rendered yet")?;
                if target == Target::Exr {
                    crate::output::write_exr(path, film.width(), film.height(), &crate::output::film_layers(&film))?;
                } else {
                    crate::output::write_png(
                        path,
                        film.width(),
                        film.height(),
                        &film.mean(self.view_buffer),
                        self.tone,
                        self.exposure,
                    )?;
                }
                Ok(Some(format!("wrote {} ({} spp)", path.display(), film.spp())))
            }
            Target::Vdb => {
                let grid = self.scene.build_grid()?;
                crate::output::write_bytes_atomically(path, &modeler::vdb::vdb_bytes(&grid, "density")?)?;
                Ok(Some(format!("wrote {}", path.display())))
            }
            Target::Mitsuba => {
                let scene = self.scene.build_scene(None)?;
                crate::mitsuba::export(&scene, 256, path)?;
                Ok(Some(format!("wrote cloud.vol and scene.xml to {}", path.display())))
            }
        }
    }

    pub fn scene(&self) -> &SceneFile {
        &self.scene
    }

    /// The integrator mode of the latest published image.
    pub fn rendered_mode(&self) -> Option<engine::Mode> {
        self.worker.mailbox.lock().unwrap().latest.as_ref().map(|p| p.mode)
    }

    /// The render worker's current message (an error, or why prediction fell back).
    pub fn worker_message(&self) -> Option<String> {
        self.worker.mailbox.lock().unwrap().error.as_ref().map(|(_, m)| m.clone())
    }

    /// The recent-files list, newest first.
    pub fn recent(&self) -> &[std::path::PathBuf] {
        &self.recent
    }

    fn remember(&mut self, path: &std::path::Path) {
        let path = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
        self.recent.retain(|p| *p != path);
        self.recent.insert(0, path);
        self.recent.truncate(RECENT_MAX);
    }

    fn open_scene(&mut self, path: std::path::PathBuf) -> anyhow::Result<Option<String>> {
        let mut scene = SceneFile::load(&path)?;
        scene.validate()?;
        // Keep relative cloud and model files working after the scene moves into memory.
        if let (Some(f), Some(dir)) = (&scene.grid.file, &scene.base_dir) {
            scene.grid.file = Some(dir.join(f).display().to_string());
        }
        if let Some(m) = scene.model_path() {
            scene.render.model = Some(m.display().to_string());
        }
        self.set_scene(scene);
        self.remember(&path);
        Ok(Some(format!("opened {}", path.display())))
    }

    fn open_vdb(&mut self, path: std::path::PathBuf) -> anyhow::Result<Option<String>> {
        // Check it now, so a bad file is reported here rather than by the worker.
        modeler::vdb::read_vdb(&path, None)?;
        let mut scene = self.scene.clone();
        let g = &mut scene.grid;
        (g.builtin, g.preset, g.params, g.file, g.grid_name) =
            (None, None, None, Some(path.display().to_string()), None);
        self.set_scene(scene);
        self.remember(&path);
        Ok(Some(format!("opened {}", path.display())))
    }

    /// Checks the model now (a bad file is reported here, naming what is wrong) and
    /// switches to prediction with it.
    fn load_model(&mut self, path: std::path::PathBuf) -> anyhow::Result<Option<String>> {
        models::global::GlobalModel::load(&path)?;
        self.scene.render.model = Some(path.display().to_string());
        self.scene.render.mode = "predict".into();
        Ok(Some(format!("predicting with {}", path.display())))
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
            ui.label("Drag the image to orbit, scroll to zoom; Shift-drag or right-drag moves the sun.");

            ui.separator();
            ui.heading("Render");
            ui.horizontal(|ui| {
                ui.radio_value(&mut self.scene.render.mode, "reference".to_string(), "path tracing");
                ui.radio_value(&mut self.scene.render.mode, "predict".to_string(), "prediction at bounce k")
                    .on_hover_text("vertices 1 .. k-1 path traced, the learned model predicts the rest at vertex k");
                ui.radio_value(&mut self.scene.render.mode, "preview".to_string(), "instant preview").on_hover_text(
                    "ray marching: single scattering from the sun's transmittance field, the higher orders from \
                     the learned model (or the octave approximation); clean at once, biased by the model's error",
                );
            });
            if self.scene.render.mode == "preview" {
                ui.horizontal(|ui| {
                    ui.label("higher orders");
                    ui.selectable_value(&mut self.scene.render.preview, "learned".to_string(), "learned");
                    ui.selectable_value(&mut self.scene.render.preview, "octaves".to_string(), "octaves")
                        .on_hover_text("Wrenninge et al. 2013: N = 3, a = b = c = 0.5");
                });
            }
            ui.horizontal(|ui| {
                ui.label("algorithm");
                ui.selectable_value(&mut self.scene.render.integrator, "path".to_string(), "unidirectional");
                ui.selectable_value(&mut self.scene.render.integrator, "bdpt".to_string(), "bidirectional")
                    .on_hover_text(
                        "volumetric BDPT: light subpaths from the sun joined to camera subpaths, with MIS; with \
                     prediction, the point-to-point model predicts the transport between k-segment subpaths",
                    );
            });
            let p2p = self.scene.render.mode == "predict" && self.scene.render.integrator == "bdpt";
            let k_label =
                if p2p { "k (segments per subpath; high = orders 2k+1 and up)" } else { "k (first high order)" };
            ui.add(egui::Slider::new(&mut self.scene.k, 1..=8).text(k_label));
            if self.scene.render.mode == "predict" {
                ui.add(egui::Slider::new(&mut self.scene.render.p, 0.05..=1.0).text("prediction probability p"));
                if p2p {
                    ui.add(egui::Slider::new(&mut self.scene.render.r, 0.0..=0.3).text("distance threshold r"))
                        .on_hover_text(
                            "end vertices closer than r are joined by extending the subpaths, not predicted",
                        );
                    let max_m = engine::integrator::bdpt::Prediction::MAX_CANDIDATES;
                    ui.add(
                        egui::Slider::new(&mut self.scene.render.candidates, 1..=max_m)
                            .logarithmic(true)
                            .text("light subpath candidates"),
                    )
                    .on_hover_text(
                        "light subpaths offered to each camera end vertex, one chosen by resampling; 1 is the \
                         thesis's pairing; the others are picked from a pool traced once per pass, so more \
                         lower the noise for little cost",
                    );
                    let max_n = engine::integrator::bdpt::Prediction::MAX_EXTENSION_SAMPLES;
                    ui.add(
                        egui::Slider::new(&mut self.scene.render.extension_samples, 1..=max_n)
                            .logarithmic(true)
                            .text("samples per close pair"),
                    )
                    .on_hover_text(
                        "point-to-point samples averaged where the end vertices are closer than r (those pairs \
                         carry most of the noise when the sun is behind the camera)",
                    );
                }
                ui.checkbox(&mut self.compare, "compare with path tracing")
                    .on_hover_text("reference and prediction side by side, with the low, high and error buffers");
                if self.compare {
                    ui.horizontal(|ui| {
                        let layout = &mut self.compare_view.layout;
                        ui.selectable_value(layout, Layout::SideBySide, "side by side");
                        ui.selectable_value(layout, Layout::Wipe, "wipe")
                            .on_hover_text("both over the whole view; drag the divider");
                    });
                }
                ui.label(match (p2p, &self.scene.render.model, &self.scene.render.p2p_model) {
                    (true, _, Some(m)) => format!("model: {m}"),
                    (true, _, None) => "model: shipped point-to-point model".to_string(),
                    (false, Some(m), _) => format!("model: {m}"),
                    (false, None, _) => "model: shipped global model".to_string(),
                });
            }
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
            let key = (p.generation, p.film.spp(), self.exposure, self.view_buffer, self.tone);
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
        self.view_rect = rect;
        ui.painter().rect_filled(rect, 0.0, egui::Color32::from_gray(12));
        let side_by_side = self.compare && published.as_ref().is_some_and(|p| p.reference.is_some());
        let k = self.scene.k;
        // Where the wipe divider is on screen, when the wipe view is up.
        let mut divider: Option<(egui::Rect, f32)> = None;
        if side_by_side {
            if let Some(p) = &published {
                self.compare_view.update(ui.ctx(), p, self.tone, self.exposure, self.view_buffer);
            }
            let reference = self.compare_view.reference.clone();
            match self.compare_view.layout {
                Layout::SideBySide => {
                    let half = rect.width() / 2.0;
                    let left = egui::Rect::from_min_size(rect.min, egui::vec2(half, rect.height()));
                    let right =
                        egui::Rect::from_min_size(rect.min + egui::vec2(half, 0.0), egui::vec2(half, rect.height()));
                    if let Some(t) = &reference {
                        paint_fitted(ui, t, left, "path tracing (reference)");
                    }
                    if let Some(t) = &self.texture {
                        paint_fitted(ui, t, right, &format!("prediction at bounce {k}"));
                    }
                }
                Layout::Wipe => {
                    if let (Some(r), Some(t)) = (&reference, &self.texture) {
                        let shown = fitted(t, rect);
                        let x = shown.min.x + self.compare_view.wipe * shown.width();
                        let (left, right) = (
                            egui::Rect::from_min_max(shown.min, egui::pos2(x, shown.max.y)),
                            egui::Rect::from_min_max(egui::pos2(x, shown.min.y), shown.max),
                        );
                        paint_part(ui, r, shown, left);
                        paint_part(ui, t, shown, right);
                        let stroke = egui::Stroke::new(2.0, egui::Color32::from_gray(230));
                        ui.painter().vline(x, shown.y_range(), stroke);
                        ui.painter().circle(egui::pos2(x, shown.center().y), 7.0, egui::Color32::from_gray(40), stroke);
                        caption(
                            ui,
                            rect.min + egui::vec2(8.0, 6.0),
                            egui::Align2::LEFT_TOP,
                            "path tracing (reference)",
                        );
                        caption(
                            ui,
                            egui::pos2(rect.max.x - 8.0, rect.min.y + 6.0),
                            egui::Align2::RIGHT_TOP,
                            &format!("prediction at bounce {k}"),
                        );
                        divider = Some((shown, x));
                    } else if let Some(t) = &self.texture {
                        paint_fitted(ui, t, rect, "");
                    }
                }
            }
        } else if let Some(t) = &self.texture {
            paint_fitted(ui, t, rect, "");
        }
        self.paint_sun(ui, rect);

        // Dragging: the wipe divider when grabbed near it, the sun with Shift or the
        // secondary button, otherwise the orbit.
        if response.drag_started() {
            // Where the button went down: a drag starts only after the pointer has moved.
            let origin = ui.input(|i| i.pointer.press_origin()).or(response.interact_pointer_pos());
            let near = |(shown, x): (egui::Rect, f32)| {
                origin.is_some_and(|p| (p.x - x).abs() < 10.0 && shown.y_range().contains(p.y))
            };
            self.drag = if divider.is_some_and(near) {
                ViewDrag::Wipe
            } else if response.dragged_by(egui::PointerButton::Secondary) || ui.input(|i| i.modifiers.shift) {
                ViewDrag::Sun
            } else {
                ViewDrag::Orbit
            };
        }
        if response.dragged() {
            let d = response.drag_delta();
            match self.drag {
                ViewDrag::Wipe => {
                    if let (Some((shown, _)), Some(p)) = (divider, response.interact_pointer_pos()) {
                        self.compare_view.wipe = ((p.x - shown.min.x) / shown.width()).clamp(0.0, 1.0);
                    }
                }
                ViewDrag::Sun => {
                    self.sun_azimuth_deg = (self.sun_azimuth_deg + d.x * 0.4).rem_euclid(360.0);
                    self.sun_elevation_deg = (self.sun_elevation_deg - d.y * 0.3).clamp(-89.0, 89.0);
                    self.apply_sun();
                }
                ViewDrag::Orbit => {
                    self.orbit.yaw_deg -= d.x * 0.4;
                    self.orbit.pitch_deg = (self.orbit.pitch_deg + d.y * 0.4).clamp(-89.0, 89.0);
                }
            }
        }
        if response.hovered() {
            let scroll = ui.ctx().input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                self.orbit.distance = (self.orbit.distance * (-scroll * 0.002).exp()).clamp(1.0, 10.0);
            }
        }
    }

    /// Marks where the sun is, when it is in front of the camera: a disc at its
    /// projection, or an arrow on the image's edge pointing toward it.
    fn paint_sun(&self, ui: &egui::Ui, rect: egui::Rect) {
        let Some(texture) = &self.texture else { return };
        let shown = fitted(texture, rect);
        let cam = &self.scene.camera;
        let target = Vec3::from_array(cam.target);
        let pos = Vec3::from_array(cam.position.unwrap_or([0.0, 0.0, 3.0]));
        let forward = (target - pos).normalize_or(Vec3::NEG_Z);
        let right = forward.cross(Vec3::from_array(cam.up)).normalize_or(Vec3::X);
        let up = right.cross(forward);
        let to_sun = -Vec3::from_array(self.scene.sun.direction).normalize_or(Vec3::NEG_Y);
        let depth = to_sun.dot(forward);
        let tan_half = (cam.fov_y_deg.to_radians() / 2.0).tan();
        let aspect = shown.width() / shown.height().max(1.0);
        let colour = egui::Color32::from_rgb(255, 214, 90);
        if depth > 1e-3 {
            let sx = to_sun.dot(right) / depth / (tan_half * aspect);
            let sy = to_sun.dot(up) / depth / tan_half;
            if sx.abs() <= 1.0 && sy.abs() <= 1.0 {
                let p = shown.center() + egui::vec2(sx * shown.width() / 2.0, -sy * shown.height() / 2.0);
                ui.painter().circle_stroke(p, 9.0, egui::Stroke::new(2.0, colour));
                ui.painter().circle_filled(p, 4.0, colour);
                return;
            }
        }
        // Behind or outside the frame: a small arrow on the frame's edge.
        let dir = egui::vec2(to_sun.dot(right), -to_sun.dot(up));
        if dir.length() < 1e-4 {
            return;
        }
        let dir = dir.normalized();
        let half = shown.size() / 2.0 - egui::vec2(14.0, 14.0);
        let t = (half.x / dir.x.abs().max(1e-6)).min(half.y / dir.y.abs().max(1e-6));
        let tip = shown.center() + dir * t;
        ui.painter().arrow(tip - dir * 14.0, dir * 12.0, egui::Stroke::new(2.0, colour));
    }

    fn status(&self, ui: &mut egui::Ui) {
        let mb = self.worker.mailbox.lock().unwrap();
        ui.horizontal(|ui| {
            if let Some(p) = &mb.latest {
                match p.standing_in {
                    Some((which, under)) => {
                        let render = match under {
                            Some(n) => format!("render under it at {:.1} % noise", 100.0 * n),
                            None => "render starting".into(),
                        };
                        ui.label(format!(
                            "instant preview ({which}), {} passes   {:.2} s   {render}, shown below {:.0} %",
                            p.film.spp(),
                            p.render_secs,
                            100.0 * worker::HANDOFF_NOISE
                        ))
                        .on_hover_text(
                            "ray marched single scattering from the sun's transmittance field, higher orders from \
                             the learned model or the octave approximation; the scene's own render replaces it once \
                             it is clean",
                        );
                    }
                    None => {
                        let noise = if p.noise.is_finite() {
                            format!("{:.1} %", 100.0 * p.noise)
                        } else {
                            "not known yet".to_string()
                        };
                        ui.label(format!(
                            "{} spp   {:.1} s   {:.2} M samples/s   noise {noise}{}",
                            p.film.spp(),
                            p.render_secs,
                            p.samples_per_sec / 1e6,
                            if p.coarse { "   (coarse cloud while dragging)" } else { "" }
                        ));
                    }
                }
            } else {
                ui.label("starting…");
            }
            ui.label(format!("   UI {:.1} ms (max {:.1} ms over 1 s)", self.frame_ms.0, self.frame_ms.1))
                .on_hover_text("CPU time of the window's own work per frame; rendering runs on other threads");
            if mb.building {
                ui.spinner();
                ui.label("building the cloud…");
            }
        });
        if let Some((_, e)) = &mb.error {
            ui.colored_label(egui::Color32::from_rgb(255, 110, 90), e);
        }
        if let Some((text, is_error)) = &self.message {
            let colour =
                if *is_error { egui::Color32::from_rgb(255, 110, 90) } else { egui::Color32::from_rgb(140, 200, 140) };
            ui.colored_label(colour, text);
        }
    }

    /// Sends the scene to the worker when it changed (coarse while the pointer is down).
    fn sync(&mut self, ctx: &egui::Context) {
        self.apply_camera();
        let dragging = ctx.input(|i| i.pointer.any_down());
        let changed = self
            .sent
            .as_ref()
            .is_none_or(|(s, coarse, cmp)| *s != self.scene || (*coarse && !dragging) || *cmp != self.compare);
        if !dragging {
            self.history.record(&self.scene);
        }
        if changed {
            if let Err(e) = self.scene.validate() {
                self.worker.mailbox.lock().unwrap().error = Some((0, e.to_string()));
                return;
            }
            let grid_changed = self.sent.as_ref().is_none_or(|(s, _, _)| s.grid != self.scene.grid);
            let coarse = dragging && grid_changed || dragging && self.sent.as_ref().is_some_and(|(_, c, _)| *c);
            self.worker.render_compare(&self.scene, coarse, self.compare);
            self.sent = Some((self.scene.clone(), coarse, self.compare));
        }
    }
}

impl eframe::App for NimbusApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let started = std::time::Instant::now();
        egui::Panel::top("menu").show(ui, |ui| self.menu(ui));
        egui::Panel::right("controls").resizable(true).default_size(300.0).show(ui, |ui| self.controls(ui));
        egui::Panel::bottom("status").show(ui, |ui| self.status(ui));
        if self.compare && self.scene.render.mode == "predict" {
            egui::Panel::left("buffers").resizable(true).default_size(200.0).show(ui, |ui| self.compare_view.panel(ui));
        }
        egui::CentralPanel::default().show(ui, |ui| self.viewport(ui));
        let ctx = ui.ctx().clone();
        self.shortcuts(&ctx);
        self.apply_actions();
        self.sync(&ctx);
        let ms = started.elapsed().as_secs_f32() * 1e3;
        let (_, max, since) = self.frame_ms;
        self.frame_ms = if since.elapsed().as_secs_f32() > 1.0 { (ms, ms, started) } else { (ms, max.max(ms), since) };
    }

    fn save(&mut self, storage: &mut dyn eframe::Storage) {
        storage.set_string(STORAGE_SCENE, self.scene.to_toml());
        let recent: Vec<String> = self.recent.iter().map(|p| p.display().to_string()).collect();
        storage.set_string(STORAGE_RECENT, recent.join("\n"));
    }
}

/// Where a texture lands in `rect`: scaled to fit and centred.
fn fitted(t: &egui::TextureHandle, rect: egui::Rect) -> egui::Rect {
    let size = t.size_vec2();
    let scale = (rect.width() / size.x).min(rect.height() / size.y);
    egui::Rect::from_center_size(rect.center(), size * scale)
}

/// Draws a texture into `rect`, scaled to fit and centred, with a caption on top.
fn paint_fitted(ui: &egui::Ui, t: &egui::TextureHandle, rect: egui::Rect, text: &str) {
    let uv = egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0));
    ui.painter().image(t.id(), fitted(t, rect), uv, egui::Color32::WHITE);
    if !text.is_empty() {
        caption(ui, rect.min + egui::vec2(8.0, 6.0), egui::Align2::LEFT_TOP, text);
    }
}

/// Draws the part `part` of a texture laid out over `shown`.
fn paint_part(ui: &egui::Ui, t: &egui::TextureHandle, shown: egui::Rect, part: egui::Rect) {
    let uv = |p: egui::Pos2| egui::pos2((p.x - shown.min.x) / shown.width(), (p.y - shown.min.y) / shown.height());
    let uv = egui::Rect::from_min_max(uv(part.min), uv(part.max));
    ui.painter().image(t.id(), part, uv, egui::Color32::WHITE);
}

fn caption(ui: &egui::Ui, at: egui::Pos2, align: egui::Align2, text: &str) {
    ui.painter().text(at, align, text, egui::FontId::proportional(14.0), egui::Color32::from_gray(220));
}

/// Opens the window; returns when it is closed.
pub fn run() -> anyhow::Result<()> {
    let options = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default().with_inner_size([1180.0, 760.0]).with_title("Nimbus"),
        ..Default::default()
    };
    eframe::run_native("Nimbus", options, Box::new(|cc| Ok(Box::new(NimbusApp::new(&cc.egui_ctx, cc.storage)))))
        .map_err(|e| {
            anyhow::anyhow!(
                "cannot open the Nimbus window: {e} (the subcommands work without a display: nimbus --help)"
            )
        })
}
