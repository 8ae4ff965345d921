//! Writers: binary PLY point clouds and triangle meshes, JSON, CSV tables (feature `csv`),
//! all written atomically.

use crate::error::{Error, Result};
use crate::io::render::TriangleMesh;
use crate::math::Vec3;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};

fn write_err(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Write { path: path.to_path_buf(), source }
}

/// The longest name [`check_name`] takes, in characters.
pub const MAX_NAME_CHARS: usize = 64;

/// Whether `name` may name the files diffluid writes (a scene's default output folder
/// `out/<name>`, a body's frames `bodies/<name>_NNNN.ply`, its ParaView series
/// `vtk/body_<name>.pvd`): 1 to [`MAX_NAME_CHARS`] characters, each a letter, a digit, `_`,
/// `-` or `.`, the first not a `.`. So no name holds a path separator, `..`, a drive, a NUL
/// or XML markup, and none can write outside the output folder. The error says what is
/// wrong, for a message that names the key.
pub fn check_name(name: &str) -> std::result::Result<(), String> {
    const RULE: &str = "a name is 1 to 64 letters, digits, '_', '-' or '.' (not first), \
                        because it names files";
    let count = name.chars().count();
    if count == 0 || count > MAX_NAME_CHARS {
        return Err(format!("{count} characters: {RULE}"));
    }
    if let Some(c) = name.chars().find(|c| !(c.is_alphanumeric() || matches!(c, '_' | '-' | '.'))) {
        return Err(format!("{:?} holds {c:?}: {RULE}", name));
    }
    if name.starts_with('.') {
        return Err(format!("{name:?} starts with '.': {RULE}"));
    }
    Ok(())
}

/// Every body name may name files ([`check_name`]) and none is given twice: what a run's
/// outputs need, since a body's frames, its rows and its ParaView series go by its name.
pub fn check_body_names<'a>(names: impl IntoIterator<Item = &'a str>) -> Result<()> {
    let mut seen = std::collections::HashSet::new();
    for name in names {
        let bad = |message: String| Error::InvalidSettings { key: "body name".into(), message };
        check_name(name).map_err(bad)?;
        if !seen.insert(name) {
            return Err(bad(format!(
                "two bodies are named {name:?}: their files and rows would mix (give each its own \
                 name)"
            )));
        }
    }
    Ok(())
}

/// `text` with the five characters XML gives a meaning (`& < > " '`) escaped, for an
/// attribute value or element text.
pub fn xml_escape(text: &str) -> std::borrow::Cow<'_, str> {
    if !text.contains(['&', '<', '>', '"', '\'']) {
        return std::borrow::Cow::Borrowed(text);
    }
    let mut out = String::with_capacity(text.len() + 16);
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            c => out.push(c),
        }
    }
    std::borrow::Cow::Owned(out)
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

/// Writes a triangle mesh as a binary little-endian PLY: `float x y z` per vertex and an
/// `element face` with `property list uchar int vertex_indices` (three per face), which
/// ParaView, Blender and MeshLab read. A triangle index past the vertices (or beyond what an
/// `int` holds) is an error and nothing is written.
pub fn write_ply_mesh(path: &Path, vertices: &[Vec3], triangles: &[[u32; 3]]) -> Result<()> {
    check_triangles(path, vertices.len(), triangles)?;
    let mut buf = Vec::with_capacity(256 + 12 * vertices.len() + 13 * triangles.len());
    write!(
        buf,
        "ply\nformat binary_little_endian 1.0\ncomment diffluid surface mesh\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nelement face {}\n\
         property list uchar int vertex_indices\nend_header\n",
        vertices.len(),
        triangles.len()
    )
    .expect("writing to memory");
    for p in vertices {
        for c in p.to_array() {
            buf.extend_from_slice(&(c as f32).to_le_bytes());
        }
    }
    for t in triangles {
        buf.push(3);
        for &i in t {
            buf.extend_from_slice(&(i as i32).to_le_bytes());
        }
    }
    write_atomic(path, &buf)
}

/// What a surface mesh asked of a build without the `surface` feature says.
pub const SURFACE_FEATURE_MISSING: &str =
    "needs diffluid built with the `surface` feature (a default feature)";

/// How a triangle mesh is written.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MeshFormat {
    /// Binary little-endian PLY ([`write_ply_mesh`]).
    #[default]
    Ply,
    /// Wavefront OBJ, text ([`write_obj_mesh`]).
    Obj,
}

impl MeshFormat {
    /// The file extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            MeshFormat::Ply => "ply",
            MeshFormat::Obj => "obj",
        }
    }

    /// Writes a mesh in this format.
    pub fn write(self, path: &Path, vertices: &[Vec3], triangles: &[[u32; 3]]) -> Result<()> {
        match self {
            MeshFormat::Ply => write_ply_mesh(path, vertices, triangles),
            MeshFormat::Obj => write_obj_mesh(path, vertices, triangles),
        }
    }
}

/// Writes a triangle mesh as a Wavefront OBJ (`v x y z` lines with every f64 digit that
/// reads back to the same value, then `f a b c` lines, 1-based). A triangle index past the
/// vertices is an error and nothing is written.
pub fn write_obj_mesh(path: &Path, vertices: &[Vec3], triangles: &[[u32; 3]]) -> Result<()> {
    check_triangles(path, vertices.len(), triangles)?;
    let mut buf = Vec::with_capacity(64 * vertices.len() + 32 * triangles.len());
    writeln!(
        buf,
        "# diffluid surface mesh: {} vertices, {} triangles",
        vertices.len(),
        triangles.len()
    )
    .expect("writing to memory");
    for p in vertices {
        writeln!(buf, "v {} {} {}", p.x, p.y, p.z).expect("writing to memory");
    }
    for t in triangles {
        writeln!(buf, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1).expect("writing to memory");
    }
    write_atomic(path, &buf)
}

/// Every triangle index below `count` (and within what an `i32` holds).
fn check_triangles(path: &Path, count: usize, triangles: &[[u32; 3]]) -> Result<()> {
    let limit = count.min(i32::MAX as usize);
    match triangles.iter().enumerate().find(|(_, t)| t.iter().any(|&i| i as usize >= limit)) {
        None => Ok(()),
        Some((n, t)) => Err(Error::Write {
            path: path.to_path_buf(),
            source: std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("triangle {n} {t:?} refers past the {count} vertices"),
            ),
        }),
    }
}

/// Reads a triangle mesh written by [`MeshFormat::write`], by the file's extension: a binary
/// little-endian PLY of `float x y z` vertices and `uchar`-counted `int` (or `uint`) index
/// lists of three, or an OBJ (through tobj, triangulated; a material library it names is not
/// opened). Only a regular file of at most [`MAX_INPUT_BYTES`](crate::math::input) is read.
pub fn read_mesh(path: &Path) -> Result<TriangleMesh> {
    let fail = |message: String| Error::Read { path: path.to_path_buf(), message };
    let ext = path.extension().and_then(|e| e.to_str());
    if !matches!(ext, Some("ply" | "obj")) {
        return Err(fail("not a .ply or .obj mesh".into()));
    }
    let bytes = crate::math::input::read_file(path).map_err(|e| fail(e.to_string()))?;
    if ext == Some("ply") {
        return read_ply_mesh(&bytes).map_err(fail);
    }
    let options = tobj::LoadOptions { triangulate: true, ..Default::default() };
    let (models, _) =
        tobj::load_obj_buf(&mut &*bytes, &options, |_| Err(tobj::LoadError::OpenFileFailed))
            .map_err(|e| fail(e.to_string()))?;
    let mut mesh = TriangleMesh::default();
    for m in models {
        let base = mesh.vertices.len();
        mesh.vertices.extend(m.mesh.positions.chunks_exact(3).map(|p| Vec3::new(p[0], p[1], p[2])));
        for t in m.mesh.indices.chunks_exact(3) {
            let tri = [0, 1, 2].map(|k| u32::try_from(base + t[k] as usize).ok());
            match tri {
                [Some(a), Some(b), Some(c)]
                    if [a, b, c].iter().all(|&i| (i as usize) < mesh.vertices.len()) =>
                {
                    mesh.triangles.push([a, b, c])
                }
                _ => return Err(fail(format!("face {t:?} refers past the vertices"))),
            }
        }
    }
    Ok(mesh)
}

/// The PLY reader of [`read_mesh`]; the error says what is not as written. The counts of
/// the header are checked against the data's length (in checked arithmetic: a count whose
/// size overflows is refused) before anything is allocated.
fn read_ply_mesh(bytes: &[u8]) -> std::result::Result<TriangleMesh, String> {
    const END: &[u8] = b"end_header\n";
    let at =
        bytes.windows(END.len()).position(|w| w == END).ok_or("not a PLY file (no end_header)")?
            + END.len();
    let header = std::str::from_utf8(&bytes[..at]).map_err(|_| "a PLY header that is not text")?;
    let mut lines = header.lines();
    if lines.next() != Some("ply") {
        return Err("not a PLY file".into());
    }
    let (mut vertices, mut faces, mut element) = (None, None, "");
    let mut vertex_props = Vec::new();
    let mut index_type = "";
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["format", f, _] if *f != "binary_little_endian" => {
                return Err(format!("PLY format {f}: only binary_little_endian is read"))
            }
            ["element", name, count] => {
                let count: usize = count.parse().map_err(|_| format!("bad count in '{line}'"))?;
                let seen = match *name {
                    "vertex" => vertices.replace(count),
                    "face" => faces.replace(count),
                    other => return Err(format!("unexpected PLY element '{other}'")),
                };
                if seen.is_some() {
                    return Err(format!("a second '{name}' element"));
                }
                element = name;
            }
            ["property", "float", name] if element == "vertex" => vertex_props.push(*name),
            ["property", "list", "uchar", t, "vertex_indices"] if element == "face" => {
                index_type = if *t == "int" || *t == "uint" {
                    t
                } else {
                    return Err(format!("face indices of type {t}"));
                }
            }
            ["property", ..] => return Err(format!("unexpected PLY property '{line}'")),
            _ => {}
        }
    }
    if vertex_props != ["x", "y", "z"] {
        return Err(format!("vertex properties {vertex_props:?}, not float x y z"));
    }
    let (nv, nf) = (vertices.ok_or("no vertex element")?, faces.unwrap_or(0));
    if nf > 0 && index_type.is_empty() {
        return Err("faces without vertex_indices".into());
    }
    let body = &bytes[at..];
    let vertex_bytes = nv.checked_mul(12);
    let expected = vertex_bytes.zip(nf.checked_mul(13)).and_then(|(v, f)| v.checked_add(f));
    let (Some(vertex_bytes), Some(expected)) = (vertex_bytes, expected) else {
        return Err(format!(
            "{nv} vertices and {nf} triangles: more than a file can hold ({} bytes of data)",
            body.len()
        ));
    };
    if body.len() != expected {
        return Err(format!(
            "{} bytes of data for {nv} vertices and {nf} triangles (expected {expected})",
            body.len()
        ));
    }
    let word = |b: &[u8], i: usize| -> [u8; 4] { b[4 * i..4 * i + 4].try_into().expect("4 bytes") };
    let vertices: Vec<Vec3> = body[..vertex_bytes]
        .chunks_exact(12)
        .map(|b| {
            Vec3::new(
                f32::from_le_bytes(word(b, 0)) as f64,
                f32::from_le_bytes(word(b, 1)) as f64,
                f32::from_le_bytes(word(b, 2)) as f64,
            )
        })
        .collect();
    let mut triangles = Vec::with_capacity(nf);
    for (n, f) in body[vertex_bytes..].chunks_exact(13).enumerate() {
        if f[0] != 3 {
            return Err(format!("face {n} has {} vertices, not 3", f[0]));
        }
        let t = [0, 1, 2].map(|k| u32::from_le_bytes(word(&f[1..], k)));
        if t.iter().any(|&i| i as usize >= nv) {
            return Err(format!("face {n} {t:?} refers past the {nv} vertices"));
        }
        triangles.push(t);
    }
    Ok(TriangleMesh { vertices, triangles })
}

/// Writes a value as pretty JSON.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_vec_pretty(value).expect("serialisable");
    write_atomic(path, &text)
}

/// Writes `rows` as a CSV table with a header (the field names), atomically.
#[cfg(feature = "csv")]
pub fn write_csv<T: Serialize>(path: &Path, rows: &[T]) -> Result<()> {
    let fail = |e: csv::Error| Error::Write {
        path: path.to_path_buf(),
        source: std::io::Error::other(e.to_string()),
    };
    let mut w = csv::Writer::from_writer(Vec::new());
    for r in rows {
        w.serialize(r).map_err(fail)?;
    }
    let bytes = w.into_inner().map_err(|e| fail(e.into_error().into()))?;
    write_atomic(path, &bytes)
}

/// Writes a file through a temporary and a rename, so a reader never sees half a file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via_rename(path, bytes, false)
}

/// [`write_atomic`] for what must survive a power loss (checkpoints): the temporary is
/// flushed to the disk (fsync) before the rename and the folder after it, so the old file or
/// the new one is there afterwards, never an empty one.
pub fn write_durable(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via_rename(path, bytes, true)
}

fn write_via_rename(path: &Path, bytes: &[u8], sync: bool) -> Result<()> {
    let (dir, tmp) = temporary_beside(path, "tmp")?;
    let mut f = tmp.as_file();
    f.write_all(bytes).map_err(write_err(tmp.path()))?;
    if sync {
        f.sync_all().map_err(write_err(tmp.path()))?;
    }
    tmp.persist(path).map_err(|e| Error::Write { path: path.to_path_buf(), source: e.error })?;
    if sync {
        // The rename lives in the folder's entries: flush them too (where the platform lets
        // a folder be opened).
        if let Ok(d) = std::fs::File::open(&dir) {
            d.sync_all().ok();
        }
    }
    Ok(())
}

/// Writes `path` through `write`, which is handed a temporary path in the same folder with
/// the same extension (for writers that take a path and pick the format by its extension,
/// as plotters does for PNG and GIF), then renames the temporary over `path`. When `write`
/// fails, `path` is left as it was and the temporary is removed.
pub fn write_through(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("tmp");
    let (_, tmp) = temporary_beside(path, ext)?;
    write(tmp.path())?;
    tmp.persist(path).map_err(|e| Error::Write { path: path.to_path_buf(), source: e.error })?;
    Ok(())
}

/// The prefix of every temporary diffluid writes (`.tmp-<file name>-<random>.<ext>`), so
/// that what a killed writer left behind can be told apart and cleared.
pub const TEMPORARY_PREFIX: &str = ".tmp-";

/// A new, uniquely named empty file in `path`'s folder (made if missing), removed when
/// dropped unless persisted; and the folder.
fn temporary_beside(path: &Path, ext: &str) -> Result<(PathBuf, tempfile::NamedTempFile)> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).map_err(write_err(&dir))?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let (prefix, suffix) = (format!("{TEMPORARY_PREFIX}{name}-"), format!(".{ext}"));
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix).suffix(&suffix);
    // The file's mode as `File::create` gives it (tempfile's default is owner-only).
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let tmp = builder.tempfile_in(&dir).map_err(write_err(&dir))?;
    Ok((dir, tmp))
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
        assert_eq!(f32::from_le_bytes(bytes[pos + 4..pos + 8].try_into().unwrap()), 2.0);
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn ply_mesh_has_counts_in_header_and_thirteen_bytes_per_face() {
        let dir = std::env::temp_dir().join(format!("diffluid-plymesh-{}", std::process::id()));
        let path = dir.join("m.ply");
        let vertices = [Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(0.0, 0.0, 2.5)];
        let triangles = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        write_ply_mesh(&path, &vertices, &triangles).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let end = b"end_header\n";
        let pos = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        let header = std::str::from_utf8(&bytes[..pos]).unwrap();
        let count = |element: &str| -> usize {
            header
                .lines()
                .find_map(|l| l.strip_prefix(&format!("element {element} ")))
                .unwrap()
                .parse()
                .unwrap()
        };
        let (nv, nf) = (count("vertex"), count("face"));
        assert_eq!((nv, nf), (4, 4));
        assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"));
        assert!(header.contains("property list uchar int vertex_indices\n"));
        assert_eq!(bytes.len() - pos, 12 * nv + 13 * nf);
        let body = &bytes[pos..];
        let f32_at = |o: usize| f32::from_le_bytes(body[o..o + 4].try_into().unwrap());
        assert_eq!(f32_at(3 * 12 + 8), 2.5);
        let face = &body[12 * nv + 13..12 * nv + 26];
        assert_eq!(face[0], 3);
        let idx: Vec<i32> =
            face[1..].chunks_exact(4).map(|c| i32::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(idx, [0, 1, 3]);
        assert!(write_ply_mesh(&dir.join("bad.ply"), &vertices, &[[0, 1, 4]]).is_err());
        assert!(!dir.join("bad.ply").exists());
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn meshes_read_back_as_written() {
        let dir = std::env::temp_dir().join(format!("diffluid-meshio-{}", std::process::id()));
        let vertices = vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(0.1, 0.2, 2.5)];
        let triangles = vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        for format in [MeshFormat::Ply, MeshFormat::Obj] {
            let path = dir.join(format!("m.{}", format.extension()));
            format.write(&path, &vertices, &triangles).unwrap();
            let m = read_mesh(&path).unwrap();
            // The same triangles corner by corner (tobj numbers the vertices by first use);
            // PLY holds f32, OBJ every digit.
            let tol = if format == MeshFormat::Ply { 1e-7 } else { 0.0 };
            assert_eq!(m.triangles.len(), triangles.len());
            for (s, t) in m.triangles.iter().zip(&triangles) {
                for k in 0..3 {
                    let (a, b) = (m.vertices[s[k] as usize], vertices[t[k] as usize]);
                    assert!((a - b).abs().max_element() <= tol, "{format:?}: {a} against {b}");
                }
            }
        }
        // A truncated PLY, a text file and an unknown extension are errors naming the file.
        let ply = std::fs::read(dir.join("m.ply")).unwrap();
        write_atomic(&dir.join("cut.ply"), &ply[..ply.len() - 5]).unwrap();
        let e = read_mesh(&dir.join("cut.ply")).unwrap_err().to_string();
        assert!(e.contains("cut.ply") && e.contains("bytes of data"), "{e}");
        write_atomic(&dir.join("text.ply"), b"hello").unwrap();
        assert!(read_mesh(&dir.join("text.ply")).unwrap_err().to_string().contains("not a PLY"));
        assert!(read_mesh(&dir.join("m.stl")).is_err());
        std::fs::remove_dir_all(dir).ok();
    }

    /// Two writers of one file (two runs into one folder, a checkpoint and its reader) each
    /// write through a temporary of their own: every write succeeds, a reader sees one whole
    /// version or the other, and no temporary is left. With one temporary name per file
    /// (`x.tmp`), one writer's rename took the other's half-written file or found it gone.
    /// Files with the same stem (`a.json`, `a.csv`) shared that name too.
    #[test]
    fn concurrent_writers_of_one_file_never_mix() {
        let dir = std::env::temp_dir().join(format!("diffluid-concurrent-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.json");
        let versions: Vec<Vec<u8>> = (0..2u8).map(|k| vec![b'a' + k; 200_000]).collect();
        std::thread::scope(|s| {
            for v in &versions {
                let path = &path;
                s.spawn(move || {
                    for _ in 0..200 {
                        write_atomic(path, v).unwrap();
                    }
                });
            }
            s.spawn(|| {
                for _ in 0..200 {
                    write_atomic(&dir.join("a.csv"), b"x,y\n").unwrap();
                    if let Ok(b) = std::fs::read(&path) {
                        assert!(versions.contains(&b), "a torn file of {} bytes", b.len());
                    }
                }
            });
        });
        let mut left: Vec<_> =
            std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
        left.sort();
        assert_eq!(left, ["a.csv", "a.json"], "temporaries left behind");
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A writer that fails leaves the file as it was and removes its temporary.
    #[test]
    fn a_failed_write_through_keeps_the_file() {
        let dir = std::env::temp_dir().join(format!("diffluid-through-{}", std::process::id()));
        let path = dir.join("p.png");
        write_atomic(&path, b"old").unwrap();
        let failed = write_through(&path, |tmp| {
            assert_eq!(tmp.parent(), Some(dir.as_path()));
            assert_eq!(tmp.extension().and_then(|e| e.to_str()), Some("png"));
            std::fs::write(tmp, b"half").unwrap();
            Err(Error::Write { path: tmp.to_path_buf(), source: std::io::Error::other("no") })
        });
        assert!(failed.is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "the temporary was left");
        write_through(&path, |tmp| write_atomic(tmp, b"new")).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).ok();
    }
}
