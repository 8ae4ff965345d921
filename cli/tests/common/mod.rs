//! What the command line's test groups share: the library's test helpers (the repository's
//! assets, the built-in scenes' text, temporary folders; `tests/common/mod.rs`) and the
//! binary.

#[path = "../../../tests/common/mod.rs"]
mod shared;

pub use shared::*;

/// The `diffluid` binary this package builds.
pub const EXE: &str = env!("CARGO_BIN_EXE_diffluid");
