//! Transports carry HID reports between hgcd and a device: real hardware through hidapi
//! ([`hid`]), an in-process simulated device ([`sim`], the device itself lives in
//! [`crate::sim`]), or a Unix stream socket to an external simulator or bridge ([`socket`]). The servo loop sees only the [`Transport`] trait.

pub mod hid;
pub mod sim;
pub mod socket;

use std::time::Duration;

use thiserror::Error;

use crate::config::{Config, DeviceSpec};
use crate::protocol::{InputReport, MAX_REPORT_LEN, OUTPUT_REPORT_LEN};
use crate::sim::SimError;

/// How fast a device clock may run slow against the host's unless its transport says otherwise
/// ([`Transport::clock_drift`]): 200 ppm, twice a crystal's usual tolerance.
pub const CLOCK_DRIFT: f64 = 2e-4;

/// Why a transport failed. Every variant names the device (`spec`); the OS or library error that
/// caused it, where there is one, is kept as the [`source`](std::error::Error::source).
#[derive(Debug, Error)]
pub enum TransportError {
    /// No plugged-in device matches the spec.
    #[error(
        "cannot open device {spec}: no such device is plugged in \
         (run `hgcd devices` to list what hgcd can see)"
    )]
    NotFound { spec: String },
    /// The device node, socket or a helper thread could not be opened or started.
    #[error("cannot open device {spec}: {doing}{}", access_hint(.source))]
    Open {
        spec: String,
        /// What hgcd was doing, e.g. "opening /dev/hidraw3".
        doing: String,
        #[source]
        source: std::io::Error,
    },
    /// hidapi could not start or could not open the device.
    #[error("cannot open device {spec}: {doing}")]
    Hid {
        spec: String,
        doing: String,
        #[source]
        source: hidapi::HidError,
    },
    /// Another process holds the device's lock.
    #[error(
        "cannot open device {spec}: {node} is in use by another hgcd process \
         (the daemon? use `hgcd calibrate --via-daemon`)"
    )]
    Busy { spec: String, node: String },
    /// The simulated device's configuration cannot be used (`[sim]`: its model, start
    /// position or `sim.mass_grid`).
    #[error("cannot open device {spec}: its simulated plant cannot be built")]
    Simulation {
        spec: String,
        #[source]
        source: SimError,
    },
    /// The device went away: unplugged, its socket peer closed, or its writer failed.
    #[error("device {spec} disconnected")]
    Disconnected {
        spec: String,
        #[source]
        source: std::io::Error,
    },
    /// The socket peer broke the framing (`docs/hid-protocol.md`, "Socket framing"): the stream
    /// cannot be resynchronised.
    #[error("device {spec} sent a frame of length {length} (must be 1 to {MAX_REPORT_LEN})")]
    Framing { spec: String, length: usize },
}

impl TransportError {
    /// Whether the device cannot be opened or is gone (as opposed to a fault of the link itself):
    /// `hgcd` exits with its own status for these, so udev can start it again on replug.
    pub fn device_unavailable(&self) -> bool {
        !matches!(self, Self::Framing { .. })
    }
}

/// The remedy for a permission error, appended to its message.
fn access_hint(e: &std::io::Error) -> &'static str {
    if e.kind() == std::io::ErrorKind::PermissionDenied {
        " (permission denied: install udev/70-hgcd.rules and add yourself to group `hgcd`, \
         see docs/install.md)"
    } else {
        ""
    }
}

/// One device connection, as the servo loop uses it.
pub trait Transport: Send {
    /// Wait at most `timeout` for the next input report. Returns the newest *valid* report
    /// available (older queued ones are skipped, as after an overrun; see `Burst`), a garbled
    /// one only when nothing valid came, `Ok(None)` when nothing came in time.
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError>;

    /// Hand an output report to the device. Must not block the caller for longer than a small
    /// fraction of a servo period.
    fn write_output(&mut self, report: &[u8; OUTPUT_REPORT_LEN]) -> Result<(), TransportError>;

    /// Seconds on this transport's clock: virtual time for batch simulations, monotonic otherwise.
    fn now(&self) -> f64;

    /// Garbled reports dropped from bursts since the last call (not counting one `read_input`
    /// returned). Transports that deliver one report per read have none.
    fn take_garbled_skipped(&mut self) -> u64 {
        0
    }

    /// How far this device's clock may run slow against the host's, as a fraction; the loop's
    /// lateness statistics allow for it. A simulated device times its reports by the host's
    /// clock and drifts not at all.
    fn clock_drift(&self) -> f64 {
        CLOCK_DRIFT
    }

    /// Human-readable description for logs.
    fn describe(&self) -> String;

    /// The spec of the device actually opened, when it says more than the one asked for (a HID
    /// device's serial number). Grids are named after it, so a device opened with or without its
    /// serial finds the same grid.
    fn resolved_spec(&self) -> Option<DeviceSpec> {
        None
    }
}

/// Picks the report to act on from a burst of queued input reports, offered oldest first: the
/// newest valid one. A garbled report is never chosen over a valid one, so a device (or a line)
/// that garbles the last report of every burst still drives the loop; garbled ones are counted.
#[derive(Debug, Default)]
pub(crate) struct Burst {
    /// Length of the chosen report (in the caller's buffer) and whether it is valid.
    chosen: Option<(usize, bool)>,
    garbled: u64,
}

impl Burst {
    /// Consider `report` (newer than all offered before); copied into `buf` if it is chosen.
    pub(crate) fn offer(&mut self, report: &[u8], buf: &mut [u8; MAX_REPORT_LEN]) {
        let n = report.len().min(MAX_REPORT_LEN);
        let valid = InputReport::decode(&report[..n]).is_ok();
        if !valid {
            self.garbled += 1;
        }
        if valid || !matches!(self.chosen, Some((_, true))) {
            buf[..n].copy_from_slice(&report[..n]);
            self.chosen = Some((n, valid));
        }
    }

    /// Whether a report has been chosen.
    pub(crate) fn is_empty(&self) -> bool {
        self.chosen.is_none()
    }

    /// The chosen report's length, and the garbled reports dropped (a garbled report that was
    /// chosen is left for the loop to count).
    pub(crate) fn finish(self) -> (Option<usize>, u64) {
        match self.chosen {
            Some((n, true)) => (Some(n), self.garbled),
            Some((n, false)) => (Some(n), self.garbled - 1),
            None => (None, 0),
        }
    }
}

/// How a simulated device keeps time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pacing {
    /// As fast as the CPU allows; the device clock is virtual (batch work and tests).
    Virtual,
    /// One report per period of wall-clock time, as a USB interrupt endpoint would pace the host.
    RealTime,
}

/// Open the device `spec` names. `pacing` applies to simulated devices only.
pub fn open(
    spec: &DeviceSpec,
    config: &Config,
    pacing: Pacing,
) -> Result<Box<dyn Transport>, TransportError> {
    match spec {
        DeviceSpec::Hid { vid, pid, serial } => Ok(Box::new(hid::HidTransport::open(
            *vid,
            *pid,
            serial.as_deref(),
        )?)),
        DeviceSpec::Sim { model } => {
            let device = crate::sim::SimDevice::from_config(model, config).map_err(|source| {
                TransportError::Simulation {
                    spec: spec.to_string(),
                    source,
                }
            })?;
            Ok(Box::new(sim::SimTransport::new(device, pacing)))
        }
        DeviceSpec::Socket { path } => Ok(Box::new(socket::SocketTransport::connect(path)?)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::error::Error as _;

    #[test]
    fn errors_keep_their_cause_and_name_the_remedy() {
        let denied = TransportError::Open {
            spec: "hid:1234:0006".into(),
            doing: "opening /dev/hidraw3".into(),
            source: std::io::Error::from(std::io::ErrorKind::PermissionDenied),
        };
        assert!(denied.to_string().contains("udev/70-hgcd.rules"));
        let cause = denied.source().unwrap().downcast_ref::<std::io::Error>();
        assert_eq!(
            cause.map(std::io::Error::kind),
            Some(std::io::ErrorKind::PermissionDenied)
        );
        assert!(denied.device_unavailable());
        let framing = TransportError::Framing {
            spec: "socket:/tmp/d".into(),
            length: 200,
        };
        assert!(!framing.device_unavailable());
        assert!(framing.to_string().contains("length 200"));
    }
}
