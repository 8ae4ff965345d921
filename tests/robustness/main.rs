//! Robustness: bad and crafted input gives a clear error naming the problem (never a panic or
//! a silent wrong answer), and a failed step leaves the state as it was.

#[allow(dead_code)] // each group uses part of it
#[path = "../common/mod.rs"]
mod common;

mod failed_step;
mod fuzz_files;
mod fuzz_scenes;
mod shells;
