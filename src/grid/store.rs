//! Where grid files live and how they are read and written: bounded reads, and an atomic
//! replace that keeps the old file as a backup.

use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use super::GridError;

/// Largest grid file read, bytes.
pub const MAX_FILE_BYTES: u64 = 64 << 20;

/// Where the grid of the device with id `device_id` (`DeviceSpec::device_id`) lives in
/// `state_dir`.
pub fn grid_path(state_dir: &Path, device_id: &str) -> PathBuf {
    state_dir.join(format!("{device_id}.toml"))
}

/// The text of the grid file at `path` (at most [`MAX_FILE_BYTES`]). Errors:
/// [`GridError::Missing`] when there is no file, [`GridError::TooLarge`], [`GridError::Read`].
pub(super) fn read_text(path: &Path) -> Result<String, GridError> {
    if !path.exists() {
        return Err(GridError::Missing {
            path: path.to_path_buf(),
        });
    }
    let read_error = |source| GridError::Read {
        path: path.to_path_buf(),
        source,
    };
    let size = fs::metadata(path).map_err(read_error)?.len();
    if size > MAX_FILE_BYTES {
        return Err(GridError::TooLarge {
            path: path.to_path_buf(),
            max: MAX_FILE_BYTES,
        });
    }
    fs::read_to_string(path).map_err(read_error)
}

/// The directory `path` is in, and its file name.
fn split(path: &Path) -> io::Result<(PathBuf, String)> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "not a file path"))?
        .to_string_lossy()
        .into_owned();
    Ok((dir, name))
}

/// Replace the file at `path` by `bytes` atomically: temporary file in the same directory, fsync,
/// rename over `path`, fsync of the directory. An existing file at `path` is first kept as
/// `<name>.bak`. On any error nothing at `path` has changed and the temporary file is removed.
pub(super) fn replace_atomically(path: &Path, bytes: &[u8]) -> Result<(), GridError> {
    let write_error = |source| GridError::Write {
        path: path.to_path_buf(),
        source,
    };
    let (dir, name) = split(path).map_err(write_error)?;
    let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
    let result = (|| {
        let mut file = File::create(&tmp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        drop(file);
        if path.exists() {
            let backup = dir.join(format!("{name}.bak"));
            fs::copy(path, &backup)?;
            File::open(&backup)?.sync_all()?;
        }
        fs::rename(&tmp, path)?;
        File::open(&dir)?.sync_all()
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result.map_err(write_error)
}

/// Check before a calibration that the directory of `path` exists (creating it) and takes a
/// file, so a long calibration does not end in an unwritable directory. Errors:
/// [`GridError::CreateDir`], [`GridError::Unwritable`].
pub fn check_writable(path: &Path) -> Result<(), GridError> {
    let (dir, _) = split(path).map_err(|source| GridError::CreateDir {
        dir: path.to_path_buf(),
        source,
    })?;
    fs::create_dir_all(&dir).map_err(|source| GridError::CreateDir {
        dir: dir.clone(),
        source,
    })?;
    let probe = dir.join(format!(".hgcd-probe-{}", std::process::id()));
    let written = fs::write(&probe, b"probe");
    let _ = fs::remove_file(&probe);
    written.map_err(|source| GridError::Unwritable { dir, source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_path_where_nothing_exists_is_a_missing_grid() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("dev.toml");
        assert!(matches!(
            read_text(&missing),
            Err(GridError::Missing { .. })
        ));
        // A state directory that does not exist yet holds no grid either.
        assert!(matches!(
            read_text(&dir.path().join("state/dev.toml")),
            Err(GridError::Missing { .. })
        ));
    }

    #[test]
    fn a_file_over_the_limit_is_refused_before_it_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        // Sparse: no disk space needed.
        File::create(&path)
            .unwrap()
            .set_len(MAX_FILE_BYTES + 1)
            .unwrap();
        assert!(matches!(read_text(&path), Err(GridError::TooLarge { .. })));
    }

    #[test]
    fn the_backup_holds_the_old_file_and_nothing_else_is_left() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        fs::write(&path, "old").unwrap();
        replace_atomically(&path, b"new").unwrap();
        assert_eq!(fs::read_to_string(&path).unwrap(), "new");
        let bak = dir.path().join("dev.toml.bak");
        assert_eq!(fs::read_to_string(&bak).unwrap(), "old");
        // The next save replaces the backup.
        replace_atomically(&path, b"newer").unwrap();
        assert_eq!(fs::read_to_string(&bak).unwrap(), "new");
        let mut names: Vec<_> = fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        names.sort();
        assert_eq!(names, ["dev.toml", "dev.toml.bak"]);
    }

    #[test]
    fn the_writable_check_creates_the_directory_and_leaves_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state/dev.toml");
        check_writable(&path).unwrap();
        assert_eq!(fs::read_dir(dir.path().join("state")).unwrap().count(), 0);
        let blocker = dir.path().join("file");
        fs::write(&blocker, "").unwrap();
        assert!(matches!(
            check_writable(&blocker.join("dev.toml")),
            Err(GridError::CreateDir { .. })
        ));
    }
}
