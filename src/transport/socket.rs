//! `socket:PATH`: HID reports framed over a Unix stream socket, so an external simulator or a
//! hardware-in-the-loop bridge can stand in for the device. hgcd connects as the client; the device
//! side listens. Each frame is one length byte N (1–64) followed by the N bytes of one report,
//! report ID first, exactly as over HID (`docs/hid-protocol.md`, "Socket framing").

use std::io::{ErrorKind, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::time::{Duration, Instant};

use super::{Burst, Transport, TransportError};
use crate::protocol::{MAX_REPORT_LEN, OUTPUT_REPORT_LEN};
use crate::sys::wait_readable;

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
}

impl SocketTransport {
    pub fn connect(path: &Path) -> Result<Self, TransportError> {
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
        Ok(Self {
            stream,
            spec,
            pending: [0; 2 * (MAX_REPORT_LEN + 1)],
            filled: 0,
            start: Instant::now(),
            garbled_skipped: 0,
        })
    }

    fn disconnected(&self, source: std::io::Error) -> TransportError {
        TransportError::Disconnected {
            spec: self.spec.clone(),
            source,
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
                Ok(0) => return Err(self.disconnected(peer_closed())),
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
                        .map_err(|e| self.disconnected(e))?;
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(self.disconnected(e)),
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

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn take_garbled_skipped(&mut self) -> u64 {
        std::mem::take(&mut self.garbled_skipped)
    }

    fn describe(&self) -> String {
        self.spec.clone()
    }
}

/// The cause of a disconnection when the peer closed its end.
fn peer_closed() -> std::io::Error {
    std::io::Error::new(
        ErrorKind::UnexpectedEof,
        "the device side closed the connection",
    )
}
