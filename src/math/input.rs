//! Bounded reads of the files diffluid is given: scene files, OBJ meshes, checkpoints, a
//! run's summary and frames. Only a regular file is read (a FIFO would block for ever, a
//! device such as `/dev/zero` never ends), and never more than [`MAX_INPUT_BYTES`].
//!
//! The file is opened non-blocking where the platform allows it (Linux with glibc), so that
//! opening a FIFO with no writer returns at once, and the kind of file is checked on the
//! open handle, so a file swapped for another between a look and the read cannot slip past.

use std::fs::File;
use std::io::{self, Read};
use std::path::Path;

/// The largest file diffluid reads: 1 GiB. An OBJ mesh of this size holds about 20 million
/// triangles, a scene file or checkpoint is kilobytes; a larger file is refused before it
/// is read.
pub const MAX_INPUT_BYTES: u64 = 1 << 30;

/// The contents of the regular file at `path` (symbolic links followed), at most
/// [`MAX_INPUT_BYTES`]. Errors: those of opening and reading, a path that is not a regular
/// file (kind [`io::ErrorKind::InvalidInput`], the message names what it is), and a file
/// larger than the limit (kind [`io::ErrorKind::FileTooLarge`]).
pub fn read_file(path: &Path) -> io::Result<Vec<u8>> {
    read_file_limited(path, MAX_INPUT_BYTES)
}

/// [`read_file`] as UTF-8 text (kind [`io::ErrorKind::InvalidData`] when it is not).
pub fn read_text(path: &Path) -> io::Result<String> {
    String::from_utf8(read_file(path)?)
        .map_err(|_| io::Error::new(io::ErrorKind::InvalidData, "not UTF-8 text"))
}

/// [`read_file`] with another limit.
pub fn read_file_limited(path: &Path, limit: u64) -> io::Result<Vec<u8>> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file: File = options.open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("not a regular file ({})", kind(&meta.file_type())),
        ));
    }
    let too_large = |size: u64| {
        io::Error::new(
            io::ErrorKind::FileTooLarge,
            format!("{size} bytes, more than the {limit} bytes diffluid reads from a file"),
        )
    };
    if meta.len() > limit {
        return Err(too_large(meta.len()));
    }
    // The length may change while the file is read: read one byte past the limit at most.
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(limit + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// What a file that is not a regular file is, in words.
fn kind(t: &std::fs::FileType) -> &'static str {
    if t.is_dir() {
        return "a folder";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "a FIFO";
        }
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    "not a file"
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regular_files_are_read_and_others_refused() {
        let dir = std::env::temp_dir().join(format!("diffluid-input-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("a.txt");
        std::fs::write(&file, "0123456789").unwrap();
        assert_eq!(read_text(&file).unwrap(), "0123456789");
        assert_eq!(read_file_limited(&file, 10).unwrap().len(), 10);
        let e = read_file_limited(&file, 9).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::FileTooLarge);
        assert!(e.to_string().contains("10 bytes"), "{e}");
        let e = read_file(&dir).unwrap_err();
        assert!(e.to_string().contains("not a regular file (a folder)"), "{e}");
        #[cfg(unix)]
        {
            let e = read_file(Path::new("/dev/zero")).unwrap_err();
            assert_eq!(e.to_string(), "not a regular file (a character device)");
        }
        std::fs::write(&file, [0xff, 0xfe]).unwrap();
        assert_eq!(read_text(&file).unwrap_err().kind(), io::ErrorKind::InvalidData);
        std::fs::remove_dir_all(&dir).ok();
    }
}
