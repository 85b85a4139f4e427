//! The Modeler panel: every `modeler::CloudParams` parameter as a slider, grouped as
//! the modeler documents them, with its range, unit and description; the seed with
//! "new variation"; a preset browser whose thumbnails are rendered once per session on
//! a helper thread; and "save as preset" into the user's preset folder.
//!
//! The panel edits the scene's grid description only; the window's usual path does
//! the rest (a coarse rebuild and the instant preview while a slider moves, the full
//! cloud on release, undo through the history).

use super::widgets::slider;
use crate::scene::{GridDesc, SceneFile};
use eframe::egui;
use modeler::{CloudParams, Group, PARAMS};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, TryRecvError};

/// Thumbnail size in pixels.
pub const THUMB: u32 = 72;

/// Thumbnails per row of the preset browser.
const BROWSER_COLUMNS: usize = 5;

/// An entry of the preset browser: the modeler's presets and the user's own.
#[derive(Clone, Debug, PartialEq)]
pub struct Preset {
    pub name: String,
    /// Built into the modeler (else a file in the user's preset folder).
    pub builtin: bool,
    pub params: CloudParams,
}

/// A rendered thumbnail: (preset name, RGBA pixels).
type Thumb = (String, Vec<u8>);

pub struct ModelerPanel {
    /// The user's presets live here (`NAME.toml`, the parameters as TOML); None: no
    /// folder (saving is off).
    user_dir: Option<PathBuf>,
    presets: Vec<Preset>,
    /// Why a user preset could not be read.
    problems: Vec<String>,
    thumbs: HashMap<String, egui::TextureHandle>,
    /// Thumbnails on their way from the helper thread.
    rendering: Option<Receiver<Thumb>>,
    /// Names queued for the next helper thread.
    queued: Vec<Preset>,
    pub browser_open: bool,
    save_name: String,
}

/// Modeler presets by name (`modeler::PRESET_NAMES`).
fn builtin_presets() -> Vec<Preset> {
    modeler::PRESET_NAMES
        .iter()
        .map(|n| Preset { name: n.to_string(), builtin: true, params: modeler::preset(n).expect("listed preset") })
        .collect()
}

/// A name a preset file can have: letters, digits, space, '-' and '_', 1 to 64 of them.
pub fn valid_preset_name(name: &str) -> bool {
    let n = name.trim();
    !n.is_empty() && n.len() <= 64 && n.chars().all(|c| c.is_alphanumeric() || matches!(c, ' ' | '-' | '_'))
}

impl ModelerPanel {
    pub fn new(user_dir: Option<PathBuf>) -> Self {
        let mut panel = ModelerPanel {
            user_dir: None,
            presets: Vec::new(),
            problems: Vec::new(),
            thumbs: HashMap::new(),
            rendering: None,
            queued: Vec::new(),
            browser_open: false,
            save_name: String::new(),
        };
        panel.set_user_dir(user_dir);
        panel
    }

    /// Points the user's presets at `dir` and lists them.
    pub fn set_user_dir(&mut self, dir: Option<PathBuf>) {
        self.user_dir = dir;
        self.reload();
    }

    pub fn presets(&self) -> &[Preset] {
        &self.presets
    }

    /// Problems met reading the user's presets (a file that does not parse, say).
    pub fn problems(&self) -> &[String] {
        &self.problems
    }

    /// Thumbnails rendered so far.
    pub fn thumbnails(&self) -> usize {
        self.thumbs.len()
    }

    fn reload(&mut self) {
        self.presets = builtin_presets();
        self.problems.clear();
        let Some(dir) = &self.user_dir else { return };
        let Ok(rd) = std::fs::read_dir(dir) else { return };
        let mut files: Vec<PathBuf> =
            rd.flatten().map(|e| e.path()).filter(|p| p.extension().is_some_and(|e| e == "toml")).collect();
        files.sort();
        for path in files {
            let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            let parsed = std::fs::read_to_string(&path)
                .map_err(|e| e.to_string())
                .and_then(|t| toml::from_str::<CloudParams>(&t).map_err(|e| e.message().to_string()))
                .and_then(|p| p.validate().map(|_| p).map_err(|e| e.to_string()));
            match parsed {
                Ok(params) => self.presets.push(Preset { name, builtin: false, params }),
                Err(e) => self.problems.push(format!("preset {}: {e}", path.display())),
            }
        }
    }

    /// Writes `params` as the user preset `name` (atomically) and lists it.
    pub fn save_preset(&mut self, name: &str, params: &CloudParams) -> anyhow::Result<PathBuf> {
        let name = name.trim();
        anyhow::ensure!(
            valid_preset_name(name),
            "a preset name is 1 to 64 letters, digits, spaces, '-' or '_' (not {name:?})"
        );
        anyhow::ensure!(!modeler::PRESET_NAMES.contains(&name), "{name} is a built-in preset's name");
        let dir = self.user_dir.clone().ok_or_else(|| anyhow::anyhow!("no folder for presets"))?;
        std::fs::create_dir_all(&dir).map_err(|e| anyhow::anyhow!("cannot create {}: {e}", dir.display()))?;
        let path = preset_path(&dir, name);
        let text = toml::to_string_pretty(params).expect("parameters serialize");
        crate::output::write_bytes_atomically(&path, text.as_bytes())?;
        self.thumbs.remove(name);
        self.reload();
        Ok(path)
    }

    /// Renders the thumbnails not rendered yet, one helper thread at a time.
    fn pump(&mut self, ctx: &egui::Context) {
        if let Some(rx) = &self.rendering {
            loop {
                match rx.try_recv() {
                    Ok((name, rgba)) => {
                        let image = egui::ColorImage::from_rgba_unmultiplied([THUMB as usize; 2], &rgba);
                        let t = ctx.load_texture(format!("nimbus-preset-{name}"), image, egui::TextureOptions::LINEAR);
                        self.thumbs.insert(name, t);
                    }
                    Err(TryRecvError::Empty) => return,
                    Err(TryRecvError::Disconnected) => {
                        self.rendering = None;
                        break;
                    }
                }
            }
        }
        let missing: Vec<Preset> =
            self.presets.iter().filter(|p| !self.thumbs.contains_key(&p.name)).cloned().collect();
        if missing.is_empty() || missing == self.queued {
            return;
        }
        self.queued = missing.clone();
        let (tx, rx) = std::sync::mpsc::channel();
        let wake = ctx.clone();
        let spawned = std::thread::Builder::new().name("nimbus-thumbnails".into()).spawn(move || {
            for p in missing {
                if let Some(rgba) = thumbnail(&p.params) {
                    if tx.send((p.name, rgba)).is_err() {
                        return;
                    }
                    wake.request_repaint();
                }
            }
        });
        if spawned.is_ok() {
            self.rendering = Some(rx);
        }
    }

    /// The panel's controls for `grid`; returns true when the grid changed.
    pub fn ui(&mut self, ui: &mut egui::Ui, grid: &mut GridDesc) -> bool {
        let mut changed = false;
        ui.horizontal(|ui| {
            if ui.button("presets…").on_hover_text("the modeler's presets and your own, with thumbnails").clicked() {
                self.browser_open = !self.browser_open;
            }
            if ui.button("new cloud").on_hover_text("the modeler's default parameters").clicked() {
                set_params(grid, CloudParams::default());
                changed = true;
            }
        });
        let current = grid.params.clone().or_else(|| grid.preset.as_deref().and_then(modeler::preset));
        let Some(mut p) = current else {
            ui.label(if grid.file.is_some() {
                "A cloud read from a file: its shape has no modeler parameters. Start from a preset or a new cloud."
            } else {
                "The built-in clouds are analytic: they have no modeler parameters. Start from a preset or a new cloud."
            });
            return changed;
        };
        let before = p.clone();
        ui.horizontal(|ui| {
            ui.label("seed").on_hover_text("the seed of the hierarchy and of every noise");
            ui.add(egui::DragValue::new(&mut p.seed));
            if ui.button("new variation").on_hover_text("the same parameters with another seed").clicked() {
                p.seed = next_seed(p.seed);
            }
        });
        for group in Group::ALL {
            egui::CollapsingHeader::new(group.name()).default_open(group == Group::Hierarchy).show(ui, |ui| {
                for spec in PARAMS.iter().filter(|s| s.group == group) {
                    let mut v = p.get(spec.name).expect("a listed parameter");
                    let label = spec.name.replace('_', " ");
                    let tip = if spec.unit.is_empty() {
                        format!("{} ({})", spec.doc, spec.range)
                    } else {
                        format!("{} ({}, in {})", spec.doc, spec.range, spec.unit)
                    };
                    let r = if spec.integer {
                        let mut n = v as u32;
                        let r = ui.add(slider(&mut n, spec.lo as u32..=spec.hi as u32).text(label));
                        v = n as f32;
                        r
                    } else {
                        ui.add(slider(&mut v, spec.lo..=spec.hi).logarithmic(spec.log).text(label))
                    };
                    if r.on_hover_text(tip).changed() {
                        p.set(spec.name, v);
                    }
                }
            });
        }
        ui.horizontal(|ui| {
            if ui.button("reset to defaults").clicked() {
                p = CloudParams { seed: p.seed, ..CloudParams::default() };
            }
        });
        if p != before {
            set_params(grid, p.clone());
            changed = true;
        }
        ui.horizontal(|ui| {
            let label = ui.label("save as preset");
            ui.add(egui::TextEdit::singleline(&mut self.save_name).desired_width(110.0).hint_text("name"))
                .labelled_by(label.id);
            let enabled = self.user_dir.is_some() && valid_preset_name(&self.save_name);
            if ui.add_enabled(enabled, egui::Button::new("save")).clicked() {
                let name = self.save_name.trim().to_string();
                match self.save_preset(&name, &p) {
                    Ok(_) => self.problems.retain(|m| !m.starts_with("saving")),
                    Err(e) => self.problems.push(format!("saving {name}: {e:#}")),
                }
            }
        });
        changed
    }

    /// The preset browser window (when open): a grid of thumbnails; a click loads
    /// the preset. Returns true when the grid changed.
    pub fn browser(&mut self, ctx: &egui::Context, grid: &mut GridDesc) -> bool {
        if !self.browser_open {
            return false;
        }
        self.pump(ctx);
        let mut open = true;
        let mut changed = false;
        egui::Window::new("Presets").open(&mut open).default_pos([160.0, 80.0]).default_height(460.0).show(ctx, |ui| {
            for m in &self.problems {
                ui.colored_label(egui::Color32::from_rgb(255, 110, 90), m);
            }
            egui::ScrollArea::vertical().show(ui, |ui| {
                egui::Grid::new("nimbus-presets").spacing([6.0, 6.0]).show(ui, |ui| {
                    for (i, preset) in self.presets.iter().enumerate() {
                        ui.vertical(|ui| {
                            ui.set_width(THUMB as f32 + 8.0);
                            let size = egui::vec2(THUMB as f32, THUMB as f32);
                            let r = match self.thumbs.get(&preset.name) {
                                Some(t) => ui.add(egui::Image::new((t.id(), size)).sense(egui::Sense::click())),
                                None => {
                                    let (rect, r) = ui.allocate_exact_size(size, egui::Sense::click());
                                    ui.painter().rect_filled(rect, 2.0, egui::Color32::from_gray(30));
                                    ui.put(rect, egui::Spinner::new());
                                    r
                                }
                            };
                            let kind = if preset.builtin { "modeler preset" } else { "your preset" };
                            let clicked = r.on_hover_text(format!("{} ({kind}): click to load", preset.name)).clicked();
                            if ui.small_button(&preset.name).clicked() || clicked {
                                if preset.builtin {
                                    (grid.builtin, grid.preset, grid.params, grid.file, grid.grid_name) =
                                        (None, Some(preset.name.clone()), None, None, None);
                                } else {
                                    set_params(grid, preset.params.clone());
                                }
                                changed = true;
                            }
                        });
                        if i % BROWSER_COLUMNS == BROWSER_COLUMNS - 1 {
                            ui.end_row();
                        }
                    }
                });
            });
        });
        if !open {
            self.browser_open = false;
        }
        changed
    }
}

/// Makes `grid` the modeler cloud of `params`.
fn set_params(grid: &mut GridDesc, params: CloudParams) {
    (grid.builtin, grid.preset, grid.params, grid.file, grid.grid_name) = (None, None, Some(params), None, None);
}

/// Another seed, spread over 32 bits so it reads well (SplitMix64's finalizer).
pub fn next_seed(seed: u64) -> u64 {
    let mut z = seed.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    (z ^ (z >> 31)) & 0xffff_ffff
}

/// A preset's thumbnail: the cloud at 40^3, a three-quarter sun, rho 40, the learned
/// preview (a coarse 16^3 lattice: the default octaves are several times too dark)
/// at [`THUMB`]^2 over four passes, tone-mapped as the window's default view. None if
/// it cannot be built.
pub fn thumbnail(params: &CloudParams) -> Option<Vec<u8>> {
    let mut s = SceneFile::from_toml_str(
        "[grid]\nresolution = 40\n[camera]\npreset = \"toplit\"\n[render]\nmode = \"preview\"\npreview_nodes = 16\n",
        "thumbnail",
    )
    .ok()?;
    s.grid.params = Some(params.clone());
    s.sun.direction = (-crate::scene::sun_vector(35.0, 50.0)).to_array();
    s.camera.preset = None;
    s.camera.position = Some([0.0, 0.45, 2.6]);
    (s.camera.width, s.camera.height) = (THUMB, THUMB);
    let scene = std::sync::Arc::new(s.build_scene(None).ok()?);
    let setup = s.integrator(&scene, 24).ok()?;
    let mut r = engine::Renderer::new(scene, setup.integrator).ok()?;
    let control = engine::RenderControl::new();
    for _ in 0..4 {
        r.render_pass(&control, 0);
    }
    let film = r.snapshot();
    Some(crate::output::ToneMap::Filmic.to_rgba8(&film.mean(engine::Buffer::Full), 1.0))
}

/// The default folder of the user's presets: beside the window's saved state.
pub fn default_user_dir() -> Option<PathBuf> {
    eframe::storage_dir("Nimbus").map(|d| d.join("presets"))
}

/// Where a preset file of `name` lives in `dir`.
pub fn preset_path(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{}.toml", name.trim()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn user_presets_save_list_and_refuse_bad_names_and_files() {
        let tmp = tempfile::tempdir().unwrap();
        let mut panel = ModelerPanel::new(Some(tmp.path().join("presets")));
        assert_eq!(panel.presets().len(), modeler::PRESET_NAMES.len());
        let p = CloudParams { roots: 3, seed: 77, ..CloudParams::default() };
        let path = panel.save_preset("tall one", &p).unwrap();
        assert_eq!(path, preset_path(&tmp.path().join("presets"), "tall one"));
        let mine = panel.presets().iter().find(|q| q.name == "tall one").expect("listed");
        assert!(!mine.builtin && mine.params == p);
        for bad in ["", "a/b", "../x", "scene-a"] {
            assert!(panel.save_preset(bad, &p).is_err(), "{bad:?} was accepted");
        }
        std::fs::write(tmp.path().join("presets/broken.toml"), "roots = 99\n").unwrap();
        panel.set_user_dir(Some(tmp.path().join("presets")));
        assert!(
            panel.problems().iter().any(|m| m.contains("broken.toml") && m.contains("roots")),
            "{:?}",
            panel.problems()
        );
        assert!(panel.presets().iter().any(|q| q.name == "tall one"));
        let mut none = ModelerPanel::new(None);
        assert!(none.save_preset("x", &p).unwrap_err().to_string().contains("no folder"));
    }

    #[test]
    fn thumbnails_show_a_cloud() {
        let rgba = thumbnail(&modeler::preset("scene-a").unwrap()).expect("a thumbnail");
        assert_eq!(rgba.len(), (THUMB * THUMB * 4) as usize);
        // The cloud covers a good part of the frame and is lit.
        let lit = rgba.chunks(4).filter(|p| p[0] > 60).count();
        assert!(lit > (THUMB * THUMB / 10) as usize, "{lit} lit pixels");
        assert_ne!(next_seed(1), 1);
        assert!(next_seed(5) <= u32::MAX as u64);
    }
}
