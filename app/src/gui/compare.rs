//! Reference vs prediction: the textures of the side-by-side and wipe views and the
//! buffer panel (low orders, predicted high orders, reference high orders, their
//! error in false colour with its scale, and the relative bias of docs/conventions.md as
//! a number).
//!
//! Preparing these images (five tone-mapped buffers and the bias with its variance)
//! costs several milliseconds at 512^2, so it runs on a helper thread: the UI hands
//! it the published films (shared, not copied) and only uploads the finished images.

use super::worker::Published;
use crate::metrics::{Image, bias, error_colours, false_colour, lit_mean};
use crate::output::ToneMap;
use eframe::egui;
use engine::{Buffer, Film};
use std::sync::Arc;
use std::sync::mpsc::{Receiver, TryRecvError};

/// What the comparison's relative bias means against its noise floor (what noise
/// alone would show): within noise below 1.5 times the floor, else significant, with
/// the part noise does not explain, sqrt(bias^2 - floor^2).
pub fn bias_verdict(rel: f64, floor: f64) -> String {
    if !(rel.is_finite() && floor.is_finite()) {
        return "relative bias: not known yet".into();
    }
    if rel <= 1.5 * floor {
        format!("relative bias {:.1} %: within noise (noise alone shows {:.1} %)", 100.0 * rel, 100.0 * floor)
    } else {
        let excess = (rel * rel - floor * floor).max(0.0).sqrt();
        format!(
            "relative bias significant: about {:.1} % (measured {:.1} %, noise {:.1} %)",
            100.0 * excess,
            100.0 * rel,
            100.0 * floor
        )
    }
}

/// The panels, in order.
pub const PANELS: [&str; 4] =
    ["low orders 1 .. k-1", "predicted high orders", "reference high orders", "error |predicted - reference| (high)"];

/// How reference and prediction share the viewport.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    SideBySide,
    /// Both images over the whole viewport, the reference left of a draggable divider.
    Wipe,
}

/// What the textures show: (generation, prediction spp, reference spp, exposure bits,
/// buffer, tone map).
type Key = (u64, u32, u32, u32, Buffer, ToneMap);

/// Images prepared off the UI thread.
struct Prepared {
    key: Key,
    size: [usize; 2],
    reference: Vec<u8>,
    panels: [Vec<u8>; 4],
    error_scale: f32,
    bias: Option<(f64, f64)>,
}

pub struct CompareView {
    /// What the textures show now.
    key: Option<Key>,
    /// A preparation under way and what it is for.
    pending: Option<(Key, Receiver<Prepared>)>,
    /// The reference image in the main view's buffer.
    pub reference: Option<egui::TextureHandle>,
    panels: [Option<egui::TextureHandle>; 4],
    /// The error colour scale: yellow at this radiance.
    error_scale: f32,
    /// Relative bias of the prediction's full image against the reference's, and the
    /// noise floor of that number (docs/conventions.md; 16x box downscale).
    pub bias: Option<(f64, f64)>,
    enlarged: Option<usize>,
    pub layout: Layout,
    /// Divider of the wipe view, as a fraction of the image width from the left.
    pub wipe: f32,
}

impl Default for CompareView {
    fn default() -> Self {
        CompareView {
            key: None,
            pending: None,
            reference: None,
            panels: Default::default(),
            error_scale: 1.0,
            bias: None,
            enlarged: None,
            layout: Layout::SideBySide,
            wipe: 0.5,
        }
    }
}

fn texture(ctx: &egui::Context, slot: &mut Option<egui::TextureHandle>, name: &str, size: [usize; 2], rgba: &[u8]) {
    let image = egui::ColorImage::from_rgba_unmultiplied(size, rgba);
    match slot {
        Some(t) => t.set(image, egui::TextureOptions::LINEAR),
        None => *slot = Some(ctx.load_texture(name, image, egui::TextureOptions::LINEAR)),
    }
}

fn prepare(key: Key, film: &Film, reference: &Film, tone: ToneMap, exposure: f32, buffer: Buffer) -> Prepared {
    let (w, h) = (film.width(), film.height());
    let (pred_high, ref_high) = (film.mean(Buffer::High), reference.mean(Buffer::High));
    let error_scale = lit_mean(&ref_high).max(1e-6);
    let error: Vec<u8> =
        error_colours(&pred_high, &ref_high, error_scale).into_iter().flat_map(|[r, g, b]| [r, g, b, 255]).collect();
    let panels = [
        tone.to_rgba8(&film.mean(Buffer::Low), exposure),
        tone.to_rgba8(&pred_high, exposure),
        tone.to_rgba8(&ref_high, exposure),
        error,
    ];
    let bias = (reference.spp() > 0 && film.spp() > 0).then(|| {
        let img = |f: &Film| Image { w, h, mean: f.mean(Buffer::Full), var: f.variance_of_mean(Buffer::Full) };
        let (_, rel, floor) = bias(&img(reference), &img(film));
        (rel, floor)
    });
    Prepared {
        key,
        size: [w as usize, h as usize],
        reference: tone.to_rgba8(&reference.mean(buffer), exposure),
        panels,
        error_scale: error_scale as f32,
        bias,
    }
}

impl CompareView {
    /// Starts preparing the images of a newly published pass (unless one is under
    /// way) and uploads finished ones. Never blocks on the preparation.
    pub fn update(&mut self, ctx: &egui::Context, p: &Published, tone: ToneMap, exposure: f32, buffer: Buffer) {
        if let Some((_, rx)) = &self.pending {
            match rx.try_recv() {
                Ok(done) => {
                    self.pending = None;
                    self.upload(ctx, done);
                }
                Err(TryRecvError::Empty) => return,
                Err(TryRecvError::Disconnected) => self.pending = None,
            }
        }
        let Some(reference) = &p.reference else { return };
        let key = (p.generation, p.film.spp(), reference.spp(), exposure.to_bits(), buffer, tone);
        if self.key == Some(key) {
            return;
        }
        let (film, reference) = (Arc::clone(&p.film), Arc::clone(reference));
        let (tx, rx) = std::sync::mpsc::channel();
        let wake = ctx.clone();
        let spawned = std::thread::Builder::new().name("nimbus-compare".into()).spawn(move || {
            let _ = tx.send(prepare(key, &film, &reference, tone, exposure, buffer));
            wake.request_repaint();
        });
        match spawned {
            Ok(_) => self.pending = Some((key, rx)),
            // No thread to be had: prepare here rather than show nothing.
            Err(_) => {
                let done = prepare(key, &p.film, p.reference.as_ref().unwrap(), tone, exposure, buffer);
                self.upload(ctx, done);
            }
        }
    }

    fn upload(&mut self, ctx: &egui::Context, done: Prepared) {
        self.key = Some(done.key);
        texture(ctx, &mut self.reference, "nimbus-reference", done.size, &done.reference);
        for (i, rgba) in done.panels.iter().enumerate() {
            texture(ctx, &mut self.panels[i], PANELS[i], done.size, rgba);
        }
        self.error_scale = done.error_scale;
        self.bias = done.bias;
    }

    /// The side panel: thumbnails (click to enlarge), the error scale, the bias.
    pub fn panel(&mut self, ui: &mut egui::Ui) {
        ui.heading("Compare");
        match self.bias {
            Some((rel, floor)) => {
                ui.label(bias_verdict(rel, floor)).on_hover_text(
                    "mean |prediction - reference| over 16 x 16 pixel blocks, divided by the reference's mean \
                     (docs/conventions.md); noise in either image alone shows a few percent, so the number is \
                     significant only well above that floor, which falls as both renders accumulate",
                );
            }
            None => {
                ui.label("relative bias: waiting for samples");
            }
        }
        egui::ScrollArea::vertical().show(ui, |ui| {
            let width = ui.available_width().min(240.0);
            for (i, name) in PANELS.iter().enumerate() {
                ui.label(*name);
                if let Some(t) = &self.panels[i] {
                    let size = t.size_vec2() * (width / t.size_vec2().x);
                    let r = ui.add(egui::Image::new((t.id(), size)).sense(egui::Sense::click()));
                    if r.on_hover_text("click to enlarge").clicked() {
                        self.enlarged = Some(i);
                    }
                }
                if i == 3 {
                    ui.horizontal(|ui| {
                        let (rect, _) = ui.allocate_exact_size(egui::vec2(width * 0.6, 10.0), egui::Sense::hover());
                        for s in 0..32 {
                            let x0 = rect.min.x + rect.width() * s as f32 / 32.0;
                            let c = false_colour((s as f32 + 0.5) / 32.0);
                            ui.painter().rect_filled(
                                egui::Rect::from_min_max(
                                    egui::pos2(x0, rect.min.y),
                                    egui::pos2(x0 + rect.width() / 32.0 + 0.5, rect.max.y),
                                ),
                                0.0,
                                egui::Color32::from_rgb(c[0], c[1], c[2]),
                            );
                        }
                        ui.label(format!("0 .. {:.3}", self.error_scale));
                    });
                }
                ui.add_space(6.0);
            }
        });
        if let Some(i) = self.enlarged {
            let mut open = true;
            egui::Window::new(PANELS[i]).open(&mut open).default_size([520.0, 540.0]).show(ui.ctx(), |ui| {
                if let Some(t) = &self.panels[i] {
                    let w = ui.available_width();
                    ui.add(egui::Image::new((t.id(), t.size_vec2() * (w / t.size_vec2().x))));
                }
            });
            if !open {
                self.enlarged = None;
            }
        }
    }
}
