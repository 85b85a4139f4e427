//! The training curve as a PNG (like the thesis's figure 5.6): train and test mean
//! squared error per epoch on a log scale, drawn directly into pixels with a tiny
//! built-in font, so no font files or plotting stack are needed.

use crate::train::EpochRecord;

const W: u32 = 640;
const H: u32 = 400;
const LEFT: i32 = 70;
const RIGHT: i32 = 20;
const TOP: i32 = 30;
const BOTTOM: i32 = 50;
pub const TRAIN_COLOUR: [u8; 3] = [31, 119, 180];
pub const TEST_COLOUR: [u8; 3] = [214, 39, 40];

/// 3x5 glyphs, rows top to bottom, 3 bits each (MSB left).
fn glyph(c: char) -> [u8; 5] {
    match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 2, 2],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        'e' => [0, 7, 7, 4, 7],
        'E' => [7, 4, 7, 4, 7],
        'p' => [0, 7, 5, 7, 4],
        'o' => [0, 7, 5, 5, 7],
        'c' => [0, 7, 4, 4, 7],
        'h' => [4, 4, 7, 5, 5],
        'M' => [5, 7, 7, 5, 5],
        'S' => [7, 4, 7, 1, 7],
        't' => [2, 7, 2, 2, 3],
        'r' => [0, 7, 4, 4, 4],
        'a' => [0, 7, 1, 7, 7],
        'i' => [2, 0, 2, 2, 2],
        'n' => [0, 7, 5, 5, 5],
        's' => [0, 7, 6, 1, 7],
        'l' => [2, 2, 2, 2, 3],
        'g' => [0, 7, 7, 1, 7],
        '(' => [1, 2, 2, 2, 1],
        ')' => [4, 2, 2, 2, 4],
        _ => [0; 5],
    }
}

struct Canvas {
    px: Vec<u8>,
}

impl Canvas {
    fn set(&mut self, x: i32, y: i32, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as u32) < W && (y as u32) < H {
            let i = 3 * (y as usize * W as usize + x as usize);
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }

    fn text(&mut self, x: i32, y: i32, s: &str, scale: i32, c: [u8; 3]) {
        for (k, ch) in s.chars().enumerate() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..3 {
                    if bits & (4 >> col) != 0 {
                        for dy in 0..scale {
                            for dx in 0..scale {
                                self.set(x + (k as i32 * 4 + col) * scale + dx, y + row as i32 * scale + dy, c);
                            }
                        }
                    }
                }
            }
        }
    }

    fn line(&mut self, (x0, y0): (f32, f32), (x1, y1): (f32, f32), c: [u8; 3], width: i32) {
        let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as i32).max(1);
        for i in 0..=n {
            let t = i as f32 / n as f32;
            let (x, y) = ((x0 + (x1 - x0) * t).round() as i32, (y0 + (y1 - y0) * t).round() as i32);
            for d in 0..width {
                self.set(x, y + d - width / 2, c);
                self.set(x + d - width / 2, y, c);
            }
        }
    }
}

/// PNG bytes of the loss curves (log10 MSE against epoch).
pub fn loss_plot_png(history: &[EpochRecord]) -> Vec<u8> {
    let mut cv = Canvas { px: vec![255; (W * H * 3) as usize] };
    let (x0, x1, y0, y1) = (LEFT, W as i32 - RIGHT, TOP, H as i32 - BOTTOM);
    let vals: Vec<f64> =
        history.iter().flat_map(|h| [h.train_mse, h.test_mse]).filter(|v| *v > 0.0 && v.is_finite()).collect();
    let (lo, hi) = vals.iter().fold((f64::MAX, f64::MIN), |(l, h), v| (l.min(v.log10()), h.max(v.log10())));
    let (lo, hi) = if vals.is_empty() { (-1.0, 0.0) } else { (lo.floor(), hi.ceil().max(lo.floor() + 1.0)) };
    let epochs = history.len().max(2) as f32;
    let px = |e: f32| x0 as f32 + (e - 1.0) / (epochs - 1.0) * (x1 - x0) as f32;
    let py = |v: f64| y1 as f32 - ((v.max(1e-30).log10() - lo) / (hi - lo)) as f32 * (y1 - y0) as f32;
    let grey = [200, 200, 200];
    let black = [0, 0, 0];
    // Decade grid lines and labels.
    let mut d = lo;
    while d <= hi + 1e-9 {
        let y = py(10f64.powf(d));
        cv.line((x0 as f32, y), (x1 as f32, y), grey, 1);
        cv.text(8, y as i32 - 5, &format!("1e{}", d as i32), 2, black);
        d += 1.0;
    }
    let step = (history.len() / 10).max(1);
    for e in (1..=history.len()).step_by(step) {
        let x = px(e as f32);
        cv.line((x, y0 as f32), (x, y1 as f32), grey, 1);
        cv.text(x as i32 - 4, y1 + 8, &e.to_string(), 2, black);
    }
    cv.line((x0 as f32, y0 as f32), (x0 as f32, y1 as f32), black, 1);
    cv.line((x0 as f32, y1 as f32), (x1 as f32, y1 as f32), black, 1);
    cv.text(W as i32 / 2 - 20, H as i32 - 18, "epoch", 2, black);
    cv.text(LEFT, 8, "MSE", 2, black);
    cv.line((W as f32 - 200.0, 14.0), (W as f32 - 180.0, 14.0), TRAIN_COLOUR, 3);
    cv.text(W as i32 - 175, 9, "train", 2, TRAIN_COLOUR);
    cv.line((W as f32 - 110.0, 14.0), (W as f32 - 90.0, 14.0), TEST_COLOUR, 3);
    cv.text(W as i32 - 85, 9, "test", 2, TEST_COLOUR);
    for (colour, pick) in [(TRAIN_COLOUR, 0), (TEST_COLOUR, 1)] {
        let pts: Vec<(f32, f32)> = history
            .iter()
            .map(|h| (px(h.epoch as f32), py(if pick == 0 { h.train_mse } else { h.test_mse })))
            .collect();
        for w in pts.windows(2) {
            cv.line(w[0], w[1], colour, 3);
        }
        for p in &pts {
            cv.line((p.0 - 2.0, p.1), (p.0 + 2.0, p.1), colour, 4);
        }
    }
    let img = image::RgbImage::from_raw(W, H, cv.px).expect("sized");
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).expect("PNG encodes in memory");
    out.into_inner()
}
