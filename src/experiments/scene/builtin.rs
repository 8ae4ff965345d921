//! The scenes shipped with diffluid, built into the library so that the tests and the CLI
//! load them from anywhere.

use super::spec::Scene;
use crate::error::{Error, Result};
use std::path::Path;

/// The scene `cargo run --release` runs when no scene is given.
pub const DEFAULT_SCENE: &str = include_str!("../../../assets/scenes/block_drop.toml");

/// Scenes shipped with diffluid, by name, so tests and the CLI can load them anywhere.
pub const BUILTIN_SCENES: &[(&str, &str)] = &[
    ("dam_break", include_str!("../../../assets/scenes/dam_break.toml")),
    ("still_water", include_str!("../../../assets/scenes/still_water.toml")),
    ("block_drop", include_str!("../../../assets/scenes/block_drop.toml")),
    ("dam_break_ball", include_str!("../../../assets/scenes/dam_break_ball.toml")),
    ("floating_box", include_str!("../../../assets/scenes/floating_box.toml")),
    ("gradcheck_box", include_str!("../../../assets/scenes/gradcheck_box.toml")),
    ("recover_box", include_str!("../../../assets/scenes/recover_box.toml")),
    ("gradcheck_live", include_str!("../../../assets/scenes/gradcheck_live.toml")),
    ("surge_ball", include_str!("../../../assets/scenes/surge_ball.toml")),
    ("surge_target", include_str!("../../../assets/scenes/surge_target.toml")),
    ("paddle_push", include_str!("../../../assets/scenes/paddle_push.toml")),
    ("gradcheck_control", include_str!("../../../assets/scenes/gradcheck_control.toml")),
    ("large_tank", include_str!("../../../assets/scenes/large_tank.toml")),
];

impl Scene {
    /// A scene shipped with diffluid, by name (`dam_break`, `still_water`, ...).
    pub fn builtin(name: &str) -> Result<Scene> {
        let text =
            BUILTIN_SCENES.iter().find(|(n, _)| *n == name).map(|(_, t)| *t).ok_or_else(|| {
                Error::InvalidScene {
                    origin: "<builtin>".into(),
                    message: format!("no built-in scene named {name:?}"),
                }
            })?;
        // The built-in scenes ship with the crate: their relative mesh paths start from its
        // `assets/scenes/`.
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes");
        Scene::from_toml_in(text, &format!("<builtin {name}>"), base)
    }

    /// The embedded default scene.
    pub fn embedded_default() -> Scene {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes");
        Scene::from_toml_in(DEFAULT_SCENE, "<embedded>", base).expect("the embedded scene is valid")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_scenes_parse() {
        for (name, _) in BUILTIN_SCENES {
            Scene::builtin(name).unwrap();
        }
    }
}
