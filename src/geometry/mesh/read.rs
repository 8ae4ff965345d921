//! Reading an OBJ file's vertices and triangles (with tobj), and the meshes built into the
//! library for a binary that no longer has its source tree.

use crate::math::Vec3;
use std::borrow::Cow;
use std::path::{Component, Path, PathBuf};

/// The meshes of `assets/meshes/`, built into the library: the built-in scenes name them by
/// their path in the source tree, which an installed or moved binary no longer has.
const SHIPPED_MESHES: &[(&str, &[u8])] = &[
    ("cube.obj", include_bytes!("../../../assets/meshes/cube.obj")),
    ("hull.obj", include_bytes!("../../../assets/meshes/hull.obj")),
];

/// The built-in copy of the mesh at `path`, if `path` (with its `.` and `..` resolved
/// lexically) is one of [`SHIPPED_MESHES`] in the source tree's `assets/meshes/`.
pub(super) fn shipped_mesh(path: &Path) -> Option<&'static [u8]> {
    let mut resolved = PathBuf::new();
    for part in path.components() {
        match part {
            Component::CurDir => {}
            Component::ParentDir => {
                resolved.pop();
            }
            other => resolved.push(other),
        }
    }
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/meshes");
    let name = resolved.strip_prefix(dir).ok()?.to_str()?;
    SHIPPED_MESHES.iter().find(|(n, _)| *n == name).map(|(_, bytes)| *bytes)
}

/// An OBJ file's vertices and triangles (faces triangulated, points and lines dropped). A
/// shipped mesh whose file is gone is read from its built-in copy ([`SHIPPED_MESHES`]).
pub(super) fn read_obj(path: &Path) -> Result<(Vec<Vec3>, Vec<[u32; 3]>), String> {
    let name = path.display();
    // Read the file ourselves: tobj only says "open file failed", not why.
    let bytes = match crate::math::input::read_file(path) {
        Ok(bytes) => Cow::Owned(bytes),
        Err(e) => Cow::Borrowed(
            shipped_mesh(path).ok_or_else(|| format!("cannot read mesh {name}: {e}"))?,
        ),
    };
    let options = tobj::LoadOptions {
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
        ..Default::default()
    };
    // Materials are not needed: a referenced .mtl file is not opened.
    let (models, _materials) =
        tobj::load_obj_buf(&mut &*bytes, &options, |_| Err(tobj::LoadError::OpenFileFailed))
            .map_err(|e| format!("mesh {name} is not a valid OBJ file: {e}"))?;

    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    for model in &models {
        let base = positions.len();
        let mesh = &model.mesh;
        positions.extend(mesh.positions.chunks_exact(3).map(|p| Vec3::new(p[0], p[1], p[2])));
        for t in mesh.indices.chunks_exact(3) {
            let mut tri = [0u32; 3];
            for (k, &i) in t.iter().enumerate() {
                tri[k] = u32::try_from(base + i as usize)
                    .map_err(|_| format!("mesh {name} has too many vertices"))?;
            }
            triangles.push(tri);
        }
    }
    Ok((positions, triangles))
}
