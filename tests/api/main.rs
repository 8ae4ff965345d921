//! The library's shape: the checks `add_body` makes, the path a program embedding it walks,
//! and the layers no module reaches above.

#[allow(dead_code)] // each group uses part of it
#[path = "../common/mod.rs"]
mod common;

mod body_checks;
mod embedding;
mod layers;
