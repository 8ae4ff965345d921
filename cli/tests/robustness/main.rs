//! The binary on bad input: scene files, crafted checkpoints and meshes, non-finite states;
//! each refused with one `error:` line naming the problem, never a panic.

#[allow(dead_code)] // each group uses part of it
#[path = "../common/mod.rs"]
mod common;

mod bad_input;
mod crafted_files;
mod non_finite;
