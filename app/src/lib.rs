//! The `nimbus` application: scene files, built-in clouds, file output, the window
//! and the command line. `main.rs` is a thin wrapper so tests reach everything here.
//!
//! - [`scene`] (scene files), [`cloud`] (built-in clouds), [`progressive`]
//!   (headless progressive rendering, automatic p), [`output`] (EXR, PNG, npy,
//!   atomic writes), [`mitsuba`] (Mitsuba 3 scene export), [`metrics`] (images and
//!   the figures of merit);
//! - [`cli`]: the subcommands of the user's path; [`lab`]: `eval` and `bench`;
//! - [`gui`]: the window and its render worker (feature `gui`).

pub mod cli;
pub mod cloud;
#[cfg(feature = "gui")]
pub mod gui;
pub mod lab;
pub mod metrics;
pub mod mitsuba;
pub mod output;
pub mod progressive;
pub mod scene;
