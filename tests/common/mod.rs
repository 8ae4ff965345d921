//! What the library's test groups share: the repository's assets, the built-in scenes' text
//! to edit into a test's own, and temporary folders that clean up after themselves.

use std::path::{Path, PathBuf};

/// A file under the repository's `assets/`.
pub fn asset(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("assets").join(rel)
}

/// The TOML text of the built-in scene `name` (`assets/scenes/<name>.toml`).
pub fn builtin_text(name: &str) -> &'static str {
    diffluid::experiments::scene::BUILTIN_SCENES
        .iter()
        .find(|(n, _)| *n == name)
        .unwrap_or_else(|| panic!("no built-in scene {name:?}"))
        .1
}

/// A fresh, empty folder under the system temp directory (its name starts with
/// `diffluid-<tag>-`), removed when dropped.
pub struct TempDir(tempfile::TempDir);

impl TempDir {
    /// A new folder; `tag` names the test in the folder's name.
    pub fn new(tag: &str) -> TempDir {
        let dir = tempfile::Builder::new()
            .prefix(&format!("diffluid-{tag}-"))
            .tempdir()
            .expect("a temporary folder");
        TempDir(dir)
    }
}

impl std::ops::Deref for TempDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<Path> for TempDir {
    fn as_ref(&self) -> &Path {
        self
    }
}
