//! `nimbus turntable`: a scene rendered as N frames with the camera (or the sun)
//! turned about the vertical axis through the camera's target, each frame as EXR
//! (every buffer) and PNG, then an animated PNG of them all. Resumable: frames
//! already written are kept, and a run into a folder holding another turntable's
//! frames is refused rather than mixing the two. Every mode of `nimbus render`
//! (path tracing, prediction at bounce k, the instant preview). A folder with frames
//! but no manifest is refused too.
//!
//! Every frame uses the scene's seed, so with a sample count (not a time budget)
//! the frames are the same for any thread count, and the noise pattern is the same
//! from frame to frame where nothing moves.

use super::common::{RunArgs, init_threads, on_ctrl_c, progress_bar};
use crate::output::{self, ToneMap};
use crate::scene::{PredictorCache, SceneFile};
use anyhow::{Context, Result, bail};
use clap::Args;
use engine::{PassOutcome, RenderControl, Renderer};
use glam::{Quat, Vec3};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct TurntableArgs {
    /// Scene file (TOML).
    pub scene: PathBuf,
    /// Frames over the whole turn.
    #[arg(long, default_value_t = 36)]
    pub frames: u32,
    /// What turns: the camera (around the cloud) or the sun.
    #[arg(long, value_name = "camera|sun", default_value = "camera")]
    pub orbit: String,
    /// Degrees turned over all the frames (the last frame stops one step short of it,
    /// so a full turn loops).
    #[arg(long, default_value_t = 360.0)]
    pub degrees: f32,
    /// Folder of the frames (frame-0000.exr, frame-0000.png, ...), turntable.json and
    /// the animation (turntable.png, an animated PNG).
    #[arg(long)]
    pub out: PathBuf,
    /// Samples per pixel per frame (default 64).
    #[arg(long, conflicts_with = "time_per_frame")]
    pub spp: Option<u32>,
    /// Seconds per frame, set-up included, instead of a sample count (equal-time
    /// comparisons; at least one pass; the frames then depend on the machine's speed).
    #[arg(long, value_name = "SECONDS")]
    pub time_per_frame: Option<f64>,
    /// Prediction at bounce K (orders 1 .. K-1 path traced).
    #[arg(long, value_name = "K")]
    pub predict: Option<u32>,
    /// Full light transport, no prediction.
    #[arg(long, conflicts_with = "predict")]
    pub reference: bool,
    /// The instant preview (learned or octaves).
    #[arg(long, value_name = "learned|octaves", num_args = 0..=1, default_missing_value = "learned",
          conflicts_with_all = ["predict", "reference"])]
    pub preview: Option<String>,
    /// The shipped model: auto, cloud or global (overrides the scene's render.predictor).
    #[arg(long, value_parser = super::common::predictor_arg)]
    pub predictor: Option<String>,
    /// Override the resolution: WIDTHxHEIGHT.
    #[arg(long)]
    pub size: Option<String>,
    /// Override the scene's seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Exposure in stops for the PNGs and the animation.
    #[arg(long, default_value_t = 0.0)]
    pub exposure: f32,
    /// Tone curve: filmic or clamp.
    #[arg(long, default_value = "filmic")]
    pub tonemap: String,
    /// Frames per second of the animation.
    #[arg(long, default_value_t = 12)]
    pub fps: u16,
    #[command(flatten)]
    pub run: RunArgs,
}

/// What the frames of a folder were made with: a rerun must match it to resume.
#[derive(serde::Serialize, serde::Deserialize, PartialEq, Debug)]
struct Manifest {
    /// The scene as rendered (every override applied), as TOML.
    scene: String,
    frames: u32,
    orbit: String,
    degrees: f32,
    spp: Option<u32>,
    time_per_frame: Option<f64>,
    /// How the PNGs and the animation are tone-mapped.
    exposure: f32,
    tonemap: String,
    /// Fingerprint of the model's bytes (weights and sidecar), when the mode uses one:
    /// a model retrained into the same file is another turntable.
    model: Option<String>,
}

/// The fingerprint of the model `file`'s mode uses (None for path tracing and the
/// octave preview).
fn model_fingerprint(file: &SceneFile) -> Result<Option<String>> {
    let uses_model =
        file.render.mode == "predict" || (file.render.mode == "preview" && file.render.preview == "learned");
    if !uses_model {
        return Ok(None);
    }
    let fp = if file.render.mode == "predict" && file.render.integrator == "bdpt" {
        match file.p2p_model_path() {
            Some(p) => models::fingerprint::model_file_fingerprint(&p)?,
            None => models::p2p::model::shipped_fingerprint(),
        }
    } else {
        match file.model_path() {
            Some(p) => models::fingerprint::model_file_fingerprint(&p)?,
            None => models::prediction::shipped_fingerprint(file.predictor_kind()),
        }
    };
    Ok(Some(format!("{fp:016x}")))
}

/// The name of frame `i`'s files, without extension.
pub fn frame_stem(i: u32) -> String {
    format!("frame-{i:04}")
}

/// Turns `file`'s camera (or sun) by `degrees` about the vertical axis through the
/// camera's target.
pub fn turned(file: &SceneFile, orbit: &str, degrees: f32) -> Result<SceneFile> {
    let mut f = file.clone();
    let rot = Quat::from_rotation_y(degrees.to_radians());
    match orbit {
        "camera" => {
            // Resolve a preset into a position first (it depends on the sun).
            let cam = file.build_camera()?;
            let target = Vec3::from_array(file.camera.target);
            let from = cam.position() - target;
            f.camera.position = Some((target + rot * from).to_array());
            f.camera.up = (rot * cam.up()).to_array();
            f.camera.preset = None;
        }
        "sun" => {
            // Keep the camera where the unturned scene puts it.
            let cam = file.build_camera()?;
            f.camera.position = Some(cam.position().to_array());
            f.camera.up = cam.up().to_array();
            f.camera.preset = None;
            f.sun.direction = (rot * Vec3::from_array(file.sun.direction)).to_array();
        }
        other => bail!("--orbit {other:?}: choose camera or sun"),
    }
    Ok(f)
}

pub fn turntable(args: TurntableArgs) -> Result<()> {
    init_threads(args.run.threads)?;
    let tone = ToneMap::from_name(&args.tonemap)
        .with_context(|| format!("--tonemap {}: choose filmic or clamp", args.tonemap))?;
    if !(1..=100_000).contains(&args.frames) {
        bail!("--frames must be 1 ..= 100000, got {}", args.frames);
    }
    if !args.degrees.is_finite() {
        bail!("--degrees must be a finite number, got {}", args.degrees);
    }
    if args.spp == Some(0) {
        bail!("--spp must be at least 1");
    }
    if let Some(t) = args.time_per_frame {
        if !(t > 0.0 && t.is_finite()) {
            bail!("--time-per-frame must be a positive number of seconds, got {t}");
        }
    }
    if args.fps == 0 {
        bail!("--fps must be at least 1");
    }
    if !args.exposure.is_finite() {
        bail!("--exposure must be a finite number of stops, got {}", args.exposure);
    }
    if !matches!(args.orbit.as_str(), "camera" | "sun") {
        bail!("--orbit {:?}: choose camera or sun", args.orbit);
    }
    let mut file = SceneFile::load(&args.scene)?;
    if let Some(seed) = args.seed {
        file.seed = seed;
    }
    if let Some(size) = &args.size {
        (file.camera.width, file.camera.height) = super::render::parse_size(size)?;
    }
    if let Some(k) = args.predict {
        (file.k, file.render.mode) = (k, "predict".into());
    }
    if args.reference {
        file.render.mode = "reference".into();
    }
    if let Some(which) = &args.preview {
        (file.render.mode, file.render.preview) = ("preview".into(), which.clone());
    }
    if let Some(p) = &args.predictor {
        file.render.predictor = p.clone();
    }
    // Relative files of the scene keep working from the folder nimbus runs in.
    file.absolutize_paths();
    file.validate()?;
    let spp = args.spp.unwrap_or(if args.time_per_frame.is_some() { u32::MAX } else { 64 });

    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let manifest = Manifest {
        scene: file.to_toml(),
        frames: args.frames,
        orbit: args.orbit.clone(),
        degrees: args.degrees,
        spp: args.spp.or((args.time_per_frame.is_none()).then_some(64)),
        time_per_frame: args.time_per_frame,
        exposure: args.exposure,
        tonemap: args.tonemap.clone(),
        model: model_fingerprint(&file)?,
    };
    let manifest_path = args.out.join("turntable.json");
    let any_frame = std::fs::read_dir(&args.out)
        .with_context(|| format!("cannot list {}", args.out.display()))?
        .flatten()
        .any(|e| e.file_name().to_string_lossy().starts_with("frame-"));
    if any_frame && !manifest_path.exists() {
        bail!(
            "{} holds frames but no turntable.json: they are not known to be this turntable's; use another --out \
             or remove them",
            args.out.display()
        );
    }
    // Without frames there is nothing to mix up: a manifest left by a run that
    // stopped before its first frame is replaced.
    if manifest_path.exists() && any_frame {
        let text = std::fs::read_to_string(&manifest_path)
            .with_context(|| format!("cannot read {}", manifest_path.display()))?;
        let old: Manifest = serde_json::from_str(&text)
            .with_context(|| format!("{} is not a turntable manifest; use another --out", manifest_path.display()))?;
        if old != manifest {
            bail!(
                "{} holds the frames of another turntable (other scene or settings); use another --out or remove \
                 the folder",
                args.out.display()
            );
        }
    } else {
        output::write_bytes_atomically(&manifest_path, serde_json::to_string_pretty(&manifest)?.as_bytes())?;
    }

    let exists = |i: u32| {
        let stem = frame_stem(i);
        args.out.join(format!("{stem}.exr")).is_file() && args.out.join(format!("{stem}.png")).is_file()
    };
    let todo: Vec<u32> = (0..args.frames).filter(|i| !exists(*i)).collect();
    if todo.len() < args.frames as usize {
        eprintln!("resuming: {} of {} frames already written", args.frames as usize - todo.len(), args.frames);
    }
    let control = Arc::new(RenderControl::new());
    {
        let c = control.clone();
        on_ctrl_c("stopping: the frames written are kept; the same command resumes", move || c.request_stop());
    }
    let grid = Arc::new(file.build_grid()?);
    let mut cache = PredictorCache::default();
    let bar = progress_bar(args.frames as u64, "frames", args.run.quiet);
    bar.set_position((args.frames as usize - todo.len()) as u64);
    let start = Instant::now();
    for i in todo {
        let angle = args.degrees * i as f32 / args.frames as f32;
        // A time budget counts the frame's set-up too (a learned preview's lattice is
        // built for every camera), so modes compare at equal time per frame.
        let frame_start = Instant::now();
        let frame = turned(&file, &args.orbit, angle)?;
        let scene = Arc::new(frame.build_scene(Some(grid.clone()))?);
        let setup = frame.integrator_cached(
            &scene,
            models::global::depth_field::DEFAULT_MAX_NODES,
            &mut cache,
            engine::Cancel::NEVER,
        )?;
        if let (Some(w), 0) = (&setup.warning, i) {
            bar.suspend(|| eprintln!("warning: {w}"));
        }
        let mut renderer = Renderer::new(scene, setup.integrator)?;
        let generation = control.generation();
        let mut cancelled = false;
        while renderer.spp() < spp {
            if renderer.render_pass(&control, generation) == PassOutcome::Cancelled {
                cancelled = true;
                break;
            }
            if args.time_per_frame.is_some_and(|t| frame_start.elapsed().as_secs_f64() >= t) {
                break;
            }
        }
        if cancelled || control.stop_requested() {
            bar.finish_and_clear();
            bail!(
                "stopped at frame {i}: {} frames are written in {}; the same command resumes",
                (0..args.frames).filter(|j| exists(*j)).count(),
                args.out.display()
            );
        }
        let film = renderer.snapshot();
        let stem = frame_stem(i);
        super::render::write_outputs(
            &film,
            &args.out.join(format!("{stem}.exr")),
            Some(&args.out.join(format!("{stem}.png"))),
            tone,
            args.exposure,
        )?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let animation = args.out.join("turntable.png");
    write_animation(&args.out, args.frames, args.fps, &animation)?;
    println!(
        "{}",
        serde_json::json!({
            "frames": args.frames,
            "out": args.out,
            "animation": animation,
            "seconds": start.elapsed().as_secs_f64(),
        })
    );
    Ok(())
}

/// An animated PNG of the frames' PNGs, looping, at `fps` frames per second.
pub fn write_animation(dir: &Path, frames: u32, fps: u16, out: &Path) -> Result<()> {
    let mut images = Vec::with_capacity(frames as usize);
    for i in 0..frames {
        let path = dir.join(format!("{}.png", frame_stem(i)));
        let img = image::open(&path).with_context(|| format!("cannot read {}", path.display()))?.to_rgba8();
        images.push(img);
    }
    let (w, h) = images.first().map(|i| i.dimensions()).context("no frames")?;
    if let Some(bad) = images.iter().position(|i| i.dimensions() != (w, h)) {
        bail!("{}.png is not {w} x {h} like the first frame", frame_stem(bad as u32));
    }
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, w, h);
        enc.set_color(png::ColorType::Rgba);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_animated(frames, 0).context("animated PNG")?;
        enc.set_frame_delay(1, fps).context("animated PNG")?;
        let mut writer = enc.write_header().context("animated PNG")?;
        for img in &images {
            writer.write_image_data(img.as_raw()).context("animated PNG")?;
        }
        writer.finish().context("animated PNG")?;
    }
    output::write_bytes_atomically(out, &bytes)
}
