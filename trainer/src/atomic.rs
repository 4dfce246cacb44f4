//! The one way the CLI writes a file: to a temporary name in the same directory, flushed and
//! synced, then renamed over the target. A kill or a full disk at any moment leaves either the
//! previous file or the new one, never a torn file, and a write error is returned with its
//! cause (nothing is dropped by a `Drop` impl that cannot report it).

use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result};

/// Write `bytes` to `path` atomically (creating the parent directory).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = written_temporary(path, bytes)?;
    tmp.persist(path).with_context(|| format!("renaming the temporary file to {}", path.display()))?;
    Ok(())
}

/// Like [`write_atomic`], and the file it replaces becomes `previous`. The new bytes are
/// written and synced first: a failed write (a full disk) leaves both files as they were, and
/// a kill between the two renames leaves `previous` complete.
pub fn write_atomic_keeping_previous(path: &Path, previous: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = written_temporary(path, bytes)?;
    if path.exists() {
        std::fs::rename(path, previous)
            .with_context(|| format!("keeping {} as {}", path.display(), previous.display()))?;
    }
    tmp.persist(path).with_context(|| format!("renaming the temporary file to {}", path.display()))?;
    Ok(())
}

/// `bytes` in a synced temporary file next to `path` (removed again if anything fails).
fn written_temporary(path: &Path, bytes: &[u8]) -> Result<tempfile::NamedTempFile> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut tmp = tempfile::Builder::new()
        .prefix(&format!(".{}.", path.file_name().and_then(|n| n.to_str()).unwrap_or("file")))
        .suffix(".tmp")
        .tempfile_in(dir)
        .with_context(|| format!("creating a temporary file in {}", dir.display()))?;
    tmp.write_all(bytes).with_context(|| format!("writing {}", path.display()))?;
    tmp.as_file().sync_all().with_context(|| format!("syncing {}", path.display()))?;
    Ok(tmp)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_the_file_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("sub/state.bin");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        let names: Vec<_> =
            std::fs::read_dir(dir.path().join("sub")).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, vec![std::ffi::OsString::from("state.bin")]);
    }

    #[test]
    fn keeping_the_previous_file() {
        let dir = tempfile::tempdir().unwrap();
        let (p, prev) = (dir.path().join("state"), dir.path().join("state.prev"));
        write_atomic_keeping_previous(&p, &prev, b"one").unwrap();
        assert!(!prev.exists(), "nothing to keep the first time");
        write_atomic_keeping_previous(&p, &prev, b"two").unwrap();
        assert_eq!((std::fs::read(&p).unwrap(), std::fs::read(&prev).unwrap()), (b"two".to_vec(), b"one".to_vec()));
        // The temporary cannot be created (the directory is a file): both files stay.
        let e = write_atomic_keeping_previous(&p.join("x"), &prev, b"three").unwrap_err();
        assert!(format!("{e:#}").contains("creating"), "{e:#}");
        assert_eq!((std::fs::read(&p).unwrap(), std::fs::read(&prev).unwrap()), (b"two".to_vec(), b"one".to_vec()));
    }

    #[test]
    fn a_failed_write_is_an_error_and_keeps_the_previous_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x");
        write_atomic(&p, b"old").unwrap();
        // The target is a non-empty directory: the rename fails, the error says where.
        let d = dir.path().join("d");
        std::fs::create_dir_all(d.join("inner")).unwrap();
        let e = write_atomic(&d, b"new").unwrap_err();
        assert!(format!("{e:#}").contains(&d.display().to_string()), "{e:#}");
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
    }
}
