//! `nimbus eval`: the thesis's evaluations, reproduced. [`global`] is the global
//! model's (thesis 5.5: bias, TTUV, speedup and time to preview against path tracing
//! per scene, lighting, density and k); [`p2p`] the point-to-point model's in BDPT
//! (thesis 6.5). [`common`] holds the tracked renders, the render cache's files and
//! image sheets they share.

pub mod cloud_points;
pub mod common;
pub mod global;
pub mod p2p;
pub mod preview;
pub mod temporal;

use anyhow::Result;
use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum EvalCommand {
    /// The point-to-point model in BDPT (thesis 6.5): bias, TTUV and speedup against
    /// BDPT's high orders and against path tracing, backlit and frontlit, k = 1 .. 4.
    P2p(p2p::EvalP2pArgs),
    /// Temporal stability of turntables (`nimbus turntable`): the temporal error of a
    /// mode's frames against path-traced reference frames, and the static flicker
    /// over several seeds.
    Temporal(temporal::EvalTemporalArgs),
    /// A cloud-aware model's relative bias on point data sets of `nimbus datagen
    /// cloud`: overall, per camera-path vertex and per cloud.
    CloudPoints(cloud_points::EvalCloudPointsArgs),
}

/// Runs `nimbus eval` (the global model's study) or `nimbus eval p2p`.
pub fn run(which: Option<EvalCommand>, args: global::EvalArgs) -> Result<()> {
    match which {
        Some(EvalCommand::P2p(args)) => p2p::eval_p2p(&args).map(|_| ()),
        Some(EvalCommand::Temporal(args)) => temporal::eval_temporal(&args).map(|_| ()),
        Some(EvalCommand::CloudPoints(args)) => cloud_points::eval_cloud_points(&args).map(|_| ()),
        None => global::eval(&args).map(|_| ()),
    }
}
