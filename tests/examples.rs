//! The examples as a newcomer runs them, built by cargo and run as programs against a daemon on a
//! simulated device. The device is gated: a relay between the example and the daemon lets the
//! device make its next report only once the example has answered the last one, so the example
//! closes its loop on every tick, however loaded the machine, and no test waits on the wall clock.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use nalgebra::Vector3;

use hgcd::client::{Client, Role};
use hgcd::config::Config;
use hgcd::grid::MassGrid;

mod common;
use common::daemon::TestDaemon;
use common::tap::{Gate, Tap};
use common::{distance_mm, output_within, with_device_id, WAIT};

/// The example `name`, built by cargo with the profile this test was built with (a no-op when
/// `cargo test` has built the examples already).
fn example(name: &str) -> PathBuf {
    // The binary under test sits in the profile's directory: target/<dir>/hgcd.
    let profile_dir = Path::new(env!("CARGO_BIN_EXE_hgcd")).parent().unwrap();
    let profile = match profile_dir.file_name().and_then(|n| n.to_str()) {
        Some("debug") => "test",
        Some(other) => other,
        None => panic!("no profile directory above {}", profile_dir.display()),
    };
    let built = Command::new(env!("CARGO"))
        .args(["build", "--quiet", "--example", name, "--profile", profile])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .status()
        .unwrap();
    assert!(built.success(), "building example {name}");
    profile_dir.join("examples").join(name)
}

/// A daemon on the simulated device (the configuration's, with no friction unless it says so)
/// whose reports wait at a gate.
struct Running {
    daemon: common::daemon::Running,
    gate: Arc<Gate>,
}

impl std::ops::Deref for Running {
    type Target = common::daemon::Running;
    fn deref(&self) -> &Self::Target {
        &self.daemon
    }
}

impl Running {
    /// `mass`: the device's grid, a uniform mass (kg), if any, made for the device the config's
    /// `sim.serial` names.
    fn start(config: Config, mass: Option<f64>) -> Self {
        let id = match config.sim.serial.as_str() {
            "" => "sim-point-mass".to_string(),
            serial => format!("sim-point-mass-{serial}"),
        };
        let grid = mass.map(|m| {
            let grid = MassGrid::uniform(
                m,
                9.81,
                Vector3::z(),
                Vector3::new(-0.08, -0.08, -0.08),
                0.08,
                [3, 3, 3],
            );
            with_device_id(grid, &id)
        });
        let gate = Gate::new();
        let daemon = TestDaemon::new(config)
            .plant_from_config()
            .grid(grid.as_ref())
            .start_with(|sim| Tap::new(sim).gated(gate.clone()));
        Self { daemon, gate }
    }

    /// A socket for one application, relayed to the daemon in lock-step (see [`relay`]).
    fn lock_step_socket(&self) -> (PathBuf, JoinHandle<()>) {
        let path = self.dir.path().join("relay.sock");
        let listener = UnixListener::bind(&path).unwrap();
        let (daemon, gate) = (self.socket.clone(), self.gate.clone());
        let relay = std::thread::spawn(move || {
            let (app, _) = listener.accept().unwrap();
            relay(app, UnixStream::connect(daemon).unwrap(), &gate);
        });
        (path, relay)
    }

    fn stop(mut self) {
        self.signals.stop.store(true, Ordering::SeqCst);
        self.gate.open();
        self.daemon.join().unwrap();
    }
}

impl Drop for Running {
    /// A test that failed half-way leaves no daemon waiting at its gate.
    fn drop(&mut self) {
        self.signals.stop.store(true, Ordering::SeqCst);
        self.gate.open();
    }
}

/// The `type` of a protocol line.
fn kind(line: &str) -> String {
    let value: serde_json::Value = serde_json::from_str(line).unwrap_or_default();
    value["type"].as_str().unwrap_or_default().to_string()
}

/// Carry the lines of one application's connection `app` to and from the daemon's `daemon`, and
/// run the gated device one tick each time the application is waiting for one: after it has
/// subscribed and after each `set_force`. Before the tick, a `status` round trip of the relay's
/// own on the same connection (the daemon handles a connection's requests in order; the
/// application never sees that reply) makes sure the daemon has the application's request.
fn relay(app: UnixStream, daemon: UnixStream, gate: &Gate) {
    // For each status request on the way, in order: whether the relay asked it.
    let asked: Arc<Mutex<VecDeque<bool>>> = Arc::default();
    let (synced, answered) = crossbeam_channel::unbounded();
    let down = {
        let (mut to_app, from_daemon) = (app.try_clone().unwrap(), daemon.try_clone().unwrap());
        let asked = asked.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(from_daemon).lines() {
                let Ok(line) = line else { break };
                if kind(&line) == "status" && asked.lock().unwrap().pop_front() == Some(true) {
                    let _ = synced.send(());
                } else if writeln!(to_app, "{line}").is_err() {
                    break;
                }
            }
        })
    };
    let mut to_daemon = daemon;
    for line in BufReader::new(app).lines() {
        let Ok(line) = line else { break };
        let kind = kind(&line);
        if kind == "status" {
            asked.lock().unwrap().push_back(false);
        }
        if writeln!(to_daemon, "{line}").is_err() {
            break;
        }
        if kind == "subscribe" || kind == "set_force" {
            asked.lock().unwrap().push_back(true);
            if writeln!(to_daemon, "{{\"type\":\"status\"}}").is_err() {
                break;
            }
            match answered.recv_timeout(WAIT) {
                Ok(()) => {}
                Err(crossbeam_channel::RecvTimeoutError::Disconnected) => break,
                Err(e) => panic!("the daemon did not answer the relay's status: {e}"),
            }
            gate.advance(1);
        }
    }
    let _ = to_daemon.shutdown(std::net::Shutdown::Both);
    down.join().unwrap();
}

/// Run the example `virtual_wall` with `args` against `socket`; its output. It must end within
/// [`RUN_LIMIT`] (it runs a few seconds of device time, a few seconds of wall-clock time).
fn virtual_wall(socket: &Path, args: &[&str]) -> Output {
    let mut command = Command::new(example("virtual_wall"));
    command
        .arg("--socket")
        .arg(socket)
        .args(args)
        // A panic would print its backtrace: the test below checks there is none.
        .env("RUST_BACKTRACE", "1")
        .stdin(Stdio::null());
    output_within(command, RUN_LIMIT)
}

/// How long an example may run before the test gives up on it.
const RUN_LIMIT: std::time::Duration = std::time::Duration::from_secs(120);

/// The mean penetration the example reports, m.
fn reported_penetration(stdout: &str) -> f64 {
    let after = stdout
        .split("mean penetration over the last 1 s: ")
        .nth(1)
        .unwrap_or_else(|| panic!("no penetration reported: {stdout}"));
    let mm: f64 = after.split(" mm").next().unwrap().parse().unwrap();
    mm * 1e-3
}

/// `virtual_wall` at 1 N/mm for 3 s on `running`'s device in lock-step, the daemon stopped after:
/// the example succeeds and reports a mean penetration within 5 % of `expected` (m). What it
/// printed.
fn sinks_into_the_wall(running: Running, expected: f64) -> String {
    let (socket, relay) = running.lock_step_socket();
    let out = virtual_wall(&socket, &["--stiffness", "1", "--duration", "3"]);
    relay.join().unwrap();
    running.stop();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let penetration = reported_penetration(&stdout);
    assert!(
        (penetration / expected - 1.0).abs() < 0.05,
        "penetration {:.3} mm, expected {:.3} mm: {stdout}",
        penetration * 1e3,
        expected * 1e3
    );
    stdout
}

#[test]
fn virtual_wall_on_an_uncalibrated_daemon_holds_the_handle_at_its_weight_over_k() {
    // As a newcomer meets it: the default simulated device (120 g, no friction), no grid.
    let config = Config::default();
    let (m, g, k) = (config.sim.mass_kg, config.sim.g, 1000.0);
    let running = Running::start(config, None);
    // The uncompensated handle falls onto the lower stop, 80 mm below the wall, before the example
    // starts: there the wall's spring asks for 80 N, far beyond the daemon's 8 N limit.
    running.gate.advance(500);
    // Resting on the wall, the spring carries the whole uncompensated weight.
    let stdout = sinks_into_the_wall(running, m * g / k); // 1.18 mm
                                                          // It says why: no compensation, so the handle's own weight is on the wall.
    assert!(stdout.contains("gravity compensation: none"), "{stdout}");
    assert!(stdout.contains("own weight"), "{stdout}");
}

#[test]
fn virtual_wall_with_compensation_sinks_only_the_probe() {
    // The paper's experiment: a 30 g probe on a compensated handle, 1 N/mm.
    let mut config = Config::default();
    config.sim.probe_mass_kg = 0.03;
    let (m_p, g, k) = (0.03, config.sim.g, 1000.0);
    let running = Running::start(config.clone(), Some(config.sim.mass_kg));
    let stdout = sinks_into_the_wall(running, m_p * g / k); // 0.29 mm
    assert!(stdout.contains("gravity compensation: scalar"), "{stdout}");
}

#[test]
fn virtual_wall_says_in_one_line_why_it_cannot_run() {
    let running = Running::start(Config::default(), None);
    // Another application owns the force: the daemon lets the example only observe.
    let _owner = Client::connect(&running.socket, Role::Control, "owner").unwrap();
    let owned = virtual_wall(&running.socket, &[]);
    let missing = virtual_wall(&running.dir.path().join("nothing.sock"), &[]);
    let bad = virtual_wall(&running.socket, &["--stiffness=-1"]);
    drop(_owner);
    running.stop();
    for (out, says) in [
        (owned, "another application owns the force"),
        (missing, "--socket"),
        (bad, "--stiffness"),
    ] {
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{stderr}");
        assert!(stderr.starts_with("virtual_wall: "), "{stderr}");
        assert!(stderr.contains(says), "{stderr}");
        assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    }
}

/// The example `two_handles` with `args`, on a host where no daemon runs by default (an empty
/// runtime directory); its output, once it ended within [`RUN_LIMIT`].
fn two_handles(args: &[&std::ffi::OsStr]) -> Output {
    let empty = tempfile::tempdir().unwrap();
    let child = Command::new(example("two_handles"))
        .args(args)
        .env("RUNTIME_DIRECTORY", empty.path())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || tx.send(child.wait_with_output()));
    rx.recv_timeout(RUN_LIMIT)
        .unwrap_or_else(|_| panic!("two_handles did not end within {RUN_LIMIT:?}"))
        .unwrap()
}

#[test]
fn two_handles_on_two_daemons_pulls_the_handles_together() {
    example("two_handles"); // built before the gated devices start waiting for it
                            // Two compensated simulated devices, two units of one model, their handles 30 mm apart.
    let daemon = |serial: &str, x_mm: f64| {
        let mut config = Config::default();
        config.sim.serial = serial.into();
        config.sim.start_position_mm = [x_mm, 0.0, 0.0];
        let mass = config.sim.mass_kg;
        Running::start(config, Some(mass))
    };
    let (a, b) = (daemon("A", 0.0), daemon("B", 30.0));
    let (socket_a, relay_a) = a.lock_step_socket();
    let (socket_b, relay_b) = b.lock_step_socket();
    let socket = std::ffi::OsStr::new("--socket");
    let out = two_handles(&[
        socket,
        socket_a.as_os_str(),
        socket,
        socket_b.as_os_str(),
        "--duration".as_ref(),
        "1".as_ref(),
    ]);
    relay_a.join().unwrap();
    relay_b.join().unwrap();
    a.stop();
    b.stop();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let gap = |at: &str| distance_mm(&stdout, at);
    assert!(
        stdout.contains("sim-point-mass-A and sim-point-mass-B"),
        "{stdout}"
    );
    assert!((gap("the start") - 30.0).abs() < 0.1, "{stdout}");
    assert!(gap("the end") < 0.1, "{stdout}");
}

#[test]
fn two_handles_says_in_one_line_what_it_needs() {
    let device = std::ffi::OsStr::new("--device");
    let one = two_handles(&[device, "sim-point-mass-A".as_ref()]);
    let none = two_handles(&[device, "A".as_ref(), device, "B".as_ref()]);
    for (out, says) in [
        (one, "two_handles: name two daemons"),
        (none, "two_handles: no daemon is running"),
    ] {
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{stderr}");
        assert!(stderr.starts_with(says), "{stderr}");
        assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    }
}

#[test]
fn bare_loop_says_in_one_line_what_its_argument_is() {
    // Before: a panic ("seconds as a number") with a backtrace.
    let out = Command::new(example("bare_loop"))
        .arg("ten")
        .env("RUST_BACKTRACE", "1")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.starts_with("bare_loop: "), "{stderr}");
    assert!(stderr.contains("seconds"), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
}
