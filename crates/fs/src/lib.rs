//! Crash-consistent file output: [`write_atomic`] writes into a temporary file beside the
//! target, syncs it and renames it over the target, so a reader never sees a half-written
//! file and a failed write leaves the old one in place. A leaf crate: every deform crate
//! that writes files uses it. [`lock_folder`] gives one run at a time an output folder, and
//! [`npy`] reads and writes the `.npy` arrays of datasets and coefficient fields.
//!
//! ```
//! let dir = tempfile::tempdir().unwrap();
//! let path = dir.path().join("report.md");
//! deform_fs::write_atomic(&path, |w| w.write_all(b"# results\n")).unwrap();
//! assert_eq!(std::fs::read_to_string(&path).unwrap(), "# results\n");
//! ```

pub mod npy;

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// `relative` resolved against `dir` (an absolute `relative` stands alone), with `.`
/// components dropped and each `name/..` pair removed, as users read paths: the runner
/// printed `xtask/../assets/experiments/../scenes/beam.ron` for `assets/scenes/beam.ron`.
/// Lexical, like cargo's own paths: a symbolic link followed by `..` is not resolved.
///
/// ```
/// use std::path::Path;
/// let p = deform_fs::join_clean(Path::new("xtask/../assets/experiments"), Path::new("../scenes/a.ron"));
/// assert_eq!(p, Path::new("assets/scenes/a.ron"));
/// ```
pub fn join_clean(dir: &Path, relative: &Path) -> PathBuf {
    use std::path::Component;
    let mut out = PathBuf::new();
    for c in dir.join(relative).components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir
                if matches!(out.components().next_back(), Some(Component::Normal(_))) =>
            {
                out.pop();
            }
            other => out.push(other),
        }
    }
    if out.as_os_str().is_empty() {
        out.push(".");
    }
    out
}

/// A file that could not be written.
#[derive(Debug, thiserror::Error)]
#[error("{}: {error}", path.display())]
pub struct WriteError {
    /// The target file.
    pub path: PathBuf,
    /// The OS error (shown in the message, so not chained as a source).
    pub error: std::io::Error,
}

/// Writes `path` atomically: `body` writes into a buffered temporary file beside it,
/// which is synced and renamed over `path` only if everything succeeded.
///
/// # Errors
/// [`WriteError`] naming `path`; the temporary file is removed.
pub fn write_atomic(
    path: &Path,
    body: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), WriteError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
    let result = (|| {
        let file = fs::File::create(&tmp)?;
        let mut w = BufWriter::new(file);
        body(&mut w)?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result.map_err(|error| WriteError {
        path: path.to_owned(),
        error,
    })
}

/// An exclusive lock on an output folder, held until dropped. The operating system
/// releases it when the process ends, so a killed run leaves no stale lock.
#[derive(Debug)]
pub struct FolderLock {
    _file: fs::File,
}

/// A folder that could not be locked.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Another run holds the lock.
    #[error("{}: another run is writing into this folder; wait for it to finish or choose another folder", dir.display())]
    Busy {
        /// The folder.
        dir: PathBuf,
    },
    /// The folder or its lock file could not be created.
    #[error("{}: {error}", path.display())]
    Io {
        /// The folder or lock file.
        path: PathBuf,
        /// The OS error.
        error: std::io::Error,
    },
}

/// Creates `dir` if needed and locks it for one run: a second run into the same folder,
/// from this process or another, gets [`LockError::Busy`] instead of mixing its files
/// with the first's. The lock is the hidden file `.deform.lock` in `dir`.
///
/// # Errors
/// [`LockError`].
pub fn lock_folder(dir: &Path) -> Result<FolderLock, LockError> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |error| LockError::Io { path, error }
    };
    fs::create_dir_all(dir).map_err(io(dir))?;
    let path = dir.join(".deform.lock");
    let file = fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(io(&path))?;
    match file.try_lock() {
        Ok(()) => Ok(FolderLock { _file: file }),
        Err(fs::TryLockError::WouldBlock) => Err(LockError::Busy {
            dir: dir.to_owned(),
        }),
        Err(fs::TryLockError::Error(error)) => Err(LockError::Io { path, error }),
    }
}

/// Starts a run in `dir` by removing what an earlier run left there: every entry whose name
/// `ours(name, is_dir)` claims (directories with their contents), and the stale temporaries
/// of killed atomic writes (`.NAME.tmpPID`). Other files are left alone. Take
/// [`lock_folder`] first, so no running writer is cleared away.
///
/// # Errors
/// [`WriteError`] naming the entry that could not be removed.
pub fn clear_previous_run(dir: &Path, ours: impl Fn(&str, bool) -> bool) -> Result<(), WriteError> {
    let fail = |path: &Path| {
        let path = path.to_owned();
        move |error| WriteError { path, error }
    };
    for entry in fs::read_dir(dir).map_err(fail(dir))?.flatten() {
        let (name, path) = (
            entry.file_name().to_string_lossy().into_owned(),
            entry.path(),
        );
        let is_dir = path.is_dir();
        let temporary = !is_dir && name.starts_with('.') && name.contains(".tmp");
        if temporary || (ours(&name, is_dir) && name != ".deform.lock") {
            let removed = if is_dir {
                fs::remove_dir_all(&path)
            } else {
                fs::remove_file(&path)
            };
            removed.map_err(fail(&path))?;
        }
    }
    Ok(())
}

/// Writes `text` to `path` atomically.
///
/// # Errors
/// As [`write_atomic`].
pub fn write_text(path: &Path, text: &str) -> Result<(), WriteError> {
    write_atomic(path, |w| w.write_all(text.as_bytes()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clearing_removes_what_the_predicate_claims_and_stale_temporaries_only() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for f in ["old.csv", "notes.txt", ".old.csv.tmp123"] {
            std::fs::write(d.join(f), "x").unwrap();
        }
        std::fs::create_dir_all(d.join("frames/base")).unwrap();
        std::fs::write(d.join("frames/base/a.vtu"), "x").unwrap();
        let _lock = lock_folder(d).unwrap();
        clear_previous_run(d, |name, is_dir| {
            name.ends_with(".csv") || (is_dir && name == "frames")
        })
        .unwrap();
        let mut left: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        assert_eq!(left, [".deform.lock", "notes.txt"]);
    }

    #[test]
    fn a_locked_folder_refuses_a_second_run_until_the_first_ends() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("run");
        let first = lock_folder(&out).unwrap();
        let e = lock_folder(&out).unwrap_err();
        assert!(matches!(&e, LockError::Busy { dir } if *dir == out), "{e}");
        assert!(e.to_string().contains("another run"), "{e}");
        drop(first);
        lock_folder(&out).unwrap();
    }

    #[test]
    fn a_failed_write_keeps_the_old_file_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.txt");
        write_text(&path, "old").unwrap();
        let err = write_atomic(&path, |w| {
            w.write_all(b"half")?;
            Err(std::io::Error::other("disk full"))
        })
        .unwrap_err();
        assert!(err.to_string().contains("a.txt") && err.to_string().contains("disk full"));
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_missing_folder_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no/such/dir/a.txt");
        let err = write_text(&path, "x").unwrap_err();
        assert_eq!(err.path, path);
    }
}
