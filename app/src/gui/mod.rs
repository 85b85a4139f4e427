//! The Nimbus window (eframe/egui with wgpu): a progressive viewport, cloud, medium,
//! light and camera controls, and a status bar. Rendering happens on the worker
//! thread (`worker`); the UI only edits a scene description, sends it, and shows the
//! latest finished pass through one texture.

pub mod compare;
pub mod files;
pub mod modeler_panel;
pub mod widgets;
pub mod worker;

use crate::output::ToneMap;
use crate::scene::{CameraPreset, SceneFile, default_up, sun_angles_of, sun_vector};
pub use compare::bias_verdict;
use compare::{CompareView, Layout};
use eframe::egui;
use engine::Buffer;
use glam::Vec3;
use widgets::slider;
use worker::{RenderTarget, WorkerHandle};

/// The default sun of a fresh start, (elevation, azimuth) in degrees: a three-quarter
/// light from above the camera's right shoulder, so the cloud's form shows in light
/// and shadow (a sun overhead gives a flat grey blob from the side).
pub const DEFAULT_SUN: (f32, f32) = (35.0, 50.0);

/// The default scene a fresh start shows: the built-in cumulus under a three-quarter
/// sun, seen from slightly above.
pub fn default_scene() -> SceneFile {
    let mut s =
        SceneFile::from_toml_str(include_str!("../../../assets/scenes/cumulus.toml"), "assets/scenes/cumulus.toml")
            .expect("the bundled scene parses");
    s.grid.resolution = 96;
    s.k = 2;
    s.sun.direction = (-sun_vector(DEFAULT_SUN.0, DEFAULT_SUN.1)).to_array();
    let d = s.camera.distance;
    let pitch = 10f32.to_radians();
    s.camera.preset = None;
    s.camera.position = Some([0.0, d * pitch.sin(), d * pitch.cos()]);
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
    /// Pick another model (.safetensors with its .json sidecar) for prediction.
    LoadModel,
    /// Switch prediction to this model file without a dialog.
    LoadModelFrom(std::path::PathBuf),
    /// Write the latest image as EXR (every buffer) and PNG into the renders folder,
    /// named by the time, without a dialog.
    SaveRender,
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

/// What a file dialog is for; its answer becomes an [`Action`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pick {
    OpenScene,
    OpenVdb,
    LoadModel,
    Write(Target),
}

impl Pick {
    fn request(self) -> files::Request {
        use files::{Kind, Request};
        match self {
            Pick::OpenScene => {
                Request::new(Kind::Open, "Open a scene or a cloud", "Nimbus scene or OpenVDB", &["toml", "vdb"], "")
            }
            Pick::OpenVdb => Request::new(Kind::Open, "Open a VDB cloud", "OpenVDB", &["vdb"], ""),
            Pick::LoadModel => {
                Request::new(Kind::Open, "Load a model of prediction at bounce k", "Nimbus model", &["safetensors"], "")
            }
            Pick::Write(Target::Scene) => {
                Request::new(Kind::Save, "Save the scene", "Nimbus scene", &["toml"], "scene.toml")
            }
            Pick::Write(Target::Exr) => {
                Request::new(Kind::Save, "Export the image, every buffer", "OpenEXR", &["exr"], "nimbus.exr")
            }
            Pick::Write(Target::Png) => {
                Request::new(Kind::Save, "Export the image as shown", "PNG", &["png"], "nimbus.png")
            }
            Pick::Write(Target::Vdb) => Request::new(Kind::Save, "Export the cloud", "OpenVDB", &["vdb"], "cloud.vdb"),
            Pick::Write(Target::Mitsuba) => {
                Request::new(Kind::Folder, "Export a Mitsuba 3 scene into a folder", "", &[], "")
            }
        }
    }

    fn finish(self, path: std::path::PathBuf) -> Action {
        match self {
            Pick::OpenScene | Pick::OpenVdb => Action::OpenPath(path),
            Pick::LoadModel => Action::LoadModelFrom(path),
            Pick::Write(t) => Action::WriteTo(t, path),
        }
    }
}

/// Output sizes offered for export and the scene file: (name, width, height).
pub const OUTPUT_SIZES: [(&str, u32, u32); 7] = [
    ("256 x 256", 256, 256),
    ("512 x 512", 512, 512),
    ("1024 x 1024", 1024, 1024),
    ("1280 x 720 (HD)", 1280, 720),
    ("1920 x 1080 (full HD)", 1920, 1080),
    ("1080 x 1350 (portrait 4:5)", 1080, 1350),
    ("2048 x 1024 (2:1)", 2048, 1024),
];

/// The image size rendered for a viewport of `size` physical pixels at `scale`:
/// multiples of 8 (so small resizes do not restart the render), 16 ..= 2048.
pub fn viewport_render_size(size: egui::Vec2, scale: f32) -> (u32, u32) {
    let px = |v: f32| (((v * scale) / 8.0).round() as u32 * 8).clamp(16, 2048);
    (px(size.x), px(size.y))
}

/// A radiance as (colour with its largest channel 1, intensity).
fn colour_and_intensity(c: crate::scene::Rgb) -> ([f32; 3], f32) {
    let v = c.to_vec3();
    let i = v.max_element();
    if i > 0.0 { ((v / i).to_array(), i) } else { ([1.0; 3], 0.0) }
}

/// The radiance of `colour` at `intensity` (grey when the colour is white).
fn radiance_of(colour: [f32; 3], intensity: f32) -> crate::scene::Rgb {
    if colour == [1.0; 3] {
        crate::scene::Rgb::Grey(intensity)
    } else {
        crate::scene::Rgb::Rgb(colour.map(|c| c * intensity))
    }
}

/// A colour button and an intensity slider for a radiance of at most `max`; the
/// new radiance when either changed. `labels`: the slider's text and the colour's
/// tooltip.
fn colour_row(
    ui: &mut egui::Ui,
    value: crate::scene::Rgb,
    max: f32,
    labels: (&str, &str),
    tip: &str,
) -> Option<crate::scene::Rgb> {
    let (mut colour, mut intensity) = colour_and_intensity(value);
    let mut changed = false;
    ui.horizontal(|ui| {
        changed |= egui::color_picker::color_edit_button_rgb(ui, &mut colour).on_hover_text(labels.1).changed();
        changed |= ui.add(slider(&mut intensity, 0.0..=max).text(labels.0)).on_hover_text(tip).changed();
    });
    changed.then(|| radiance_of(colour, intensity))
}

/// A file name from the wall clock, UTC: `nimbus-YYYYMMDD-HHMMSS`.
fn timestamp_name() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("nimbus-{y:04}{m:02}{d:02}-{:02}{:02}{:02}", rem / 3600, rem / 60 % 60, rem % 60)
}

/// A relative noise for the status bar ("not known yet" below 2 spp).
fn noise_text(n: f64) -> String {
    if n.is_finite() { format!("{:.1} %", 100.0 * n) } else { "not known yet".into() }
}

/// The status bar's text for a published image: the preview standing in and how far
/// the render under it is, or the render's samples, time, speed and noise (both
/// sides in compare mode), and the coarse cloud only when the cloud is coarse.
pub fn status_text(p: &worker::Published) -> String {
    let coarse = if p.coarse { "   (cloud at 48^3 while the slider moves)" } else { "" };
    if let Some((which, under)) = p.standing_in {
        let render = match under {
            Some(n) => format!("render under it at {} noise", noise_text(n)),
            None => "render starting".into(),
        };
        return format!(
            "instant preview ({which}), {} passes   {:.2} s   {render}, shown below {:.0} %{coarse}",
            p.film.spp(),
            p.render_secs,
            100.0 * worker::HANDOFF_NOISE
        );
    }
    let what = match p.mode {
        _ if p.is_preview => "instant preview",
        engine::Mode::Reference => "path tracing",
        engine::Mode::Predict { .. } => "prediction",
    };
    let done = if p.done { "   done" } else { "" };
    match (&p.reference, p.reference_noise) {
        (Some(r), Some(rn)) => format!(
            "{what}: {} spp, noise {}   reference: {} spp, noise {}   {:.1} s   {:.2} M samples/s{done}{coarse}",
            p.film.spp(),
            noise_text(p.noise),
            r.spp(),
            noise_text(rn),
            p.render_secs,
            p.samples_per_sec / 1e6
        ),
        _ => format!(
            "{what}: {} spp   {:.1} s   {:.2} M samples/s   noise {}{done}{coarse}",
            p.film.spp(),
            p.render_secs,
            p.samples_per_sec / 1e6,
            noise_text(p.noise)
        ),
    }
}

/// What the shape box shows for `g`.
fn grid_label(g: &crate::scene::GridDesc) -> String {
    match (&g.builtin, &g.preset, &g.file, &g.params) {
        (Some(b), _, _, _) => format!("builtin: {b}"),
        (_, Some(p), _, _) => p.clone(),
        (_, _, Some(f), _) => {
            format!("file: {}", std::path::Path::new(f).file_name().map(|n| n.to_string_lossy()).unwrap_or_default())
        }
        (_, _, _, Some(p)) => format!("modeler cloud (seed {})", p.seed),
        _ => "custom parameters".into(),
    }
}

/// Where "save render" writes: the user's pictures folder, else the current one.
pub fn default_render_dir() -> std::path::PathBuf {
    match std::env::var_os("HOME") {
        Some(h) => std::path::Path::new(&h).join("Pictures").join("Nimbus"),
        None => std::path::PathBuf::from("nimbus-renders"),
    }
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
/// The status bar's height: three rows (figures, the worker's message, the window's).
const STATUS_HEIGHT: f32 = 64.0;
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
    /// The last scene sent to the worker, whether its cloud was coarse, whether in
    /// compare mode, whether the pointer was down.
    sent: Option<(SceneFile, bool, bool, bool)>,
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
    /// Where the scene's own image was drawn in the last frame.
    image_rect: Option<egui::Rect>,
    /// Physical pixels per point in the last frame.
    pixels_per_point: f32,
    modeler: modeler_panel::ModelerPanel,
    /// The file dialog open now and what its answer is for.
    dialog: Option<(Pick, files::Dialog)>,
    /// Use the desktop's dialogs (cleared when the portal turns out not to answer).
    native_dialogs: bool,
    /// The folder the next dialog starts in.
    dialog_dir: std::path::PathBuf,
    /// Where "save render" writes (None: no folder; the action says so).
    render_dir: Option<std::path::PathBuf>,
    /// Render at the viewport's size times this (None: at the scene's output size).
    viewport_scale: Option<f32>,
    /// Keep the output size's aspect ratio when one side is edited.
    aspect_lock: bool,
    target: RenderTarget,
    /// The target of the last render sent.
    sent_target: RenderTarget,
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
            image_rect: None,
            pixels_per_point: 1.0,
            // The user's presets and renders only for the real window (with storage);
            // a window without storage (tests) touches no folder unless told to.
            modeler: modeler_panel::ModelerPanel::new(storage.and_then(|_| modeler_panel::default_user_dir())),
            dialog: None,
            native_dialogs: true,
            dialog_dir: std::env::current_dir().unwrap_or_default(),
            render_dir: storage.map(|_| default_render_dir()),
            viewport_scale: Some(0.5),
            aspect_lock: true,
            target: RenderTarget::Unlimited,
            sent_target: RenderTarget::Unlimited,
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
        self.preset_name = grid_label(g);
        self.scene = scene;
        self.apply_camera();
    }

    /// Renders at the viewport's size times `scale` (Some), or at the scene's output
    /// size (None).
    pub fn set_viewport_scale(&mut self, scale: Option<f32>) {
        self.viewport_scale = scale.map(|s| s.clamp(0.1, 1.0));
    }

    /// The size the window renders at now: the viewport's (scaled) or the output size.
    pub fn render_size(&self) -> (u32, u32) {
        match self.viewport_scale {
            Some(scale) if self.view_rect.is_positive() => {
                viewport_render_size(self.view_rect.size() * self.pixels_per_point, scale)
            }
            _ => (self.scene.camera.width, self.scene.camera.height),
        }
    }

    /// When the render stops.
    pub fn set_target(&mut self, target: RenderTarget) {
        self.target = target;
    }

    /// Where "save render" writes.
    pub fn set_render_dir(&mut self, dir: Option<std::path::PathBuf>) {
        self.render_dir = dir;
    }

    /// Where the user's modeler presets are kept.
    pub fn set_preset_dir(&mut self, dir: Option<std::path::PathBuf>) {
        self.modeler.set_user_dir(dir);
    }

    /// The modeler panel (presets, thumbnails).
    pub fn modeler(&self) -> &modeler_panel::ModelerPanel {
        &self.modeler
    }

    /// Use the desktop's file dialogs (true) or always the window's own (false).
    pub fn set_native_dialogs(&mut self, on: bool) {
        self.native_dialogs = on;
    }

    /// What the open file dialog is for, if one is open.
    pub fn dialog(&self) -> Option<Pick> {
        self.dialog.as_ref().map(|(p, _)| *p)
    }

    /// The folder file dialogs start in.
    pub fn set_dialog_dir(&mut self, dir: std::path::PathBuf) {
        self.dialog_dir = dir;
    }

    /// Where the sun's marker is on screen, when the sun is inside the image.
    pub fn sun_marker(&self) -> Option<egui::Pos2> {
        let shown = self.image_rect?;
        let (forward, right, up, tan_half) = self.camera_basis();
        let to_sun = -Vec3::from_array(self.scene.sun.direction).normalize_or(Vec3::NEG_Y);
        let depth = to_sun.dot(forward);
        if depth <= 1e-3 {
            return None;
        }
        let aspect = shown.width() / shown.height().max(1.0);
        let sx = to_sun.dot(right) / depth / (tan_half * aspect);
        let sy = to_sun.dot(up) / depth / tan_half;
        (sx.abs() <= 1.0 && sy.abs() <= 1.0)
            .then(|| shown.center() + egui::vec2(sx * shown.width() / 2.0, -sy * shown.height() / 2.0))
    }

    /// The camera's forward, right and up vectors and tan(fov_y / 2).
    fn camera_basis(&self) -> (Vec3, Vec3, Vec3, f32) {
        let cam = &self.scene.camera;
        let target = Vec3::from_array(cam.target);
        let pos = Vec3::from_array(cam.position.unwrap_or([0.0, 0.0, 3.0]));
        let forward = (target - pos).normalize_or(Vec3::NEG_Z);
        let right = forward.cross(Vec3::from_array(cam.up)).normalize_or(Vec3::X);
        let up = right.cross(forward);
        (forward, right, up, (cam.fov_y_deg.to_radians() / 2.0).tan())
    }

    /// Puts the sun where the pointer at `p` looks (its marker lands under it).
    fn point_sun_at(&mut self, p: egui::Pos2) {
        let Some(shown) = self.image_rect else { return };
        let (forward, right, up, tan_half) = self.camera_basis();
        let aspect = shown.width() / shown.height().max(1.0);
        let sx = (p.x - shown.center().x) / (shown.width() / 2.0);
        let sy = -(p.y - shown.center().y) / (shown.height() / 2.0);
        let dir = forward + right * (sx * tan_half * aspect) + up * (sy * tan_half);
        let (el, az) = sun_angles_of(dir);
        (self.sun_elevation_deg, self.sun_azimuth_deg) = (el.clamp(-89.0, 89.0), az);
        self.apply_sun();
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

    /// The size of the latest published image.
    pub fn rendered_size(&self) -> Option<(u32, u32)> {
        self.worker.mailbox.lock().unwrap().latest.as_ref().map(|p| (p.film.width(), p.film.height()))
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
                    ("Save render (EXR + PNG to the renders folder)  Ctrl+Shift+E", Action::SaveRender),
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
                if ui.button("Load model…").clicked() {
                    self.actions.push(Action::LoadModel);
                    ui.close();
                }
                ui.checkbox(&mut self.native_dialogs, "use the desktop's file dialogs").on_hover_text(
                    "through the XDG desktop portal when one runs; otherwise, or when off, the window draws its own",
                );
                if let Some(dir) = &self.render_dir {
                    ui.weak(format!("renders folder: {}", dir.display()));
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
            (KeyboardShortcut::new(Modifiers::COMMAND | Modifiers::SHIFT, Key::E), Action::SaveRender),
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
            Action::LoadModel => self.ask(Pick::LoadModel),
            Action::LoadModelFrom(path) => self.load_model(path),
            Action::OpenScene => self.ask(Pick::OpenScene),
            Action::OpenVdb => self.ask(Pick::OpenVdb),
            Action::SaveScene => self.ask(Pick::Write(Target::Scene)),
            Action::ExportExr | Action::ExportPng => {
                // Refuse before asking for a file when there is nothing to write.
                self.worker.mailbox.lock().unwrap().latest.as_ref().context("nothing rendered yet")?;
                self.ask(Pick::Write(if action == Action::ExportExr { Target::Exr } else { Target::Png }))
            }
            Action::ExportVdb => self.ask(Pick::Write(Target::Vdb)),
            Action::ExportMitsuba => self.ask(Pick::Write(Target::Mitsuba)),
            Action::SaveRender => self.save_render(),
            Action::WriteTo(target, path) => self.write_to(target, &path),
        }
    }

    /// Opens a file dialog for `pick` (the desktop's when its portal answers, else the
    /// window's own); its answer is applied as an action when it comes.
    fn ask(&mut self, pick: Pick) -> anyhow::Result<Option<String>> {
        if self.dialog.is_some() {
            anyhow::bail!("a file dialog is already open");
        }
        let native = self.native_dialogs && files::portal_available();
        self.dialog = Some((pick, files::Dialog::open(pick.request(), native, &self.dialog_dir)));
        Ok(None)
    }

    /// Shows or polls the open file dialog; a chosen path becomes its action.
    fn dialogs(&mut self, ctx: &egui::Context) {
        let Some((pick, dialog)) = &mut self.dialog else { return };
        let pick = *pick;
        match dialog.show(ctx, &mut self.native_dialogs, &self.dialog_dir) {
            files::Outcome::Pending => {}
            files::Outcome::Cancelled => self.dialog = None,
            files::Outcome::Picked(path) => {
                let dir = if pick == Pick::Write(Target::Mitsuba) { Some(path.as_path()) } else { path.parent() };
                if let Some(d) = dir.filter(|d| d.is_dir()) {
                    self.dialog_dir = d.to_path_buf();
                }
                self.actions.push(pick.finish(path));
                self.dialog = None;
            }
        }
    }

    /// Writes the latest image as EXR and PNG into the renders folder.
    fn save_render(&mut self) -> anyhow::Result<Option<String>> {
        use anyhow::Context as _;
        let dir = self.render_dir.clone().context("no folder for renders")?;
        self.worker.mailbox.lock().unwrap().latest.as_ref().context("nothing rendered yet")?;
        std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let stem = timestamp_name();
        let mut name = stem.clone();
        for n in 2.. {
            if !dir.join(format!("{name}.exr")).exists() && !dir.join(format!("{name}.png")).exists() {
                break;
            }
            name = format!("{stem}-{n}");
        }
        let (exr, png) = (dir.join(format!("{name}.exr")), dir.join(format!("{name}.png")));
        self.write_to(Target::Exr, &exr)?;
        self.write_to(Target::Png, &png)?;
        let spp = self.rendered().map(|r| r.1).unwrap_or(0);
        Ok(Some(format!("saved {} and {}.png ({spp} spp)", exr.display(), name)))
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
                let (w, h) = (film.width(), film.height());
                let cam = &self.scene.camera;
                let size = if (w, h) != (cam.width, cam.height) {
                    format!(
                        "{w} x {h}, the viewport's size; turn off \"render at the viewport's size\" for the output \
                         size {} x {}",
                        cam.width, cam.height
                    )
                } else {
                    format!("{w} x {h}")
                };
                Ok(Some(format!("wrote {} ({size}, {} spp)", path.display(), film.spp())))
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
        scene.absolutize_paths();
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
        models::prediction::PredictionModel::load(&path)?;
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

    fn grid_changed(&mut self) {
        self.preset_name = grid_label(&self.scene.grid);
    }

    fn controls(&mut self, ui: &mut egui::Ui) {
        // Sliders share the panel with their value and label: narrow enough that the
        // label fits the panel's default width.
        ui.spacing_mut().slider_width = 150.0;
        egui::ScrollArea::vertical().auto_shrink([false, false]).show(ui, |ui| {
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
            ui.add(slider(&mut self.scene.grid.resolution, 32..=256).text("voxels per axis")).on_hover_text(
                "the grid the cloud is built on: more voxels keep finer detail and cost memory and build time \
                     (48 while a cloud slider is dragged)",
            );
            egui::CollapsingHeader::new("Modeler").default_open(true).show(ui, |ui| {
                if self.modeler.ui(ui, &mut self.scene.grid) {
                    self.grid_changed();
                }
            });

            ui.separator();
            ui.heading("Medium");
            let m = &mut self.scene.medium;
            ui.add(slider(&mut m.rho, 0.5..=400.0).logarithmic(true).text("density rho")).on_hover_text(
                "extinction at full density, per box width: light travels 1/rho of the cloud's box between \
                 collisions (rho 40: 1/40 of the box); higher is denser, brighter edges, darker core",
            );
            ui.add(slider(&mut m.albedo, 0.0..=1.0).text("albedo")).on_hover_text(
                "the fraction of light scattered at each collision, the rest absorbed: 1 for water clouds, lower \
                 for smoke",
            );
            egui::ComboBox::from_label("phase function").selected_text(&m.phase).show_ui(ui, |ui| {
                for (p, tip) in [
                    ("hg", "Henyey-Greenstein with asymmetry g (clouds: forward scattering, g about 0.85)"),
                    ("isotropic", "scatters equally in every direction"),
                    ("rayleigh", "molecules: a little more forward and backward than sideways"),
                    ("hazy", "Mie, hazy atmosphere (Nishita et al.)"),
                    ("murky", "Mie, murky atmosphere: strongly forward"),
                ] {
                    ui.selectable_value(&mut m.phase, p.to_string(), p).on_hover_text(tip);
                }
            });
            if m.phase == "hg" {
                ui.add(slider(&mut m.g, -0.95..=0.95).text("anisotropy g")).on_hover_text(
                    "mean cosine of the scattering angle: 0 scatters evenly, toward 1 keeps light going forward \
                     (silver lining when backlit), negative sends it back",
                );
            }

            ui.separator();
            ui.heading("Light");
            let mut sun_changed = ui
                .add(slider(&mut self.sun_elevation_deg, -89.0..=89.0).text("sun elevation").suffix("°"))
                .on_hover_text("degrees above the horizon; 90 is straight overhead")
                .changed();
            sun_changed |= ui
                .add(slider(&mut self.sun_azimuth_deg, 0.0..=360.0).text("sun azimuth").suffix("°"))
                .on_hover_text("degrees around the vertical, 0 toward +z, 90 toward +x")
                .changed();
            sun_changed |= self.sky_dome(ui);
            if sun_changed {
                self.apply_sun();
            }
            if let Some(r) = colour_row(
                ui,
                self.scene.sun.radiance,
                10.0,
                ("sun irradiance", "the sun's colour"),
                "irradiance on a surface facing the sun (linear, scene units); exposure scales the image instead",
            ) {
                self.scene.sun.radiance = r;
            }
            ui.add(slider(&mut self.scene.sun.angular_radius_deg, 0.0..=10.0).text("sun radius").suffix("°"))
                .on_hover_text(
                    "angular radius of the sun's disc: 0 is a point sun (hard shadows), the real sun is 0.27°",
                );
            let sky = &mut self.scene.sky;
            if let Some(r) = colour_row(
                ui,
                sky.radiance,
                2.0,
                ("sky radiance", "the sky's colour (at the zenith when the horizon differs)"),
                "radiance of the sky overhead, and all around unless the horizon is set (0: black, the sun alone)",
            ) {
                sky.radiance = r;
            }
            if let Some(r) = colour_row(
                ui,
                sky.horizon.unwrap_or(sky.radiance),
                2.0,
                ("horizon radiance", "the sky's colour at the horizon"),
                "the sky runs from this at the horizon to the sky radiance above at the zenith",
            ) {
                sky.horizon = Some(r);
            }
            let mut ground = sky.ground_albedo.is_some();
            ui.horizontal(|ui| {
                ui.checkbox(&mut ground, "ground").on_hover_text(
                    "a ground plane below the horizon, lit by the sun and the sky (not shadowed by the cloud); \
                     off: the horizon's colour continues below",
                );
                let mut a = sky.ground_albedo.unwrap_or(0.3);
                if ground {
                    ui.add(slider(&mut a, 0.0..=1.0).text("ground albedo"))
                        .on_hover_text("the fraction of light the ground reflects: grass 0.2, snow 0.8");
                }
                sky.ground_albedo = ground.then_some(a);
            });

            ui.separator();
            ui.heading("Camera");
            ui.horizontal_wrapped(|ui| {
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
            ui.add(slider(&mut self.orbit.distance, 1.0..=10.0).text("distance"))
                .on_hover_text("from the cloud's centre, in box widths");
            ui.add(slider(&mut self.scene.camera.fov_y_deg, 5.0..=90.0).text("field of view").suffix("°"))
                .on_hover_text("vertical angle the image covers");
            ui.label(
                "Drag the image to orbit, scroll to zoom; Shift-drag or right-drag puts the sun under the pointer.",
            );

            ui.separator();
            ui.heading("Render");
            ui.horizontal_wrapped(|ui| {
                ui.radio_value(&mut self.scene.render.mode, "reference".to_string(), "path tracing")
                    .on_hover_text("the reference: every bounce traced, unbiased, converges slowly");
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
                if self.scene.render.preview == "learned" {
                    self.predictor_controls(ui);
                }
            }
            ui.horizontal_wrapped(|ui| {
                ui.label("algorithm");
                ui.selectable_value(&mut self.scene.render.integrator, "path".to_string(), "unidirectional");
                ui.selectable_value(&mut self.scene.render.integrator, "bdpt".to_string(), "bidirectional")
                    .on_hover_text(
                        "volumetric BDPT: light subpaths from the sun joined to camera subpaths, with MIS; with \
                     prediction, the point-to-point model predicts the transport between k-segment subpaths",
                    );
            });
            let p2p = self.scene.render.mode == "predict" && self.scene.render.integrator == "bdpt";
            let k_tip = if p2p {
                "segments per subpath: the orders 2k+1 and up are predicted"
            } else {
                "the first scattering order counted as high (predicted in prediction mode)"
            };
            ui.add(slider(&mut self.scene.k, 1..=8).text("k")).on_hover_text(k_tip);
            if self.scene.render.mode == "predict" {
                ui.add(slider(&mut self.scene.render.p, 0.05..=1.0).text("prediction prob. p"))
                    .on_hover_text("the probability of predicting at vertex k instead of tracing on (thesis 5.4)");
                if p2p {
                    ui.add(slider(&mut self.scene.render.r, 0.0..=0.3).text("distance threshold r")).on_hover_text(
                        "end vertices closer than r (box widths) are joined by extending the subpaths, not \
                             predicted",
                    );
                    let max_m = engine::integrator::bdpt::Prediction::MAX_CANDIDATES;
                    ui.add(
                        slider(&mut self.scene.render.candidates, 1..=max_m).logarithmic(true).text("light candidates"),
                    )
                    .on_hover_text(
                        "light subpaths offered to each camera end vertex, one chosen by resampling; 1 is the \
                         thesis's pairing; the others are picked from a pool traced once per pass, so more \
                         lower the noise for little cost",
                    );
                    let max_n = engine::integrator::bdpt::Prediction::MAX_EXTENSION_SAMPLES;
                    ui.add(
                        slider(&mut self.scene.render.extension_samples, 1..=max_n)
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
                match (p2p, &self.scene.render.p2p_model) {
                    (true, Some(m)) => _ = ui.label(format!("model: {m}")),
                    (true, None) => _ = ui.label("model: shipped point-to-point model"),
                    (false, _) => self.predictor_controls(ui),
                }
            }
            self.target_controls(ui);

            ui.separator();
            ui.heading("Image");
            ui.horizontal_wrapped(|ui| {
                ui.label("show");
                for b in Buffer::ALL {
                    ui.selectable_value(&mut self.view_buffer, b, b.name());
                }
            });
            ui.add(slider(&mut self.exposure, -4.0..=6.0).text("exposure").suffix(" stops"))
                .on_hover_text("brightens (positive) or darkens the view and the PNG; the EXR keeps radiance");
            ui.horizontal(|ui| {
                ui.label("tone curve");
                ui.selectable_value(&mut self.tone, ToneMap::Filmic, "filmic");
                ui.selectable_value(&mut self.tone, ToneMap::Clamp, "clamp");
            });
            self.size_controls(ui);
        });
    }

    /// The model of prediction at bounce k and of the learned preview: the scene's
    /// model file if it names one, else the shipped one to choose, auto (the
    /// cloud-aware model under a sun alone, the global one under a sky or a soft sun)
    /// or either by name.
    fn predictor_controls(&mut self, ui: &mut egui::Ui) {
        if let Some(m) = &self.scene.render.model {
            ui.label(format!("model: {m}"));
            return;
        }
        let auto = match self.scene.predictor_kind() {
            models::prediction::PredictorKind::Global => "auto (global)",
            _ => "auto (cloud-aware)",
        };
        ui.horizontal_wrapped(|ui| {
            ui.label("model");
            let p = &mut self.scene.render.predictor;
            ui.selectable_value(p, "auto".to_string(), auto).on_hover_text(
                "the cloud-aware model under the sun alone; the thesis's global model under a sky or a soft \
                 sun, whose light the cloud-aware model (bound to one sun direction) does not answer",
            );
            ui.selectable_value(p, "cloud".to_string(), "cloud-aware")
                .on_hover_text("reads the cloud's density and the sun's transmittance around each point");
            ui.selectable_value(p, "global".to_string(), "global")
                .on_hover_text("the thesis's model: optical depths to the edge of a homogeneous convex medium");
        });
    }

    /// The render's target: until the next change, a number of samples per pixel or
    /// of seconds.
    fn target_controls(&mut self, ui: &mut egui::Ui) {
        ui.horizontal_wrapped(|ui| {
            ui.label("stop at").on_hover_text("the render stops there and says done; any change starts it again");
            let mut kind = match self.target {
                RenderTarget::Unlimited => 0,
                RenderTarget::Spp(_) => 1,
                RenderTarget::Seconds(_) => 2,
            };
            ui.selectable_value(&mut kind, 0, "never");
            ui.selectable_value(&mut kind, 1, "spp");
            ui.selectable_value(&mut kind, 2, "seconds");
            self.target = match (kind, self.target) {
                (1, RenderTarget::Spp(mut n)) => {
                    ui.add(egui::DragValue::new(&mut n).range(1..=1_000_000).suffix(" spp"));
                    RenderTarget::Spp(n)
                }
                (1, _) => RenderTarget::Spp(256),
                (2, RenderTarget::Seconds(mut t)) => {
                    ui.add(egui::DragValue::new(&mut t).range(0.5..=86_400.0).suffix(" s"));
                    RenderTarget::Seconds(t)
                }
                (2, _) => RenderTarget::Seconds(30.0),
                _ => RenderTarget::Unlimited,
            };
        });
    }

    /// The rendered size: the viewport's (scaled), or the scene's output size with
    /// presets and an aspect lock.
    fn size_controls(&mut self, ui: &mut egui::Ui) {
        let mut fit = self.viewport_scale.is_some();
        ui.checkbox(&mut fit, "render at the viewport's size").on_hover_text(
            "on: the image fills the viewport at the scale below; off: it is rendered at the output size and fitted \
             in; exports write the image as rendered",
        );
        if fit {
            let mut scale = self.viewport_scale.unwrap_or(0.5) * 100.0;
            ui.add(slider(&mut scale, 10.0..=100.0).text("resolution scale").suffix(" %"))
                .on_hover_text("of the viewport's pixels: lower renders faster");
            self.viewport_scale = Some(scale / 100.0);
            let (w, h) = self.render_size();
            ui.weak(format!("rendering {w} x {h}"));
        } else {
            self.viewport_scale = None;
        }
        ui.label("output size (scene file; rendered when the box above is off)");
        let cam = &mut self.scene.camera;
        let current = OUTPUT_SIZES
            .iter()
            .find(|(_, w, h)| (*w, *h) == (cam.width, cam.height))
            .map(|(n, _, _)| n.to_string())
            .unwrap_or_else(|| "custom".into());
        egui::ComboBox::from_label("presets").selected_text(current).show_ui(ui, |ui| {
            for (name, w, h) in OUTPUT_SIZES {
                if ui.selectable_label((cam.width, cam.height) == (w, h), name).clicked() {
                    (cam.width, cam.height) = (w, h);
                }
            }
        });
        ui.horizontal(|ui| {
            let (w0, h0) = (cam.width, cam.height);
            let (mut w, mut h) = (w0, h0);
            ui.label("width");
            let dw = ui
                .add(egui::DragValue::new(&mut w).range(16..=4096).clamp_existing_to_range(false).suffix(" px"))
                .changed();
            ui.label("height");
            let dh = ui
                .add(egui::DragValue::new(&mut h).range(16..=4096).clamp_existing_to_range(false).suffix(" px"))
                .changed();
            ui.checkbox(&mut self.aspect_lock, "lock aspect");
            if self.aspect_lock && dw && w0 > 0 {
                h = ((w as f64 * h0 as f64 / w0 as f64).round() as u32).clamp(16, 4096);
            } else if self.aspect_lock && dh && h0 > 0 {
                w = ((h as f64 * w0 as f64 / h0 as f64).round() as u32).clamp(16, 4096);
            }
            (cam.width, cam.height) = (w, h);
        });
    }

    /// A small sky dome seen from above: the centre is the zenith, the rim the
    /// horizon; the sun's disc and the camera's direction are marked. Clicking or
    /// dragging puts the sun there. Returns true when the sun moved.
    fn sky_dome(&mut self, ui: &mut egui::Ui) -> bool {
        let size = 110.0;
        let (rect, response) = ui.allocate_exact_size(egui::vec2(size, size), egui::Sense::click_and_drag());
        let response =
            response.on_hover_text("the sky from above: the rim is the horizon; click or drag to place the sun");
        let (c, radius) = (rect.center(), size / 2.0 - 4.0);
        let painter = ui.painter_at(rect);
        painter.circle_filled(c, radius, egui::Color32::from_rgb(36, 52, 78));
        painter.circle_stroke(c, radius, egui::Stroke::new(1.0, egui::Color32::from_gray(150)));
        painter.circle_stroke(c, radius / 2.0, egui::Stroke::new(0.5, egui::Color32::from_gray(90)));
        // Screen x is +x, screen up is -z (north up), so azimuth 0 (+z) points down.
        let at = |el: f32, az: f32| {
            let r = radius * (1.0 - el.max(0.0) / 90.0);
            let az = az.to_radians();
            c + egui::vec2(r * az.sin(), r * az.cos())
        };
        let (forward, _, _, _) = self.camera_basis();
        let (cam_el, cam_az) = sun_angles_of(-forward);
        painter.circle_stroke(at(cam_el, cam_az), 4.0, egui::Stroke::new(1.5, egui::Color32::from_gray(220)));
        painter.text(
            at(cam_el, cam_az) + egui::vec2(6.0, 0.0),
            egui::Align2::LEFT_CENTER,
            "camera",
            egui::FontId::proportional(10.0),
            egui::Color32::from_gray(200),
        );
        let sun = at(self.sun_elevation_deg, self.sun_azimuth_deg);
        let below = self.sun_elevation_deg < 0.0;
        let colour = if below { egui::Color32::from_rgb(140, 110, 50) } else { egui::Color32::from_rgb(255, 214, 90) };
        painter.circle_filled(sun, 5.0, colour);
        if let Some(p) = response.interact_pointer_pos().filter(|_| response.clicked() || response.dragged()) {
            let d = p - c;
            let r = (d.length() / radius).min(1.0);
            self.sun_elevation_deg = (90.0 * (1.0 - r)).clamp(0.0, 89.0);
            self.sun_azimuth_deg = d.x.atan2(d.y).to_degrees().rem_euclid(360.0);
            return true;
        }
        false
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
        self.pixels_per_point = ui.ctx().pixels_per_point();
        ui.painter().rect_filled(rect, 0.0, egui::Color32::from_gray(12));
        let side_by_side = self.compare && published.as_ref().is_some_and(|p| p.reference.is_some());
        let k = self.scene.k;
        // Where the wipe divider is on screen, when the wipe view is up.
        let mut divider: Option<(egui::Rect, f32)> = None;
        let mut shown_at: Option<egui::Rect> = None;
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
                        shown_at = Some(fitted(t, right));
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
        // Where the scene's own image is (the right half side by side): the sun's
        // marker and the sun drag map through it.
        self.image_rect = shown_at.or_else(|| self.texture.as_ref().map(|t| fitted(t, rect)));
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
                    if let Some(p) = response.interact_pointer_pos() {
                        self.point_sun_at(p);
                    }
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
        let shown = self.image_rect.unwrap_or_else(|| fitted(texture, rect));
        let (_, right, up, _) = self.camera_basis();
        let to_sun = -Vec3::from_array(self.scene.sun.direction).normalize_or(Vec3::NEG_Y);
        let colour = egui::Color32::from_rgb(255, 214, 90);
        if let Some(p) = self.sun_marker() {
            ui.painter().circle_stroke(p, 9.0, egui::Stroke::new(2.0, colour));
            ui.painter().circle_filled(p, 4.0, colour);
            return;
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
                let label = ui.label(status_text(p));
                if p.standing_in.is_some() {
                    label.on_hover_text(
                        "ray marched single scattering from the sun's transmittance field, higher orders from the \
                         learned model or the octave approximation; the scene's own render replaces it once it is \
                         clean",
                    );
                } else {
                    label.on_hover_text("noise: relative standard error over the cloud's pixels (the sky left out)");
                }
                if let Some(f) = p.progress {
                    let text = if p.done { "done".to_string() } else { format!("{:.0} %", 100.0 * f) };
                    ui.add(egui::ProgressBar::new(f as f32).desired_width(120.0).text(text));
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
        // One line each, cut with an ellipsis (the whole text on hover).
        let line = |ui: &mut egui::Ui, colour: egui::Color32, text: &str| {
            ui.add(egui::Label::new(egui::RichText::new(text).color(colour)).truncate()).on_hover_text(text);
        };
        if let Some((_, e)) = &mb.error {
            line(ui, egui::Color32::from_rgb(255, 110, 90), e);
        }
        if let Some((text, is_error)) = &self.message {
            let colour =
                if *is_error { egui::Color32::from_rgb(255, 110, 90) } else { egui::Color32::from_rgb(140, 200, 140) };
            line(ui, colour, text);
        }
    }

    /// The status bar's text for the latest image (what the window shows).
    pub fn status_line(&self) -> Option<String> {
        self.worker.mailbox.lock().unwrap().latest.as_ref().map(status_text)
    }

    /// Sends the scene to the worker when it changed (coarse while the pointer is down).
    fn sync(&mut self, ctx: &egui::Context) {
        self.apply_camera();
        let dragging = ctx.input(|i| i.pointer.any_down());
        // What the worker renders: the scene at the viewport's size (or its own).
        let mut render = self.scene.clone();
        (render.camera.width, render.camera.height) = self.render_size();
        let changed = self.sent.as_ref().is_none_or(|(s, _, cmp, was_dragging)| {
            *s != render || (*was_dragging && !dragging) || *cmp != self.compare
        });
        // A new target alone goes to the render under way: its samples are kept.
        if !changed && self.target != self.sent_target {
            self.worker.set_target(self.target);
        }
        self.sent_target = self.target;
        if !dragging {
            self.history.record(&self.scene);
        }
        if changed {
            if let Err(e) = self.scene.validate() {
                self.worker.mailbox.lock().unwrap().error = Some((0, e.to_string()));
                return;
            }
            // The cloud is built coarse while a cloud slider moves (and stays so until
            // the pointer is released); a sun or camera drag keeps the full cloud.
            let grid_changed = self.sent.as_ref().is_none_or(|(s, ..)| s.grid != self.scene.grid);
            let coarse = dragging && (grid_changed || self.sent.as_ref().is_some_and(|(_, c, ..)| *c));
            self.worker.render_with(&render, coarse, dragging, self.compare, self.target);
            self.sent = Some((render, coarse, self.compare, dragging));
        }
    }
}

impl eframe::App for NimbusApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let started = std::time::Instant::now();
        egui::Panel::top("menu").show(ui, |ui| self.menu(ui));
        egui::Panel::right("controls").resizable(true).default_size(350.0).show(ui, |ui| self.controls(ui));
        // A fixed height: rows that come and go (a message, an error) must not resize
        // the viewport, whose size the render follows.
        egui::Panel::bottom("status").exact_size(STATUS_HEIGHT).show(ui, |ui| self.status(ui));
        if self.compare && self.scene.render.mode == "predict" {
            egui::Panel::left("buffers").resizable(true).default_size(200.0).show(ui, |ui| self.compare_view.panel(ui));
        }
        egui::CentralPanel::default().show(ui, |ui| self.viewport(ui));
        let ctx = ui.ctx().clone();
        if self.modeler.browser(&ctx, &mut self.scene.grid) {
            self.grid_changed();
        }
        self.dialogs(&ctx);
        if self.dialog.is_none() {
            self.shortcuts(&ctx);
        }
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
