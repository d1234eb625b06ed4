//! The in-process link to a simulated device ([`crate::sim::SimDevice`]): the mock-HID backend
//! behind `sim:MODEL`, in virtual time (as fast as the host runs) or real time.

use std::time::{Duration, Instant};

use super::{NoDeviceInfo, Pacing, Transport, TransportError};
use crate::profile::Codec;
use crate::protocol::{DeviceInfo, DEVICE_INFO_LEN, MAX_REPORT_LEN};
use crate::sim::SimDevice;
use crate::sys::sleep_until;

/// A [`SimDevice`] behind the [`Transport`] trait, in virtual or real time.
pub struct SimTransport {
    device: SimDevice,
    /// The firmware's device-info report, asked for when the link was made.
    info: Result<DeviceInfo, NoDeviceInfo>,
    pacing: Pacing,
    started: bool,
    start: Instant,
    /// Wall-clock time of the next report when pacing in real time.
    next_report: Instant,
}

impl SimTransport {
    pub fn new(device: SimDevice, pacing: Pacing) -> Self {
        let now = Instant::now();
        let profile = device.profile();
        let info = if profile.wire.has_device_info() {
            // As a HID host would: ask for the feature report and decode its bytes.
            let mut report = [0u8; DEVICE_INFO_LEN];
            device.device_info_report(false, &mut report);
            DeviceInfo::decode(&report).map_err(NoDeviceInfo::Malformed)
        } else {
            profile
                .device_info(1.0 / device.period())
                .ok_or(NoDeviceInfo::NotAsked)
        };
        Self {
            info,
            device,
            pacing,
            started: false,
            start: now,
            next_report: now,
        }
    }

    pub fn device(&self) -> &SimDevice {
        &self.device
    }

    fn period(&self) -> Duration {
        Duration::from_secs_f64(self.device.period())
    }
}

impl Transport for SimTransport {
    fn sim_world(&self) -> Option<std::sync::Arc<crate::sim::LiveWorld>> {
        Some(self.device.world())
    }

    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        if self.device.is_silent() {
            // The device keeps moving but says nothing: the host's read times out.
            let periods = (timeout.as_secs_f64() / self.device.period())
                .ceil()
                .max(1.0) as u32;
            if self.pacing == Pacing::RealTime {
                std::thread::sleep(timeout);
            }
            for _ in 0..periods {
                self.device.advance();
            }
            return Ok(None);
        }
        // The first report shows the state at power-on; each later one follows a period of
        // integration under the command the host sent in reply to the previous report.
        if self.started {
            self.device.advance();
        }
        self.started = true;
        if self.pacing == Pacing::RealTime {
            let period = self.period();
            self.next_report += period;
            let now = Instant::now();
            if now < self.next_report {
                sleep_until(self.next_report);
            } else {
                // The host was late: reports it did not collect are gone, as with a USB endpoint
                // that overwrote its buffer. Skip ahead rather than deliver a burst.
                while self.next_report + period <= now {
                    self.device.advance();
                    self.next_report += period;
                }
            }
        }
        Ok(Some(self.device.input_report(buf)))
    }

    fn write_output(&mut self, report: &[u8]) -> Result<(), TransportError> {
        // A real device silently drops malformed reports; so does the firmware (and counts them).
        let _ = self.device.receive_output(report);
        Ok(())
    }

    fn now(&self) -> f64 {
        match self.pacing {
            Pacing::Virtual => self.device.time(),
            Pacing::RealTime => self.start.elapsed().as_secs_f64(),
        }
    }

    fn clock_drift(&self) -> f64 {
        0.0
    }

    fn codec(&self) -> Codec {
        self.device.profile().codec()
    }

    fn device_info(&self) -> Result<&DeviceInfo, &NoDeviceInfo> {
        self.info.as_ref()
    }

    fn describe(&self) -> String {
        let mode = match self.pacing {
            Pacing::Virtual => "virtual time",
            Pacing::RealTime => "real time",
        };
        format!("simulated device ({mode})")
    }
}
