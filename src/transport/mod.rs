//! Transports carry HID reports between hgcd and a device: real hardware through hidapi
//! ([`hid`]), the mock-HID firmware around a simulated plant ([`sim`]), or a Unix stream socket to an
//! external simulator or bridge ([`socket`]). The servo loop sees only the [`Transport`] trait.

pub mod hid;
pub mod sim;
pub mod socket;

use std::time::Duration;

use thiserror::Error;

use crate::config::{Config, DeviceSpec};
use crate::protocol::OUTPUT_REPORT_LEN;

/// Largest report a transport hands up; longer ones are cut and then rejected by the decoder.
pub const MAX_REPORT_LEN: usize = 64;

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
    /// Wait at most `timeout` for the next input report. Returns the newest report available (older
    /// queued ones are skipped, as after an overrun), `Ok(None)` when none came in time.
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

    /// Human-readable description for logs.
    fn describe(&self) -> String;

    /// The spec of the device actually opened, when it says more than the one asked for (a HID
    /// device's serial number). Grids are named after it, so a device opened with or without its
    /// serial finds the same grid.
    fn resolved_spec(&self) -> Option<DeviceSpec> {
        None
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
            let device =
                sim::SimDevice::from_config(model, config).map_err(|e| TransportError::Open {
                    spec: spec.to_string(),
                    reason: e.to_string(),
                })?;
            Ok(Box::new(sim::SimTransport::new(device, pacing)))
        }
        DeviceSpec::Socket { path } => Ok(Box::new(socket::SocketTransport::connect(path)?)),
    }
}
