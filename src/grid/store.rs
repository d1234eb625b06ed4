//! Where grid files live and how they are read and written.
//!
//! Reading opens regular files only (a symbolic link to one is followed), without blocking and
//! bounded: a FIFO, a device, a directory or a dangling link where a grid should be is an error
//! with one line saying so, never a hang or an unbounded read. "No grid" means nothing at all
//! exists at the path.
//!
//! Writing never leaves a partial or empty file: the new text goes to a temporary file that is
//! fsynced before anything else changes; the backup of the old grid is a hard link (no data space
//! needed) renamed into place; then the new file is renamed over the old one.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

use super::GridError;

/// Largest grid file read, bytes.
pub const MAX_FILE_BYTES: u64 = 64 << 20;

/// Where the grid of the device with id `device_id` (`DeviceSpec::device_id`) lives in
/// `state_dir`.
pub fn grid_path(state_dir: &Path, device_id: &str) -> PathBuf {
    state_dir.join(format!("{device_id}.toml"))
}

/// The text of the grid file at `path`. Errors: [`GridError::Missing`] when nothing exists there;
/// [`GridError::NotRegular`], [`GridError::DanglingLink`], [`GridError::TooLarge`],
/// [`GridError::Read`] (including a path that cannot be searched), [`GridError::Syntax`] for text
/// that is not UTF-8.
pub(super) fn read_regular(path: &Path) -> Result<String, GridError> {
    let read_error = |source| GridError::Read {
        path: path.to_path_buf(),
        source,
    };
    let link = match fs::symlink_metadata(path) {
        Ok(meta) => meta,
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            return Err(GridError::Missing {
                path: path.to_path_buf(),
            })
        }
        Err(e) => return Err(read_error(e)),
    };
    // What the path leads to, before opening it: opening a device or a FIFO can block or act.
    let target = match fs::metadata(path) {
        Ok(meta) => meta,
        Err(e) if link.file_type().is_symlink() && e.kind() == io::ErrorKind::NotFound => {
            return Err(GridError::DanglingLink {
                path: path.to_path_buf(),
                target: fs::read_link(path).unwrap_or_default(),
            })
        }
        Err(e) => return Err(read_error(e)),
    };
    not_regular(path, &target)?;
    // O_NONBLOCK: should the path be swapped for a FIFO between the check and the open, the open
    // does not wait for a writer; the type is then checked again on the open descriptor.
    let file = OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(path)
        .map_err(read_error)?;
    let meta = file.metadata().map_err(read_error)?;
    not_regular(path, &meta)?;
    let too_large = || GridError::TooLarge {
        path: path.to_path_buf(),
        max: MAX_FILE_BYTES,
    };
    if meta.len() > MAX_FILE_BYTES {
        return Err(too_large());
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(MAX_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(read_error)?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(too_large());
    }
    String::from_utf8(bytes).map_err(|e| GridError::Syntax {
        path: path.to_path_buf(),
        message: format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to()),
    })
}

fn not_regular(path: &Path, meta: &fs::Metadata) -> Result<(), GridError> {
    let t = meta.file_type();
    let kind = if t.is_file() {
        return Ok(());
    } else if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "of an unknown type"
    };
    Err(GridError::NotRegular {
        path: path.to_path_buf(),
        kind,
    })
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

/// Replace the file at `path` by `bytes` atomically, keeping the old file as `<name>.bak`:
/// 1. write `.<name>.tmp<pid>` in the same directory and fsync it: a full disk, a quota or a file
///    size limit fails here, before anything else has changed;
/// 2. if a file is at `path`, hard-link it as `.<name>.bak.tmp<pid>` (a copy where the file system
///    or the kernel's link protection refuses links) and rename that over `<name>.bak`;
/// 3. rename the temporary file over `path` and fsync the directory.
///
/// On any error the temporary files are removed and `path` and `<name>.bak` are as they were.
pub(super) fn replace_atomically(path: &Path, bytes: &[u8]) -> Result<(), GridError> {
    let write_error = |source| GridError::Write {
        path: path.to_path_buf(),
        source,
    };
    let (dir, name) = split(path).map_err(write_error)?;
    let pid = std::process::id();
    let tmp = dir.join(format!(".{name}.tmp{pid}"));
    let bak_tmp = dir.join(format!(".{name}.bak.tmp{pid}"));
    let result = (|| {
        let mut file = File::create(&tmp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        drop(file);
        let old = fs::symlink_metadata(path).ok();
        if old.is_some_and(|m| m.is_file() || m.file_type().is_symlink()) {
            let _ = fs::remove_file(&bak_tmp);
            if fs::hard_link(path, &bak_tmp).is_err() {
                copy_synced(path, &bak_tmp)?;
            }
            fs::rename(&bak_tmp, dir.join(format!("{name}.bak")))?;
        }
        fs::rename(&tmp, path)?;
        File::open(&dir)?.sync_all()
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
        let _ = fs::remove_file(&bak_tmp);
    }
    result.map_err(write_error)
}

/// Put the file kept as `<name>.bak` back at `path`, byte for byte, atomically, keeping the file
/// it replaces as `<name>.bak` in its turn. Errors: those of reading the backup
/// ([`GridError::Missing`] where none is kept) and of `replace_atomically`.
pub fn restore_backup(path: &Path) -> Result<(), GridError> {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".bak");
    let text = read_regular(&path.with_file_name(name))?;
    replace_atomically(path, text.as_bytes())
}

fn copy_synced(from: &Path, to: &Path) -> io::Result<()> {
    let mut source = File::open(from)?;
    let mut copy = File::create(to)?;
    io::copy(&mut source, &mut copy)?;
    copy.sync_all()
}

/// Check before a calibration that the directory of `path` exists (creating it) and takes a file
/// of `bytes` bytes: a probe of that size is written, fsynced and removed, so a full disk, a quota
/// or a file size limit fails now rather than after the calibration. Errors:
/// [`GridError::CreateDir`], [`GridError::NoRoom`].
pub fn check_room(path: &Path, bytes: u64) -> Result<(), GridError> {
    let (dir, name) = split(path).map_err(|source| GridError::CreateDir {
        dir: path.to_path_buf(),
        source,
    })?;
    fs::create_dir_all(&dir).map_err(|source| GridError::CreateDir {
        dir: dir.clone(),
        source,
    })?;
    let probe = dir.join(format!(".{name}.probe{}", std::process::id()));
    let result = (|| {
        let mut file = File::create(&probe)?;
        // Text-like bytes that do not compress to nothing on a compressing file system.
        let mut chunk = [0u8; 64 << 10];
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for b in chunk.iter_mut() {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            *b = b'0' + (state % 10) as u8;
        }
        let mut left = bytes;
        while left > 0 {
            let n = left.min(chunk.len() as u64) as usize;
            file.write_all(&chunk[..n])?;
            left -= n as u64;
        }
        file.sync_all()
    })();
    let _ = fs::remove_file(&probe);
    result.map_err(|source| GridError::NoRoom { dir, bytes, source })
}

/// The integration tests' file size limit, for the child of a unit test below.
#[cfg(test)]
#[path = "../../tests/common/file_size.rs"]
mod file_size;

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::{symlink, MetadataExt, PermissionsExt};
    use std::time::Duration;

    use super::file_size::limit_file_size;
    use crate::grid::lattice::tests::sample;
    use crate::grid::GridFile;

    /// `read_regular` on another thread, with a deadline: a path that blocks fails the test
    /// instead of hanging it.
    fn read_within_deadline(path: &Path) -> Result<String, GridError> {
        let (tx, rx) = std::sync::mpsc::channel();
        let path = path.to_path_buf();
        std::thread::spawn(move || {
            let _ = tx.send(read_regular(&path));
        });
        rx.recv_timeout(Duration::from_secs(20))
            .expect("reading the path blocked")
    }

    /// The kind of file a read was refused for ([`GridError::NotRegular`]); any other outcome
    /// fails the test.
    fn refused_kind(read: Result<String, GridError>) -> &'static str {
        match read {
            Err(GridError::NotRegular { kind, .. }) => kind,
            other => panic!("not refused as not a regular file: {other:?}"),
        }
    }

    fn mkfifo(path: &Path) {
        let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: `c` is a valid NUL-terminated path for the duration of the call.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
    }

    #[test]
    fn a_fifo_is_refused_at_once_without_waiting_for_a_writer() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        mkfifo(&path);
        assert_eq!(
            refused_kind(read_within_deadline(&path)),
            "a FIFO (named pipe)"
        );
        // Also through a symbolic link.
        let link = dir.path().join("link.toml");
        symlink(&path, &link).unwrap();
        refused_kind(read_within_deadline(&link));
    }

    #[test]
    fn a_link_to_dev_zero_is_refused_without_reading_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        symlink("/dev/zero", &path).unwrap();
        assert_eq!(
            refused_kind(read_within_deadline(&path)),
            "a character device"
        );
    }

    #[test]
    fn a_dangling_link_is_an_error_not_a_missing_grid() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        symlink(dir.path().join("gone.toml"), &path).unwrap();
        let err = read_regular(&path).unwrap_err();
        assert!(matches!(err, GridError::DanglingLink { .. }), "{err}");
        assert!(err.to_string().contains("gone.toml"), "{err}");
    }

    #[test]
    fn only_a_path_where_nothing_exists_is_a_missing_grid() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("dev.toml");
        assert!(matches!(
            read_regular(&missing),
            Err(GridError::Missing { .. })
        ));
        // A state directory that does not exist yet holds no grid either.
        assert!(matches!(
            read_regular(&dir.path().join("state/dev.toml")),
            Err(GridError::Missing { .. })
        ));
        // A directory, a link loop and a path through a regular file are errors.
        fs::create_dir(&missing).unwrap();
        assert_eq!(refused_kind(read_regular(&missing)), "a directory");
        let looped = dir.path().join("loop.toml");
        symlink(&looped, &looped).unwrap();
        assert!(matches!(read_regular(&looped), Err(GridError::Read { .. })));
        let file = dir.path().join("plain");
        fs::write(&file, "").unwrap();
        assert!(matches!(
            read_regular(&file.join("dev.toml")),
            Err(GridError::Read { .. })
        ));
    }

    #[test]
    fn an_unsearchable_state_directory_is_an_error_not_a_missing_grid() {
        // SAFETY: geteuid has no preconditions.
        if unsafe { libc::geteuid() } == 0 {
            // Root searches any directory whatever its mode; `tests/grid_files.rs` covers this
            // case as root by running `hgcd` as another user.
            eprintln!("skipped: running as root, which bypasses directory permissions");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        fs::create_dir(&state).unwrap();
        fs::set_permissions(&state, fs::Permissions::from_mode(0o000)).unwrap();
        let result = read_regular(&state.join("dev.toml"));
        fs::set_permissions(&state, fs::Permissions::from_mode(0o700)).unwrap();
        match result {
            Err(GridError::Read { source, .. }) => {
                assert_eq!(source.kind(), io::ErrorKind::PermissionDenied)
            }
            other => panic!("{other:?}"),
        }
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
        assert!(matches!(
            read_regular(&path),
            Err(GridError::TooLarge { .. })
        ));
    }

    #[test]
    fn a_link_to_a_grid_file_is_followed() {
        let dir = tempfile::tempdir().unwrap();
        let real = dir.path().join("real.toml");
        GridFile::from(sample()).save_atomic(&real).unwrap();
        let link = dir.path().join("dev.toml");
        symlink(&real, &link).unwrap();
        assert_eq!(GridFile::load(&link).unwrap().grid, sample());
    }

    #[test]
    fn the_backup_is_a_link_to_the_old_file_and_nothing_else_is_left() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        fs::write(&path, "old").unwrap();
        let old_inode = fs::metadata(&path).unwrap().ino();
        replace_atomically(&path, b"new").unwrap();
        assert_eq!(fs::read_to_string(&path).unwrap(), "new");
        let bak = dir.path().join("dev.toml.bak");
        assert_eq!(fs::read_to_string(&bak).unwrap(), "old");
        assert_eq!(fs::metadata(&bak).unwrap().ino(), old_inode);
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

    /// Set by the parent of [`a_failing_write_leaves_the_old_file_and_its_backup`] in the child
    /// it runs under a file size limit: the directory to work in.
    const LIMITED_CHILD: &str = "HGCD_TEST_FSIZE_CHILD_DIR";

    #[test]
    fn a_failing_write_leaves_the_old_file_and_its_backup() {
        if let Some(dir) = std::env::var_os(LIMITED_CHILD) {
            // The child, where files may not grow past 4 KiB. A new file of 8 KiB cannot be
            // written at all.
            let dir = Path::new(&dir);
            let err = replace_atomically(&dir.join("a/dev.toml"), &[b'n'; 8 << 10]).unwrap_err();
            assert!(matches!(err, GridError::Write { .. }), "{err}");
            // A new file of 2 KiB can, and the backup of the old one (16 KiB) needs no data.
            replace_atomically(&dir.join("b/dev.toml"), &[b'n'; 2 << 10]).unwrap();
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let (old, older) = (vec![b'o'; 16 << 10], vec![b'b'; 16 << 10]);
        for sub in ["a", "b"] {
            fs::create_dir(dir.path().join(sub)).unwrap();
            fs::write(dir.path().join(sub).join("dev.toml"), &old).unwrap();
            fs::write(dir.path().join(sub).join("dev.toml.bak"), &older).unwrap();
        }
        let mut child = std::process::Command::new(std::env::current_exe().unwrap());
        child
            .args([
                "--exact",
                "grid::store::tests::a_failing_write_leaves_the_old_file_and_its_backup",
                "--test-threads=1",
            ])
            .env(LIMITED_CHILD, dir.path());
        limit_file_size(&mut child, 4 << 10);
        let out = child.output().unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success() && stdout.contains("1 passed"),
            "{stdout}"
        );
        let read = |sub: &str, name: &str| fs::read(dir.path().join(sub).join(name)).unwrap();
        let names = |sub: &str| fs::read_dir(dir.path().join(sub)).unwrap().count();
        // The failed save changed nothing and left no temporary file.
        assert_eq!(read("a", "dev.toml"), old);
        assert_eq!(read("a", "dev.toml.bak"), older);
        assert_eq!(names("a"), 2);
        // The successful one kept the whole old file as the backup.
        assert_eq!(read("b", "dev.toml"), vec![b'n'; 2 << 10]);
        assert_eq!(read("b", "dev.toml.bak"), old);
        assert_eq!(names("b"), 2);
    }

    #[test]
    fn the_room_check_creates_the_directory_and_leaves_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state/dev.toml");
        check_room(&path, 100_000).unwrap();
        assert_eq!(fs::read_dir(dir.path().join("state")).unwrap().count(), 0);
        let blocker = dir.path().join("file");
        fs::write(&blocker, "").unwrap();
        assert!(matches!(
            check_room(&blocker.join("dev.toml"), 10),
            Err(GridError::CreateDir { .. })
        ));
    }
}
