//! Smoke test of the real binary: `nimbus` with no arguments opens the window under
//! Xvfb (Mesa's software Vulkan), stays up, and shows a cloud. CI installs xvfb,
//! mesa-vulkan-drivers and imagemagick (for `import`); elsewhere the test is skipped
//! with a message when they are missing.

#![cfg(feature = "gui")]

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn have(tool: &str) -> bool {
    Command::new("sh").args(["-c", &format!("command -v {tool}")]).output().map(|o| o.status.success()).unwrap_or(false)
}

struct Kill(std::process::Child);
impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn window_opens_and_shows_a_cloud() {
    if !(have("Xvfb") && have("import")) {
        assert!(std::env::var_os("CI").is_none(), "CI must install xvfb, mesa-vulkan-drivers and imagemagick");
        eprintln!("skipping: Xvfb or ImageMagick's import is missing");
        return;
    }
    let display = format!(":{}", 90 + std::process::id() % 100);
    let _xvfb = Kill(
        Command::new("Xvfb")
            .args([display.as_str(), "-screen", "0", "1280x800x24"])
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    std::thread::sleep(Duration::from_secs(2));
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().to_path_buf();
    let mut app = Kill(
        Command::new(env!("CARGO_BIN_EXE_nimbus"))
            .env("DISPLAY", &display)
            .env("WGPU_BACKEND", "vulkan")
            .env("XDG_RUNTIME_DIR", &dir)
            .env("HOME", &dir) // a fresh profile: the default cloud, not a saved scene
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let shot = dir.join("screen.png");
    let start = Instant::now();
    loop {
        if let Some(status) = app.0.try_wait().unwrap() {
            let mut err = String::new();
            use std::io::Read;
            app.0.stderr.take().unwrap().read_to_string(&mut err).unwrap();
            panic!("nimbus exited with {status}: {err}");
        }
        let ok = Command::new("import")
            .args(["-display", &display, "-window", "root", shot.to_str().unwrap()])
            .status()
            .unwrap();
        if ok.success() {
            // Bright pixels in the viewport (left two thirds) mean a rendered cloud.
            let img = image::open(&shot).unwrap().to_rgb8();
            let bright = img
                .enumerate_pixels()
                .filter(|(x, y, p)| {
                    *x < img.width() * 2 / 3 && *y > 40 && *y < img.height() - 60 && p.0.iter().all(|c| *c > 120)
                })
                .count();
            if bright > 2000 {
                break;
            }
        }
        assert!(start.elapsed() < Duration::from_secs(120), "no cloud on screen after 120 s");
        std::thread::sleep(Duration::from_secs(2));
    }
    drop(app);
}
