//! Transports carry HID reports between hgcd and a device: real hardware through hidapi
//! ([`hid`]), an in-process simulated device ([`sim`], the device itself lives in
//! [`crate::sim`]), or a Unix stream socket to an external simulator or bridge ([`socket`]). The servo loop sees only the [`Transport`] trait.

pub mod hid;
pub mod sim;
pub mod socket;

use std::time::Duration;

use thiserror::Error;
use tracing::{info, warn};

use crate::config::{Config, DeviceSpec};
use crate::grid::DeviceIdentity;
use crate::profile::{Codec, Profile, ProfileError, Wire};
use crate::protocol::{DeviceInfo, ProtocolError, MAX_REPORT_LEN};
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
    /// A lock-step device sent nothing for [`socket::LOCKSTEP_STALL`] of wall-clock time: its
    /// clock stands still while it is silent, so no watchdog can tell; it has hung.
    #[error("device {spec} (lock-step) has sent nothing for {after:?}: it has stopped")]
    Stalled { spec: String, after: Duration },
    /// The device's profile cannot be loaded (`device.profile`, `--profile`).
    #[error("cannot open device {spec}: {source}")]
    Profile {
        spec: String,
        #[source]
        source: ProfileError,
    },
    /// The device's native rate (its device-info report) is not the host's `servo.rate_hz`.
    #[error(
        "device {spec} reports at {device_hz} Hz (its device-info report) but servo.rate_hz is \
         {servo_hz}: set servo.rate_hz = {device_hz}"
    )]
    Rate {
        spec: String,
        device_hz: f64,
        servo_hz: f64,
    },
}

impl TransportError {
    /// Whether the device cannot be opened or is gone (as opposed to a fault of the link itself,
    /// or a device hgcd is not configured for): `hgcd` exits with its own status for these, so
    /// udev can start it again on replug.
    pub fn device_unavailable(&self) -> bool {
        !matches!(
            self,
            Self::Framing { .. } | Self::Rate { .. } | Self::Profile { .. }
        )
    }
}

/// Why a device gave no device-info report when it was opened (it then runs as before the report
/// existed: grid named after its spec, calibration cube from the config).
#[derive(Clone, Debug, Error, PartialEq)]
pub enum NoDeviceInfo {
    /// The transport does not ask (a test double).
    #[error("it was not asked")]
    NotAsked,
    /// No answer within the wait (a device that does not know the request ignores it).
    #[error("it did not answer within {0:?}")]
    NoAnswer(Duration),
    /// The device refused the request (a HID device without the feature report stalls it).
    #[error("it refused the request ({0})")]
    Refused(String),
    /// It answered with a report that does not decode.
    #[error("its answer is malformed: {0}")]
    Malformed(#[source] ProtocolError),
}

/// Returned by transports that do not ask for device info.
static NOT_ASKED: NoDeviceInfo = NoDeviceInfo::NotAsked;

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
    ///
    /// # Errors
    /// [`TransportError::Disconnected`] when the device is gone; from a socket device also
    /// [`TransportError::Framing`] and [`TransportError::Stalled`].
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError>;

    /// Hand an output report (at most [`crate::protocol::OUTPUT_REPORT_LEN`] bytes, in the
    /// device's protocol) to the device. Must not block the caller for longer than a small
    /// fraction of a servo period.
    ///
    /// # Errors
    /// [`TransportError::Disconnected`] when the device is gone.
    fn write_output(&mut self, report: &[u8]) -> Result<(), TransportError>;

    /// The host side of the device's profile: what turns its reports into positions and forces
    /// into its reports. Protocol v1 unless the transport was opened with another profile.
    fn codec(&self) -> Codec {
        Codec::Cartesian
    }

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

    /// For a simulated device in this process, where its payload and gravity can be changed
    /// while it runs (`hgcd run` on SIGHUP; docs/simulated-devices.md). None for real devices.
    fn sim_world(&self) -> Option<std::sync::Arc<crate::sim::LiveWorld>> {
        None
    }

    /// The spec of the device actually opened, when it says more than the one asked for (a HID
    /// device's serial number). Grids are named after it, so a device opened with or without its
    /// serial finds the same grid.
    fn resolved_spec(&self) -> Option<DeviceSpec> {
        None
    }

    /// What the device said about itself in its device-info report, asked for once when it was
    /// opened (`docs/hid-protocol.md` §5a), or why it said nothing; for a device whose protocol
    /// has no such report, what its profile says in its place.
    fn device_info(&self) -> Result<&DeviceInfo, &NoDeviceInfo> {
        Err(&NOT_ASKED)
    }
}

/// Who the device behind `transport`, opened with `spec`, is: the spec it resolved to and its
/// device-info report. Logs what the device said about itself, or, once, that it said nothing
/// and hgcd falls back to its spec and config.
///
/// # Errors
/// [`TransportError::Rate`] for a device whose native rate is not `servo.rate_hz`.
pub fn identify(
    transport: &dyn Transport,
    spec: &DeviceSpec,
    config: &Config,
) -> Result<DeviceIdentity, TransportError> {
    let spec = transport.resolved_spec().unwrap_or_else(|| spec.clone());
    let info = match transport.device_info() {
        Ok(info) => info.clone(),
        Err(why) => {
            if *why != NoDeviceInfo::NotAsked {
                warn!(
                    "device {spec} gave no device-info report ({why}): its grid is named after \
                     its spec ({}) and it is calibrated in the configured workspace",
                    spec.device_id()
                );
            }
            return Ok(DeviceIdentity::of_spec(spec));
        }
    };
    let servo_hz = config.servo.rate_hz;
    if (info.rate_hz - servo_hz).abs() > 1e-3 {
        return Err(TransportError::Rate {
            spec: spec.to_string(),
            device_hz: info.rate_hz,
            servo_hz,
        });
    }
    let (lo, hi) = info.workspace();
    let (lo, hi) = (lo * 1e3, hi * 1e3);
    info!(
        "device {spec}: {}{}, workspace ({:.1}, {:.1}, {:.1}) to ({:.1}, {:.1}, {:.1}) mm, force \
         limit {} N, {} Hz{}",
        info.model,
        if info.serial.is_empty() {
            String::new()
        } else {
            format!(" serial {}", info.serial)
        },
        lo.x,
        lo.y,
        lo.z,
        hi.x,
        hi.y,
        hi.z,
        info.max_force,
        info.rate_hz,
        if info.lockstep {
            ", lock-step (the run counts device time)"
        } else {
            ""
        }
    );
    if info.max_force < config.safety.max_force_n {
        warn!(
            "device {spec} renders at most {} N: the host limits its forces to that, not to \
             safety.max_force_n ({} N)",
            info.max_force, config.safety.max_force_n
        );
    }
    Ok(DeviceIdentity::new(spec, Some(info)))
}

/// Picks the report to act on from a burst of queued input reports, offered oldest first: the
/// newest valid one. A garbled report is never chosen over a valid one, so a device (or a line)
/// that garbles the last report of every burst still drives the loop; garbled ones are counted.
#[derive(Debug)]
pub(crate) struct Burst {
    /// The protocol valid reports are in.
    wire: Wire,
    /// Length of the chosen report (in the caller's buffer) and whether it is valid.
    chosen: Option<(usize, bool)>,
    garbled: u64,
}

impl Burst {
    /// An empty burst of reports in `wire`'s protocol.
    pub(crate) fn new(wire: Wire) -> Self {
        Self {
            wire,
            chosen: None,
            garbled: 0,
        }
    }

    /// Consider `report` (newer than all offered before); copied into `buf` if it is chosen.
    pub(crate) fn offer(&mut self, report: &[u8], buf: &mut [u8; MAX_REPORT_LEN]) {
        let n = report.len().min(MAX_REPORT_LEN);
        let valid = self.wire.input_valid(&report[..n]);
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

impl Pacing {
    /// Whether the device sets the loop's pace rather than the wall clock: a simulated device in
    /// virtual time, or one that declares lock-step (its device-info report). Such a loop runs
    /// flat out, so it must never take a core at real-time priority.
    pub fn set_by_device(self, device: &DeviceIdentity) -> bool {
        self == Pacing::Virtual || device.info.as_ref().is_some_and(|i| i.lockstep)
    }
}

/// How a transport speaks to a device of `profile` (a simulated device knows its own).
#[derive(Clone, Debug)]
pub struct Speaks {
    pub wire: Wire,
    /// For a protocol without a device-info report, what the profile says in its place.
    pub info: Option<DeviceInfo>,
    pub codec: Codec,
}

impl Default for Speaks {
    /// Protocol v1 (the default profile, [`crate::profile::CARTESIAN_V1`]).
    fn default() -> Self {
        Self {
            wire: Wire::CartesianV1,
            info: None,
            codec: Codec::Cartesian,
        }
    }
}

impl Speaks {
    /// A device of `profile` reporting at `rate_hz`.
    pub fn profile(profile: &Profile, rate_hz: f64) -> Self {
        Self {
            wire: profile.wire,
            info: profile.device_info(rate_hz),
            codec: profile.codec(),
        }
    }
}

/// Open the device `spec` names, speaking its profile ([`Profile::for_device`]). `pacing`
/// applies to simulated devices only.
///
/// # Errors
/// Those of [`hid::HidTransport::open`] and [`socket::SocketTransport::connect`],
/// [`TransportError::Profile`] for a profile that does not load, and
/// [`TransportError::Simulation`] for a simulated device its `[sim]` section cannot build.
pub fn open(
    spec: &DeviceSpec,
    config: &Config,
    pacing: Pacing,
) -> Result<Box<dyn Transport>, TransportError> {
    let speaks = || {
        Profile::for_device(spec, config)
            .map(|p| Speaks::profile(&p, config.servo.rate_hz))
            .map_err(|source| TransportError::Profile {
                spec: spec.to_string(),
                source,
            })
    };
    match spec {
        DeviceSpec::Hid { vid, pid, serial } => Ok(Box::new(hid::HidTransport::open(
            *vid,
            *pid,
            serial.as_deref(),
            speaks()?,
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
        DeviceSpec::Socket { path } => {
            Ok(Box::new(socket::SocketTransport::connect(path, speaks()?)?))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::error::Error as _;

    #[test]
    fn a_device_that_reports_at_another_rate_is_refused_naming_the_key_to_set() {
        let config = Config::default();
        let device = crate::sim::SimDevice::from_config("point-mass", &config).unwrap();
        let sim = sim::SimTransport::new(device, Pacing::Virtual);
        let spec: DeviceSpec = "sim:point-mass".parse().unwrap();
        let identity = identify(&sim, &spec, &config).unwrap();
        assert_eq!(identity.grid_id(), "sim-point-mass");
        assert_eq!(identity.info.unwrap().model, "sim-point-mass");
        let mut slower = config.clone();
        slower.servo.rate_hz = 500.0;
        let err = identify(&sim, &spec, &slower).unwrap_err();
        assert_eq!(
            err.to_string(),
            "device sim:point-mass reports at 1000 Hz (its device-info report) but \
             servo.rate_hz is 500: set servo.rate_hz = 1000"
        );
        assert!(!err.device_unavailable());
    }

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
