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
