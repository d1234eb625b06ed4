//! The servo thread never allocates once its loop runs: a counting global allocator counts every
//! allocation per thread, and a hook on the tap transport (which runs on the servo thread) checks
//! that count at every report after a short warm-up, through each transport and each servo-side
//! controller.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use crossbeam_channel::Sender;
use nalgebra::Vector3;

use hgcd::client::{Client, Role};
use hgcd::config::Config;
use hgcd::control::calibration::{Calibration, CalibrationParams};
use hgcd::control::Controller;
use hgcd::discrepancy::record::{RecordParams, Recorder};
use hgcd::grid::GridFile;
use hgcd::protocol::OUTPUT_REPORT_LEN;
use hgcd::servo::{self, ServoEvent, ServoOptions};
use hgcd::sim::SimDevice;
use hgcd::transport::hid::OutputWriter;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::socket::SocketTransport;
use hgcd::transport::{Pacing, Speaks, Transport};
use hgcd::validate::controller::ExperimentController;
use hgcd::validate::probe::{ContactPlan, Probe, ProbeParams};

mod common;
use common::daemon::TestDaemon;
use common::tap::Tap;
use common::{pd_hold, phantom_arm_grid, serve_one_host, truth_field_27, with_device_id, Ticks};

struct Counting;

thread_local! {
    /// Allocations (alloc, alloc_zeroed, realloc) made by the current thread.
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

fn count() {
    let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
}

// SAFETY: every call is forwarded to the system allocator unchanged; the counter is a
// thread-local Cell with a const initialiser and no destructor, so counting never allocates.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        System.alloc(layout)
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        count();
        System.alloc_zeroed(layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        System.realloc(ptr, layout, new_size)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations_here() -> u64 {
    ALLOCATIONS.with(Cell::get)
}

/// Reports seen before the count starts: the loop's first ticks may still touch lazily
/// initialised state (thread-locals, the first page of a ring).
const WARM_UP: u64 = 50;

/// What the tap saw: reports read, and allocations on the reading thread after the warm-up.
#[derive(Default)]
struct Seen {
    reads: AtomicU64,
    allocations: AtomicU64,
}

/// A tap on `inner` that counts reads and, after the warm-up, the allocations of the thread that
/// reads (the servo thread).
fn counting<T: Transport>(inner: T) -> (Tap<T>, Arc<Seen>) {
    let seen = Arc::new(Seen::default());
    let counts = seen.clone();
    let mut baseline = None;
    let tap = Tap::new(inner).on_read(move || {
        let reads = counts.reads.fetch_add(1, Ordering::Relaxed) + 1;
        let now = allocations_here();
        match baseline {
            None if reads >= WARM_UP => baseline = Some(now),
            Some(base) => counts.allocations.store(now - base, Ordering::Relaxed),
            None => {}
        }
    });
    (tap, seen)
}

fn config() -> Config {
    let mut config = Config::default();
    config.servo.lock_memory = false;
    config.servo.realtime_priority = 0;
    config
}

/// The simulated `model` in virtual time behind a counting tap.
fn counting_sim(model: &str, config: &Config) -> (Tap<SimTransport>, Arc<Seen>) {
    counting(SimTransport::new(
        SimDevice::from_config(model, config).unwrap(),
        Pacing::Virtual,
    ))
}

/// [`config`] with the simulated masses of [`truth_field_27`], its grid file kept in `dir`.
fn config_with_truth(dir: &Path) -> Config {
    let mut config = config();
    let truth = dir.join("truth.toml");
    GridFile::from(truth_field_27())
        .save_atomic(&truth)
        .unwrap();
    config.sim.mass_grid = Some(truth);
    config
}

/// Run `controller` on `transport` until `options` end it.
fn run(
    transport: &mut dyn Transport,
    controller: &mut dyn Controller,
    options: &ServoOptions,
    events: Option<&Sender<ServoEvent>>,
) {
    servo::run(
        transport,
        controller,
        options,
        &AtomicBool::new(false),
        events,
    )
    .unwrap();
}

fn assert_quiet(what: &str, seen: &Seen, at_least: u64) {
    let reads = seen.reads.load(Ordering::Relaxed);
    assert!(reads >= at_least, "{what}: only {reads} reports");
    assert_eq!(
        seen.allocations.load(Ordering::Relaxed),
        0,
        "{what}: the servo thread allocated after its warm-up"
    );
}

/// A PD hold on the simulated device `sim:MODEL` allocates nothing per tick, its events (if any)
/// sent to `events`.
fn quiet_pd_hold_on(model: &str, events: Option<&Sender<ServoEvent>>) {
    let config = config();
    let (mut tap, seen) = counting_sim(model, &config);
    let mut options = ServoOptions::from_config(&config);
    options.duration = Some(2.0);
    run(&mut tap, &mut pd_hold(), &options, events);
    assert_quiet(model, &seen, 2000);
}

#[test]
fn a_simulated_device_in_virtual_time_with_a_pd_hold() {
    let (events, _rx) = crossbeam_channel::bounded(16);
    quiet_pd_hold_on("point-mass", Some(&events));
}

#[test]
fn the_phantom_in_virtual_time_with_a_pd_hold() {
    quiet_pd_hold_on("phantom", None);
}

#[test]
fn the_delta_in_virtual_time_with_a_pd_hold() {
    quiet_pd_hold_on("delta", None);
}

#[test]
fn the_woodenhaptics_arm_through_its_joint_space_protocol_with_a_pd_hold() {
    // Counts to position and force to currents through the profile's kinematics, every tick.
    quiet_pd_hold_on("woodenhaptics", None);
}

#[test]
fn compensation_with_the_arm_and_residual_model_on_the_phantom() {
    use hgcd::control::compensation::{Compensation, ForceOffset, GravityModel};
    // Inverse kinematics, the Jacobian's solve and the residual lattice, every tick; a handle
    // released under compensation drifts through the cube and beyond it.
    let config = config();
    let model = GravityModel::configured(phantom_arm_grid(), None, Default::default()).unwrap();
    let mut compensation = Compensation::new(Some(Box::new(model)), ForceOffset::new(0.05, 0.05));
    let (mut tap, seen) = counting_sim("phantom", &config);
    let mut options = ServoOptions::from_config(&config);
    options.duration = Some(2.0);
    run(&mut tap, &mut compensation, &options, None);
    assert_quiet("arm + residual compensation", &seen, 2000);
}

/// A whole calibration on `sim:MODEL` of `config`, as `hgcd calibrate` runs it (on an arm its
/// strokes turn the profile's joints evenly), allocates nothing per tick.
fn quiet_calibration_on(model: &str, config: &Config) {
    let (mut tap, seen) = counting_sim(model, config);
    let (tx, _rx) = crossbeam_channel::bounded(4096);
    let spec = format!("sim:{model}").parse().unwrap();
    let params = CalibrationParams::for_device(config, &spec);
    let mut calibration = Calibration::new(params, Some(tx)).unwrap();
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    run(&mut tap, &mut calibration, &options, None);
    assert!(
        matches!(calibration.outcome(), Some(Ok(_))),
        "the calibration completes"
    );
    assert_quiet(&format!("calibration on sim:{model}"), &seen, 10_000);
}

#[test]
fn a_calibration_on_the_woodenhaptics_arm_through_its_joint_space_protocol() {
    quiet_calibration_on("woodenhaptics", &config());
}

#[test]
fn a_calibration_on_a_simulated_device() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config_with_truth(dir.path());
    config.sim.damping_n_s_per_m = 1.0;
    quiet_calibration_on("point-mass", &config);
}

/// The scalar model of the truth field the tests' devices carry.
fn truth_model() -> hgcd::control::compensation::GravityModel {
    use hgcd::control::compensation::{CompensationMode, GravityModel, OutsideGrid};
    GravityModel::new(
        GridFile::from(truth_field_27()),
        CompensationMode::Scalar,
        OutsideGrid::HoldNearest,
    )
    .unwrap()
}

#[test]
fn the_validation_experiment_with_a_model_swap_between_runs() {
    use hgcd::control::compensation::{Compensation, ForceOffset};
    let dir = tempfile::tempdir().unwrap();
    let mut config = config_with_truth(dir.path());
    config.sim.probe_mass_kg = 0.03;
    let (mut tap, seen) = counting_sim("point-mass", &config);
    // Uncompensated, then the scalar model: the second run swaps it in on the servo thread.
    let model = truth_model();
    let grid = truth_field_27();
    let plan = ContactPlan::paper(Vector3::zeros(), 0.03, grid.gravity_direction, 2, 2);
    // The defaults (validation.*, safety.max_force_n) on a surface of 1 N/mm.
    let params = ProbeParams::configured(&config, 1000.0);
    let (tx, _rx) = crossbeam_channel::bounded(4096);
    let mut experiment = ExperimentController::new(
        Compensation::new(None, ForceOffset::new(0.05, 0.05)),
        vec![None, Some(Box::new(model))],
        Probe::new(plan, params),
        Some(tx),
    );
    let mut options = ServoOptions::from_config(&config);
    options.stop_on_fault = true;
    run(&mut tap, &mut experiment, &options, None);
    let rests = experiment.into_rests();
    // Two runs of 27 points, two repetitions each, each read from above and from below.
    assert_eq!(rests.len(), 2 * 27 * 2 * 2, "the experiment completes");
    assert!(rests.iter().all(|r| r.settled));
    assert_quiet("validation experiment", &seen, 10_000);
}

#[test]
fn an_identification_run_of_hgcd_record() {
    let mut config = config();
    config.sim.force_delay_ms = 3.0;
    let (mut tap, seen) = counting_sim("point-mass", &config);
    let model = truth_model();
    let params = RecordParams::inside(&model, 12.0);
    let mut recorder = Recorder::new(params, model, config.servo_period());
    run(
        &mut tap,
        &mut recorder,
        &ServoOptions::from_config(&config),
        None,
    );
    assert!(recorder.into_rows().len() >= 12_000, "the run completes");
    assert_quiet("identification run", &seen, 10_000);
}

#[test]
fn a_device_behind_the_socket_transport() {
    let config = config();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("device.sock");
    let (stop_device, device) = serve_one_host(&path, &config, "point-mass");
    let (mut tap, seen) = counting(SocketTransport::connect(&path, Speaks::default()).unwrap());
    let mut options = ServoOptions::from_config(&config);
    options.watchdog = 5.0; // wall clock in lock-step: generous on a loaded machine
    run(&mut tap, &mut Ticks(pd_hold(), 1000), &options, None);
    drop(tap);
    stop_device.store(true, Ordering::SeqCst);
    device.join().unwrap();
    assert_quiet("socket", &seen, 1000);
}

#[test]
fn the_daemon_with_a_client_sending_offsets_and_reading_states() {
    let mut seen = None;
    let daemon = TestDaemon::new(config())
        .grid(Some(&with_device_id(truth_field_27(), "sim-point-mass")))
        .start_with(|sim| {
            let (tap, counts) = counting(sim);
            seen = Some(counts);
            tap
        });
    let seen = seen.expect("the tap was made");
    let mut client = Client::connect(&daemon.socket, Role::Control, "offsets").unwrap();
    client
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    client.subscribe(1000.0).unwrap();
    for n in 1..=2000u32 {
        let x = 0.1 * (f64::from(n) * 0.01).sin();
        client.set_force(Vector3::new(x, 0.0, 0.0)).unwrap();
    }
    let _ = client.status().unwrap();
    // On a loaded machine the servo thread may not have run many ticks yet: let it (bounded).
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while seen.reads.load(Ordering::Relaxed) < 2000 {
        assert!(
            std::time::Instant::now() < deadline,
            "the daemon's servo loop made no progress"
        );
        let _ = client.next_state().unwrap();
    }
    drop(client);
    daemon.stop().unwrap();
    assert_quiet("daemon", &seen, 1000);
}

#[test]
fn handing_output_reports_to_the_hid_writer_thread() {
    let written = Arc::new(AtomicU64::new(0));
    let sink = written.clone();
    let mut writer = OutputWriter::spawn(move |_| {
        sink.fetch_add(1, Ordering::Relaxed);
        Ok(())
    })
    .unwrap();
    let mut report = [0u8; OUTPUT_REPORT_LEN];
    writer.send(&report);
    let before = allocations_here();
    for n in 0..10_000u32 {
        report[..4].copy_from_slice(&n.to_le_bytes());
        writer.send(&report);
    }
    assert_eq!(allocations_here(), before, "send allocated");
    drop(writer);
    assert!(written.load(Ordering::Relaxed) >= 1);
}
