//! What the subcommands share: the render threads, progress bars, Ctrl-C handling.

use anyhow::{Context, Result, bail};
use clap::Args;
use engine::RenderControl;
use engine::integrator::bdpt::Prediction;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Checks `--predictor` as clap parses it: a shipped model's name
/// ([`models::prediction::PredictorKind`]), kept as given.
pub fn predictor_arg(s: &str) -> Result<String, String> {
    use models::prediction::PredictorKind;
    PredictorKind::parse(s).map(|_| s.to_string()).ok_or_else(|| format!("choose {}", PredictorKind::NAMES))
}

/// Starts the render threads: `threads` of them, or all cores when None.
pub fn init_threads(threads: Option<usize>) -> Result<usize> {
    if let Some(n) = threads {
        if n == 0 {
            bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .thread_name(|i| format!("nimbus-render-{i}"))
            .build_global()
            .context("cannot start the render threads")?;
    }
    Ok(rayon::current_num_threads())
}

/// The first Ctrl-C prints `what` and calls `stop` (the command winds down and keeps
/// its work); a second one quits at once with exit status 130. If a handler is
/// already installed (tests), the command goes on without one.
pub fn on_ctrl_c(what: &'static str, stop: impl Fn() + Send + 'static) {
    let presses = std::sync::atomic::AtomicU32::new(0);
    let _ = ctrlc::set_handler(move || {
        if presses.fetch_add(1, Ordering::SeqCst) == 0 {
            eprintln!("\n{what} (Ctrl-C again quits at once)");
            stop();
        } else {
            eprintln!("\nquitting");
            std::process::exit(130);
        }
    });
}

/// Ctrl-C asks `control` to stop; the pass under way is abandoned within a row of
/// samples and the finished passes are kept.
pub fn stop_on_ctrl_c(control: &Arc<RenderControl>) {
    let c = control.clone();
    on_ctrl_c("stopping: the finished passes are kept", move || c.request_stop());
}

/// The CLI's progress bar; `unit` names what is counted (spp, points, batches).
pub fn progress_bar(len: u64, unit: &str, quiet: bool) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(&format!(
            "{{spinner}} [{{elapsed_precise}}] {{bar:40}} {{pos}}/{{len}} {unit}  ETA {{eta}}  {{msg}}"
        ))
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar
}

/// A flag that Ctrl-C sets (see [`on_ctrl_c`]), with `what` to say it was seen.
pub fn cancel_on_ctrl_c(what: &'static str) -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    on_ctrl_c(what, move || f.store(true, Ordering::Relaxed));
    flag
}

/// Nimbus version and the commit it was built from.
pub fn code_version() -> String {
    format!("nimbus {} ({})", env!("CARGO_PKG_VERSION"), option_env!("NIMBUS_GIT_COMMIT").unwrap_or("unknown commit"))
}

/// Threads and progress output: the flags every long-running command takes.
#[derive(Args, Debug, Clone, Default)]
pub struct RunArgs {
    /// Worker threads (default: all cores). The result does not depend on it.
    #[arg(long)]
    pub threads: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// Which part of a data set a run makes and where it goes.
#[derive(Args, Debug, Clone)]
pub struct DatagenRunArgs {
    /// Make only part i of N (0-based), e.g. --shard 3/16; join the parts with
    /// `nimbus datagen merge`.
    #[arg(long, default_value = "0/1")]
    pub shard: String,
    /// Output directory (created; one made with the same settings is resumed).
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub run: RunArgs,
}

/// The settings of BDPT's prediction mode; unset ones keep the scene's (or the
/// defaults).
#[derive(Args, Debug, Clone, Default)]
pub struct BdptPredictionArgs {
    /// Distance threshold r: end vertices closer than r are extended by the
    /// point-to-point estimator, not predicted (default 0.04; the thesis's 0.08).
    #[arg(long)]
    pub r: Option<f32>,
    /// Light subpaths offered to each camera end vertex, one chosen by resampling
    /// (default 256, picked from the pass's pool; 1 is the thesis's pairing).
    #[arg(long)]
    pub candidates: Option<u32>,
    /// Point-to-point samples for each pair of end vertices closer than r (default 8).
    #[arg(long)]
    pub extension_samples: Option<u32>,
}

impl BdptPredictionArgs {
    pub fn r(&self) -> f32 {
        self.r.unwrap_or(Prediction::DEFAULT_R)
    }
    pub fn candidates(&self) -> u32 {
        self.candidates.unwrap_or(Prediction::DEFAULT_CANDIDATES)
    }
    pub fn extension_samples(&self) -> u32 {
        self.extension_samples.unwrap_or(Prediction::DEFAULT_EXTENSION_SAMPLES)
    }
}
