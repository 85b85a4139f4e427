//! The `nimbus` application: scene files, built-in clouds, file output and the
//! command line. `main.rs` is a thin wrapper so tests reach everything here.

pub mod cli;
pub mod cloud;
pub mod datagen_cmd;
pub mod eval_cmd;
pub mod eval_p2p;
#[cfg(feature = "gui")]
pub mod gui;
pub mod mitsuba;
pub mod model_cmd;
pub mod output;
pub mod progressive;
pub mod scene;
pub mod train_cmd;
