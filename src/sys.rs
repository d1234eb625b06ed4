//! Thin safe wrappers over the Linux calls that `std` does not offer: waiting on a descriptor with a
//! precise timeout, reading without waiting, sleeping to an absolute deadline.

use std::io::ErrorKind;
use std::os::unix::io::AsRawFd;
use std::time::{Duration, Instant};

/// Wait until `stream` is readable or `timeout` passes (ppoll: nanosecond timeout, no tick
/// rounding); whether it is readable (or at its end, or failed: a read then says which). EINTR
/// counts as a wake-up (`false`); the caller re-checks.
pub fn wait_readable(fd: &impl AsRawFd, timeout: Duration) -> std::io::Result<bool> {
    let mut fds = libc::pollfd {
        fd: fd.as_raw_fd(),
        events: libc::POLLIN,
        revents: 0,
    };
    let ts = libc::timespec {
        tv_sec: timeout.as_secs() as libc::time_t,
        tv_nsec: libc::c_long::from(timeout.subsec_nanos() as i32),
    };
    // SAFETY: one pollfd and one timespec we own, no signal mask.
    let r = unsafe { libc::ppoll(&mut fds, 1, &ts, std::ptr::null()) };
    if r < 0 {
        let e = std::io::Error::last_os_error();
        if e.kind() != ErrorKind::Interrupted {
            return Err(e);
        }
    }
    Ok(r > 0)
}

/// Read whatever is queued on `stream` without waiting (EWOULDBLOCK when nothing is).
pub fn read_available(stream: &impl AsRawFd, buf: &mut [u8]) -> std::io::Result<usize> {
    // SAFETY: recv into a buffer we own, of its length.
    let n = unsafe {
        libc::recv(
            stream.as_raw_fd(),
            buf.as_mut_ptr().cast(),
            buf.len(),
            libc::MSG_DONTWAIT,
        )
    };
    if n < 0 {
        Err(std::io::Error::last_os_error())
    } else {
        Ok(n as usize)
    }
}

/// Sleep until `deadline` on CLOCK_MONOTONIC with an absolute timer (no drift from wake-up latency).
pub fn sleep_until(deadline: Instant) {
    let now = Instant::now();
    if deadline <= now {
        return;
    }
    let remaining = deadline - now;
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    let mut nsec = ts.tv_nsec + libc::c_long::from(remaining.subsec_nanos() as i32);
    let mut sec = ts.tv_sec + remaining.as_secs() as libc::time_t;
    if nsec >= 1_000_000_000 {
        nsec -= 1_000_000_000;
        sec += 1;
    }
    let target = libc::timespec {
        tv_sec: sec,
        tv_nsec: nsec,
    };
    // SAFETY: absolute sleep on a timespec we own; EINTR just returns early, and we loop.
    while unsafe {
        libc::clock_nanosleep(
            libc::CLOCK_MONOTONIC,
            libc::TIMER_ABSTIME,
            &target,
            std::ptr::null_mut(),
        )
    } == libc::EINTR
    {}
}

/// The largest text file hgcd reads besides grids (a config, a profile, a model file, a log),
/// bytes.
pub const MAX_TEXT_BYTES: u64 = 256 << 20;

/// The text of the file at `path`, read as grids are: a regular file (through a link) or the
/// null device, opened without blocking and read to at most `MAX_TEXT_BYTES`. A FIFO, another
/// device, a directory or a socket is refused (an error of kind `InvalidInput` saying what it
/// is), never waited on; a longer file is refused rather than read without bound.
///
/// # Errors
/// As `std::fs::read_to_string`, and the refusals above.
pub fn read_text(path: &std::path::Path) -> std::io::Result<String> {
    use std::io::Read;
    use std::os::unix::fs::{FileTypeExt, MetadataExt, OpenOptionsExt};
    let kind = |meta: &std::fs::Metadata| -> Option<&'static str> {
        let t = meta.file_type();
        let null = t.is_char_device() && meta.rdev() == libc::makedev(1, 3);
        if t.is_file() || null {
            None
        } else if t.is_dir() {
            Some("a directory")
        } else if t.is_fifo() {
            Some("a FIFO (named pipe)")
        } else if t.is_char_device() || t.is_block_device() {
            Some("a device")
        } else {
            Some("a socket")
        }
    };
    let refuse = |what: &str| {
        std::io::Error::new(
            ErrorKind::InvalidInput,
            format!("{what}, not a regular file"),
        )
    };
    if let Some(what) = kind(&std::fs::metadata(path)?) {
        return Err(refuse(what));
    }
    // O_NONBLOCK: a FIFO swapped in after the check does not hold the open; checked again.
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(path)?;
    if let Some(what) = kind(&file.metadata()?) {
        return Err(refuse(what));
    }
    let mut bytes = Vec::new();
    file.take(MAX_TEXT_BYTES + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > MAX_TEXT_BYTES {
        return Err(std::io::Error::new(
            ErrorKind::InvalidInput,
            format!("larger than {} MiB", MAX_TEXT_BYTES >> 20),
        ));
    }
    String::from_utf8(bytes)
        .map_err(|e| std::io::Error::new(ErrorKind::InvalidData, format!("not UTF-8 text: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::ffi::OsStrExt;

    /// Issue 40: a FIFO as a profile hung hgcd in `open`; a link to /dev/zero grew memory
    /// without bound. Every text file hgcd reads now goes through `read_text`: both are refused
    /// at once with what they are, and `--config /dev/null` still reads as empty.
    #[test]
    fn text_files_are_read_bounded_and_never_waited_on() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("fifo.toml");
        let c = std::ffi::CString::new(fifo.as_os_str().as_bytes()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
        let zero = dir.path().join("zero.toml");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let started = Instant::now();
        for (path, says) in [
            (&fifo, "a FIFO (named pipe), not a regular file"),
            (&zero, "a device, not a regular file"),
            (&dir.path().to_path_buf(), "a directory, not a regular file"),
        ] {
            let e = read_text(path).unwrap_err();
            assert_eq!(e.kind(), ErrorKind::InvalidInput);
            assert_eq!(e.to_string(), says);
        }
        assert!(started.elapsed() < Duration::from_secs(5));
        assert_eq!(read_text(std::path::Path::new("/dev/null")).unwrap(), "");
        let plain = dir.path().join("plain.toml");
        std::fs::write(&plain, "a = 1\n").unwrap();
        assert_eq!(read_text(&plain).unwrap(), "a = 1\n");
    }
}
