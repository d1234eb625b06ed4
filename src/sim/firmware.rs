//! Emulated device firmware around a simulated plant: it decodes output reports and encodes input
//! reports exactly as a v1 device would, and answers the device-info feature report, so the whole
//! byte path runs in tests. The firmware clamps forces to its actuator limit, zeroes force when
//! the host goes silent (device-side watchdog), and can be told to stop reporting (fault
//! injection). `sim:woodenhaptics` speaks its own joint-space protocol instead
//! ([`JointFirmware`]), with the same clock, pacing and fault injection.

use std::sync::Arc;

use nalgebra::Vector3;

use super::woodenhaptics::{self, JointFirmware};
use super::{delta, phantom, Encoder, LiveWorld, Plant, PointMass, SimError};
use crate::config::{Config, DeviceSpec};
use crate::profile::{self, Profile, Wire};
use crate::protocol::{
    DeviceInfo, InputReport, OutputReport, ProtocolError, Status, DEVICE_INFO_LEN,
    INPUT_REPORT_LEN, MAX_REPORT_LEN, MODEL_LEN,
};

/// The longest actuator delay simulated, report periods (`sim.force_delay_ms` at 1 kHz is at
/// most 100).
const MAX_DELAY_PERIODS: usize = 128;

/// What the firmware drives and how it speaks.
// One per simulated device, never moved once built.
#[allow(clippy::large_enum_variant)]
enum Body {
    /// Protocol v1 around any plant, its position measured by `encoder`.
    Cartesian {
        plant: Box<dyn Plant>,
        encoder: Encoder,
    },
    /// The WoodenHaptics protocol around its arm.
    Joints(Box<JointFirmware>),
}

/// Emulated device firmware: one report period at a time.
pub struct SimDevice {
    body: Body,
    /// The profile that describes this device to a host.
    profile: Profile,
    /// Model name in the device-info report (`sim-MODEL`).
    model: String,
    /// Serial number in the device-info report (`sim.serial`; empty: none).
    serial: String,
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
    /// The actuators' delay line: the commands of the last `delay` periods, oldest first out.
    delayed: [Vector3<f64>; MAX_DELAY_PERIODS],
    delay: usize,
    delay_slot: usize,
    /// The position sensing's delay line: the positions of the last `sensing_delay` reports,
    /// oldest first out (filled with the first reading at the first report).
    sensed: [Vector3<f64>; MAX_DELAY_PERIODS],
    sensing_delay: usize,
    sensed_slot: usize,
    sensed_filled: bool,
    /// What the actuators render of each axis's command (protocol v1).
    force_scale: Vector3<f64>,
    /// Motor cogging: amplitude, N, and pitch, m (protocol v1).
    cogging: (f64, f64),
    /// The table's vibration: amplitude, N, and frequency, Hz (protocol v1).
    vibration: (f64, f64),
    enabled: bool,
    last_command_us: u64,
    saturated: bool,
    watchdog_tripped: bool,
    last_output: Option<OutputReport>,
    rejected_outputs: u64,
    /// Changes of payload and gravity made while it runs, and the last one taken.
    world: Arc<LiveWorld>,
    world_seen: u64,
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
        let body = Body::Cartesian { plant, encoder };
        Self::around(body, period, substep_hz, max_force, device_watchdog)
    }

    fn around(
        body: Body,
        period: f64,
        substep_hz: f64,
        max_force: f64,
        device_watchdog: f64,
    ) -> Self {
        Self {
            body,
            profile: Profile::cartesian(),
            model: "sim".into(),
            serial: String::new(),
            period,
            substeps: (period * substep_hz).ceil().max(1.0) as u32,
            max_force,
            device_watchdog,
            stop_reporting_after: None,
            clock_us: 0,
            sequence: 0,
            command: Vector3::zeros(),
            delayed: [Vector3::zeros(); MAX_DELAY_PERIODS],
            delay: 0,
            delay_slot: 0,
            sensed: [Vector3::zeros(); MAX_DELAY_PERIODS],
            sensing_delay: 0,
            sensed_slot: 0,
            sensed_filled: false,
            force_scale: Vector3::repeat(1.0),
            cogging: (0.0, 1.0),
            vibration: (0.0, 1.0),
            enabled: false,
            last_command_us: 0,
            saturated: false,
            watchdog_tripped: false,
            last_output: None,
            rejected_outputs: 0,
            world: Arc::default(),
            world_seen: 0,
        }
    }

    /// Where the payload on its handle and the direction of gravity can be changed while it
    /// runs; the device takes a change before its next period.
    pub fn world(&self) -> Arc<LiveWorld> {
        self.world.clone()
    }

    /// The device `sim:MODEL` a config describes (`[sim]` section, report rate from `[servo]`).
    ///
    /// # Errors
    /// [`SimError::UnknownModel`] for a model not in [`crate::config::SIM_MODELS`],
    /// [`SimError::Grid`] for a mass grid that does not load, [`SimError::Unreachable`] for a start
    /// position a linkage cannot reach.
    pub fn from_config(model: &str, config: &Config) -> Result<Self, SimError> {
        let sim = &config.sim;
        let unreachable = |model| SimError::Unreachable {
            model,
            position_mm: sim.start_position_mm,
        };
        let plant: Box<dyn Plant> = match model {
            "point-mass" => Box::new(PointMass::from_config(sim)?),
            "phantom" => Box::new(phantom::from_config(sim).map_err(|_| unreachable("phantom"))?),
            "delta" => Box::new(delta::from_config(sim).map_err(|_| unreachable("delta"))?),
            crate::config::SIM_WOODENHAPTICS => return Self::joint_from_config(config),
            _ => {
                return Err(SimError::UnknownModel {
                    model: model.into(),
                })
            }
        };
        let mut device = Self::new(
            plant,
            Encoder::from_config(sim),
            config.servo_period(),
            sim.substep_hz,
            sim.max_force_n,
            sim.device_watchdog(),
        );
        device.stop_reporting_after = sim.stop_reporting_after_s;
        device.delay =
            ((sim.force_delay() / device.period).round() as usize).min(MAX_DELAY_PERIODS);
        device.sensing_delay =
            ((sim.position_delay() / device.period).round() as usize).min(MAX_DELAY_PERIODS);
        device.force_scale = Vector3::from(sim.force_scale);
        device.cogging = (sim.cogging_n, sim.cogging_pitch_mm * 1e-3);
        device.vibration = (sim.vibration_n, sim.vibration_hz);
        device.model = format!("sim-{model}");
        device.serial = sim.serial.clone();
        Ok(device)
    }

    /// `sim:woodenhaptics`: the arm of the configured WoodenHaptics-protocol profile
    /// (`woodenhaptics_v2015` unless `device.profile` names another) behind its firmware.
    fn joint_from_config(config: &Config) -> Result<Self, SimError> {
        let sim = &config.sim;
        let spec = DeviceSpec::Sim {
            model: crate::config::SIM_WOODENHAPTICS.into(),
        };
        let profile = Profile::for_device(&spec, config)?;
        let arm = woodenhaptics::plant(sim, &profile)
            .ok_or_else(|| SimError::NoArm {
                profile: profile.name.clone(),
            })?
            .map_err(|_| SimError::Unreachable {
                model: crate::config::SIM_WOODENHAPTICS,
                position_mm: sim.start_position_mm,
            })?;
        let period = config.servo_period();
        let firmware = JointFirmware::new(arm, Encoder::from_config(sim));
        // The firmware limits currents, not forces: its force limit is the profile's.
        let mut device = Self::around(
            Body::Joints(Box::new(firmware)),
            period,
            sim.substep_hz,
            profile.max_force.unwrap_or(sim.max_force_n),
            profile::woodenhaptics::FIRMWARE_WATCHDOG,
        );
        device.stop_reporting_after = sim.stop_reporting_after_s;
        device.model = profile.name.clone();
        device.profile = profile;
        Ok(device)
    }

    /// The profile that describes this device to a host: what it speaks, and for a joint-space
    /// device what it cannot say about itself.
    pub fn profile(&self) -> &Profile {
        &self.profile
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
        match &self.body {
            Body::Cartesian { plant, .. } => plant.as_ref(),
            Body::Joints(firmware) => firmware.plant(),
        }
    }

    /// The joint-space firmware of `sim:woodenhaptics` (None for a v1 device).
    pub fn joint_firmware(&mut self) -> Option<&mut JointFirmware> {
        match &mut self.body {
            Body::Cartesian { .. } => None,
            Body::Joints(firmware) => Some(firmware),
        }
    }

    /// The last output report the firmware accepted.
    pub fn last_output(&self) -> Option<OutputReport> {
        self.last_output
    }

    /// Output reports the firmware rejected as malformed.
    pub fn rejected_outputs(&self) -> u64 {
        self.rejected_outputs
    }

    /// What the firmware says about itself: its model and serial number, the plant's workspace
    /// (its mechanical stops), its force limit and report rate. `lockstep` says how it is served
    /// (`docs/hid-protocol.md` §9).
    pub fn device_info(&self, lockstep: bool) -> DeviceInfo {
        let (lo, hi) = self.plant().workspace();
        // As much of `sim-MODEL` as the report's field holds.
        let mut model = self.model.clone();
        while model.len() > MODEL_LEN {
            model.pop();
        }
        DeviceInfo {
            model,
            serial: self.serial.clone(),
            workspace_centre: (lo + hi) / 2.0,
            workspace_half_extents: (hi - lo) / 2.0,
            max_force: self.max_force,
            rate_hz: 1.0 / self.period,
            lockstep,
        }
    }

    /// Firmware answer to a get-feature request for the device-info report.
    pub fn device_info_report(&self, lockstep: bool, out: &mut [u8; DEVICE_INFO_LEN]) {
        self.device_info(lockstep).encode(out).expect(
            "a validated config gives a serial, workspace and force limit the report carries",
        );
    }

    /// Whether the device is currently silent (fault injection).
    pub fn is_silent(&self) -> bool {
        self.stop_reporting_after.is_some_and(|t| self.time() >= t)
    }

    /// Firmware receive path: decode an output report and latch its force command.
    ///
    /// # Errors
    /// The [`ProtocolError`] of a report that does not decode (counted as rejected, not latched).
    pub fn receive_output(&mut self, bytes: &[u8]) -> Result<(), ProtocolError> {
        if let Body::Joints(firmware) = &mut self.body {
            let received = firmware.receive_output(bytes);
            if received.is_err() {
                self.rejected_outputs += 1;
            }
            return received;
        }
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
        if let Some((payload, up)) = self.world.changed(&mut self.world_seen) {
            match &mut self.body {
                Body::Cartesian { plant, .. } => plant.set_world(payload, &up),
                Body::Joints(firmware) => firmware.set_world(payload, &up),
            }
        }
        if let Body::Joints(firmware) = &mut self.body {
            firmware.advance(self.period, self.substeps);
            self.clock_us += (self.period * 1e6).round() as u64;
            return;
        }
        if (self.clock_us - self.last_command_us) as f64 * 1e-6 > self.device_watchdog {
            self.watchdog_tripped = true;
            self.command = Vector3::zeros();
        }
        let mut force = self.command;
        if self.delay > 0 {
            // The slot about to be overwritten holds the command of `delay` periods ago.
            force = std::mem::replace(&mut self.delayed[self.delay_slot], self.command);
            self.delay_slot = (self.delay_slot + 1) % self.delay;
        }
        self.saturated = false;
        for axis in 0..3 {
            if force[axis].abs() > self.max_force {
                force[axis] = force[axis].signum() * self.max_force;
                self.saturated = true;
            }
        }
        let force = force.component_mul(&self.force_scale);
        let dt = self.period / f64::from(self.substeps);
        let (cogging, pitch) = self.cogging;
        let (vibration, hz) = self.vibration;
        let start = self.time();
        if let Body::Cartesian { plant, .. } = &mut self.body {
            for i in 0..self.substeps {
                let mut disturbance = Vector3::zeros();
                if cogging > 0.0 {
                    disturbance += plant
                        .position()
                        .map(|x| cogging * (std::f64::consts::TAU * x / pitch).sin());
                }
                if vibration > 0.0 {
                    let t = start + f64::from(i) * dt;
                    disturbance += Vector3::repeat(
                        vibration * (std::f64::consts::TAU * hz * t).sin() / 3f64.sqrt(),
                    );
                }
                plant.step(&(force + disturbance), dt);
            }
        }
        self.clock_us += (self.period * 1e6).round() as u64;
        self.sequence = self.sequence.wrapping_add(1);
    }

    /// Firmware send path: the input report for the current state, in the device's protocol
    /// (its profile's wire); returns its length.
    pub fn input_report(&mut self, out: &mut [u8; MAX_REPORT_LEN]) -> usize {
        let (plant, encoder) = match &mut self.body {
            Body::Cartesian { plant, encoder } => (plant, encoder),
            Body::Joints(firmware) => {
                let mut report = [0; profile::woodenhaptics::REPORT_LEN];
                firmware.input_report(&mut report);
                out[..report.len()].copy_from_slice(&report);
                return report.len();
            }
        };
        let status = Status::default()
            .with(
                Status::MOTORS_ENABLED,
                self.enabled && !self.watchdog_tripped,
            )
            .with(Status::FORCE_SATURATED, self.saturated)
            .with(Status::DEVICE_WATCHDOG, self.watchdog_tripped);
        let (lo, hi) = plant.workspace();
        let mut measured = encoder.measure(plant.as_ref());
        if self.sensing_delay > 0 {
            if !self.sensed_filled {
                self.sensed[..self.sensing_delay].fill(measured);
                self.sensed_filled = true;
            }
            // The slot about to be overwritten holds the reading of `sensing_delay` reports ago.
            measured = std::mem::replace(&mut self.sensed[self.sensed_slot], measured);
            self.sensed_slot = (self.sensed_slot + 1) % self.sensing_delay;
        }
        let report = InputReport {
            sequence: self.sequence,
            timestamp_us: self.clock_us as u32,
            // Noise may push a reading just past a stop; the encoder cannot read beyond it.
            position: measured
                .sup(&(lo.add_scalar(-1e-3)))
                .inf(&hi.add_scalar(1e-3)),
            status,
        };
        let mut bytes = [0; INPUT_REPORT_LEN];
        report
            .encode(&mut bytes)
            .expect("simulated workspace lies within the protocol's position range");
        out[..INPUT_REPORT_LEN].copy_from_slice(&bytes);
        INPUT_REPORT_LEN
    }

    /// The protocol the device speaks.
    pub fn wire(&self) -> Wire {
        self.profile.wire
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::SIM_MODELS;

    #[test]
    fn every_simulated_model_describes_itself_in_a_device_info_report() {
        let mut config = Config::default();
        config.sim.serial = "SN-000000001".into(); // the longest serial the report carries
        config.sim.workspace_min_mm = [-1000.0, 20.0, -80.0];
        config.sim.workspace_max_mm = [1000.0, 220.0, 40.0];
        for model in SIM_MODELS
            .iter()
            .filter(|m| **m != crate::config::SIM_WOODENHAPTICS)
        {
            let device = SimDevice::from_config(model, &config).unwrap();
            let mut report = [0; DEVICE_INFO_LEN];
            device.device_info_report(true, &mut report);
            let info = DeviceInfo::decode(&report).unwrap();
            assert!(format!("sim-{model}").starts_with(&info.model));
            assert_eq!(info.serial, config.sim.serial);
            let (lo, hi) = info.workspace();
            let (stops_lo, stops_hi) = device.plant().workspace();
            assert!((lo - stops_lo).amax() < 1e-9 && (hi - stops_hi).amax() < 1e-9);
            assert_eq!(info.max_force, config.sim.max_force_n);
            assert_eq!(info.rate_hz, config.servo.rate_hz);
            assert!(info.lockstep);
        }
    }
}
