//! The device path end to end: simulated firmware, byte protocol, servo loop and safety layer, in
//! virtual time. Assertions compare with the simulator's physics, not with printed output.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crossbeam_channel::Sender;
use nalgebra::Vector3;

use hgcd::config::Config;
use hgcd::control::pd::{LinearisedGains, PdHold};
use hgcd::control::{ControlOutput, Controller, DeviceState, ZeroForce};
use hgcd::grid::GridFile;
use hgcd::profile::Profile;
use hgcd::protocol::OutputReport;
use hgcd::servo::{self, ExitReason, ServoEvent, ServoOptions, ServoReport};
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::socket::SocketTransport;
use hgcd::transport::{Pacing, Speaks, Transport};

mod common;
use common::tap::{Fault, Tap};
use common::{pd_hold, serve_one_host, truth_field_27, Ticks};

fn sim_transport(config: &Config) -> SimTransport {
    SimTransport::new(
        SimDevice::from_config("point-mass", config).unwrap(),
        Pacing::Virtual,
    )
}

/// The force of the last output report the simulated device behind `transport` received, N.
fn last_force(transport: &SimTransport) -> Vector3<f64> {
    transport.device().last_output().unwrap().force
}

/// Wraps a controller and records every state it sees.
struct Recorder<C> {
    inner: C,
    states: Vec<DeviceState>,
}

impl<C: Controller> Controller for Recorder<C> {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        self.states.push(*s);
        self.inner.tick(s)
    }
}

fn options(config: &Config, duration: f64) -> ServoOptions {
    let mut o = ServoOptions::from_config(config);
    o.duration = Some(duration);
    o
}

/// Run `controller` on `transport` for `duration` s of device time with `config`'s servo
/// options, its events to `events`.
fn run_for(
    transport: &mut dyn Transport,
    controller: &mut dyn Controller,
    config: &Config,
    duration: f64,
    events: Option<&Sender<ServoEvent>>,
) -> ServoReport {
    let stop = AtomicBool::new(false);
    servo::run(
        transport,
        controller,
        &options(config, duration),
        &stop,
        events,
    )
    .unwrap()
}

/// The watchdog fault among `events` came within a tick of its `deadline` (s).
fn assert_detected_at_the_deadline(events: &[ServoEvent], deadline: f64) {
    let silent_for = events
        .iter()
        .find_map(|e| match e {
            ServoEvent::WatchdogFault { silent_for } => Some(*silent_for),
            _ => None,
        })
        .expect("a watchdog event");
    assert!(
        silent_for >= deadline && silent_for <= deadline + 1e-3 + 1e-9,
        "detected after {silent_for} s, deadline {deadline} s"
    );
}

#[test]
fn zero_force_falls_with_g_until_the_workspace_limit() {
    let config = Config::default();
    let mut transport = sim_transport(&config);
    let mut rec = Recorder {
        inner: ZeroForce,
        states: Vec::with_capacity(1000),
    };
    let report = run_for(&mut transport, &mut rec, &config, 0.5, None);
    assert_eq!(report.exit, ExitReason::DurationReached);

    // Least-squares fit z = c0 + c1 t + c2 t² over the free flight (well before the floor at
    // −80 mm, reached after about 128 ms).
    let flight: Vec<_> = rec
        .states
        .iter()
        .filter(|s| s.time > 0.005 && s.time < 0.11)
        .collect();
    assert!(flight.len() > 90);
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    for s in &flight {
        let row = Vector3::new(1.0, s.time, s.time * s.time);
        ata += row * row.transpose();
        atb += row * s.position.z;
    }
    let c = ata.lu().solve(&atb).unwrap();
    let acceleration = 2.0 * c[2];
    assert!(
        (acceleration + 9.81).abs() < 0.01 * 9.81,
        "fall acceleration {acceleration} m/s², expected −9.81"
    );
    // Gravity is along −z: nothing moves sideways.
    assert!(flight.iter().all(|s| s.position.xy().norm() < 2e-5));
    // It meets the stop at −80 mm and stays there.
    let end = rec.states.iter().filter(|s| s.time > 0.2);
    for s in end {
        assert!((s.position.z + 0.08).abs() < 2e-5, "z = {}", s.position.z);
    }
}

#[test]
fn pd_hold_with_exact_gravity_stays_within_50_micrometres_for_10_s() {
    let field = truth_field_27();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("truth.toml");
    GridFile::from(field.clone()).save_atomic(&path).unwrap();
    let set_point = Vector3::new(0.012, -0.021, 0.017);
    let mut config = Config::default();
    config.sim.mass_grid = Some(path);
    config.sim.start_position_mm = [12.0, -21.0, 17.0];
    let mut transport = sim_transport(&config);
    let mut rec = Recorder {
        inner: PdHold {
            set_point,
            gains: LinearisedGains::from_rise_time(0.1, 1.0),
            field,
        },
        states: Vec::with_capacity(10_100),
    };
    let report = run_for(&mut transport, &mut rec, &config, 10.0, None);
    assert_eq!(report.exit, ExitReason::DurationReached);
    assert!(report.stats.ticks >= 9_999);
    let worst = rec
        .states
        .iter()
        .map(|s| (s.position - set_point).norm())
        .fold(0.0, f64::max);
    assert!(
        worst < 5e-5,
        "measured position strayed {worst} m from the set point"
    );
    let truth = transport.device().plant().position();
    assert!((truth - set_point).norm() < 5e-5);
}

/// [`pd_hold`] 10 mm above the origin.
fn pushing_hold() -> PdHold {
    PdHold {
        set_point: Vector3::new(0.0, 0.0, 0.01),
        ..pd_hold()
    }
}

/// The writes after the last pushing one: the fault's zero (motors enabled), then the shutdown.
fn assert_zeroed_at_the_fault(writes: &[(f64, OutputReport)], fault_at: f64, deadline: f64) {
    let last_push = writes
        .iter()
        .rposition(|(_, r)| r.force != Vector3::zeros())
        .expect("the controller pushed");
    let (t_push, _) = writes[last_push];
    assert!((t_push - fault_at).abs() < 2e-3, "pushed until {t_push} s");
    let (t_zero, zero) = writes[last_push + 1];
    assert!(zero.enable, "the fault's zero keeps motors enabled");
    assert_eq!(zero.force, Vector3::zeros());
    assert!(
        t_zero - t_push <= deadline + 1e-3 + 1e-9,
        "zeroed {} s after the last push, deadline {deadline} s",
        t_zero - t_push
    );
    let (_, last) = writes.last().unwrap();
    assert!(
        !last.enable && last.force == Vector3::zeros(),
        "shutdown report"
    );
}

#[test]
fn silent_device_trips_the_watchdog_and_force_is_zeroed_at_the_fault() {
    let mut config = Config::default();
    config.sim.stop_reporting_after_s = Some(1.0);
    let mut transport = Tap::new(sim_transport(&config)).recording();
    let (tx, rx) = crossbeam_channel::bounded(64);
    let report = run_for(&mut transport, &mut pushing_hold(), &config, 1.5, Some(&tx));
    assert_eq!(report.stats.watchdog_faults, 1);
    let events: Vec<_> = rx.try_iter().collect();
    let deadline = config.servo.watchdog_ms * 1e-3;
    assert_detected_at_the_deadline(&events, deadline);
    assert_zeroed_at_the_fault(&transport.writes().all(), 1.0, deadline);

    // With stop_on_fault the run ends at the fault instead.
    let mut transport = sim_transport(&config);
    let mut o = options(&config, 5.0);
    o.stop_on_fault = true;
    let report = servo::run(
        &mut transport,
        &mut pushing_hold(),
        &o,
        &AtomicBool::new(false),
        None,
    )
    .unwrap();
    assert!(matches!(report.exit, ExitReason::Fault(_)));
    assert!(transport.device().time() < 1.0 + 2.0 * deadline);
    assert_eq!(last_force(&transport), Vector3::zeros());
}

#[test]
fn a_device_that_only_babbles_trips_the_watchdog_too() {
    let config = Config::default();
    // After 1 s the device only sends reports of an unknown version.
    let mut transport = Tap::new(sim_transport(&config))
        .recording()
        .faults(|_, t| (t > 1.0).then_some(Fault::BadVersion));
    let report = run_for(&mut transport, &mut pushing_hold(), &config, 1.5, None);
    assert_eq!(report.stats.watchdog_faults, 1);
    assert!(report.stats.garbled > 400);
    assert_zeroed_at_the_fault(
        &transport.writes().all(),
        1.0,
        config.servo.watchdog_ms * 1e-3,
    );
}

#[test]
fn a_device_silent_for_a_while_is_a_fault_until_its_reports_resume() {
    let config = Config::default();
    // The device says nothing from 1.0 s to 1.1 s, then reports again.
    let mut transport = Tap::new(sim_transport(&config))
        .recording()
        .faults(|_, t| (t > 1.0 && t <= 1.1 + 1e-9).then_some(Fault::Silence));
    let (tx, rx) = crossbeam_channel::bounded(64);
    let mut hold = Recorder {
        inner: pushing_hold(),
        states: Vec::with_capacity(2100),
    };
    let set_point = hold.inner.set_point;
    let report = run_for(&mut transport, &mut hold, &config, 2.0, Some(&tx));
    assert_eq!(report.stats.watchdog_faults, 1);
    let deadline = config.servo.watchdog_ms * 1e-3;
    let events: Vec<_> = rx.try_iter().collect();
    assert_detected_at_the_deadline(&events, deadline);
    let after = events
        .iter()
        .find_map(|e| match e {
            ServoEvent::ReportsResumed { after } => Some(*after),
            _ => None,
        })
        .expect("reports resumed");
    assert!((after - 0.101).abs() < 1e-6, "resumed after {after} s");
    // While the device was silent the loop wrote once: the fault's zero, at the deadline.
    let writes = transport.writes().all();
    let during: Vec<_> = writes
        .iter()
        .filter(|(t, _)| *t > 1.0 + 1e-9 && *t <= 1.1 + 1e-9)
        .collect();
    assert_eq!(during.len(), 1, "{during:?}");
    let (t_zero, zero) = during[0];
    assert!(zero.enable && zero.force == Vector3::zeros());
    assert!(
        *t_zero - 1.0 <= deadline + 1e-3 + 1e-9,
        "zeroed at {t_zero} s"
    );
    // The handle fell while the force was off (some 5 cm in 0.1 s); the hold brought it back.
    let back = hold.states.iter().find(|s| s.time > 1.1).unwrap();
    assert!(
        back.position.z < set_point.z - 0.03,
        "at {:?} when the reports resumed",
        back.position
    );
    let last = report.last_state.unwrap();
    assert!(
        (last.position - set_point).norm() < 2e-4,
        "at {:?}, set point {set_point:?}",
        last.position
    );
}

/// Panics at a given tick while pushing (a controller bug).
struct PanicsAt(u64);

impl Controller for PanicsAt {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        assert!(s.tick < self.0, "controller bug");
        ControlOutput::force(Vector3::new(0.0, 0.0, 3.0))
    }
}

#[test]
fn a_panicking_controller_still_ends_in_zero_force() {
    let config = Config::default();
    let mut transport = sim_transport(&config);
    let stop = AtomicBool::new(false);
    let panicked = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        servo::run(
            &mut transport,
            &mut PanicsAt(100),
            &options(&config, 1.0),
            &stop,
            None,
        )
    }));
    assert!(panicked.is_err(), "the panic goes on after the zero");
    let last = transport.device().last_output().unwrap();
    assert_eq!(last.force, Vector3::zeros());
    assert!(!last.enable);
}

/// Sets the stop flag (as the SIGINT handler does) after a number of ticks, while pushing.
struct StopAfter {
    ticks: u64,
    stop: Arc<AtomicBool>,
}

impl Controller for StopAfter {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        if s.tick == self.ticks {
            self.stop.store(true, Ordering::SeqCst);
        }
        ControlOutput::force(Vector3::new(0.5, 0.0, 1.0))
    }
}

#[test]
fn stop_request_writes_zero_force_last() {
    let config = Config::default();
    let mut transport = sim_transport(&config);
    let stop = Arc::new(AtomicBool::new(false));
    let mut c = StopAfter {
        ticks: 300,
        stop: stop.clone(),
    };
    let report = servo::run(&mut transport, &mut c, &options(&config, 10.0), &stop, None).unwrap();
    assert_eq!(report.exit, ExitReason::Stopped);
    assert_eq!(report.stats.ticks, 301);
    assert_eq!(last_force(&transport), Vector3::zeros());
}

#[test]
fn garbled_reports_are_counted_and_skipped() {
    let config = Config::default();
    // Every seventh input report has an unknown version, the third after it is short.
    let mut transport = Tap::new(sim_transport(&config)).faults(|n, _| match n % 7 {
        0 => Some(Fault::BadVersion),
        3 => Some(Fault::Short),
        _ => None,
    });
    let report = run_for(&mut transport, &mut ZeroForce, &config, 1.0, None);
    // 2 of every 7 reports are bad; the good ones drive the loop. Skipped good-report sequence
    // numbers show up as missed reports, not as faults.
    assert!((report.stats.garbled as f64 - 1000.0 * 2.0 / 7.0).abs() <= 2.0);
    assert_eq!(report.stats.watchdog_faults, 0);
    assert!(report.stats.ticks > 700);
}

#[test]
fn socket_transport_carries_the_same_protocol() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("device.sock");
    let mut config = Config::default();
    config.sim.start_position_mm = [0.0, 0.0, 5.0];
    let (server_stop, server) = serve_one_host(&path, &config, "point-mass");
    let mut transport = SocketTransport::connect(&path, Speaks::default()).unwrap();
    let hold = pd_hold();
    let set_point = hold.set_point;
    let stop = AtomicBool::new(false);
    // Lock-step: the device advances one period per exchanged report pair, so count ticks.
    let mut c = Ticks(hold, 500);
    let mut o = ServoOptions::from_config(&config);
    o.watchdog = 1.0; // wall-clock watchdog: generous on a loaded CI machine
    let report = servo::run(&mut transport, &mut c, &o, &stop, None).unwrap();
    assert_eq!(report.exit, ExitReason::ControllerDone);
    let last = report.last_state.unwrap();
    assert!((last.position - set_point).norm() < 5e-5);
    drop(transport);
    server_stop.store(true, Ordering::SeqCst);
    let device = server.join().unwrap();
    assert_eq!(device.last_output().unwrap().force, Vector3::zeros());
    assert_eq!(device.rejected_outputs(), 0);
}

/// The socket carries a joint-space profile's raw reports (`docs/devices.md`): a host that speaks
/// the WoodenHaptics profile drives `sim:woodenhaptics` over it, reading positions through the
/// arm's kinematics to within the encoders' step of the plant's own, and writing currents.
#[test]
fn socket_transport_carries_a_joint_space_profile() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("device.sock");
    let config = Config::default();
    let (server_stop, server) = serve_one_host(&path, &config, "woodenhaptics");
    let profile = Profile::built_in("woodenhaptics_v2015").unwrap();
    let speaks = Speaks::profile(&profile, config.servo.rate_hz);
    let mut transport = SocketTransport::connect(&path, speaks).unwrap();
    // It has no device-info report: its profile speaks for it (and nothing waited for one).
    let info = transport.device_info().unwrap();
    assert_eq!(info.model, "woodenhaptics_v2015");
    assert_eq!(info.workspace_half_extents, Vector3::repeat(0.1));
    let stop = AtomicBool::new(false);
    let mut c = Ticks(pd_hold(), 500);
    let mut o = ServoOptions::from_config(&config);
    o.watchdog = 1.0; // wall-clock watchdog: generous on a loaded CI machine
    let report = servo::run(&mut transport, &mut c, &o, &stop, None).unwrap();
    assert_eq!(report.exit, ExitReason::ControllerDone);
    assert_eq!(report.stats.garbled, 0);
    let last = report.last_state.unwrap();
    drop(transport);
    server_stop.store(true, Ordering::SeqCst);
    let device = server.join().unwrap();
    // One count of the coarsest joint is 0.26 mrad: under 0.1 mm at the handle.
    let truth = device.plant().position();
    assert!(
        (last.position - truth).norm() < 1e-4,
        "{last:?} vs {truth:?}"
    );
    // The hold moved the handle off its start, towards the set point 5 mm up.
    assert!(truth.z > 1e-3, "{truth:?}");
    assert_eq!(device.rejected_outputs(), 0);
}

/// Remembers every state it is given; renders nothing.
struct Seen(Vec<DeviceState>);

impl Controller for Seen {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        self.0.push(*s);
        ControlOutput::force(Vector3::zeros())
    }
}

/// A WoodenHaptics powered on away from where its counters say (they start at 0 wherever the arm
/// is) with its calibration switch pressed at the calibration pose: the loop sees a device fault
/// until the host has answered with the set-encoders command, then positions the plant confirms.
#[test]
fn a_joint_space_device_asking_for_calibration_is_a_fault_until_the_host_homes_its_counters() {
    use hgcd::protocol::Status;
    let mut config = Config::default();
    // The calibration pose of woodenhaptics_v2015: base and upper arm at 0, forearm horizontal.
    config.sim.start_position_mm = [25.0, 0.0, 205.0];
    let mut device = SimDevice::from_config("woodenhaptics", &config).unwrap();
    device
        .joint_firmware()
        .unwrap()
        .press_calibration_switch([123, -456, 789]);
    let mut transport = SimTransport::new(device, Pacing::Virtual);
    let mut seen = Seen(Vec::new());
    let mut o = ServoOptions::from_config(&config);
    o.duration = Some(0.005);
    servo::run(&mut transport, &mut seen, &o, &AtomicBool::new(false), None).unwrap();
    let states = seen.0;
    assert!(states[0].status.contains(Status::FAULT));
    assert!((states[0].position - Vector3::new(0.025, 0.0, 0.205)).norm() > 0.01);
    let after = &states[1..];
    assert!(after.iter().all(|s| !s.status.contains(Status::FAULT)));
    // The jump from relative to homed counts (tens of mm in a period) is no velocity: the
    // estimator restarted; what is left is the arm starting to fall.
    assert!(after.iter().all(|s| s.velocity.norm() < 0.5), "{after:?}");
    let truth = transport.device().plant().position();
    let last = states.last().unwrap();
    assert!(
        (last.position - truth).norm() < 1e-4,
        "{last:?} vs {truth:?}"
    );
}
