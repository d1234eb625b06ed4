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

/// How fast a device clock may run slow against the host's unless its transport says otherwise
/// ([`Transport::clock_drift`]): 200 ppm, twice a crystal's usual tolerance.
pub const CLOCK_DRIFT: f64 = 2e-4;

/// Why a transport failed.
#[derive(Debug, Error)]
pub enum TransportError {
    #[error("cannot open device {spec}: {reason}")]
    Open { spec: String, reason: String },
    #[error("device disconnected: {0}")]
    Disconnected(String),
    #[error("device I/O error: {0}")]
    Io(String),
}

/// One device connection, as the servo loop uses it.
pub trait Transport: Send {
    /// Wait at most `timeout` for the next input report. Returns the newest *valid* report
    /// available (older queued ones are skipped, as after an overrun; see [`Burst`]), a garbled
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
            let device = crate::sim::SimDevice::from_config(model, config).map_err(|e| {
                TransportError::Open {
                    spec: spec.to_string(),
                    reason: e.to_string(),
                }
            })?;
            Ok(Box::new(sim::SimTransport::new(device, pacing)))
        }
        DeviceSpec::Socket { path } => Ok(Box::new(socket::SocketTransport::connect(path)?)),
    }
}
