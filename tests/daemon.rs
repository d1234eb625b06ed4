//! `hgcd run` as a daemon: compensation, the application socket, hostile clients, grids.

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender};
use nalgebra::Vector3;

use hgcd::client::{Client, Reply, Role, StateSample};
use hgcd::config::Config;
use hgcd::control::compensation::CompensationMode;
use hgcd::daemon::{Daemon, RunRequest, Signals};
use hgcd::grid::{GridFile, MassGrid};
use hgcd::protocol::{OutputReport, OUTPUT_REPORT_LEN};
use hgcd::servo::ServoReport;
use hgcd::transport::sim::{SimDevice, SimTransport};
use hgcd::transport::{Pacing, Transport, TransportError, MAX_REPORT_LEN};

mod common;
use common::{serial, truth_field_27, with_device_id};

/// Records every output report the servo loop writes.
struct Recording {
    inner: SimTransport,
    writes: Sender<OutputReport>,
}

impl Transport for Recording {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        self.inner.read_input(buf, timeout)
    }
    fn write_output(&mut self, report: &[u8; OUTPUT_REPORT_LEN]) -> Result<(), TransportError> {
        let _ = self.writes.send(OutputReport::decode(report).unwrap());
        self.inner.write_output(report)
    }
    fn now(&self) -> f64 {
        self.inner.now()
    }
    fn describe(&self) -> String {
        "recording".into()
    }
}

struct Running {
    dir: tempfile::TempDir,
    socket: PathBuf,
    signals: Signals,
    handle: JoinHandle<Result<ServoReport, hgcd::daemon::RunError>>,
    writes: Receiver<OutputReport>,
}

impl Running {
    fn client(&self, role: Role, name: &str) -> Client {
        let mut c = Client::connect(&self.socket, role, name).unwrap();
        c.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        c
    }
    /// Wait for a daemon started with a duration to end by itself.
    fn wait(self) -> Result<ServoReport, hgcd::daemon::RunError> {
        self.handle.join().unwrap()
    }
    fn stop(
        self,
    ) -> (
        Result<ServoReport, hgcd::daemon::RunError>,
        tempfile::TempDir,
        Receiver<OutputReport>,
    ) {
        self.signals.stop.store(true, Ordering::SeqCst);
        (self.handle.join().unwrap(), self.dir, self.writes)
    }
}

/// Start a daemon on a simulated device whose mass field is [`truth_field`]. `grid`: written to
/// the state dir as the device's grid.
fn start(
    config: Config,
    pacing: Pacing,
    grid: Option<&GridFile>,
    duration: Option<f64>,
) -> Running {
    launch(config, pacing, grid, &truth_field_27(), duration)
}

fn start_with_truth(
    config: Config,
    pacing: Pacing,
    grid: Option<&GridFile>,
    truth: &MassGrid,
) -> Running {
    launch(config, pacing, grid, truth, None)
}

fn launch(
    mut config: Config,
    pacing: Pacing,
    grid: Option<&GridFile>,
    truth_grid: &MassGrid,
    duration: Option<f64>,
) -> Running {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    std::fs::create_dir_all(&state).unwrap();
    let truth = dir.path().join("truth.toml");
    GridFile::from(truth_grid.clone())
        .save_atomic(&truth)
        .unwrap();
    config.sim.mass_grid = Some(truth);
    config.paths.state_dir = Some(state.clone());
    let socket = dir.path().join("hgcd.sock");
    config.app.socket = Some(socket.clone());
    // SCHED_FIFO (where permitted) for real-time runs, as the daemon would have it; a
    // virtual-time run never asks for it (see Daemon::new).
    // A frictionless point mass is a double integrator: any bias force, however small, makes it
    // drift quadratically. Real linkages have viscous friction; 1 N·s/m is typical of desktop
    // haptic devices. With it a 0.1 % mass error still drifts about 3 mm in 2 s: the drift test
    // below stays sharp.
    if config.sim.damping_n_s_per_m == 0.0 {
        config.sim.damping_n_s_per_m = 1.0;
    }
    config.servo.lock_memory = false;
    if let Some(g) = grid {
        g.save_atomic(&state.join("sim-point-mass.toml")).unwrap();
    }
    let (writes_tx, writes) = crossbeam_channel::unbounded();
    let transport = Box::new(Recording {
        inner: SimTransport::new(
            SimDevice::from_config("point-mass", &config).unwrap(),
            pacing,
        ),
        writes: writes_tx,
    });
    let request = RunRequest {
        device: "sim:point-mass".parse().unwrap(),
        duration,
        pacing,
    };
    let signals = Signals::default();
    let s2 = signals.clone();
    let (ready_tx, ready_rx) = crossbeam_channel::bounded(1);
    let handle = std::thread::spawn(move || {
        Daemon::new(config, &request).run(transport, s2, &mut |_| {
            let _ = ready_tx.send(());
        })
    });
    // Wait for readiness (or for the daemon to fail before it).
    let _ = ready_rx.recv();
    Running {
        dir,
        socket,
        signals,
        handle,
        writes,
    }
}

/// States from `client` until device time reaches `t`.
fn state_at(client: &mut Client, t: f64) -> StateSample {
    loop {
        let s = client.next_state().unwrap();
        if s.time >= t {
            return s;
        }
    }
}

fn dist(a: [f64; 3], b: Vector3<f64>) -> f64 {
    (Vector3::from(a) - b).norm()
}

#[test]
fn compensation_holds_the_handle_anywhere_in_the_grid_and_it_falls_without() {
    let _serial = serial();
    let grid = with_device_id(truth_field_27(), "sim-point-mass");
    // Release points: vertices, cell centres, points off every symmetry.
    let points_mm = [
        [0.0, 0.0, 0.0],
        [-40.0, 40.0, -40.0],
        [13.0, -27.0, 31.0],
        [-20.0, -20.0, 20.0],
        [37.0, 5.0, -38.0],
    ];
    for p in points_mm {
        let mut config = Config::default();
        config.sim.start_position_mm = p;
        let start_at = Vector3::from(p) * 1e-3;
        let running = start(config, Pacing::Virtual, Some(&grid), None);
        let mut client = running.client(Role::Control, "test");
        client.set_force(Vector3::zeros()).unwrap();
        client.subscribe(1000.0).unwrap();
        let s = state_at(&mut client, 2.0);
        let drift = dist(s.position, start_at);
        assert!(
            drift < 0.5e-3,
            "released at {p:?} mm: drifted {:.3} mm in 2 s",
            drift * 1e3
        );
        drop(client);
        running.stop().0.unwrap();
    }
    // Without a grid the same device falls.
    let mut config = Config::default();
    config.sim.start_position_mm = [13.0, -27.0, 31.0];
    let running = start(config, Pacing::Virtual, None, None);
    let mut client = running.client(Role::Control, "test");
    client.subscribe(1000.0).unwrap();
    let s = state_at(&mut client, 2.0);
    assert!(
        s.position[2] < -0.079,
        "fell to the floor: {:?}",
        s.position
    );
    drop(client);
    running.stop().0.unwrap();
}

#[test]
fn a_force_offset_appears_in_the_next_output_report() {
    let _serial = serial();
    let grid = with_device_id(truth_field_27(), "sim-point-mass");
    let running = start(Config::default(), Pacing::RealTime, Some(&grid), None);
    let mut client = running.client(Role::Control, "offsets");
    client.subscribe(1000.0).unwrap();
    let offset = Vector3::new(0.3, -0.2, 0.5);
    let seen = client.next_state().unwrap();
    client.set_force(offset).unwrap();
    let applied = loop {
        let s = client.next_state().unwrap();
        if s.offset_seq == 1 {
            break s;
        }
        assert_eq!(s.offset_seq, 0);
    };
    // The state we saw was already up to a millisecond old when it reached us; one tick for the
    // offset to cross the socket and one to be applied: within a few ticks of it.
    assert!(
        applied.tick <= seen.tick + 5,
        "seen at tick {}, applied at tick {}",
        seen.tick,
        applied.tick
    );
    drop(client);
    let (result, _dir, writes) = running.stop();
    result.unwrap();
    let writes: Vec<OutputReport> = writes.try_iter().collect();
    // Tick k writes the k-th report: the tick that took the offset sent it, not a later one, and
    // the report before it did not carry it.
    let sent = writes[applied.tick as usize].force;
    let previous = writes[applied.tick as usize - 1].force;
    assert!(
        (previous - sent).norm() > 0.5,
        "the offset arrives in one step"
    );
    assert!((sent - Vector3::from(applied.force)).norm() < 1e-5);
    let gravity = grid.grid.gravity_force(&Vector3::from(applied.position));
    assert!(
        (sent - gravity - offset).norm() < 2e-3,
        "sent {sent}, gravity {gravity} + offset {offset}"
    );
}

#[test]
fn a_stale_offset_ramps_to_zero_and_a_disconnect_removes_it_at_once() {
    let _serial = serial();
    // No grid: the force sent is the offset alone.
    let running = start(Config::default(), Pacing::RealTime, None, None);
    let mut client = running.client(Role::Control, "stale");
    client.subscribe(1000.0).unwrap();
    client.next_state().unwrap();
    let offset = Vector3::new(0.0, 0.0, 1.0);
    client.set_force(offset).unwrap();
    let first = loop {
        let s = client.next_state().unwrap();
        if s.offset_seq == 1 {
            break s;
        }
    };
    let at = |client: &mut Client, dt: f64| state_at(client, first.time + dt).force[2];
    assert!(
        (at(&mut client, 0.045) - 1.0).abs() < 1e-9,
        "fresh for 50 ms"
    );
    let mid = at(&mut client, 0.075);
    assert!(mid > 0.3 && mid < 0.7, "ramping: {mid}");
    assert_eq!(at(&mut client, 0.11), 0.0, "gone after 100 ms");

    // Fresh offset, then an abrupt disconnect: an observer sees it vanish on the next ticks.
    let mut observer = running.client(Role::Observe, "observer");
    observer.subscribe(1000.0).unwrap();
    client.set_force(offset).unwrap();
    loop {
        let s = observer.next_state().unwrap();
        if s.offset_seq == 2 {
            assert_eq!(s.force[2], 1.0);
            break;
        }
    }
    drop(client);
    let gone = loop {
        let s = observer.next_state().unwrap();
        if s.offset_seq == 0 {
            break s;
        }
        assert_eq!(s.force[2], 1.0, "full offset until it is removed");
    };
    assert_eq!(gone.force, [0.0; 3], "removed at once, no ramp");
    drop(observer);
    running.stop().0.unwrap();
}

#[test]
fn hostile_clients_do_not_disturb_the_loop_or_the_owner() {
    let _serial = serial();
    let grid = with_device_id(truth_field_27(), "sim-point-mass");
    let mut config = Config::default();
    config.app.hello_timeout_ms = 300.0;
    let running = start(config, Pacing::RealTime, Some(&grid), Some(2.0));
    let mut owner = running.client(Role::Control, "owner");
    owner.subscribe(100.0).unwrap();
    let offset = Vector3::new(0.0, 0.2, 0.0);
    owner.set_force(offset).unwrap();

    let connect = || UnixStream::connect(&running.socket).unwrap();
    let read_all = |mut s: UnixStream| {
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut out = String::new();
        let _ = s.read_to_string(&mut out);
        out
    };
    // Connections left idle without a hello are closed after app.hello_timeout_ms (300 ms here),
    // so they cannot hold every place.
    let idle: Vec<UnixStream> = (0..8).map(|_| connect()).collect();
    for s in idle {
        let out = read_all(s);
        assert!(out.contains("no hello within the time limit"), "{out:?}");
    }
    // Garbage bytes.
    let mut s = connect();
    s.write_all(b"\x00\xff\x13garbage\n").unwrap();
    let out = read_all(s);
    assert!(out.contains("\"fatal\":true"), "{out}");
    // A huge line (no newline within the limit).
    let mut s = connect();
    let _ = s.write_all(&vec![b'{'; 100_000]);
    let out = read_all(s);
    assert!(out.contains("longer than"), "{out}");
    // No hello first.
    let mut s = connect();
    s.write_all(b"{\"type\":\"set_force\",\"seq\":1,\"force\":[1,0,0]}\n")
        .unwrap();
    assert!(read_all(s).contains("first message must be hello"));
    // A flood of status requests and forces from a non-owner, then an abrupt disconnect.
    let mut s = connect();
    s.write_all(b"{\"type\":\"hello\",\"version\":1,\"role\":\"control\"}\n")
        .unwrap();
    let mut flood = Vec::new();
    for seq in 1..=2000 {
        flood.extend_from_slice(
            format!("{{\"type\":\"set_force\",\"seq\":{seq},\"force\":[5,5,5]}}\n").as_bytes(),
        );
    }
    let _ = s.write_all(&flood);
    drop(s);
    // A flood of status requests, and a subscriber that never reads (its states are dropped
    // once its queue is full, and it is closed once its socket stops taking writes).
    let mut s = connect();
    let mut flood = b"{\"type\":\"hello\",\"version\":1,\"role\":\"observe\"}\n".to_vec();
    for _ in 0..2000 {
        flood.extend_from_slice(b"{\"type\":\"status\"}\n");
    }
    s.write_all(&flood).unwrap();
    drop(s);
    let mut deaf = connect();
    deaf.write_all(b"{\"type\":\"hello\",\"version\":1,\"role\":\"observe\"}\n{\"type\":\"subscribe\",\"rate_hz\":1000}\n").unwrap();
    // Dozens of connections opened and dropped at once.
    for _ in 0..50 {
        drop(connect());
    }

    drop(deaf);
    // The owner's offset still rules.
    owner.set_force(offset).unwrap();
    let seq = owner.last_seq();
    let s = loop {
        let s = owner.next_state().unwrap();
        if s.offset_seq == seq {
            break s;
        }
    };
    let gravity = grid.grid.gravity_force(&Vector3::from(s.position));
    assert!((Vector3::from(s.force) - gravity - offset).norm() < 2e-3);
    drop(owner);
    let report = running.wait().unwrap();
    // The loop kept its rate: 2 s at 1 kHz, no watchdog fault, nothing garbled.
    assert!(report.stats.ticks >= 1950, "{}", report.stats);
    assert_eq!(report.stats.watchdog_faults, 0);
    assert!(report.stats.missed < 50, "{}", report.stats);
}

#[test]
fn only_one_client_owns_the_force() {
    let _serial = serial();
    let running = start(Config::default(), Pacing::Virtual, None, None);
    let a = running.client(Role::Control, "a");
    assert_eq!(a.role, Role::Control);
    let mut b = running.client(Role::Control, "b");
    assert_eq!(b.role, Role::Observe);
    match b.next_reply().unwrap() {
        Reply::Error { message, fatal } => {
            assert!(!fatal);
            assert!(message.contains("another client owns"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    b.set_force(Vector3::new(1.0, 0.0, 0.0)).unwrap();
    match b.next_reply().unwrap() {
        Reply::Error { message, fatal } => {
            assert!(!fatal);
            assert!(message.contains("does not own the force"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    // An observer cannot start a calibration under the owner's hands.
    b.request_calibration().unwrap();
    match b.next_reply().unwrap() {
        Reply::Error { message, fatal } => {
            assert!(!fatal);
            assert!(
                message.contains("only it may start a calibration"),
                "{message}"
            );
        }
        other => panic!("{other:?}"),
    }
    let status = b.status().unwrap();
    assert!(!status.calibrating);
    assert_eq!(status.owner.as_deref(), Some("a"));
    assert_eq!(status.clients, 2);
    drop(a);
    drop(b);
    // The owner may not send sequence numbers out of order: that closes it.
    let mut observer = running.client(Role::Observe, "observer");
    while observer.status().unwrap().owner.is_some() {}
    let mut s = UnixStream::connect(&running.socket).unwrap();
    s.write_all(b"{\"type\":\"hello\",\"version\":1,\"role\":\"control\"}\n")
        .unwrap();
    let mut owner = std::io::BufReader::new(s.try_clone().unwrap());
    let mut welcome = String::new();
    std::io::BufRead::read_line(&mut owner, &mut welcome).unwrap();
    assert!(welcome.contains("\"role\":\"control\""), "{welcome}");
    s.write_all(b"{\"type\":\"set_force\",\"seq\":5,\"force\":[0,0,0]}\n{\"type\":\"set_force\",\"seq\":4,\"force\":[0,0,0]}\n").unwrap();
    let mut rest = String::new();
    let _ = owner.read_to_string(&mut rest);
    assert!(
        rest.contains("out-of-order set_force: seq 4 after 5"),
        "{rest}"
    );
    running.stop().0.unwrap();
}

#[test]
fn a_grid_for_another_device_is_refused_unless_allowed() {
    let _serial = serial();
    let foreign = with_device_id(truth_field_27(), "hid-1234-5678-SN9");
    let running = start(Config::default(), Pacing::Virtual, Some(&foreign), None);
    let err = running.handle.join().unwrap().unwrap_err();
    let text = format!("{err:#}");
    assert!(
        text.contains("made for device `hid-1234-5678-SN9`")
            && text.contains("allow_uncompensated"),
        "{text}"
    );

    let mut config = Config::default();
    config.compensation.allow_uncompensated = true;
    let running = start(config, Pacing::Virtual, Some(&foreign), None);
    let mut c = running.client(Role::Observe, "status");
    let status = c.status().unwrap();
    assert_eq!(status.mode, "none");
    assert_eq!(status.grid, None);
    drop(c);
    running.stop().0.unwrap();
}

fn wait_for_mode(client: &mut Client, mode: &str) -> hgcd::client::Status {
    loop {
        let s = client.status().unwrap();
        if s.mode == mode {
            return s;
        }
    }
}

#[test]
fn calibration_over_the_socket_hot_swaps_the_grid_and_sighup_reloads() {
    let _serial = serial();
    let running = start(Config::default(), Pacing::Virtual, None, None);
    let grid_file = running.dir.path().join("state/sim-point-mass.toml");
    let mut c = running.client(Role::Observe, "calibrator");
    assert_eq!(c.status().unwrap().mode, "none");
    c.request_calibration().unwrap();
    let path = loop {
        if let Reply::Calibration { event, message, .. } = c.next_reply().unwrap() {
            match event.as_str() {
                "finished" => break message,
                "failed" => panic!("calibration failed: {message}"),
                _ => {}
            }
        }
    };
    assert_eq!(Path::new(&path), grid_file);
    let status = wait_for_mode(&mut c, "scalar");
    assert_eq!(status.grid.as_deref(), Some(path.as_str()));
    // The handle did not drop between the end of the calibration and the swap: it is still near
    // the last vertex of the serpentine, (40, 40, 40) mm, held by the new grid.
    c.subscribe(1000.0).unwrap();
    let s = c.next_state().unwrap();
    let last_vertex = Vector3::new(0.04, 0.04, 0.04);
    assert!(
        dist(s.position, last_vertex) < 2e-3,
        "handle at {:?} after the swap",
        s.position
    );
    c.subscribe(0.0).unwrap();
    // The grid the daemon made is for this device, and holds the truth (the truth field here).
    let file = GridFile::load(&grid_file).unwrap();
    assert_eq!(file.device.unwrap().id, "sim-point-mass");
    let grid = file.grid;
    for (n, m) in grid.masses.iter().enumerate() {
        let x = grid.vertex_position(n % 3, (n / 3) % 3, n / 9);
        let truth = truth_field_27().mass_at(&x);
        assert!((m / truth - 1.0).abs() < 0.01, "{m} vs {truth}");
    }

    // SIGHUP: the grid file is gone, so a reload drops compensation.
    std::fs::remove_file(&grid_file).unwrap();
    running.signals.reload.store(true, Ordering::SeqCst);
    wait_for_mode(&mut c, "none");
    drop(c);
    running.stop().0.unwrap();
}

/// Mean penetration of a virtual horizontal surface at the start height, rendered by a client,
/// over the last 0.5 s of `duration` s (the paper's experiment, §5).
fn wall_penalty(running: &Running, k: f64, damping: f64, duration: f64) -> f64 {
    let mut client = running.client(Role::Control, "wall");
    client.subscribe(1000.0).unwrap();
    let first = client.next_state().unwrap();
    let height = first.position[2];
    let (mut sum, mut count) = (0.0, 0);
    loop {
        let s = client.next_state().unwrap();
        if s.time - first.time > duration {
            break;
        }
        let depth = height - s.position[2];
        // Like any application, stay within the daemon's force limit (8 N per axis).
        let fz = if depth > 0.0 {
            (k * depth - damping * s.velocity[2]).clamp(-8.0, 8.0)
        } else {
            0.0
        };
        client.set_force(Vector3::new(0.0, 0.0, fz)).unwrap();
        if s.time - first.time > duration - 0.5 {
            sum += depth;
            count += 1;
        }
    }
    sum / count as f64
}

#[test]
fn paper_experiment_penalty_is_probe_weight_over_stiffness_with_compensation() {
    let _serial = serial();
    // Gravity along −z here: the surface is horizontal, as in the paper.
    let mut truth = truth_field_27();
    truth.gravity_direction = Vector3::z();
    let grid = with_device_id(truth.clone(), "sim-point-mass");
    let (m_p, k, g) = (0.03, 1000.0, 9.81);
    for p in [[13.0, -27.0, 31.0], [-30.0, 30.0, -30.0]] {
        let mut config = Config::default();
        config.sim.probe_mass_kg = m_p;
        config.sim.start_position_mm = p;
        let running = start_with_truth(config, Pacing::RealTime, Some(&grid), &truth);
        let penalty = wall_penalty(&running, k, 10.0, 2.0);
        running.stop().0.unwrap();
        let expected = m_p * g / k; // 0.294 mm
        assert!(
            (penalty / expected - 1.0).abs() < 0.05,
            "at {p:?} mm: penalty {:.3} mm, expected {:.3} mm",
            penalty * 1e3,
            expected * 1e3
        );
    }
    // Without compensation the end effector's own apparent mass sinks in too.
    let p = [13.0, -27.0, 31.0];
    let mut config = Config::default();
    config.sim.probe_mass_kg = m_p;
    config.sim.start_position_mm = p;
    let running = start_with_truth(config, Pacing::RealTime, None, &truth);
    let penalty = wall_penalty(&running, k, 10.0, 2.0);
    running.stop().0.unwrap();
    let x = Vector3::from(p) * 1e-3;
    let expected = (truth.mass_at(&x) + m_p) * g / k;
    assert!(
        (penalty / expected - 1.0).abs() < 0.05,
        "uncompensated penalty {:.3} mm, expected {:.3} mm",
        penalty * 1e3,
        expected * 1e3
    );
}

#[test]
fn a_calibration_whose_requester_disconnects_is_aborted_and_writes_nothing() {
    let _serial = serial();
    let running = start(Config::default(), Pacing::RealTime, None, None);
    let grid_file = running.dir.path().join("state/sim-point-mass.toml");
    let mut requester = running.client(Role::Observe, "calibrator");
    requester.request_calibration().unwrap();
    loop {
        if let Reply::Calibration { event, .. } = requester.next_reply().unwrap() {
            assert_eq!(event, "started");
            break;
        }
    }
    // Ctrl-C on `hgcd calibrate --via-daemon` closes the connection.
    drop(requester);
    let mut observer = running.client(Role::Observe, "observer");
    while observer.status().unwrap().calibrating {}
    assert_eq!(observer.status().unwrap().mode, "none");
    assert!(!grid_file.exists());
    drop(observer);
    running.stop().0.unwrap();
}

#[test]
fn calibrate_then_run_end_to_end_holds_the_handle() {
    let _serial = serial();
    // Calibrate the simulated device (virtual time), then compensate with the grid it produced.
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("truth.toml");
    GridFile::from(truth_field_27())
        .save_atomic(&truth)
        .unwrap();
    let mut config = Config::default();
    config.sim.mass_grid = Some(truth);
    config.sim.damping_n_s_per_m = 1.0;
    let request = hgcd::calibrate::CalibrateRequest {
        device: "sim:point-mass".parse().unwrap(),
        pacing: Pacing::Virtual,
        output: Some(dir.path().join("grid.toml")),
        state_dir: dir.path().to_path_buf(),
    };
    let run = hgcd::calibrate::calibrate(
        &config,
        &request,
        std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false)),
        &mut |_| {},
    )
    .unwrap();
    let modes = [
        CompensationMode::Scalar,
        CompensationMode::Vector,
        CompensationMode::Scalar,
    ];
    for (p, mode) in [[0.0, 0.0, 0.0], [13.0, -27.0, 31.0], [37.0, 5.0, -38.0]]
        .into_iter()
        .zip(modes)
    {
        let mut config = Config::default();
        config.sim.start_position_mm = p;
        config.sim.damping_n_s_per_m = 1.0;
        // Vector mode interpolates the holding forces the calibration measured.
        config.compensation.mode = mode;
        let running = start(config, Pacing::Virtual, Some(&run.grid), None);
        let mut client = running.client(Role::Control, "e2e");
        let expected_mode = format!("{mode:?}").to_lowercase();
        assert_eq!(client.status().unwrap().mode, expected_mode);
        client.subscribe(1000.0).unwrap();
        let s = state_at(&mut client, 2.0);
        let drift = dist(s.position, Vector3::from(p) * 1e-3);
        // The calibrated masses are within about 0.1 % of the truth on this field (five-fold
        // contrast between neighbours); on a plant with only 1 N·s/m of friction that leaves a
        // few millimetres of creep in 2 s, where the uncompensated handle falls 80 mm in 0.3 s.
        // (With the exact grid the daemon holds it within 0.5 mm: the test above.)
        assert!(
            drift < 10e-3,
            "released at {p:?} mm ({mode:?} mode): drifted {:.3} mm in 2 s",
            drift * 1e3
        );
        drop(client);
        running.stop().0.unwrap();
    }
}
