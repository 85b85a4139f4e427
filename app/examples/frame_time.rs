//! The window's own CPU time per frame in compare mode, measured headless through
//! egui_kittest: the default cloud at 256x256, prediction with the path-traced
//! comparison, for `--seconds` (default 40) after a 10 s warm-up; reports the
//! median, 90th percentile and maximum of `ui()` over the frames that follow a new
//! pass (the frames that refresh the textures).
//!
//! `cargo run --profile ci --example frame_time -- 40`

use app::gui::NimbusApp;
use egui_kittest::Harness;

fn main() {
    let seconds: u64 = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(40);
    let mut h: Harness<'static, NimbusApp> =
        Harness::builder().with_size(egui::vec2(1200.0, 800.0)).build_eframe(|cc| NimbusApp::new(&cc.egui_ctx, None));
    let mut s = h.state().scene().clone();
    s.render.mode = "predict".into();
    (s.camera.width, s.camera.height) = (256, 256);
    h.state_mut().set_scene(s);
    h.state_mut().set_compare(true);
    let start = std::time::Instant::now();
    let (mut frames, mut last) = (vec![], None);
    while start.elapsed().as_secs() < 10 + seconds {
        h.run_steps(1);
        let spp = h.state().rendered().map(|r| r.1);
        if spp != last && start.elapsed().as_secs() >= 10 {
            frames.push(h.state().frame_ms().0);
        }
        last = spp;
        std::thread::sleep(std::time::Duration::from_millis(16));
    }
    if frames.is_empty() {
        eprintln!("no pass finished in {seconds} s");
        std::process::exit(1);
    }
    frames.sort_by(f32::total_cmp);
    let q = |f: f64| frames[((frames.len() - 1) as f64 * f) as usize];
    println!(
        "ui() on frames after a new pass, compare mode, 256x256: n {}  median {:.2} ms  p90 {:.2} ms  max {:.2} ms",
        frames.len(),
        q(0.5),
        q(0.9),
        q(1.0)
    );
}
