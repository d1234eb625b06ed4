//! The mock-HID backend: emulated device firmware around a simulated plant. It decodes output
//! reports and encodes input reports exactly as a v1 device would, so the whole byte path runs in
//! tests. The firmware clamps forces to its actuator limit, zeroes force when the host goes silent
//! (device-side watchdog), and can be told to stop reporting (fault injection).

use std::time::{Duration, Instant};

use nalgebra::Vector3;

use super::{Pacing, Transport, TransportError, MAX_REPORT_LEN};
use crate::config::Config;
use crate::grid::GridError;
use crate::protocol::{
    InputReport, OutputReport, ProtocolError, Status, INPUT_REPORT_LEN, OUTPUT_REPORT_LEN,
};
use crate::sim::{Encoder, Plant, PointMass};

/// Emulated device firmware: one report period at a time.
pub struct SimDevice {
    plant: Box<dyn Plant>,
    encoder: Encoder,
    /// Report period, s.
    period: f64,
    substeps: u32,
    max_force: f64,
    device_watchdog: f64,
    stop_reporting_after: Option<f64>,
    /// Device clock, µs since power-on.
    clock_us: u64,
    sequence: u16,
    command: Vector3<f64>,
    enabled: bool,
    last_command_us: u64,
    saturated: bool,
    watchdog_tripped: bool,
    last_output: Option<OutputReport>,
    rejected_outputs: u64,
}

impl SimDevice {
    /// A device around `plant`, reporting every `period` s and integrating at `substep_hz`.
    pub fn new(
        plant: Box<dyn Plant>,
        encoder: Encoder,
        period: f64,
        substep_hz: f64,
        max_force: f64,
        device_watchdog: f64,
    ) -> Self {
        Self {
            plant,
            encoder,
            period,
            substeps: (period * substep_hz).ceil().max(1.0) as u32,
            max_force,
            device_watchdog,
            stop_reporting_after: None,
            clock_us: 0,
            sequence: 0,
            command: Vector3::zeros(),
            enabled: false,
            last_command_us: 0,
            saturated: false,
            watchdog_tripped: false,
            last_output: None,
            rejected_outputs: 0,
        }
    }

    /// The device a config describes (`[sim]` section, report rate from `[servo]`). `model` has
    /// been checked by [`crate::config::DeviceSpec`]; `point-mass` is the only model so far.
    pub fn from_config(model: &str, config: &Config) -> Result<Self, GridError> {
        debug_assert!(crate::config::SIM_MODELS.contains(&model));
        let sim = &config.sim;
        let plant: Box<dyn Plant> = Box::new(PointMass::from_config(sim)?);
        let mut device = Self::new(
            plant,
            Encoder::from_config(sim),
            config.servo_period(),
            sim.substep_hz,
            sim.max_force_n,
            sim.device_watchdog(),
        );
        device.stop_reporting_after = sim.stop_reporting_after_s;
        Ok(device)
    }

    /// Fault injection: stop sending input reports once the device clock passes `t` s.
    pub fn stop_reporting_after(&mut self, t: Option<f64>) {
        self.stop_reporting_after = t;
    }

    /// Report period, s.
    pub fn period(&self) -> f64 {
        self.period
    }

    /// Device time, s.
    pub fn time(&self) -> f64 {
        self.clock_us as f64 * 1e-6
    }

    /// The plant (ground truth for tests).
    pub fn plant(&self) -> &dyn Plant {
        self.plant.as_ref()
    }

    /// The last output report the firmware accepted.
    pub fn last_output(&self) -> Option<OutputReport> {
        self.last_output
    }

    /// Output reports the firmware rejected as malformed.
    pub fn rejected_outputs(&self) -> u64 {
        self.rejected_outputs
    }

    /// Whether the device is currently silent (fault injection).
    pub fn is_silent(&self) -> bool {
        self.stop_reporting_after.is_some_and(|t| self.time() >= t)
    }

    /// Firmware receive path: decode an output report and latch its force command.
    pub fn receive_output(&mut self, bytes: &[u8]) -> Result<(), ProtocolError> {
        match OutputReport::decode(bytes) {
            Ok(report) => {
                self.command = if report.enable {
                    report.force
                } else {
                    Vector3::zeros()
                };
                self.enabled = report.enable;
                self.last_command_us = self.clock_us;
                self.watchdog_tripped = false;
                self.last_output = Some(report);
                Ok(())
            }
            Err(e) => {
                self.rejected_outputs += 1;
                Err(e)
            }
        }
    }

    /// Integrate one report period under the latched command (clamped; zero after the device
    /// watchdog trips) and advance the clock and sequence number.
    pub fn advance(&mut self) {
        if (self.clock_us - self.last_command_us) as f64 * 1e-6 > self.device_watchdog {
            self.watchdog_tripped = true;
            self.command = Vector3::zeros();
        }
        let mut force = self.command;
        self.saturated = false;
        for axis in 0..3 {
            if force[axis].abs() > self.max_force {
                force[axis] = force[axis].signum() * self.max_force;
                self.saturated = true;
            }
        }
        let dt = self.period / f64::from(self.substeps);
        for _ in 0..self.substeps {
            self.plant.step(&force, dt);
        }
        self.clock_us += (self.period * 1e6).round() as u64;
        self.sequence = self.sequence.wrapping_add(1);
    }

    /// Firmware send path: the input report for the current state.
    pub fn input_report(&mut self, out: &mut [u8; INPUT_REPORT_LEN]) {
        let status = Status::default()
            .with(
                Status::MOTORS_ENABLED,
                self.enabled && !self.watchdog_tripped,
            )
            .with(Status::FORCE_SATURATED, self.saturated)
            .with(Status::DEVICE_WATCHDOG, self.watchdog_tripped);
        let (lo, hi) = self.plant.workspace();
        let measured = self.encoder.measure(&self.plant.position());
        let report = InputReport {
            sequence: self.sequence,
            timestamp_us: self.clock_us as u32,
            // Noise may push a reading just past a stop; the encoder cannot read beyond it.
            position: measured
                .sup(&(lo.add_scalar(-1e-3)))
                .inf(&hi.add_scalar(1e-3)),
            status,
        };
        report
            .encode(out)
            .expect("simulated workspace lies within the protocol's position range");
    }
}

/// A [`SimDevice`] behind the [`Transport`] trait, in virtual or real time.
pub struct SimTransport {
    device: SimDevice,
    pacing: Pacing,
    started: bool,
    start: Instant,
    /// Wall-clock time of the next report when pacing in real time.
    next_report: Instant,
}

impl SimTransport {
    pub fn new(device: SimDevice, pacing: Pacing) -> Self {
        let now = Instant::now();
        Self {
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

    pub fn device_mut(&mut self) -> &mut SimDevice {
        &mut self.device
    }

    fn period(&self) -> Duration {
        Duration::from_secs_f64(self.device.period)
    }
}

impl Transport for SimTransport {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        if self.device.is_silent() {
            // The device keeps moving but says nothing: the host's read times out.
            let periods = (timeout.as_secs_f64() / self.device.period).ceil().max(1.0) as u32;
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
        let mut report = [0u8; INPUT_REPORT_LEN];
        self.device.input_report(&mut report);
        buf[..INPUT_REPORT_LEN].copy_from_slice(&report);
        Ok(Some(INPUT_REPORT_LEN))
    }

    fn write_output(&mut self, report: &[u8; OUTPUT_REPORT_LEN]) -> Result<(), TransportError> {
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

    fn describe(&self) -> String {
        let mode = match self.pacing {
            Pacing::Virtual => "virtual time",
            Pacing::RealTime => "real time",
        };
        format!("simulated device ({mode})")
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
