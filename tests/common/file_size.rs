//! A file size limit for a child process. Shared by `tests/grid_files.rs` and the unit tests of
//! `src/grid/store.rs`, which include this file by its path.

use std::os::unix::process::CommandExt;
use std::process::Command;

/// Make `command` run with files limited to `bytes` (writes past it fail with EFBIG, as on a
/// full disk).
pub fn limit_file_size(command: &mut Command, bytes: u64) {
    // SAFETY: only async-signal-safe calls between fork and exec.
    unsafe {
        command.pre_exec(move || {
            libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            let limit = libc::rlimit {
                rlim_cur: bytes,
                rlim_max: bytes,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}
