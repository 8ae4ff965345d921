//! Scene files, optimisation, and the benchmark studies.
pub mod bench;
pub mod optimize;
pub mod scene;
