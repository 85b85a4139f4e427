//! Line plots as PNG, drawn directly into pixels with a tiny built-in font, so no font
//! files or plotting stack are needed: the training curve (train and test MSE per
//! epoch, like the thesis's figure 5.6) and the evaluation's bias and speedup against
//! k (figure 5.8).

const W: u32 = 640;
const H: u32 = 400;
const LEFT: i32 = 70;
const RIGHT: i32 = 20;
const TOP: i32 = 30;
const BOTTOM: i32 = 50;
pub const TRAIN_COLOUR: [u8; 3] = [31, 119, 180];
pub const TEST_COLOUR: [u8; 3] = [214, 39, 40];
/// Colours of further series (matplotlib's tab10).
pub const PALETTE: [[u8; 3]; 10] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
];

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
        'b' => [4, 4, 7, 5, 7],
        'd' => [1, 1, 7, 5, 7],
        'f' => [3, 2, 7, 2, 2],
        'k' => [4, 5, 6, 6, 5],
        'm' => [0, 7, 7, 5, 5],
        'u' => [0, 5, 5, 5, 7],
        'v' => [0, 5, 5, 5, 2],
        'w' => [0, 5, 5, 7, 7],
        'x' => [0, 5, 2, 2, 5],
        'y' => [0, 5, 7, 1, 7],
        'z' => [0, 7, 1, 2, 7],
        'j' => [1, 0, 1, 1, 6],
        'q' => [0, 7, 5, 7, 1],
        'A' => [2, 5, 7, 5, 5],
        'B' => [6, 5, 6, 5, 6],
        'C' => [7, 4, 4, 4, 7],
        'T' => [7, 2, 2, 2, 2],
        'U' => [5, 5, 5, 5, 7],
        'V' => [5, 5, 5, 5, 2],
        'D' => [6, 5, 5, 5, 6],
        'F' => [7, 4, 7, 4, 4],
        'G' => [7, 4, 5, 5, 7],
        'H' => [5, 5, 7, 5, 5],
        'I' => [7, 2, 2, 2, 7],
        'K' => [5, 5, 6, 5, 5],
        'L' => [4, 4, 4, 4, 7],
        'N' => [7, 5, 5, 5, 5],
        'O' => [7, 5, 5, 5, 7],
        'P' => [7, 5, 7, 4, 4],
        'R' => [6, 5, 6, 5, 5],
        'W' => [5, 5, 7, 7, 5],
        'X' => [5, 5, 2, 5, 5],
        'Y' => [5, 5, 2, 2, 2],
        'Z' => [7, 1, 2, 4, 7],
        '%' => [5, 1, 2, 4, 5],
        '/' => [1, 1, 2, 4, 4],
        '=' => [0, 7, 0, 7, 0],
        ',' => [0, 0, 0, 2, 4],
        ':' => [0, 2, 0, 2, 0],
        '_' => [0, 0, 0, 0, 7],
        '^' => [2, 5, 0, 0, 0],
        '+' => [0, 2, 7, 2, 0],
        _ => [0; 5],
    }
}

struct Canvas {
    w: u32,
    h: u32,
    px: Vec<u8>,
}

impl Canvas {
    fn new(w: u32, h: u32) -> Self {
        Canvas { w, h, px: vec![255; (w * h * 3) as usize] }
    }

    fn set(&mut self, x: i32, y: i32, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as u32) < self.w && (y as u32) < self.h {
            let i = 3 * (y as usize * self.w as usize + x as usize);
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

    fn png(self) -> Vec<u8> {
        let img = image::RgbImage::from_raw(self.w, self.h, self.px).expect("sized");
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).expect("PNG encodes in memory");
        out.into_inner()
    }
}

/// One line of a plot.
#[derive(Clone, Debug)]
pub struct Series {
    pub label: String,
    pub colour: [u8; 3],
    pub points: Vec<(f64, f64)>,
}

/// PNG bytes of a line plot: x linear with a tick at every x the series use (or ten
/// when there are many), y on a log scale with decade grid lines. Points with y <= 0
/// are left out. Labels use a tiny built-in font (lowercase, digits, a few capitals).
pub fn line_plot_png(title: &str, x_label: &str, y_label: &str, series: &[Series]) -> Vec<u8> {
    let legend_rows = series.len().div_ceil(3) as i32;
    let top = TOP + 14 * legend_rows;
    let h = H + (14 * legend_rows) as u32;
    let mut cv = Canvas::new(W, h);
    let (x0, x1, y0, y1) = (LEFT, W as i32 - RIGHT, top, h as i32 - BOTTOM);
    let ys: Vec<f64> =
        series.iter().flat_map(|s| s.points.iter().map(|p| p.1)).filter(|v| *v > 0.0 && v.is_finite()).collect();
    let (lo, hi) = ys.iter().fold((f64::MAX, f64::MIN), |(l, h), v| (l.min(v.log10()), h.max(v.log10())));
    let (lo, hi) = if ys.is_empty() { (-1.0, 0.0) } else { (lo.floor(), hi.ceil().max(lo.floor() + 1.0)) };
    let mut xs: Vec<f64> = series.iter().flat_map(|s| s.points.iter().map(|p| p.0)).collect();
    xs.sort_by(f64::total_cmp);
    xs.dedup();
    let (xmin, xmax) = (xs.first().copied().unwrap_or(0.0), xs.last().copied().unwrap_or(1.0));
    let xspan = if xmax > xmin { xmax - xmin } else { 1.0 };
    let px = |x: f64| x0 as f32 + ((x - xmin) / xspan) as f32 * (x1 - x0) as f32;
    let py = |v: f64| y1 as f32 - ((v.max(1e-30).log10() - lo) / (hi - lo)) as f32 * (y1 - y0) as f32;
    let (grey, black) = ([200, 200, 200], [0, 0, 0]);
    let mut d = lo;
    while d <= hi + 1e-9 {
        let y = py(10f64.powf(d));
        cv.line((x0 as f32, y), (x1 as f32, y), grey, 1);
        cv.text(8, y as i32 - 5, &format!("1e{}", d as i32), 2, black);
        d += 1.0;
    }
    let ticks: Vec<f64> = if xs.len() <= 12 {
        xs.clone()
    } else {
        let step = (xs.len() / 10).max(1);
        xs.iter().step_by(step).copied().collect()
    };
    for t in ticks {
        let x = px(t);
        cv.line((x, y0 as f32), (x, y1 as f32), grey, 1);
        let label = if t.fract() == 0.0 { format!("{}", t as i64) } else { format!("{t:.2}") };
        cv.text(x as i32 - 4, y1 + 8, &label, 2, black);
    }
    cv.line((x0 as f32, y0 as f32), (x0 as f32, y1 as f32), black, 1);
    cv.line((x0 as f32, y1 as f32), (x1 as f32, y1 as f32), black, 1);
    cv.text(W as i32 / 2 - 4 * x_label.len() as i32, h as i32 - 18, x_label, 2, black);
    cv.text(8, 8, &format!("{y_label}   {title}"), 2, black);
    for (i, s) in series.iter().enumerate() {
        let (lx, ly) = (LEFT + (i as i32 % 3) * 190, 26 + (i as i32 / 3) * 14);
        cv.line((lx as f32, ly as f32 + 5.0), (lx as f32 + 20.0, ly as f32 + 5.0), s.colour, 3);
        cv.text(lx + 25, ly, &s.label, 2, s.colour);
        let pts: Vec<(f32, f32)> =
            s.points.iter().filter(|p| p.1 > 0.0 && p.1.is_finite()).map(|p| (px(p.0), py(p.1))).collect();
        for w in pts.windows(2) {
            cv.line(w[0], w[1], s.colour, 3);
        }
        for p in &pts {
            cv.line((p.0 - 2.0, p.1), (p.0 + 2.0, p.1), s.colour, 4);
        }
    }
    cv.png()
}

/// PNG bytes of a training run's loss curves, train and test MSE against epoch (like
/// the thesis's figure 5.6), from (epoch, train, test) per epoch.
pub fn loss_plot_png(title: &str, y_label: &str, [train, test]: [[u8; 3]; 2], history: &[(f64, f64, f64)]) -> Vec<u8> {
    let curve = |label: &str, colour, pick: fn(&(f64, f64, f64)) -> f64| Series {
        label: label.into(),
        colour,
        points: history.iter().map(|h| (h.0, pick(h))).collect(),
    };
    line_plot_png(title, "epoch", y_label, &[curve("train", train, |h| h.1), curve("test", test, |h| h.2)])
}
