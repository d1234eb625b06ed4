//! `sim:woodenhaptics`: a WoodenHaptics / Polhem arm behind the firmware of its own joint-space
//! USB HID protocol (`profile::woodenhaptics`, `docs/devices.md`). The plant is a [`Linkage`]
//! with the profile's kinematics ([`ArmModel`]) and its configuration's body masses and centres
//! of mass; the firmware reads the arm's joints as quadrature counters, renders motor currents
//! (saturated at the amplifiers' full scale), homes its counters on the host's command and zeroes
//! its motors when the host stops writing. Numbers not published with the configurations
//! (friction, rotor and link inertia, joint stops) are estimates, listed in `docs/devices.md`.

use nalgebra::{Matrix3, Vector3};

use super::firmware::DelayLine;
use super::linkage::{Drives, JointState, Linkage, Mechanism, Point, UnitVariation, Unreachable};
use super::{Encoder, Plant};
use crate::config::SimConfig;
use crate::profile::woodenhaptics::{
    CurrentReport, EncoderReport, COMMAND_SET_ENCODERS, FIRMWARE_WATCHDOG, REPORT_LEN,
};
use crate::profile::{ArmModel, BodiesFile, Profile};
use crate::protocol::ProtocolError;

/// The arm's geometry (from its profile) and masses.
#[derive(Clone, Debug, PartialEq)]
pub struct WoodenArm {
    pub model: ArmModel,
    /// Upper arm (body b) and forearm (body c) masses, kg.
    pub masses: [f64; 2],
    /// Their centres of mass from their joints along each body, m.
    pub centres: [f64; 2],
    /// Constant rotational inertia: base about the vertical, bodies b and c about their pitch
    /// axes through their centres of mass (thin rods, m L²/12), kg m².
    pub inertia: Vector3<f64>,
    /// Mechanical stops (lower, upper), rad.
    pub limits: (Vector3<f64>, Vector3<f64>),
}

/// The base's inertia about the vertical axis, kg m² (an estimate: a wooden box about 0.15 m a side
/// and 1 kg turns with little more than its top; docs/devices.md).
const BASE_INERTIA: f64 = 2e-4;

impl WoodenArm {
    /// The arm a profile and its published bodies describe, varied as one unit by `variation`.
    pub fn unit(model: ArmModel, bodies: &BodiesFile, variation: &mut UnitVariation) -> Self {
        let masses = bodies.masses_kg.map(|m| variation.vary(m));
        let centres = bodies.centres_of_mass_m.map(|c| variation.vary(c));
        let rod = |m: f64, l: f64| m * l * l / 12.0;
        Self {
            model,
            masses,
            centres,
            inertia: Vector3::new(
                BASE_INERTIA,
                rod(masses[0], model.lengths[1]),
                rod(masses[1], model.lengths[2]),
            ),
            // Estimates that keep the arm away from its singular poses (body c parallel to b)
            // and hold every point of the workspace sphere.
            limits: (
                Vector3::new(-70f64, -40.0, -15.0).map(f64::to_radians),
                Vector3::new(70f64, 85.0, 110.0).map(f64::to_radians),
            ),
        }
    }
}

impl Mechanism for WoodenArm {
    fn handle(&self, joints: &JointState) -> Point {
        let l = self.model.lengths;
        self.model.point(joints, l[1], l[2])
    }

    fn joints_at(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        self.model.joints_at(x)
    }

    fn masses(&self, joints: &JointState, visit: &mut dyn FnMut(f64, &Point)) {
        // The upper arm's along body b from the shoulder, the forearm's along body c from the
        // elbow.
        let [b, c] = self.centres;
        visit(self.masses[0], &self.model.point(joints, b, 0.0));
        visit(
            self.masses[1],
            &self.model.point(joints, self.model.lengths[1], c),
        );
    }

    fn rotations(&self, _joints: &JointState) -> (Matrix3<f64>, Vector3<f64>) {
        (Matrix3::from_diagonal(&self.inertia), Vector3::zeros())
    }

    fn joint_limits(&self) -> (Vector3<f64>, Vector3<f64>) {
        self.limits
    }
}

/// The drives of a profile's arm: its capstan ratios, torque constants times full-scale current
/// as peak torque, and its encoders; Maxon RE 25 rotors and friction estimated as the PHANToM's
/// identified joint friction (docs/devices.md).
pub fn drives(model: &ArmModel) -> Drives {
    Drives {
        ratio: model.drums.component_div(&model.capstans),
        rotor_inertia: Vector3::repeat(1.08e-6),
        peak_torque: model.torque_constants * model.max_current,
        counts_per_rev: model.counts_per_rev,
        coulomb: Vector3::repeat(0.01),
        viscous: Vector3::repeat(0.0005),
    }
}

/// The plant of `sim:woodenhaptics` with `profile`'s arm, as `[sim]` describes its unit and
/// environment, or None for a profile without an arm and bodies.
///
/// # Errors
/// [`Unreachable`] when the handle cannot start at `sim.start_position_mm`.
pub fn plant(
    sim: &SimConfig,
    profile: &Profile,
) -> Option<Result<Linkage<WoodenArm>, Unreachable>> {
    let model = *profile.arm()?;
    let bodies = profile.bodies?;
    Some(Linkage::unit_from_config(
        sim,
        |variation| WoodenArm::unit(model, &bodies, variation),
        drives(&model),
    ))
}

/// The device side of the WoodenHaptics protocol around its arm: what the published firmware
/// does with each report (`firmware/main.cpp` of forsslund/haptikfabrikenapi).
pub struct JointFirmware {
    arm: Linkage<WoodenArm>,
    model: ArmModel,
    encoder: Encoder,
    /// Motor currents being rendered, A.
    currents: Vector3<f64>,
    /// What the counters read beyond the arm's absolute counts (set by the host's command).
    offset: [i32; 3],
    /// The calibration switch was pressed and the counters have not been set since.
    switch: bool,
    /// The amplifiers are enabled (an output report came within the watchdog).
    enabled: bool,
    /// Device time since the last output report, s.
    since_output: f64,
    /// The amplifiers render each latched current this many report periods late
    /// (`sim.force_delay_ms`).
    delayed: DelayLine<Vector3<f64>>,
    /// The counters report the joints as read this many reports earlier
    /// (`sim.position_delay_ms`).
    sensed: DelayLine<[i32; 3]>,
}

impl JointFirmware {
    /// Firmware around `arm`, powered on with its counters homed (reading the arm's absolute
    /// counts, as after the host's set-encoders command at the calibration pose).
    /// The arm carries `payload_kg` at its handle and gravity pulls against `up` from now on.
    pub fn set_world(&mut self, payload_kg: f64, up: &Vector3<f64>) {
        self.arm.set_world(payload_kg, up);
    }

    pub fn new(arm: Linkage<WoodenArm>, encoder: Encoder) -> Self {
        Self {
            model: arm.mechanism().model,
            arm,
            encoder,
            currents: Vector3::zeros(),
            offset: [0; 3],
            switch: false,
            enabled: false,
            since_output: 0.0,
            delayed: DelayLine::idle(0),
            sensed: DelayLine::primed(0),
        }
    }

    /// The same firmware with its currents rendered `actuation` report periods late and its
    /// counters read `sensing` reports late. (The set-encoders command and the switch act at
    /// once: for `sensing` reports after a set, the new offset rides on counts read before it.
    /// A host sets the counters with the arm at rest, where that changes nothing.)
    pub fn delayed(self, actuation: usize, sensing: usize) -> Self {
        Self {
            delayed: DelayLine::idle(actuation),
            sensed: DelayLine::primed(sensing),
            ..self
        }
    }

    /// The plant (ground truth for tests).
    pub fn plant(&self) -> &dyn Plant {
        &self.arm
    }

    /// The counters stop reading absolute counts (power-on anywhere but at the calibration
    /// pose) and the calibration switch is pressed.
    pub fn press_calibration_switch(&mut self, offset: [i32; 3]) {
        self.offset = offset;
        self.switch = true;
    }

    /// The counters' true reading (the arm's joints in counts, with the measurement noise).
    fn absolute_counts(&mut self) -> [i32; 3] {
        let q = self.arm.sensed_joints(&self.encoder.sample_noise());
        let c = self.model.counts(&q).map(f64::round);
        [c[0] as i32, c[1] as i32, c[2] as i32]
    }

    /// The input report for the arm as it is now.
    pub fn input_report(&mut self, out: &mut [u8; REPORT_LEN]) {
        let read = self.absolute_counts();
        let absolute = self.sensed.push(read);
        let mut counts = [0i16; 6];
        for j in 0..3 {
            // The firmware's counters are `int`s sent as `short`s: they wrap.
            counts[j] = (absolute[j] + self.offset[j]) as i16;
        }
        EncoderReport {
            counts,
            info: i16::from(self.switch),
        }
        .encode(out);
    }

    /// Receive an output report: set the counters (command 1) or latch the currents, clamped
    /// to the amplifiers' full scale; either way the amplifiers are enabled and the watchdog
    /// restarts.
    ///
    /// # Errors
    /// [`ProtocolError::Length`] for a report that is not 14 bytes (ignored, as the firmware
    /// does).
    pub fn receive_output(&mut self, bytes: &[u8]) -> Result<(), ProtocolError> {
        let report = CurrentReport::decode(bytes)?;
        if report.command == COMMAND_SET_ENCODERS {
            let absolute = self.absolute_counts();
            for (j, offset) in self.offset.iter_mut().enumerate() {
                *offset = i32::from(report.attributes[j]) - absolute[j];
            }
            self.switch = false;
            self.currents = Vector3::zeros();
        } else {
            let limit = self.model.max_current;
            self.currents = Vector3::from(report.currents_ma.map(f64::from))
                .map(|ma| (ma * 1e-3).clamp(-limit, limit));
        }
        self.enabled = true;
        self.since_output = 0.0;
        Ok(())
    }

    /// Integrate one report period of `period` s in `substeps` steps under the currents; past
    /// the firmware's watchdog without an output report, the amplifiers are off.
    pub fn advance(&mut self, period: f64, substeps: u32) {
        self.since_output += period;
        if self.since_output > FIRMWARE_WATCHDOG {
            self.enabled = false;
            self.currents = Vector3::zeros();
        }
        let torque = self.model.joint_torques(&self.delayed.push(self.currents));
        let dt = period / f64::from(substeps);
        for _ in 0..substeps {
            self.arm.step_joint_torque(&torque, dt);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::linkage::checks::{self, env};
    use crate::sim::linkage::Environment;

    fn profile() -> Profile {
        Profile::built_in("woodenhaptics_v2015").unwrap()
    }

    fn arm_at(x_mm: [f64; 3], env: Environment) -> Linkage<WoodenArm> {
        let p = profile();
        let model = *p.arm().unwrap();
        let arm = WoodenArm::unit(model, &p.bodies.unwrap(), &mut UnitVariation::new(0));
        checks::at(arm, drives(&model), x_mm, env)
    }

    #[test]
    fn the_arm_reaches_the_calibration_cube_and_its_dynamics_are_consistent() {
        let arm = arm_at([0.0; 3], env(1.0, 0.0));
        for x in checks::cube(4) {
            let q = arm
                .mechanism()
                .joints_at(&(Vector3::from(x) * 1e-3))
                .unwrap();
            let (lo, hi) = arm.mechanism().joint_limits();
            assert!((0..3).all(|j| q[j] > lo[j] && q[j] < hi[j]), "{x:?}: {q:?}");
            checks::assert_points_match_finite_differences(
                arm.mechanism(),
                &q,
                &Vector3::new(0.4, -0.8, 1.1),
                1e-6,
            );
            let mut plant = arm_at(x, checks::tilted());
            checks::assert_gravity_torque_is_the_gradient(&mut plant, &q);
        }
        checks::assert_holding_force_holds_still(arm_at([10.0, -20.0, 15.0], env(0.0, 0.02)));
        checks::assert_energy_is_conserved(|dt| {
            let mut plant = arm_at([0.0; 3], env(0.0, 0.0));
            let q = plant.joints();
            plant.set_state(q, Vector3::new(0.8, 0.3, 0.4));
            // The arm is not counterbalanced: it falls, relative to the kinetic energy it gains.
            let (worst, peak) = checks::free_motion_energy(&mut plant, 0.1, dt);
            worst / peak
        });
    }

    /// The firmware drives the arm by joint torques: a spring (a cable) and damping at the
    /// handle act on it all the same (they were left out on that path until 2026-12-07, and
    /// `sim.spring_n_per_m` and `sim.damping_n_s_per_m` did nothing on `sim:woodenhaptics`).
    #[test]
    fn a_spring_and_damping_at_the_handle_act_on_the_arm_driven_by_joint_torques() {
        let mut sprung = env(0.0, 0.0);
        sprung.spring = (40.0, Vector3::new(0.03, -0.02, 0.05));
        sprung.handle_damping = 2.0;
        let force = Vector3::new(0.1, -0.2, 0.5);
        checks::assert_the_environment_acts_under_joint_torques(arm_at([0.0; 3], sprung), &force);
        // And it is felt: the spring pulls the handle millimetres off its free path.
        let (mut with, mut without) = (arm_at([0.0; 3], sprung), arm_at([0.0; 3], env(0.0, 0.0)));
        for plant in [&mut with, &mut without] {
            for _ in 0..2000 {
                plant.step(&force, 1e-4);
            }
        }
        let apart = (with.position() - without.position()).norm();
        assert!(apart > 1e-3, "{apart} m apart");
    }

    #[test]
    fn the_firmware_renders_currents_homes_its_counters_and_stops_when_the_host_does() {
        let arm = arm_at([0.0; 3], env(1.0, 0.0));
        let model = arm.mechanism().model;
        let mut fw = JointFirmware::new(arm, Encoder::new(0.0, 1));
        let mut bytes = [0; REPORT_LEN];
        fw.input_report(&mut bytes);
        let homed = EncoderReport::decode(&bytes).unwrap();
        let q = fw.arm.joints();
        let expected = model.counts(&q).map(f64::round);
        assert_eq!(homed.counts[2], expected[2] as i16);
        assert_eq!(homed.info, 0);
        // Currents beyond full scale are clamped.
        let mut out = [0; REPORT_LEN];
        CurrentReport::currents([9000, -100, 0]).encode(&mut out);
        fw.receive_output(&out).unwrap();
        assert_eq!(fw.currents, Vector3::new(6.0, -0.1, 0.0));
        // Power-on elsewhere: the switch asks, the host's command sets the counters.
        fw.press_calibration_switch([100, -200, 300]);
        fw.input_report(&mut bytes);
        let asked = EncoderReport::decode(&bytes).unwrap();
        assert_eq!(asked.info, 1);
        assert_eq!(asked.counts[0], homed.counts[0] + 100);
        CurrentReport::set_encoders([1, 2, 3]).encode(&mut out);
        fw.receive_output(&out).unwrap();
        assert_eq!(fw.currents, Vector3::zeros());
        fw.input_report(&mut bytes);
        let set = EncoderReport::decode(&bytes).unwrap();
        assert_eq!((set.counts[..3].to_vec(), set.info), (vec![1, 2, 3], 0));
        // Silence for longer than the watchdog: the amplifiers are off.
        CurrentReport::currents([500, 500, 500]).encode(&mut out);
        fw.receive_output(&out).unwrap();
        assert!(fw.enabled);
        for _ in 0..499 {
            fw.advance(1e-3, 1);
        }
        assert!(fw.enabled);
        fw.advance(2e-3, 1);
        assert!(!fw.enabled);
        assert_eq!(fw.currents, Vector3::zeros());
        // A report of another length is refused.
        assert!(fw.receive_output(&out[..13]).is_err());
    }

    /// The spring at the handle is no motor's: a stiff one pulls the handle far faster than the
    /// same pull through the motors, which their peak torque limits.
    #[test]
    fn a_spring_at_the_handle_is_not_limited_to_the_motors_peak() {
        let mut stiff = env(0.0, 0.0);
        stiff.spring = (10_000.0, Vector3::new(0.05, 0.0, 0.0));
        let (mut sprung, mut pushed) = (arm_at([0.0; 3], stiff), arm_at([0.0; 3], env(0.0, 0.0)));
        let start = sprung.position();
        // What the spring pulls with at the start, k × 50 mm, sent to the motors instead.
        let pull = Vector3::new(500.0, 0.0, 0.0);
        for _ in 0..10 {
            sprung.step(&Vector3::zeros(), 1e-4);
            pushed.step(&pull, 1e-4);
        }
        let (by_spring, by_motors) = ((sprung.position() - start).x, (pushed.position() - start).x);
        assert!(
            by_spring > 5.0 * by_motors,
            "{by_spring} m against {by_motors} m"
        );
    }

    /// `sim.force_delay_ms` and `sim.position_delay_ms` on the joint-space firmware: currents
    /// latched now turn the arm three periods later, exactly as currents sent three periods
    /// later do; the counters report what they read two reports ago (the first reading until
    /// then).
    #[test]
    fn the_firmware_renders_currents_and_reports_counts_as_late_as_it_is_told() {
        let firmware = || JointFirmware::new(arm_at([0.0; 3], env(1.0, 0.0)), Encoder::new(0.0, 1));
        let (mut late, mut prompt) = (firmware().delayed(3, 2), firmware());
        let (mut on, mut off) = ([0; REPORT_LEN], [0; REPORT_LEN]);
        CurrentReport::currents([400, -300, 250]).encode(&mut on);
        CurrentReport::currents([0, 0, 0]).encode(&mut off);
        let counts = |fw: &mut JointFirmware| {
            let mut bytes = [0; REPORT_LEN];
            fw.input_report(&mut bytes);
            EncoderReport::decode(&bytes).unwrap().counts
        };
        let (mut read_late, mut read_prompt) = (Vec::new(), Vec::new());
        for period in 0..40 {
            late.receive_output(&on).unwrap();
            prompt
                .receive_output(if period < 3 { &off } else { &on })
                .unwrap();
            read_late.push(counts(&mut late));
            read_prompt.push(counts(&mut prompt));
            late.advance(1e-3, 4);
            prompt.advance(1e-3, 4);
        }
        assert_eq!(late.arm.joints(), prompt.arm.joints());
        assert_ne!(read_prompt[0], read_prompt[39], "the arm moved");
        assert_eq!(read_late[..3], [read_prompt[0]; 3]);
        assert_eq!(read_late[2..], read_prompt[..38]);
    }

    #[test]
    fn handle_friction_holds_below_its_level_and_takes_the_energy_of_a_slide() {
        checks::assert_handle_friction_sticks_and_slides(arm_at, [20.0, -15.0, 10.0]);
    }
}
