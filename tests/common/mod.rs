//! What the test groups share: the repository's assets, the built-in scenes' text to edit
//! into a test's own, the head of a scene file with a tank of still water, and temporary
//! folders that clean up after themselves. The library's groups (`tests/*/main.rs`) and the
//! command line's (`cli/tests/common`) both include this file.

use std::path::{Path, PathBuf};

/// The repository's root: the library's package folder, one above the command line's
/// (`cli/`).
fn root() -> PathBuf {
    let package = Path::new(env!("CARGO_MANIFEST_DIR"));
    match env!("CARGO_PKG_NAME") {
        "diffluid-cli" => package.join(".."),
        _ => package.to_path_buf(),
    }
}

/// A file under the repository's `assets/`.
pub fn asset(rel: &str) -> PathBuf {
    root().join("assets").join(rel)
}

/// The TOML text of the built-in scene `name` (`assets/scenes/<name>.toml`).
pub fn builtin_text(name: &str) -> &'static str {
    diffluid::experiments::scene::BUILTIN_SCENES
        .iter()
        .find(|(n, _)| *n == name)
        .unwrap_or_else(|| panic!("no built-in scene {name:?}"))
        .1
}

/// The head of a scene file: `name`, a closed tank of `size` (m) in cells of `dx`, `steps`
/// steps of 0.01 s, and water under gravity at rest in it up to `depth`. A test appends its
/// bodies and settings (`[[body]]`, `[solver]`, ...).
pub fn tank_toml(name: &str, size: [f64; 3], dx: f64, depth: f64, steps: usize) -> String {
    let [x, _, z] = size;
    tank_head(name, size, dx, steps, [[0.0; 3], [x, depth, z]])
}

/// [`tank_toml`] with the water in the box `liquid` (its min and max corners) instead.
pub fn tank_head(
    name: &str,
    size: [f64; 3],
    dx: f64,
    steps: usize,
    liquid: [[f64; 3]; 2],
) -> String {
    let [x, y, z] = size;
    let [lo, hi] = liquid;
    format!(
        r#"name = "{name}"
[domain]
size = [{x:?}, {y:?}, {z:?}]
dx = {dx:?}
[time]
dt = 0.01
steps = {steps}
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "box", min = {lo:?}, max = {hi:?} }}
"#
    )
}

/// A kinematic paddle beside a heavy ball (r 0.08 m, density 1500) just above the floor of a
/// dry tank, its water in a far corner, contact on: `ball_x` is the ball's centre, `paddle`
/// more lines of the paddle's table (its velocity, say).
pub fn paddle_and_ball(steps: usize, ball_x: f64, paddle: &str) -> String {
    let corner = [[0.8, 0.0, 0.0], [1.0, 0.05, 0.5]];
    tank_head("push", [1.0, 0.5, 0.5], 0.05, steps, corner)
        + &format!(
            r#"[[body]]
name = "paddle"
shape = {{ kind = "cuboid", half_extents = [0.03, 0.1, 0.15] }}
density = 1000.0
dynamic = false
position = [0.2, 0.12, 0.25]
{paddle}
[[body]]
name = "ball"
shape = {{ kind = "ball", radius = 0.08 }}
density = 1500.0
position = [{ball_x:?}, 0.0805, 0.25]
[contact]
enabled = true
"#
        )
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

    /// Writes `text` as `scene.toml` in the folder and returns its path.
    pub fn scene(&self, text: &str) -> PathBuf {
        let path = self.join("scene.toml");
        std::fs::write(&path, text).unwrap();
        path
    }

    /// Where runs are told to write their output.
    pub fn out(&self) -> PathBuf {
        self.join("out")
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
