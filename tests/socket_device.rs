//! The socket transport's contract (`docs/hid-protocol.md` §9) as the reference device side
//! (`hgcd::sim::socket`, behind `hgcd sim-device`) keeps it, seen by a host written in the test;
//! and calibrations over it that a busy or late host must not abort.

use std::io::{ErrorKind, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use nalgebra::Vector3;

use hgcd::calibrate::{calibrate, calibrate_on, CalibrateRequest};
use hgcd::config::Config;
use hgcd::control::calibration::CalibrationEvent;
use hgcd::control::ZeroForce;
use hgcd::protocol::{
    DeviceInfo, InputReport, OutputReport, Status, DEVICE_INFO_LEN, INPUT_REPORT_LEN,
    MAX_REPORT_LEN, OUTPUT_REPORT_LEN,
};
use hgcd::servo::{self, ServoError, ServoEvent, ServoOptions};
use hgcd::sim::socket::{self, Served};
use hgcd::sim::SimDevice;
use hgcd::transport::socket::SocketTransport;
use hgcd::transport::{Pacing, Speaks, TransportError};

mod common;
use common::serial;
use common::tap::{Fault, Tap};

/// `hgcd::sim::socket::serve` of the simulated device of `config` on a socket in `dir`, on its
/// own thread, until the returned flag is set.
fn serve(
    dir: &Path,
    config: &Config,
    lockstep: bool,
) -> (PathBuf, Arc<AtomicBool>, JoinHandle<Served>) {
    let path = dir.join("device.sock");
    let listener = UnixListener::bind(&path).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let (flag, config) = (stop.clone(), config.clone());
    let server = std::thread::spawn(move || {
        socket::serve(
            &listener,
            || SimDevice::from_config("point-mass", &config),
            lockstep,
            &flag,
        )
        .unwrap()
    });
    (path, stop, server)
}

/// A host written from the document: raw frames on a blocking stream.
struct Host(UnixStream);

impl Host {
    fn connect(path: &Path) -> Self {
        let stream = UnixStream::connect(path).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        Self(stream)
    }

    fn send(&mut self, frame: &[u8]) {
        self.0.write_all(frame).unwrap();
    }

    /// One frame from the device: its length byte and bytes.
    fn frame(&mut self) -> Vec<u8> {
        let mut n = [0u8; 1];
        self.0.read_exact(&mut n).unwrap();
        let mut bytes = vec![0; n[0] as usize];
        self.0.read_exact(&mut bytes).unwrap();
        bytes
    }

    fn report(&mut self) -> InputReport {
        let bytes = self.frame();
        assert_eq!(bytes.len(), INPUT_REPORT_LEN);
        InputReport::decode(&bytes).unwrap()
    }

    /// An output report frame: `force` N with motors enabled.
    fn reply(&mut self, force: Vector3<f64>) {
        let mut bytes = [0u8; OUTPUT_REPORT_LEN];
        OutputReport {
            sequence: 0,
            force,
            enable: true,
        }
        .encode(&mut bytes)
        .unwrap();
        self.send(&[OUTPUT_REPORT_LEN as u8]);
        self.send(&bytes);
    }

    /// Nothing comes from the device for `wait` (wall-clock time: the host is late on purpose).
    fn nothing_for(&mut self, wait: Duration) {
        self.0.set_read_timeout(Some(wait)).unwrap();
        let mut byte = [0u8; 1];
        match self.0.read(&mut byte) {
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            other => panic!("the device sent something: {other:?}"),
        }
        self.0
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
    }

    /// The device closed the connection.
    fn closed(&mut self) -> bool {
        let mut rest = Vec::new();
        self.0.read_to_end(&mut rest).is_ok()
    }
}

#[test]
fn each_connection_is_a_power_on_and_the_device_serves_host_after_host() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::default();
    config.sim.start_position_mm = [0.0, 0.0, 5.0];
    let (path, stop, server) = serve(dir.path(), &config, true);
    let mut moved = Vector3::zeros();
    for _ in 0..2 {
        let mut host = Host::connect(&path);
        // Power-on: sequence and clock at 0, motors off, the handle where the plant starts.
        let first = host.report();
        assert_eq!((first.sequence, first.timestamp_us), (0, 0));
        assert!(!first.status.contains(Status::MOTORS_ENABLED));
        assert!((first.position - Vector3::new(0.0, 0.0, 0.005)).norm() < 2e-5);
        // 50 periods of a 3 N push move it; the next host finds it at the start again.
        for k in 1..=50u16 {
            host.reply(Vector3::new(3.0, 0.0, 0.0));
            let r = host.report();
            assert_eq!(r.sequence, k);
            assert!(r.status.contains(Status::MOTORS_ENABLED));
            moved = r.position - first.position;
        }
        assert!(moved.x > 0.01, "{moved:?}");
    }
    stop.store(true, Ordering::SeqCst);
    let served = server.join().unwrap();
    assert_eq!(served.hosts, 2);
    assert_eq!(served.rejected, 0);
}

#[test]
fn in_lock_step_every_host_frame_is_a_reply_and_the_device_watchdog_counts_device_time() {
    let dir = tempfile::tempdir().unwrap();
    let config = Config::default(); // device watchdog 50 ms
    let (path, stop, server) = serve(dir.path(), &config, true);
    let mut host = Host::connect(&path);
    assert_eq!(host.report().sequence, 0);
    host.reply(Vector3::zeros());
    let r = host.report();
    assert!(r.status.contains(Status::MOTORS_ENABLED));

    // A get-feature request is answered at once and is not a reply: no report follows it.
    host.send(&[1, 0x03]);
    let info = host.frame();
    assert_eq!(info.len(), DEVICE_INFO_LEN);
    let info = DeviceInfo::decode(&info).unwrap();
    assert!(info.lockstep && info.model == "sim-point-mass");
    host.nothing_for(Duration::from_millis(100));

    // A malformed output report (5 bytes) is a reply: the device advances, applying nothing.
    host.send(&[5, 0x02, 0x01, 0, 0, 0]);
    let r = host.report();
    assert_eq!(r.sequence, 2);
    assert!(r.status.contains(Status::MOTORS_ENABLED));

    // A late host: the device waits however long, and its watchdog does not count the wait.
    host.nothing_for(Duration::from_millis(150));
    host.reply(Vector3::zeros());
    let r = host.report();
    assert_eq!(r.sequence, 3);
    assert!(!r.status.contains(Status::DEVICE_WATCHDOG));

    // Malformed replies keep it in step but do not feed its watchdog: it trips after 50 ms of
    // device time (50 periods), whatever the wall clock says.
    let mut tripped_at = None;
    for k in 1..=60u16 {
        host.send(&[1 + 19, 0x02, 0x09]); // 20 bytes whose version is 9 …
        host.send(&[0; 18]); // … the rest zero
        let r = host.report();
        assert_eq!(r.sequence, 3 + k);
        if r.status.contains(Status::DEVICE_WATCHDOG) {
            assert!(!r.status.contains(Status::MOTORS_ENABLED));
            tripped_at.get_or_insert(k);
        }
    }
    let tripped_at = tripped_at.expect("the device watchdog tripped");
    assert!(
        (50..=52).contains(&tripped_at),
        "after {tripped_at} periods"
    );

    // A length byte of 0 breaks the framing: the device hangs up and serves the next host.
    host.send(&[0]);
    assert!(host.closed());
    let mut next = Host::connect(&path);
    assert_eq!(next.report().sequence, 0);
    drop(next);
    stop.store(true, Ordering::SeqCst);
    let served = server.join().unwrap();
    assert_eq!(served.hosts, 2);
    assert_eq!(served.rejected, 61);
}

/// A lock-step device that hangs after its first report: its clock stands still, so no watchdog
/// can trip on device time; after the stall limit of wall-clock time the run ends, naming it.
#[test]
fn a_lock_step_device_that_hangs_ends_the_run_without_a_watchdog_fault() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("hung.sock");
    let listener = UnixListener::bind(&path).unwrap();
    let device = std::thread::spawn(move || {
        let (mut stream, _) = listener.accept().unwrap();
        let mut request = [0u8; 2];
        stream.read_exact(&mut request).unwrap();
        assert_eq!(request, [1, 0x03]);
        let mut sim = SimDevice::from_config("point-mass", &Config::default()).unwrap();
        let mut info = [0u8; DEVICE_INFO_LEN];
        sim.device_info_report(true, &mut info);
        let mut report = [0u8; MAX_REPORT_LEN];
        let n = sim.input_report(&mut report);
        stream.write_all(&[DEVICE_INFO_LEN as u8]).unwrap();
        stream.write_all(&info).unwrap();
        stream.write_all(&[n as u8]).unwrap();
        stream.write_all(&report[..n]).unwrap();
        // Hangs: reads what the host sends, answers nothing, until the host leaves.
        let _ = std::io::copy(&mut stream, &mut std::io::sink());
    });
    let mut transport = SocketTransport::connect(&path, Speaks::default())
        .unwrap()
        .stalled_after(Duration::from_millis(300));
    let (tx, events) = crossbeam_channel::unbounded();
    let result = servo::run(
        &mut transport,
        &mut ZeroForce,
        &ServoOptions::from_config(&Config::default()),
        &AtomicBool::new(false),
        Some(&tx),
    );
    drop(transport);
    device.join().unwrap();
    match result {
        Err(ServoError::Transport(e @ TransportError::Stalled { .. })) => {
            assert!(
                e.to_string().contains("(lock-step) has sent nothing for"),
                "{e}"
            )
        }
        other => panic!("{other:?}"),
    }
    assert!(!events
        .try_iter()
        .any(|e| matches!(e, ServoEvent::WatchdogFault { .. })));
}

/// A calibration config of 8 vertices (the paper's 40 mm cube, of which the box keeps the 2×2×2
/// below the origin) that finishes in a few seconds of device time, with the loop at normal
/// scheduling.
fn quick_calibration(extra: &str) -> Config {
    let text = format!(
        "[servo]\nrealtime_priority = 0\nlock_memory = false\n{extra}\n[device]\n\
         workspace_min_mm = [-70.0, -70.0, -70.0]\nworkspace_max_mm = [0.0, 0.0, 0.0]\n\
         [calibration]\ncentre_mm = [-20.0, -20.0, -20.0]\nspacing_mm = 40.0\n"
    );
    Config::from_toml_str(&text, Path::new("quick.toml")).unwrap()
}

fn request(path: &Path, dir: &Path) -> CalibrateRequest {
    CalibrateRequest {
        device: format!("socket:{}", path.display()).parse().unwrap(),
        pacing: Pacing::RealTime,
        output: None,
        state_dir: dir.join("state"),
    }
}

/// Two threads that spin until dropped: the load of two busy loops on a two-core machine.
struct BusyLoops(Arc<AtomicBool>, Vec<JoinHandle<()>>);

impl BusyLoops {
    fn start() -> Self {
        let done = Arc::new(AtomicBool::new(false));
        let spinners = (0..2)
            .map(|_| {
                let done = done.clone();
                std::thread::spawn(move || {
                    while !done.load(Ordering::Relaxed) {
                        std::hint::spin_loop();
                    }
                })
            })
            .collect();
        Self(done, spinners)
    }
}

impl Drop for BusyLoops {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
        for spinner in self.1.drain(..) {
            let _ = spinner.join();
        }
    }
}

/// Lock-step calibrations with the smallest watchdog there is (two periods, 2 ms) while two busy
/// loops load the machine: the device sets the pace, so the watchdog counts its time and a
/// descheduled host or device is no fault (before: a wall-clock 10 ms watchdog ended 3 to 5 of 25
/// such runs). The 20 runs (25 s here); `HGCD_LOCKSTEP_RUNS=N` runs N.
#[test]
fn lock_step_socket_calibrations_complete_with_two_busy_loops_loading_the_machine() {
    let _serial = serial();
    let runs: usize = std::env::var("HGCD_LOCKSTEP_RUNS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(20);
    let dir = tempfile::tempdir().unwrap();
    let config = quick_calibration("watchdog_ms = 2.0");
    let (path, stop, server) = serve(dir.path(), &config, true);
    let load = BusyLoops::start();
    for run in 0..runs {
        let done = calibrate(
            &config,
            &request(&path, dir.path()),
            Arc::new(AtomicBool::new(false)),
            &mut |_| {},
        )
        .unwrap_or_else(|e| panic!("run {run}: {e:#}"));
        assert_eq!(done.stats.watchdog_faults, 0);
        assert_eq!(done.result.vertices.len(), 8);
        for v in &done.result.vertices {
            assert!((v.mass / 0.12 - 1.0).abs() < 0.02, "{} kg", v.mass);
        }
    }
    drop(load);
    stop.store(true, Ordering::SeqCst);
    assert_eq!(server.join().unwrap().hosts, runs as u64);
}

/// A real-time socket calibration whose device falls silent three times for 50 ms (three late
/// ticks, each past the 20 ms watchdog, the setting `docs/hid-protocol.md` §7.5 recommends for a
/// loaded machine), each silence kept up until the host has zeroed the force (a servo thread
/// descheduled for 50 ms on a loaded machine would not see it): the calibration goes on with the
/// vertex it was on and completes (before: the first ended it, nothing written).
#[test]
fn a_real_time_socket_calibration_rides_out_late_ticks_and_resumes_its_vertex() {
    const SILENCE: f64 = 0.05;
    const ANSWERED_WITHIN: f64 = 1.0;
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let config = quick_calibration("watchdog_ms = 20.0");
    let (path, stop, server) = serve(dir.path(), &config, false);
    let late = [1.5, 3.0, 4.5];
    let tap = Tap::new(SocketTransport::connect(&path, Speaks::default()).unwrap()).recording();
    let writes = tap.writes();
    // Each silence lasts until the host has answered it with a zero force (at most
    // `ANSWERED_WITHIN`): on a loaded machine the servo thread may sleep through a fixed 50 ms
    // and never see it.
    let seen = writes.clone();
    let zeroed_since = move |at: f64| {
        seen.all()
            .iter()
            .any(|(t, r)| *t >= at && r.enable && r.force == Vector3::zeros())
    };
    let tap = tap.faults(move |_, t| {
        late.iter()
            .any(|&at| {
                t >= at && (t < at + SILENCE || (t < at + ANSWERED_WITHIN && !zeroed_since(at)))
            })
            .then_some(Fault::Silence)
    });
    let mut events = Vec::new();
    let done = calibrate_on(
        Box::new(tap),
        &config,
        &request(&path, dir.path()),
        Arc::new(AtomicBool::new(false)),
        &mut |e| events.push(*e),
    )
    .unwrap_or_else(|e| panic!("{e:#}"));
    stop.store(true, Ordering::SeqCst);
    server.join().unwrap();
    assert!(done.stats.watchdog_faults >= 3, "{}", done.stats);
    // Each silence got a zero-force report (motors on, so the device resumes) within it.
    let writes = writes.all();
    for at in late {
        assert!(
            writes.iter().any(|(t, r)| *t >= at
                && *t < at + ANSWERED_WITHIN
                && r.enable
                && r.force == Vector3::zeros()),
            "no zero force in the silence at {at} s"
        );
    }
    // Every vertex started once and finished: none started over, none given up.
    let started: Vec<usize> = events
        .iter()
        .filter_map(|e| match e {
            CalibrationEvent::VertexStarted { vertex, .. } => Some(*vertex),
            _ => None,
        })
        .collect();
    assert_eq!(started, (0..8).collect::<Vec<_>>());
    assert!(!events
        .iter()
        .any(|e| matches!(e, CalibrationEvent::Failed(_))));
    for v in &done.result.vertices {
        assert!((v.mass / 0.12 - 1.0).abs() < 0.02, "{} kg", v.mass);
    }
    assert!(done.path.exists());
}

/// How a hostile lock-step device behaves after its device-info answer.
#[derive(Clone, Copy)]
enum Hostile {
    /// Frames as fast as the socket takes them, none a valid report: one byte, a wrong length,
    /// a whole report with positions beyond the protocol's range.
    Babbles,
    /// Valid reports, each answered in lock-step, whose clock runs backwards a period at a time.
    ClockBackwards,
}

/// A lock-step device at `dir/hostile.sock` that behaves as `how` until the host leaves.
fn hostile(dir: &Path, how: Hostile) -> (PathBuf, JoinHandle<()>) {
    let path = dir.join("hostile.sock");
    let listener = UnixListener::bind(&path).unwrap();
    let device = std::thread::spawn(move || {
        let (mut stream, _) = listener.accept().unwrap();
        let mut request = [0u8; 2];
        stream.read_exact(&mut request).unwrap();
        let sim = SimDevice::from_config("point-mass", &Config::default()).unwrap();
        let mut info = [0u8; DEVICE_INFO_LEN];
        sim.device_info_report(true, &mut info);
        stream.write_all(&[DEVICE_INFO_LEN as u8]).unwrap();
        stream.write_all(&info).unwrap();
        let mut report = [0u8; INPUT_REPORT_LEN];
        let mut frame = [0u8; 1 + MAX_REPORT_LEN];
        for k in 0u32.. {
            let encoded = InputReport {
                sequence: k as u16,
                timestamp_us: 1_000_000u32.wrapping_sub(k.wrapping_mul(1000)),
                position: Vector3::zeros(),
                status: Status::default(),
            }
            .encode(&mut report);
            encoded.unwrap();
            let sent = match how {
                Hostile::Babbles => {
                    let garbage: &[u8] = match k % 3 {
                        0 => &[1, 0x01],
                        1 => &[10, 0x01, 1, 2, 3, 4, 5, 6, 7, 8, 9],
                        _ => {
                            // x = i32::MAX nm: beyond the range a report may carry.
                            report[8..12].copy_from_slice(&i32::MAX.to_le_bytes());
                            frame[0] = INPUT_REPORT_LEN as u8;
                            frame[1..=INPUT_REPORT_LEN].copy_from_slice(&report);
                            &frame[..=INPUT_REPORT_LEN]
                        }
                    };
                    stream.write_all(garbage)
                }
                Hostile::ClockBackwards => {
                    let sent = stream
                        .write_all(&[INPUT_REPORT_LEN as u8])
                        .and_then(|()| stream.write_all(&report));
                    // The host's reply: a length byte and that many bytes.
                    let mut n = [0u8; 1];
                    sent.and_then(|()| stream.read_exact(&mut n))
                        .and_then(|()| stream.read_exact(&mut frame[..usize::from(n[0])]))
                }
            };
            if sent.is_err() {
                return; // The host left.
            }
        }
    });
    (path, device)
}

/// The servo loop on the hostile device `how`, as `hgcd run --duration 2` runs it, on a thread
/// of its own; what it reported, or a panic if it is still running after a minute of wall time.
fn run_against(how: Hostile) -> (servo::ServoReport, Vec<ServoEvent>) {
    let dir = tempfile::tempdir().unwrap();
    let (path, device) = hostile(dir.path(), how);
    let (done, result) = crossbeam_channel::bounded(1);
    let (tx, events) = crossbeam_channel::unbounded();
    std::thread::spawn(move || {
        let mut transport = SocketTransport::connect(&path, Speaks::default()).unwrap();
        let mut options = ServoOptions::from_config(&Config::default());
        options.duration = Some(2.0);
        let report = servo::run(
            &mut transport,
            &mut ZeroForce,
            &options,
            &AtomicBool::new(false),
            Some(&tx),
        );
        let _ = done.send(report);
    });
    let report = result
        .recv_timeout(Duration::from_secs(60))
        .expect("the run did not end within a minute of wall time")
        .unwrap();
    device.join().unwrap();
    (report, events.try_iter().collect())
}

/// hid-protocol.md §6.2: a device that sends only garbled reports trips the host watchdog, in
/// lock-step as in real time (each frame counts a period of the device's time), and
/// `--duration` ends the run.
#[test]
fn a_lock_step_device_that_only_babbles_trips_the_watchdog_and_the_run_ends() {
    let (report, events) = run_against(Hostile::Babbles);
    assert_eq!(report.exit, servo::ExitReason::DurationReached);
    assert_eq!(report.stats.watchdog_faults, 1, "{}", report.stats);
    assert!(report.stats.garbled > 1000, "{}", report.stats);
    assert_eq!(report.stats.ticks, 0);
    assert!(events
        .iter()
        .any(|e| matches!(e, ServoEvent::WatchdogFault { .. })));
}

/// A device clock that runs backwards is counted, said once, and ends the run with a fault
/// naming it after `CLOCK_BACKWARDS_LIMIT` reports in a row.
#[test]
fn a_device_clock_that_runs_backwards_is_counted_said_once_and_ends_the_run() {
    let (report, events) = run_against(Hostile::ClockBackwards);
    assert_eq!(
        report.exit,
        servo::ExitReason::Fault(servo::Fault::ClockBackwards)
    );
    assert_eq!(
        report.stats.clock_jumps_back,
        u64::from(servo::CLOCK_BACKWARDS_LIMIT)
    );
    let said = events
        .iter()
        .filter(|e| matches!(e, ServoEvent::ClockJumpedBack))
        .count();
    assert_eq!(said, 1);
    assert!(servo::Fault::ClockBackwards
        .to_string()
        .contains("ran backwards"));
}
