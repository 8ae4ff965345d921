//! Writers: binary PLY point clouds for particles and the run summary as JSON.

use crate::error::{Error, Result};
use crate::math::Vec3;
use serde::Serialize;
use std::io::Write;
use std::path::Path;

fn write_err(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Write {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes points as a binary little-endian PLY with `float x y z` per vertex, which
/// ParaView, Blender and MeshLab read.
pub fn write_ply_points(path: &Path, points: &[Vec3]) -> Result<()> {
    let mut buf = Vec::with_capacity(128 + 12 * points.len());
    write!(
        buf,
        "ply\nformat binary_little_endian 1.0\ncomment diffluid liquid particles\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nend_header\n",
        points.len()
    )
    .expect("writing to memory");
    for p in points {
        for c in p.to_array() {
            buf.extend_from_slice(&(c as f32).to_le_bytes());
        }
    }
    write_atomic(path, &buf)
}

/// Writes a value as pretty JSON.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_vec_pretty(value).expect("serialisable");
    write_atomic(path, &text)
}

/// Writes a file through a temporary and a rename, so a reader never sees half a file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(write_err(dir))?;
    }
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(write_err(&tmp))?;
    std::fs::rename(&tmp, path).map_err(write_err(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_has_header_and_twelve_bytes_per_point() {
        let dir = std::env::temp_dir().join(format!("diffluid-ply-{}", std::process::id()));
        let path = dir.join("p.ply");
        write_ply_points(&path, &[Vec3::new(1.0, 2.0, 3.0), Vec3::ZERO]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let end = b"end_header\n";
        let pos = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        assert_eq!(bytes.len() - pos, 24);
        assert_eq!(
            f32::from_le_bytes(bytes[pos + 4..pos + 8].try_into().unwrap()),
            2.0
        );
        std::fs::remove_dir_all(dir).ok();
    }
}
