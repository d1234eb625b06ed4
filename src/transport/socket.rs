//! `socket:PATH`: HID reports framed over a Unix stream socket, so an external simulator or a
//! hardware-in-the-loop bridge can stand in for the device. hgcd connects as the client; the device
//! side listens. Each frame is one length byte N (1–64) followed by the N bytes of one report,
//! report ID first, exactly as over HID; a frame of one byte asks for the feature report it names
//! (`docs/hid-protocol.md` §9).
//!
//! Frames carry any profile's raw reports: a device of a profile without report IDs (the
//! WoodenHaptics protocol, `docs/devices.md`) sends its reports as they are, and the host does not
//! ask it for a device-info report (its profile stands in).
//!
//! On connecting, the host asks for the device-info report and waits for it at most
//! [`DEVICE_INFO_WAIT`]. A device that says it runs in lock-step advances only when the host
//! answers: its clock, not the wall clock, is then the transport's ([`Transport::now`]), so the
//! loop's watchdog and `--duration` count device time, and a device that sends nothing for
//! [`LOCKSTEP_STALL`] has hung. Every frame from such a device is one step of its time: a report
//! whose clock does not move forward (garbled, or a clock that stands still or runs backwards)
//! counts one period of its declared rate, so a device that only babbles still trips the watchdog.

use std::io::{ErrorKind, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::time::{Duration, Instant};

use super::{Burst, NoDeviceInfo, Speaks, Transport, TransportError};
use crate::profile::{Codec, Wire};
use crate::protocol::{
    DeviceClock, DeviceInfo, InputReport, DEVICE_INFO_REPORT_ID, MAX_REPORT_LEN, OUTPUT_REPORT_LEN,
};
use crate::sys::wait_readable;

/// How long the host waits for the device-info report when it connects. A device that does not
/// know the request ignores it; the host then runs it as before the report existed.
pub const DEVICE_INFO_WAIT: Duration = Duration::from_millis(500);

/// How long a lock-step device may send nothing, wall-clock time, before the run ends (unless
/// [`SocketTransport::stalled_after`] says otherwise).
pub const LOCKSTEP_STALL: Duration = Duration::from_secs(10);

/// Host side of the socket transport.
pub struct SocketTransport {
    stream: UnixStream,
    /// `socket:PATH`, as errors name the device.
    spec: String,
    /// Bytes received but not yet consumed (at most one partial frame plus one whole one).
    pending: [u8; 2 * (MAX_REPORT_LEN + 1)],
    filled: usize,
    start: Instant,
    garbled_skipped: u64,
    /// What the device answered when asked for its device-info report (or its profile says).
    info: Result<DeviceInfo, NoDeviceInfo>,
    /// The device's protocol, and the host side of its profile.
    wire: Wire,
    codec: Codec,
    /// Input reports that came while the host waited for the device-info answer: the first read
    /// hands up the newest valid one (a lock-step device waits for the host's reply to it).
    held: Option<(usize, u64)>,
    held_report: [u8; MAX_REPORT_LEN],
    /// Lock-step: the device clock, unwrapped from the reports, its newest reading, and the
    /// transport's time built from its forward steps (and a period per frame that has none), s.
    device_clock: DeviceClock,
    clock_reading: Option<f64>,
    device_time: f64,
    /// When the device last sent anything, and how long a lock-step device may send nothing.
    last_heard: Instant,
    stall: Duration,
}

impl SocketTransport {
    /// Connect to the device side listening at `path`, speaking `speaks`, and ask for its
    /// device-info report when its protocol has one.
    ///
    /// # Errors
    /// [`TransportError::Open`] when nobody listens at `path`; [`TransportError::Disconnected`]
    /// or [`TransportError::Framing`] when the device fails while it is asked.
    pub fn connect(path: &Path, speaks: Speaks) -> Result<Self, TransportError> {
        let spec = format!("socket:{}", path.display());
        let stream = UnixStream::connect(path).map_err(|source| TransportError::Open {
            spec: spec.clone(),
            doing: "connecting (is the device-side program listening there?)".into(),
            source,
        })?;
        // Non-blocking: a full socket buffer never stalls the servo loop, and waiting for input
        // uses ppoll(2), whose timeout is precise (SO_RCVTIMEO rounds to scheduler ticks).
        stream
            .set_nonblocking(true)
            .map_err(|source| TransportError::Open {
                spec: spec.clone(),
                doing: "making the socket non-blocking".into(),
                source,
            })?;
        let now = Instant::now();
        let mut transport = Self {
            stream,
            spec,
            pending: [0; 2 * (MAX_REPORT_LEN + 1)],
            filled: 0,
            start: now,
            garbled_skipped: 0,
            info: Err(NoDeviceInfo::NotAsked),
            wire: speaks.wire,
            codec: speaks.codec,
            held: None,
            held_report: [0; MAX_REPORT_LEN],
            device_clock: DeviceClock::default(),
            clock_reading: None,
            device_time: 0.0,
            last_heard: now,
            stall: LOCKSTEP_STALL,
        };
        transport.info = match speaks.info {
            // A protocol without the report: its profile speaks for the device.
            Some(info) => Ok(info),
            None => transport.ask_device_info()?,
        };
        Ok(transport)
    }

    /// Take a lock-step device that sends nothing for `limit` of wall-clock time as hung
    /// (default [`LOCKSTEP_STALL`]).
    pub fn stalled_after(mut self, limit: Duration) -> Self {
        self.stall = limit;
        self
    }

    fn disconnected(&self, source: std::io::Error) -> TransportError {
        TransportError::Disconnected {
            spec: self.spec.clone(),
            source,
        }
    }

    fn lockstep(&self) -> bool {
        self.info.as_ref().is_ok_and(|info| info.lockstep)
    }

    /// Send the get-feature request for the device-info report and wait for the answer at most
    /// [`DEVICE_INFO_WAIT`], keeping the input reports that come meanwhile for the first read.
    fn ask_device_info(&mut self) -> Result<Result<DeviceInfo, NoDeviceInfo>, TransportError> {
        self.stream
            .write_all(&[1, DEVICE_INFO_REPORT_ID])
            .map_err(|e| self.disconnected(e))?;
        let deadline = Instant::now() + DEVICE_INFO_WAIT;
        let mut burst = Burst::new(self.wire);
        let mut held = [0u8; MAX_REPORT_LEN];
        let mut frame = [0u8; MAX_REPORT_LEN];
        let answer = loop {
            let mut answer = None;
            while let Some(n) = self.take_frame(&mut frame)? {
                if frame[0] == DEVICE_INFO_REPORT_ID {
                    answer = Some(DeviceInfo::decode(&frame[..n]).map_err(NoDeviceInfo::Malformed));
                } else {
                    burst.offer(&frame[..n], &mut held);
                }
            }
            if let Some(answer) = answer {
                break answer;
            }
            let now = Instant::now();
            if now >= deadline {
                break Err(NoDeviceInfo::NoAnswer(DEVICE_INFO_WAIT));
            }
            self.receive(deadline - now)?;
        };
        if let (Some(n), garbled) = burst.finish() {
            self.held = Some((n, garbled));
            self.held_report = held;
        }
        Ok(answer)
    }

    /// Wait at most `timeout` for bytes from the device and add them to `pending`.
    fn receive(&mut self, timeout: Duration) -> Result<(), TransportError> {
        loop {
            let space = self.pending.len() - self.filled;
            match self
                .stream
                .read(&mut self.pending[self.filled..self.filled + space])
            {
                Ok(0) => return Err(self.disconnected(peer_closed())),
                Ok(n) => {
                    self.filled += n;
                    self.last_heard = Instant::now();
                    return Ok(());
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    if timeout.is_zero() {
                        return Ok(());
                    }
                    wait_readable(&self.stream, timeout).map_err(|e| self.disconnected(e))?;
                    return self.receive(Duration::ZERO);
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(self.disconnected(e)),
            }
        }
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
            return Err(TransportError::Framing {
                spec: self.spec.clone(),
                length: n,
            });
        }
        if self.filled < n + 1 {
            return Ok(None);
        }
        buf[..n].copy_from_slice(&self.pending[1..=n]);
        self.pending.copy_within(n + 1..self.filled, 0);
        self.filled -= n + 1;
        Ok(Some(n))
    }

    /// Hand up the chosen report (`Burst::finish`). In lock-step the burst moves the clock: by the
    /// chosen report's forward step, or by a period for each of its frames when there is none.
    fn chosen(&mut self, chosen: Option<usize>, garbled: u64, buf: &[u8]) -> Option<usize> {
        self.garbled_skipped += garbled;
        if let (Some(n), Ok(info)) = (chosen, &self.info) {
            if info.lockstep {
                let reading = InputReport::decode(&buf[..n])
                    .ok()
                    .map(|report| self.device_clock.seconds(report.timestamp_us).0);
                match (reading, self.clock_reading) {
                    (Some(now), Some(before)) if now > before => self.device_time += now - before,
                    // The first reading is the clock's origin.
                    (Some(_), None) => {}
                    // The chosen report and the garbled ones dropped before it.
                    _ => self.device_time += (garbled + 1) as f64 / info.rate_hz,
                }
                self.clock_reading = reading.or(self.clock_reading);
            }
        }
        chosen
    }
}

impl Transport for SocketTransport {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        if let Some((n, garbled)) = self.held.take() {
            buf.copy_from_slice(&self.held_report);
            return Ok(self.chosen(Some(n), garbled, &buf[..]));
        }
        let deadline = Instant::now() + timeout;
        let mut burst = Burst::new(self.wire);
        let mut frame = [0u8; MAX_REPORT_LEN];
        loop {
            // Drain every complete frame; keep the newest valid one (skip ahead after an overrun).
            // A device-info answer that came after the host stopped waiting is not a report.
            while let Some(n) = self.take_frame(&mut frame)? {
                if !(self.wire.has_device_info() && frame[0] == DEVICE_INFO_REPORT_ID) {
                    burst.offer(&frame[..n], buf);
                }
            }
            let before = self.filled;
            self.receive(Duration::ZERO)?;
            if self.filled > before {
                continue;
            }
            // Nothing queued: return what we have, or wait for more.
            if !burst.is_empty() {
                let (chosen, garbled) = burst.finish();
                return Ok(self.chosen(chosen, garbled, &buf[..]));
            }
            if self.lockstep() && self.last_heard.elapsed() >= self.stall {
                return Err(TransportError::Stalled {
                    spec: self.spec.clone(),
                    after: self.last_heard.elapsed(),
                });
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            self.receive(deadline - now)?;
        }
    }

    fn write_output(&mut self, report: &[u8]) -> Result<(), TransportError> {
        let mut frame = [0u8; OUTPUT_REPORT_LEN + 1];
        let n = report.len().min(OUTPUT_REPORT_LEN);
        frame[0] = n as u8;
        frame[1..=n].copy_from_slice(&report[..n]);
        let frame = &frame[..=n];
        let mut sent = 0;
        while sent < frame.len() {
            match self.stream.write(&frame[sent..]) {
                Ok(0) => return Err(self.disconnected(peer_closed())),
                Ok(n) => sent += n,
                // Nothing sent: drop this report (the next one supersedes it).
                Err(e) if sent == 0 && e.kind() == ErrorKind::WouldBlock => return Ok(()),
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                // Half a frame on the wire would desynchronise the stream: give up on the peer.
                Err(e) => return Err(self.disconnected(e)),
            }
        }
        Ok(())
    }

    /// Device time for a lock-step device (it stands still while the device is silent; see the
    /// module's doc), wall-clock time since connecting otherwise.
    fn now(&self) -> f64 {
        if self.lockstep() {
            self.device_time
        } else {
            self.start.elapsed().as_secs_f64()
        }
    }

    fn take_garbled_skipped(&mut self) -> u64 {
        std::mem::take(&mut self.garbled_skipped)
    }

    fn clock_drift(&self) -> f64 {
        if self.lockstep() {
            0.0
        } else {
            super::CLOCK_DRIFT
        }
    }

    fn codec(&self) -> Codec {
        self.codec.clone()
    }

    fn describe(&self) -> String {
        if self.lockstep() {
            format!("{} (lock-step)", self.spec)
        } else {
            self.spec.clone()
        }
    }

    fn device_info(&self) -> Result<&DeviceInfo, &NoDeviceInfo> {
        self.info.as_ref()
    }
}

/// The cause of a disconnection when the peer closed its end.
fn peer_closed() -> std::io::Error {
    std::io::Error::new(
        ErrorKind::UnexpectedEof,
        "the device side closed the connection",
    )
}
