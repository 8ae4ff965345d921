//! The commands of the `diffluid` binary run as a user runs them: `bench`, `control`,
//! `gradcheck` and `optimize` (with checkpoints and resuming).

#[allow(dead_code)] // each group uses part of it
#[path = "../common/mod.rs"]
mod common;

mod bench;
mod control;
mod gradcheck_cli;
mod optimize;
