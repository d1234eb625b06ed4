//! `socket:PATH`: HID reports framed over a Unix stream socket, so an external simulator or a
//! hardware-in-the-loop bridge can stand in for the device. hgcd connects as the client; the device
//! side listens. Each frame is one length byte N (1–64) followed by the N bytes of one report,
//! report ID first, exactly as over HID (`docs/hid-protocol.md`, "Socket framing").

use std::io::{ErrorKind, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use super::sim::SimDevice;
use super::{Burst, Transport, TransportError, MAX_REPORT_LEN};
use crate::protocol::{INPUT_REPORT_LEN, OUTPUT_REPORT_LEN};

/// Host side of the socket transport.
pub struct SocketTransport {
    stream: UnixStream,
    path: String,
    /// Bytes received but not yet consumed (at most one partial frame plus one whole one).
    pending: [u8; 2 * (MAX_REPORT_LEN + 1)],
    filled: usize,
    start: Instant,
    dropped_writes: u64,
    garbled_skipped: u64,
}

impl SocketTransport {
    pub fn connect(path: &Path) -> Result<Self, TransportError> {
        let stream = UnixStream::connect(path).map_err(|e| TransportError::Open {
            spec: format!("socket:{}", path.display()),
            reason: format!("{e} (is the device-side program listening there?)"),
        })?;
        // Non-blocking: a full socket buffer never stalls the servo loop, and waiting for input
        // uses ppoll(2), whose timeout is precise (SO_RCVTIMEO rounds to scheduler ticks).
        stream
            .set_nonblocking(true)
            .map_err(|e| TransportError::Io(e.to_string()))?;
        Ok(Self {
            stream,
            path: path.display().to_string(),
            pending: [0; 2 * (MAX_REPORT_LEN + 1)],
            filled: 0,
            start: Instant::now(),
            dropped_writes: 0,
            garbled_skipped: 0,
        })
    }

    /// Output reports dropped because the peer was not reading.
    pub fn dropped_writes(&self) -> u64 {
        self.dropped_writes
    }

    /// Take one complete frame from `pending` into `buf`, if there is one.
    fn take_frame(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
    ) -> Result<Option<usize>, TransportError> {
        if self.filled == 0 {
            return Ok(None);
        }
        let n = self.pending[0] as usize;
        if n == 0 || n > MAX_REPORT_LEN {
            return Err(TransportError::Io(format!(
                "bad frame length {n} from socket peer"
            )));
        }
        if self.filled < n + 1 {
            return Ok(None);
        }
        buf[..n].copy_from_slice(&self.pending[1..=n]);
        self.pending.copy_within(n + 1..self.filled, 0);
        self.filled -= n + 1;
        Ok(Some(n))
    }
}

impl Transport for SocketTransport {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        let deadline = Instant::now() + timeout;
        let mut burst = Burst::default();
        let mut frame = [0u8; MAX_REPORT_LEN];
        loop {
            // Drain every complete frame; keep the newest valid one (skip ahead after an overrun).
            while let Some(n) = self.take_frame(&mut frame)? {
                burst.offer(&frame[..n], buf);
            }
            let space = self.pending.len() - self.filled;
            match self
                .stream
                .read(&mut self.pending[self.filled..self.filled + space])
            {
                Ok(0) => {
                    return Err(TransportError::Disconnected(format!(
                        "{} closed",
                        self.path
                    )))
                }
                Ok(n) => self.filled += n,
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    // Nothing queued: return what we have, or wait for more.
                    if !burst.is_empty() {
                        let (chosen, garbled) = burst.finish();
                        self.garbled_skipped += garbled;
                        return Ok(chosen);
                    }
                    let now = Instant::now();
                    if now >= deadline {
                        return Ok(None);
                    }
                    wait_readable(&self.stream, deadline - now)
                        .map_err(|e| TransportError::Io(e.to_string()))?;
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(TransportError::Disconnected(e.to_string())),
            }
        }
    }

    fn write_output(&mut self, report: &[u8; OUTPUT_REPORT_LEN]) -> Result<(), TransportError> {
        let mut frame = [0u8; OUTPUT_REPORT_LEN + 1];
        frame[0] = OUTPUT_REPORT_LEN as u8;
        frame[1..].copy_from_slice(report);
        let mut sent = 0;
        while sent < frame.len() {
            match self.stream.write(&frame[sent..]) {
                Ok(0) => {
                    return Err(TransportError::Disconnected(format!(
                        "{} closed",
                        self.path
                    )))
                }
                Ok(n) => sent += n,
                // Nothing sent: drop this report (the next one supersedes it).
                Err(e) if sent == 0 && e.kind() == ErrorKind::WouldBlock => {
                    self.dropped_writes += 1;
                    return Ok(());
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                // Half a frame on the wire would desynchronise the stream: give up on the peer.
                Err(e) => {
                    return Err(TransportError::Disconnected(format!(
                        "{}: {e} after a partial frame",
                        self.path
                    )))
                }
            }
        }
        Ok(())
    }

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn take_garbled_skipped(&mut self) -> u64 {
        std::mem::take(&mut self.garbled_skipped)
    }

    fn describe(&self) -> String {
        format!("socket {}", self.path)
    }
}

/// Wait until `stream` is readable or `timeout` passes (ppoll: nanosecond timeout, no tick
/// rounding). EINTR counts as a wake-up; the caller re-checks.
fn wait_readable(fd: &impl std::os::unix::io::AsRawFd, timeout: Duration) -> std::io::Result<()> {
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
    Ok(())
}

/// Device side: serve `device` to one host connected to `listener`. In lock-step mode each input
/// report waits for the host's output report (deterministic, as fast as both sides allow); otherwise
/// reports go out in real time, one per period. Returns when the host disconnects or `stop` is set.
pub fn serve(
    listener: &UnixListener,
    device: &mut SimDevice,
    lockstep: bool,
    stop: &AtomicBool,
) -> std::io::Result<()> {
    listener.set_nonblocking(true)?;
    let mut stream = loop {
        match listener.accept() {
            Ok((stream, _)) => break stream,
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                if stop.load(Ordering::Relaxed) {
                    return Ok(());
                }
                // Wake at once when the host connects (its watchdog starts with its loop).
                wait_readable(listener, Duration::from_millis(50))?;
            }
            Err(e) => return Err(e),
        }
    };
    // Blocking writes; reads only what has arrived (recv with MSG_DONTWAIT after ppoll).
    stream.set_nonblocking(false)?;
    let period = Duration::from_secs_f64(device.period());
    let mut next = Instant::now();
    let mut inbuf = Vec::with_capacity(256);
    let mut first = true;
    let result = loop {
        if stop.load(Ordering::Relaxed) {
            break Ok(());
        }
        // The first report shows the power-on state, as over HID.
        if !first {
            device.advance();
        }
        first = false;
        if !device.is_silent() {
            let mut report = [0u8; INPUT_REPORT_LEN];
            device.input_report(&mut report);
            let mut frame = vec![INPUT_REPORT_LEN as u8];
            frame.extend_from_slice(&report);
            if stream.write_all(&frame).is_err() {
                break Ok(()); // the host went away
            }
        }
        next += period;
        // Lock-step: until the host's output report (at most 100 ms). Real time: until the next
        // period starts.
        let until = if lockstep {
            Instant::now() + Duration::from_millis(100)
        } else {
            next
        };
        let mut got_output = false;
        let mut host_gone = false;
        while !(stop.load(Ordering::Relaxed) || lockstep && got_output || host_gone) {
            let now = Instant::now();
            if now >= until {
                break;
            }
            wait_readable(&stream, until - now)?;
            host_gone = receive(&stream, &mut inbuf)?;
            got_output |= apply_frames(&mut inbuf, device)?;
        }
        if host_gone {
            break Ok(());
        }
        if !lockstep && Instant::now() > next + period {
            // Fell behind (a stall): drop the missed periods rather than burst.
            next = Instant::now();
        }
    };
    // Whatever the host sent last (its final zero-force report) still reaches the firmware.
    let _ = receive(&stream, &mut inbuf);
    let _ = apply_frames(&mut inbuf, device);
    result
}

/// Move whatever the host has sent into `inbuf`; true when the host has closed its side.
fn receive(stream: &UnixStream, inbuf: &mut Vec<u8>) -> std::io::Result<bool> {
    let mut chunk = [0u8; 256];
    loop {
        match read_available(stream, &mut chunk) {
            Ok(0) => return Ok(true),
            Ok(n) => inbuf.extend_from_slice(&chunk[..n]),
            Err(e) if e.kind() == ErrorKind::WouldBlock => return Ok(false),
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(_) => return Ok(true),
        }
    }
}

/// Hand every complete output frame in `inbuf` to the firmware; true if there was one.
fn apply_frames(inbuf: &mut Vec<u8>, device: &mut SimDevice) -> std::io::Result<bool> {
    let mut any = false;
    while let Some(&n) = inbuf.first() {
        let n = n as usize;
        if n == 0 || n > MAX_REPORT_LEN {
            return Err(std::io::Error::new(
                ErrorKind::InvalidData,
                format!("bad frame length {n} from host"),
            ));
        }
        if inbuf.len() < n + 1 {
            break;
        }
        let _ = device.receive_output(&inbuf[1..=n]);
        inbuf.drain(..=n);
        any = true;
    }
    Ok(any)
}

/// Read whatever is queued on `stream` without waiting (EWOULDBLOCK when nothing is).
fn read_available(stream: &UnixStream, buf: &mut [u8]) -> std::io::Result<usize> {
    use std::os::unix::io::AsRawFd;
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
