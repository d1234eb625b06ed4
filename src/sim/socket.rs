//! The device side of the socket transport (`docs/hid-protocol.md` §9): serves [`SimDevice`]s to
//! hosts that connect with `--device socket:PATH`, as `hgcd sim-device` does and as an external
//! simulator or hardware bridge would.
//!
//! The contract it keeps: it serves successive hosts, one at a time, and each connection is a
//! power-on (a fresh device: clock and sequence at 0, no command, motors off). A one-byte frame
//! asks for a feature report (the device-info report is answered at once). A frame of 2 to 64
//! bytes is an output report, applied through the firmware's checks; in lock-step it is the
//! host's reply to the pending input report, valid or not. A length byte of 0 or above 64 breaks
//! the framing: the connection is closed (as a disconnect, force zeroed) and the next host served.
//! In lock-step the device waits for the reply however long it takes: its clock, and so its
//! watchdog, advance one period per reply, never by wall-clock time.

use std::io::{ErrorKind, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use tracing::info;

use super::SimDevice;
use crate::protocol::{DEVICE_INFO_LEN, DEVICE_INFO_REPORT_ID, MAX_REPORT_LEN};
use crate::sys::{read_available, wait_readable};

/// How often a device waiting on a host or for one looks at the stop flag.
const STOP_POLL: Duration = Duration::from_millis(50);

/// How one host's connection ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HostEnd {
    /// The host closed the connection.
    Left,
    /// The host sent a length byte of 0 or above 64; the device closed the connection.
    Framing { length: usize },
    /// The stop flag was set.
    Stopped,
}

/// What [`serve`] served.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Served {
    /// Connections served.
    pub hosts: u64,
    /// Device time, summed over the connections, s.
    pub device_time: f64,
    /// Malformed output reports the firmware rejected, over the connections.
    pub rejected: u64,
}

/// Serve successive hosts on `listener` until `stop` is set. Each connection is a power-on: the
/// device it is served is a fresh one from `power_on`. In lock-step mode each input report waits
/// for the host's reply (deterministic, as fast as both sides allow); otherwise reports go out in
/// real time, one per period.
///
/// # Errors
/// Those of [`accept`] and [`serve_host`], and `power_on`'s error wrapped in an I/O error;
/// serving then ends.
pub fn serve<E>(
    listener: &UnixListener,
    mut power_on: impl FnMut() -> Result<SimDevice, E>,
    lockstep: bool,
    stop: &AtomicBool,
) -> std::io::Result<Served>
where
    E: std::error::Error + Send + Sync + 'static,
{
    let mut served = Served::default();
    while let Some(stream) = accept(listener, stop)? {
        let mut device = power_on().map_err(std::io::Error::other)?;
        served.hosts += 1;
        info!("host {} connected: device powered on", served.hosts);
        let end = serve_host(stream, &mut device, lockstep, stop)?;
        served.device_time += device.time();
        served.rejected += device.rejected_outputs();
        info!(
            "host {} {}: {:.3} s of device time, {} output reports rejected",
            served.hosts,
            match end {
                HostEnd::Left => "left".to_string(),
                HostEnd::Framing { length } =>
                    format!("broke the framing (length byte {length}): connection closed"),
                HostEnd::Stopped => "disconnected: stopping".to_string(),
            },
            device.time(),
            device.rejected_outputs()
        );
    }
    Ok(served)
}

/// Wait for the next host on `listener`; None once `stop` is set.
///
/// # Errors
/// The I/O error of a failed accept or wait.
pub fn accept(listener: &UnixListener, stop: &AtomicBool) -> std::io::Result<Option<UnixStream>> {
    listener.set_nonblocking(true)?;
    loop {
        match listener.accept() {
            Ok((stream, _)) => return Ok(Some(stream)),
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                if stop.load(Ordering::Relaxed) {
                    return Ok(None);
                }
                // Wakes at once when the host connects (its watchdog starts with its loop).
                wait_readable(listener, STOP_POLL)?;
            }
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// Serve `device` to the host connected on `stream` until the host leaves, breaks the framing or
/// `stop` is set. The first report shows the device as it is; each later one follows one period.
///
/// # Errors
/// The I/O error of setting up `stream` or waiting on it (a host that leaves is
/// [`HostEnd::Left`], not an error).
pub fn serve_host(
    stream: UnixStream,
    device: &mut SimDevice,
    lockstep: bool,
    stop: &AtomicBool,
) -> std::io::Result<HostEnd> {
    // Blocking writes; reads only what has arrived (recv with MSG_DONTWAIT after ppoll).
    stream.set_nonblocking(false)?;
    let mut link = Link {
        stream,
        inbuf: Vec::with_capacity(256),
        lockstep,
    };
    let period = Duration::from_secs_f64(device.period());
    let mut next = Instant::now();
    let mut first = true;
    let end = 'run: loop {
        if stop.load(Ordering::Relaxed) {
            break HostEnd::Stopped;
        }
        // The first report shows the power-on state, as over HID.
        if !first {
            device.advance();
        }
        first = false;
        let reporting = !device.is_silent();
        if reporting {
            let mut report = [0u8; MAX_REPORT_LEN];
            let n = device.input_report(&mut report);
            let mut frame = [0u8; MAX_REPORT_LEN + 1];
            frame[0] = n as u8;
            frame[1..=n].copy_from_slice(&report[..n]);
            if link.stream.write_all(&frame[..=n]).is_err() {
                break HostEnd::Left;
            }
        }
        next += period;
        // Lock-step: until the host's reply, however long it takes. Real time, or a silent
        // device: until the next period starts.
        let awaiting_reply = lockstep && reporting;
        loop {
            match link.take(device)? {
                Frames::Replies(n) if awaiting_reply && n > 0 => break,
                Frames::Replies(_) => {}
                Frames::End(end) => break 'run end,
            }
            if stop.load(Ordering::Relaxed) {
                break 'run HostEnd::Stopped;
            }
            let now = Instant::now();
            let wait = if awaiting_reply {
                STOP_POLL
            } else if now < next {
                (next - now).min(STOP_POLL)
            } else {
                break;
            };
            wait_readable(&link.stream, wait)?;
        }
        let now = Instant::now();
        if awaiting_reply || now > next + period {
            // Lock-step: periods follow replies, not the wall clock. Real time: fell behind (a
            // stall), so drop the missed periods rather than burst.
            next = now;
        }
    };
    // Whatever the host sent last (its final zero-force report) still reaches the firmware.
    let _ = link.take(device);
    Ok(end)
}

/// What [`Link::take`] found.
enum Frames {
    /// This many output reports (valid or not) were handed to the firmware.
    Replies(u32),
    /// The connection is over.
    End(HostEnd),
}

/// The device's end of one connection.
struct Link {
    stream: UnixStream,
    /// Bytes received but not yet framed.
    inbuf: Vec<u8>,
    lockstep: bool,
}

impl Link {
    /// Read what the host has sent and act on every complete frame: answer feature requests,
    /// hand output reports to the firmware.
    fn take(&mut self, device: &mut SimDevice) -> std::io::Result<Frames> {
        let mut chunk = [0u8; 256];
        let mut closed = false;
        loop {
            match read_available(&self.stream, &mut chunk) {
                Ok(0) => {
                    closed = true;
                    break;
                }
                Ok(n) => self.inbuf.extend_from_slice(&chunk[..n]),
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(_) => {
                    closed = true;
                    break;
                }
            }
        }
        let mut replies = 0;
        while let Some(&n) = self.inbuf.first() {
            let n = n as usize;
            if n == 0 || n > MAX_REPORT_LEN {
                return Ok(Frames::End(HostEnd::Framing { length: n }));
            }
            if self.inbuf.len() < n + 1 {
                break;
            }
            if n == 1 {
                // A get-feature request; report IDs without a feature report are ignored (and
                // so is every request to a device whose protocol has none).
                if self.inbuf[1] == DEVICE_INFO_REPORT_ID && device.wire().has_device_info() {
                    let mut frame = [0u8; DEVICE_INFO_LEN + 1];
                    frame[0] = DEVICE_INFO_LEN as u8;
                    device.device_info_report(
                        self.lockstep,
                        (&mut frame[1..]).try_into().expect("device-info length"),
                    );
                    if self.stream.write_all(&frame).is_err() {
                        closed = true;
                    }
                }
            } else {
                // Malformed ones are rejected and counted by the firmware; each is a reply.
                let _ = device.receive_output(&self.inbuf[1..=n]);
                replies += 1;
            }
            self.inbuf.drain(..=n);
        }
        Ok(if closed {
            Frames::End(HostEnd::Left)
        } else {
            Frames::Replies(replies)
        })
    }
}
