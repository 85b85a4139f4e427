//! What the subcommands share: the render threads, progress bars, Ctrl-C handling.

use anyhow::{Context, Result, bail};
use engine::RenderControl;
use indicatif::{ProgressBar, ProgressStyle};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

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

/// Ctrl-C asks `control` to stop after the current pass.
pub fn stop_on_ctrl_c(control: &Arc<RenderControl>) {
    let c = control.clone();
    // If a handler is already installed (tests), keep going without one.
    let _ = ctrlc::set_handler(move || {
        eprintln!("\nstopping after the current pass; the samples so far are kept");
        c.request_stop();
    });
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

/// Ctrl-C sets the flag: the chunks on disk are kept, the run can be resumed.
pub fn cancel_on_ctrl_c() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    let _ = ctrlc::set_handler(move || {
        eprintln!("\nstopping: finished chunks are kept; run the same command again to resume");
        f.store(true, Ordering::Relaxed);
    });
    flag
}

/// Nimbus version and the commit it was built from.
pub fn code_version() -> String {
    format!("nimbus {} ({})", env!("CARGO_PKG_VERSION"), option_env!("NIMBUS_GIT_COMMIT").unwrap_or("unknown commit"))
}
