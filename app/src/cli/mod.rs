//! The `nimbus` command line: headless versions of what the window does, one file
//! per subcommand ([`render`], [`modeler`] for `model` and `sheet`, [`mitsuba`],
//! [`datagen`], [`train`]); `eval` and `bench` live in [`crate::lab`]. [`common`]
//! holds what the subcommands share: threads, progress bars, Ctrl-C, flag groups.

pub mod common;
pub mod datagen;
pub mod mitsuba;
pub mod modeler;
pub mod render;
pub mod train;
pub mod turntable;

use crate::lab;
use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(name = "nimbus", version, about = "Author and render clouds: path traced low orders, learned high orders")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Option<Command>,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Render a scene file to a multi-layer EXR (and optionally a PNG).
    Render(render::RenderArgs),
    /// Build a procedural cloud and write it out (.vdb, .vol Mitsuba volume, or .raw + .json).
    Model(modeler::ModelArgs),
    /// Write a scene's cloud, sun and camera as a Mitsuba 3 scene (cloud.vol + scene.xml).
    Mitsuba(mitsuba::MitsubaArgs),
    /// Render every modeler preset into one contact-sheet PNG.
    Sheet(modeler::SheetArgs),
    /// Render a sequence with the camera or the sun turning about the cloud: frames
    /// as EXR + PNG and an animated PNG; resumable; any mode.
    Turntable(turntable::TurntableArgs),
    /// Make training data for the learned models (resumable, shardable).
    Datagen {
        #[command(subcommand)]
        which: datagen::DatagenCommand,
    },
    /// Train a learned model on generated data.
    Train {
        #[command(subcommand)]
        which: train::TrainCommand,
    },
    /// The thesis's evaluation of the global model: bias, TTUV and speedup against path
    /// tracing per scene, lighting, density and k; tables, plots and image sheets.
    /// `nimbus eval p2p` evaluates the point-to-point model instead (thesis 6.5).
    #[command(args_conflicts_with_subcommands = true)]
    Eval {
        #[command(subcommand)]
        which: Option<lab::eval::EvalCommand>,
        #[command(flatten)]
        args: lab::eval::global::EvalArgs,
    },
    /// Benchmarks.
    Bench {
        #[command(subcommand)]
        which: lab::bench::BenchCommand,
    },
}

/// Runs the CLI.
pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        #[cfg(feature = "gui")]
        None => crate::gui::run(),
        #[cfg(not(feature = "gui"))]
        None => {
            use clap::CommandFactory;
            Cli::command().print_help()?;
            anyhow::bail!("this nimbus was built without the window (feature \"gui\"); use the subcommands")
        }
        Some(Command::Render(args)) => render::render(args),
        Some(Command::Model(args)) => modeler::model(args),
        Some(Command::Sheet(args)) => modeler::sheet(args),
        Some(Command::Turntable(args)) => turntable::turntable(args),
        Some(Command::Mitsuba(args)) => mitsuba::mitsuba(args),
        Some(Command::Datagen { which }) => datagen::datagen(which),
        Some(Command::Train { which }) => train::train(which),
        Some(Command::Eval { which, args }) => lab::eval::run(which, args),
        Some(Command::Bench { which }) => lab::bench::run(which),
    }
}
