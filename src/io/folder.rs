//! The folder a run writes into (feature `csv`): locked, so that two runs never write into
//! one at once, and cleared of what an earlier run wrote there, so that frames of two runs
//! never mix (a 20-step run into the folder of a 25-step run left frames 21 to 25, and
//! `render` drew them as the end of the new run).
//!
//! A run owns the files it writes: `summary.json`, `bodies.csv`, `particles/NNNN.ply`,
//! `bodies/<name>_NNNN.ply`, `surface/NNNN.ply|obj`, `vtk/*.vtp|vti|pvd`, what `render`
//! draws (`render.gif`, `render_NNNN.png`), the temporaries of a write that was killed
//! (`.tmp-*`) and the lock `.diffluid-run.lock`. A folder that holds nothing else is taken and
//! cleared of them; a folder with other files in it is refused unless forced, and then only
//! the run's own files go.

use crate::error::{Error, Result};
use crate::io::output::TEMPORARY_PREFIX;
use std::fs::File;
use std::path::{Path, PathBuf};

/// The lock file a run holds in its folder while it writes. It stays when the run ends (a
/// lock file removed while another process opens it would let a third lock a new one).
pub const LOCK_FILE: &str = ".diffluid-run.lock";

/// A run's output folder, locked until this is dropped (or the process ends, however it
/// ends: the lock is the operating system's).
#[derive(Debug)]
pub struct RunFolder {
    path: PathBuf,
    /// Holds the lock.
    _lock: File,
}

impl RunFolder {
    /// Takes `path` for a run: creates it if needed, locks it (an error if another run holds
    /// it), and clears the files an earlier run wrote. A folder holding files no run writes
    /// is refused unless `force`; with `force` those files are kept.
    pub fn claim(path: &Path, force: bool) -> Result<RunFolder> {
        let fail = |message: String| Error::Write {
            path: path.to_path_buf(),
            source: std::io::Error::other(message),
        };
        let io_fail = |source| Error::Write { path: path.to_path_buf(), source };
        let (lock, created) = RunFolder::lock_file(path)?;
        let lock_path = path.join(LOCK_FILE);
        let mut foreign = Vec::new();
        let mut owned = Vec::new();
        sort_entries(path, &mut owned, &mut foreign).map_err(io_fail)?;
        if !foreign.is_empty() && !force {
            if created {
                std::fs::remove_file(&lock_path).ok();
            }
            foreign.sort();
            let shown: Vec<String> =
                foreign.iter().take(3).map(|p| p.display().to_string()).collect();
            let more = if foreign.len() > 3 { ", ..." } else { "" };
            return Err(fail(format!(
                "it holds files a run does not write ({}{more}): give a new or empty folder, or \
                 --force to write into it anyway (a run's own files are cleared, the others kept)",
                shown.join(", ")
            )));
        }
        for p in &owned {
            std::fs::remove_file(p).map_err(|source| Error::Write { path: p.clone(), source })?;
        }
        // The run's folders that are empty now go too (the run makes the ones it writes).
        for sub in RUN_FOLDERS {
            std::fs::remove_dir(path.join(sub)).ok();
        }
        Ok(RunFolder { path: path.to_path_buf(), _lock: lock })
    }

    /// Locks `path` (made if needed) and clears nothing: for a command whose folder holds
    /// what it resumes from (`optimize`'s checkpoint) and whose files have fixed names.
    pub fn lock(path: &Path) -> Result<RunFolder> {
        let (lock, _) = RunFolder::lock_file(path)?;
        Ok(RunFolder { path: path.to_path_buf(), _lock: lock })
    }

    /// The folder made, and its lock file opened (made, when the bool says so) and locked.
    fn lock_file(path: &Path) -> Result<(File, bool)> {
        let io_fail = |source| Error::Write { path: path.to_path_buf(), source };
        std::fs::create_dir_all(path).map_err(io_fail)?;
        let lock_path = path.join(LOCK_FILE);
        let (lock, created) =
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&lock_path) {
                Ok(f) => (f, true),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let f = std::fs::OpenOptions::new().write(true).open(&lock_path);
                    (f.map_err(io_fail)?, false)
                }
                Err(e) => return Err(io_fail(e)),
            };
        // Called through the trait: std's `File::try_lock` (Rust 1.89) is newer than the
        // crate's minimum Rust.
        match fs4::FileExt::try_lock(&lock) {
            Ok(()) => Ok((lock, created)),
            Err(fs4::TryLockError::WouldBlock) => Err(Error::Write {
                path: path.to_path_buf(),
                source: std::io::Error::other(format!(
                    "another diffluid command is writing into it (it holds {})",
                    lock_path.display()
                )),
            }),
            Err(fs4::TryLockError::Error(e)) => Err(io_fail(e)),
        }
    }

    /// The folder.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// The folders a run writes into its output folder.
const RUN_FOLDERS: [&str; 4] = ["particles", "bodies", "surface", "vtk"];

/// Whether `name`, a file directly in the output folder (`folder` None) or in one of
/// [`RUN_FOLDERS`], is one a run writes.
fn run_writes(folder: Option<&str>, name: &str) -> bool {
    let frame = |stem: &str| !stem.is_empty() && stem.bytes().all(|b| b.is_ascii_digit());
    if name.starts_with(TEMPORARY_PREFIX) {
        return true;
    }
    let (stem, ext) = name.rsplit_once('.').unwrap_or((name, ""));
    match folder {
        None => {
            matches!(name, "summary.json" | "bodies.csv" | "render.gif" | LOCK_FILE)
                || (ext == "png" && stem.strip_prefix("render_").is_some_and(frame))
        }
        Some("particles") => ext == "ply" && frame(stem),
        Some("bodies") => ext == "ply" && stem.rsplit_once('_').is_some_and(|(_, n)| frame(n)),
        Some("surface") => (ext == "ply" || ext == "obj") && frame(stem),
        Some("vtk") => matches!(ext, "vtp" | "vti" | "pvd"),
        Some(_) => false,
    }
}

/// Sorts the entries of the output folder `dir` into the files a run writes (to clear;
/// the lock file left out) and the others.
fn sort_entries(
    dir: &Path,
    owned: &mut Vec<PathBuf>,
    foreign: &mut Vec<PathBuf>,
) -> std::io::Result<()> {
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let kind = entry.file_type()?;
        if kind.is_dir() && RUN_FOLDERS.contains(&name.as_str()) {
            for inner in std::fs::read_dir(entry.path())? {
                let inner = inner?;
                let file = inner.file_name().to_string_lossy().into_owned();
                if inner.file_type()?.is_file() && run_writes(Some(&name), &file) {
                    owned.push(inner.path());
                } else {
                    foreign.push(inner.path());
                }
            }
        } else if kind.is_file() && run_writes(None, &name) {
            if name != LOCK_FILE {
                owned.push(entry.path());
            }
        } else {
            foreign.push(entry.path());
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_owns_its_frames_and_nothing_else() {
        for (folder, name) in [
            (None, "summary.json"),
            (None, "render_0012.png"),
            (None, ".tmp-summary.json-abc123.tmp"),
            (Some("particles"), "0003.ply"),
            (Some("particles"), "12345.ply"),
            (Some("bodies"), "my_ball_0003.ply"),
            (Some("surface"), "0003.obj"),
            (Some("vtk"), "body_b.pvd"),
        ] {
            assert!(run_writes(folder, name), "{folder:?} {name}");
        }
        for (folder, name) in [
            (None, "notes.txt"),
            (None, "result.json"),
            (None, "render_x.png"),
            (Some("particles"), "a.ply"),
            (Some("bodies"), "ball.ply"),
            (Some("surface"), "0003.stl"),
            (Some("vtk"), "readme"),
            (Some("other"), "0001.ply"),
        ] {
            assert!(!run_writes(folder, name), "{folder:?} {name}");
        }
    }
}
