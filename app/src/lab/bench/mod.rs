//! `nimbus bench`: speed and memory, reported as ratios against baselines measured in
//! the same run (docs/benchmarks.md has the figures and their commands).

pub mod datagen;
pub mod model;
pub mod predict;
pub mod render;
#[cfg(feature = "gui")]
pub mod window;

use anyhow::Result;
use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Samples per second on the fixed benchmark scene (128^3 multi-lobe cloud,
    /// rho 40, albedo 1, g 0.85, toplit, 256x256, full transport).
    Render(render::BenchRenderArgs),
    /// Time to rebuild clouds from presets (128^3 and 256^3).
    Model(model::BenchModelArgs),
    /// Seconds per ground-truth data point, the thesis's table 5.1, one thread.
    Datagen(datagen::BenchDatagenArgs),
    /// Microseconds per point-to-point prediction (features, deep residual network).
    PredictP2p(predict::BenchPredictP2pArgs),
    /// Seconds per point-to-point data point, the thesis's table 6.1, one thread.
    DatagenP2p(datagen::BenchDatagenP2pArgs),
    /// Nanoseconds per prediction of the global model, network alone and with features.
    Predict(predict::BenchPredictArgs),
    /// Microseconds per prediction of the cloud-aware model (stencil features and
    /// network, one thread) and the seconds of its per-cloud, per-sun fields.
    PredictCloud(predict::BenchPredictCloudArgs),
    /// The window's responsiveness without a window: milliseconds from a parameter
    /// change to the first image the render worker publishes.
    #[cfg(feature = "gui")]
    Latency(window::BenchLatencyArgs),
    /// Resident memory over a long accumulation in the window's render worker
    /// (prediction with the path-traced comparison, the heaviest mode), sampled at
    /// intervals, with the images tone-mapped each frame as the viewport does.
    #[cfg(feature = "gui")]
    Memory(window::BenchMemoryArgs),
}

/// Runs one benchmark.
pub fn run(which: BenchCommand) -> Result<()> {
    match which {
        BenchCommand::Render(args) => render::bench_render(args),
        BenchCommand::Model(args) => model::bench_model(args),
        BenchCommand::Datagen(args) => datagen::bench_datagen(args),
        BenchCommand::DatagenP2p(args) => datagen::bench_datagen_p2p(args),
        BenchCommand::Predict(args) => predict::bench_predict(args),
        BenchCommand::PredictP2p(args) => predict::bench_predict_p2p(args),
        BenchCommand::PredictCloud(args) => predict::bench_predict_cloud(args),
        #[cfg(feature = "gui")]
        BenchCommand::Latency(args) => window::bench_latency(args),
        #[cfg(feature = "gui")]
        BenchCommand::Memory(args) => window::bench_memory(args),
    }
}
