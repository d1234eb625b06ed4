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

/// The longest delay simulated, report periods (`sim.force_delay_ms` and
/// `sim.position_delay_ms` at 1 kHz are at most 100).
const MAX_DELAY_PERIODS: usize = 128;

/// A delay of `delay` seconds in whole report periods of `period` seconds.
pub(crate) fn delay_periods(delay: f64, period: f64) -> usize {
    ((delay / period).round() as usize).min(MAX_DELAY_PERIODS)
}

/// A delay of whole report periods: each value pushed comes out `periods` pushes later (at
/// once for none). Allocation-free, as the firmware it sits in.
#[derive(Clone, Debug)]
pub(crate) struct DelayLine<T: Copy> {
    slots: [T; MAX_DELAY_PERIODS],
    periods: usize,
    next: usize,
    /// Whether the slots hold values yet; until then the first value pushed fills them.
    filled: bool,
}

impl<T: Copy + Default> DelayLine<T> {
    /// A line whose first `periods` outputs are `T::default()` (an actuator given nothing
    /// yet renders nothing). `periods` is capped at [`MAX_DELAY_PERIODS`].
    pub(crate) fn idle(periods: usize) -> Self {
        Self {
            slots: [T::default(); MAX_DELAY_PERIODS],
            periods: periods.min(MAX_DELAY_PERIODS),
            next: 0,
            filled: true,
        }
    }

    /// A line whose first `periods` outputs repeat the first value pushed (a sensor reads
    /// where the handle already was when it powered on).
    pub(crate) fn primed(periods: usize) -> Self {
        Self {
            filled: false,
            ..Self::idle(periods)
        }
    }

    /// Push this period's value; the value of `periods` pushes ago.
    pub(crate) fn push(&mut self, value: T) -> T {
        if self.periods == 0 {
            return value;
        }
        if !self.filled {
            self.slots[..self.periods].fill(value);
            self.filled = true;
        }
        // The slot about to be overwritten holds the value of `periods` pushes ago.
        let out = std::mem::replace(&mut self.slots[self.next], value);
        self.next = (self.next + 1) % self.periods;
        out
    }
}

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
    /// The actuators' delay line (`sim.force_delay_ms`), protocol v1.
    delayed: DelayLine<Vector3<f64>>,
    /// The position sensing's delay line (`sim.position_delay_ms`), protocol v1.
    sensed: DelayLine<Vector3<f64>>,
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
            delayed: DelayLine::idle(0),
            sensed: DelayLine::primed(0),
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
    /// position a linkage cannot reach; for `sim:woodenhaptics`, [`SimError::NoArm`] for a
    /// profile without an arm and bodies and [`SimError::CartesianOnly`] for a force along the
    /// axes it does not simulate.
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
        device.delayed = DelayLine::idle(delay_periods(sim.force_delay(), device.period));
        device.sensed = DelayLine::primed(delay_periods(sim.position_delay(), device.period));
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
        // Forces along the device's axes, which a joint-space firmware never sees.
        let cartesian_only = [
            ("sim.force_scale", sim.force_scale != [1.0; 3]),
            ("sim.cogging_n", sim.cogging_n != 0.0),
            ("sim.vibration_n", sim.vibration_n != 0.0),
        ];
        if let Some((key, _)) = cartesian_only.into_iter().find(|(_, set)| *set) {
            return Err(SimError::CartesianOnly { key });
        }
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
        let firmware = JointFirmware::new(arm, Encoder::from_config(sim)).delayed(
            delay_periods(sim.force_delay(), period),
            delay_periods(sim.position_delay(), period),
        );
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
        let mut force = self.delayed.push(self.command);
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
        let measured = self.sensed.push(encoder.measure(plant.as_ref()));
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

    /// `[sim]`'s spring and actuation delay reach the joint-space firmware's arm from a config:
    /// the spring pulls it off the path it falls on without one, and currents sent at once turn
    /// the arm of a 3 ms delay exactly as the same currents sent 3 periods later turn the
    /// undelayed one.
    #[test]
    fn a_woodenhaptics_config_gives_its_spring_and_delay_to_the_arm() {
        use crate::profile::woodenhaptics::{CurrentReport, REPORT_LEN};
        let model = crate::config::SIM_WOODENHAPTICS;
        let device = |set: &dyn Fn(&mut Config)| {
            let mut config = Config::default();
            set(&mut config);
            SimDevice::from_config(model, &config).unwrap()
        };
        let run = |device: &mut SimDevice, currents: &dyn Fn(usize) -> [i16; 3]| {
            let mut out = [0; REPORT_LEN];
            for period in 0..20 {
                CurrentReport::currents(currents(period)).encode(&mut out);
                device.receive_output(&out).unwrap();
                device.advance();
            }
            device.plant().position()
        };
        let none = |_: usize| [0; 3];
        let free = run(&mut device(&|_| {}), &none);
        let sprung = run(
            &mut device(&|c| {
                c.sim.spring_n_per_m = 200.0;
                c.sim.spring_anchor_mm = [50.0, 0.0, 0.0];
            }),
            &none,
        );
        assert!((sprung - free).norm() > 1e-3, "{sprung} against {free}");
        let push = [300, -200, 250];
        let late = run(&mut device(&|c| c.sim.force_delay_ms = 3.0), &|_| push);
        let sent_late = run(&mut device(&|_| {}), &|period| {
            if period < 3 {
                [0; 3]
            } else {
                push
            }
        });
        assert_eq!(late, sent_late);
        assert!((late - free).norm() > 1e-3, "the currents moved it");
    }

    /// Forces along the device's axes are protocol v1's: the joint-space firmware refuses each
    /// with its key rather than leave it silently out.
    #[test]
    fn a_force_along_the_axes_is_refused_on_the_joint_space_firmware() {
        let model = crate::config::SIM_WOODENHAPTICS;
        assert!(SimDevice::from_config(model, &Config::default()).is_ok());
        for key in ["sim.force_scale", "sim.cogging_n", "sim.vibration_n"] {
            let mut config = Config::default();
            match key {
                "sim.force_scale" => config.sim.force_scale = [0.9, 1.0, 1.0],
                "sim.cogging_n" => config.sim.cogging_n = 0.05,
                _ => config.sim.vibration_n = 0.05,
            }
            match SimDevice::from_config(model, &config) {
                Err(SimError::CartesianOnly { key: refused }) => assert_eq!(refused, key),
                other => panic!("{key}: {:?}", other.err()),
            }
            assert!(SimDevice::from_config("phantom", &config).is_ok(), "{key}");
        }
    }
}
