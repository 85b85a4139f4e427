//! Small widgets the window's panels share.

use eframe::egui;

/// A slider that keeps a value from a file outside its range as it is (egui's
/// default clamps it, which would rewrite the scene the moment the panel is drawn);
/// only edits made with it stay in the range.
pub fn slider<'a, N: egui::emath::Numeric>(value: &'a mut N, range: std::ops::RangeInclusive<N>) -> egui::Slider<'a> {
    egui::Slider::new(value, range).clamping(egui::SliderClamping::Edits)
}
