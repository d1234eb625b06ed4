//! The C and Python clients (`clients/c`, `clients/python`) run as their users run them: the C
//! example built with the system's `cc` against `libhgcd_c`, the Python example with `python3`,
//! each against a daemon on a simulated device. The tests assert the physics they render (the
//! wall's penetration, the spring's restoring force) and the one-line error each gives when the
//! daemon's replies are garbage or the daemon goes away.
//!
//! The device is gated (lock-step): a [`Relay`] between the example and the daemon sees each
//! state go out and the example's answer come back, and the test lets the next report through
//! only once the daemon has taken that answer, as on a real-time machine that keeps up.
//!
//! Needs `cc` and `python3` on PATH (README): a test fails naming the one that is missing.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::thread::JoinHandle;
use std::time::Instant;

use nalgebra::Vector3;

use hgcd::app::protocol;
use hgcd::client::{Client, ClientError, Reply, Role, StateSample};
use hgcd::config::Config;
use hgcd::grid::MassGrid;

mod common;
use common::daemon::{Running, TestDaemon};
use common::tap::{Gate, Tap};
use common::{distance_mm, tilted_v_g, truth_field_27, wait_for, with_device_id, WAIT};

/// The probe mass hung on the handle, kg, and g, m/s².
const PROBE_KG: f64 = 0.03;
const G: f64 = 9.81;

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// `name` from PATH; the test fails saying what it is for when it is not there.
fn tool(name: &str, why: &str) -> PathBuf {
    std::env::var_os("PATH")
        .iter()
        .flat_map(std::env::split_paths)
        .map(|dir| dir.join(name))
        .find(|p| p.is_file())
        .unwrap_or_else(|| panic!("`{name}` is not on PATH: {why}"))
}

/// The directory cargo builds into and this test's profile directory in it (`debug`, or
/// `release` under `cargo test --release`): this test runs from `TARGET/PROFILE/deps/`.
fn target_dir() -> (PathBuf, String) {
    let exe = std::env::current_exe().unwrap();
    let mut up = exe.ancestors().skip(2);
    let profile = up
        .next()
        .and_then(|p| p.file_name())
        .expect("TARGET/PROFILE/deps/TEST");
    let profile = profile.to_string_lossy().into_owned();
    (up.next().unwrap().to_path_buf(), profile)
}

/// The C examples (`clients/c/examples/*.c`), built once per run: `cargo build -p hgcd-c` with
/// this test's profile, then `cc` against the shared library, warnings as errors. The directory
/// of the programs.
fn c_examples() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let cc = tool(
            "cc",
            "the C client tests build clients/c/examples/*.c with the system's C compiler \
             (Debian: apt-get install gcc)",
        );
        let (target, profile) = target_dir();
        let mut build = Command::new(env!("CARGO"));
        build
            .args(["build", "-p", "hgcd-c", "--target-dir"])
            .arg(&target)
            .current_dir(repo());
        if profile == "release" {
            build.arg("--release");
        }
        let built = build.output().unwrap();
        assert!(
            built.status.success(),
            "cargo build -p hgcd-c failed:\n{}",
            String::from_utf8_lossy(&built.stderr)
        );
        let lib = target.join(profile);
        let out = target.join("clients-test");
        std::fs::create_dir_all(&out).unwrap();
        for name in ["virtual_wall", "two_handles"] {
            let compiled = Command::new(&cc)
                .args(["-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-I"])
                .arg(repo().join("clients/c/include"))
                .arg(repo().join(format!("clients/c/examples/{name}.c")))
                .arg("-L")
                .arg(&lib)
                .args(["-lhgcd_c", "-lm"])
                .arg(format!("-Wl,-rpath,{}", lib.display()))
                .arg("-o")
                .arg(out.join(name))
                .output()
                .unwrap();
            assert!(
                compiled.status.success(),
                "cc could not build the C example {name}:\n{}",
                String::from_utf8_lossy(&compiled.stderr)
            );
        }
        out
    })
}

/// The C wall example on `socket`, with `args`.
fn c_wall_on(socket: &Path, args: &[&str]) -> Command {
    let mut c = Command::new(c_examples().join("virtual_wall"));
    c.arg("--socket").arg(socket).args(args);
    c
}

/// The Python trial example on `socket`, with `args`.
fn python_trial_on(socket: &Path, args: &[&str]) -> Command {
    let python = tool(
        "python3",
        "the Python client tests run clients/python/examples/spring_trial.py with it \
         (Debian: apt-get install python3)",
    );
    let mut c = Command::new(python);
    c.env("PYTHONDONTWRITEBYTECODE", "1")
        .arg(repo().join("clients/python/examples/spring_trial.py"))
        .arg("--socket")
        .arg(socket)
        .args(args);
    c
}

/// Two compensated simulated devices (`vertical_field`, exact grids), two units of one model
/// whose handles start 30 mm apart along x, each behind a relay; the gated daemons, gates and
/// relays.
fn two_devices() -> [(Running, Arc<Gate>, Relay); 2] {
    let field = vertical_field();
    [("A", 0.0), ("B", 30.0)].map(|(serial, x_mm)| {
        let mut config = Config::default();
        config.sim.serial = serial.into();
        config.sim.start_position_mm = [x_mm, 0.0, 0.0];
        let grid = with_device_id(field.clone(), &format!("sim-point-mass-{serial}"));
        let gate = Gate::new();
        let running = TestDaemon::new(config)
            .truth(&field)
            .grid(Some(&grid))
            .start_with(|sim| Tap::new(sim).gated(gate.clone()));
        let relay = Relay::start(running.dir.path(), &running.socket);
        (running, gate, relay)
    })
}

/// Couple the two devices of [`two_devices`] with `example` (given both relays' sockets) for
/// 1 s; the distances between the handles it reports at the start and at the end, mm.
fn couple(example: impl FnOnce(&[&Path; 2]) -> Command) -> (f64, f64) {
    let [(a, gate_a, relay_a), (b, gate_b, relay_b)] = two_devices();
    let output = lock_step(
        &[(&gate_a, &relay_a), (&gate_b, &relay_b)],
        example(&[&relay_a.path, &relay_b.path]),
    );
    stop(a, &gate_a);
    stop(b, &gate_b);
    let stdout = text(&output.stdout);
    assert!(output.status.success(), "{stdout}{}", text(&output.stderr));
    (
        distance_mm(&stdout, "the start"),
        distance_mm(&stdout, "the end"),
    )
}

#[test]
fn the_c_and_python_couplings_pull_two_handles_together() {
    // Built before any daemon starts: a gated device gives up after GATE_WAIT without a tick.
    let program = c_examples().join("two_handles");
    let c = couple(|sockets| {
        let mut c = Command::new(program);
        for socket in sockets {
            c.arg("--socket").arg(socket);
        }
        c.args(["--duration", "1"]);
        c
    });
    let python = couple(|sockets| {
        let mut c = Command::new(tool("python3", "the Python client tests run with it"));
        c.env("PYTHONDONTWRITEBYTECODE", "1")
            .arg(repo().join("clients/python/examples/two_handles.py"));
        for socket in sockets {
            c.arg("--socket").arg(socket);
        }
        c.args(["--duration", "1"]);
        c
    });
    for (language, (start, end)) in [("C", c), ("Python", python)] {
        assert!(
            (start - 30.0).abs() < 0.1,
            "{language}: {start} mm at the start"
        );
        assert!(end < 0.1, "{language}: {end} mm at the end");
    }
}

/// A daemon on a gated simulated device carrying a 30 g probe, with `truth` as its mass field and
/// the exact grid of it stored, so it compensates everything but the probe.
fn start(truth: &MassGrid) -> (Running, Arc<Gate>) {
    let mut config = Config::default();
    config.sim.probe_mass_kg = PROBE_KG;
    let gate = Gate::new();
    let grid = with_device_id(truth.clone(), "sim-point-mass");
    let running = TestDaemon::new(config)
        .truth(truth)
        .grid(Some(&grid))
        .start_with(|sim| Tap::new(sim).gated(gate.clone()));
    (running, gate)
}

/// Stop a gated daemon.
fn stop(running: Running, gate: &Gate) {
    gate.open();
    running.stop().expect("the daemon stops cleanly");
}

/// What went through a [`Relay`].
#[derive(Default)]
struct Traffic {
    /// States sent to the client, in order.
    states: Vec<StateSample>,
    /// The daemon has handled the client's subscribe.
    subscribed: bool,
    /// The tick of the state the client's last handled `set_force` answered.
    answered: Option<u64>,
    /// The client or the daemon closed its side, or the client process ended.
    over: bool,
}

/// What the status reply at the head of the queue stands for.
enum Pending {
    /// The client's own status request: its reply goes to the client.
    Client,
    /// A status the relay added after a client request, in order, so its reply says the daemon
    /// has handled that request.
    Subscribe,
    Answer(Option<u64>),
    Other,
}

/// Forwards lines between one client and the daemon, recording states and knowing when the
/// daemon has handled each request: the server reads a connection's requests in order, so after
/// each one the relay asks for status on the same connection and keeps the reply to itself.
#[derive(Clone)]
struct Relay {
    path: PathBuf,
    shared: Arc<(Mutex<Traffic>, Condvar)>,
}

impl Relay {
    /// Listen at `dir/relay.sock` for one client and connect it to the daemon at `daemon`.
    fn start(dir: &Path, daemon: &Path) -> Self {
        let path = dir.join("relay.sock");
        let listener = UnixListener::bind(&path).unwrap();
        let relay = Self {
            path,
            shared: Arc::default(),
        };
        let daemon = daemon.to_path_buf();
        let r = relay.clone();
        std::thread::spawn(move || {
            let Ok((client, _)) = listener.accept() else {
                return;
            };
            let upstream = UnixStream::connect(&daemon).unwrap();
            let pending = Arc::new(Mutex::new(VecDeque::new()));
            let (up_r, up_p) = (r.clone(), pending.clone());
            let (client_in, upstream_out) =
                (client.try_clone().unwrap(), upstream.try_clone().unwrap());
            std::thread::spawn(move || up_r.requests(client_in, upstream_out, &up_p));
            r.replies(upstream, client, &pending);
        });
        relay
    }

    fn traffic(&self) -> MutexGuard<'_, Traffic> {
        self.shared.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn update(&self, change: impl FnOnce(&mut Traffic)) {
        change(&mut self.traffic());
        self.shared.1.notify_all();
    }

    /// Wait until `done` holds; fail the test, naming `what`, after [`WAIT`].
    fn wait(&self, what: &str, done: impl Fn(&Traffic) -> bool) {
        let deadline = Instant::now() + WAIT;
        let mut t = self.traffic();
        while !done(&t) {
            let left = deadline.saturating_duration_since(Instant::now());
            assert!(!left.is_zero(), "waited {WAIT:?} for {what}");
            t = self.shared.1.wait_timeout(t, left).unwrap().0;
        }
    }

    /// Client to daemon.
    fn requests(
        &self,
        client: UnixStream,
        mut upstream: UnixStream,
        pending: &Mutex<VecDeque<Pending>>,
    ) {
        for line in BufReader::new(client).lines() {
            let Ok(line) = line else { break };
            let kind = serde_json::from_str::<serde_json::Value>(&line)
                .ok()
                .and_then(|v| v["type"].as_str().map(str::to_string))
                .unwrap_or_default();
            let entry = match kind.as_str() {
                "status" => Pending::Client,
                "subscribe" => Pending::Subscribe,
                "set_force" => Pending::Answer(self.traffic().states.last().map(|s| s.tick)),
                _ => Pending::Other,
            };
            let ours = !matches!(entry, Pending::Client);
            pending.lock().unwrap().push_back(entry);
            let mut out = line + "\n";
            if ours {
                out.push_str("{\"type\":\"status\"}\n");
            }
            if upstream.write_all(out.as_bytes()).is_err() {
                break;
            }
        }
        let _ = upstream.shutdown(std::net::Shutdown::Write);
        self.update(|t| t.over = true);
    }

    /// Daemon to client.
    fn replies(
        &self,
        upstream: UnixStream,
        mut client: UnixStream,
        pending: &Mutex<VecDeque<Pending>>,
    ) {
        for line in BufReader::new(upstream).lines() {
            let Ok(line) = line else { break };
            let reply = serde_json::from_str::<Reply>(&line).ok();
            match reply {
                Some(Reply::Status(_)) => {
                    let entry = pending.lock().unwrap().pop_front();
                    match entry {
                        Some(Pending::Client) | None => {}
                        Some(Pending::Subscribe) => {
                            self.update(|t| t.subscribed = true);
                            continue;
                        }
                        Some(Pending::Answer(tick)) => {
                            self.update(|t| t.answered = tick);
                            continue;
                        }
                        Some(Pending::Other) => continue,
                    }
                }
                Some(Reply::State(s)) => self.update(|t| t.states.push(s)),
                _ => {}
            }
            if client.write_all((line + "\n").as_bytes()).is_err() {
                break;
            }
        }
        let _ = client.shutdown(std::net::Shutdown::Both);
        self.update(|t| t.over = true);
    }
}

/// Run `example` (its `--socket` the relays') against gated daemons in lock-step until it ends:
/// each tick's state goes out on every device, and the next reports only once each daemon has
/// taken the example's answer. Its output.
fn lock_step(devices: &[(&Gate, &Relay)], mut example: Command) -> Output {
    let child = example
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let watchers: Vec<Relay> = devices.iter().map(|(_, r)| (*r).clone()).collect();
    let waiter: JoinHandle<Output> = std::thread::spawn(move || {
        let output = child.wait_with_output().unwrap();
        for watcher in watchers {
            watcher.update(|t| t.over = true);
        }
        output
    });
    for (_, relay) in devices {
        relay.wait("the example to subscribe", |t| t.subscribed || t.over);
    }
    let mut ticks = 0;
    while !devices.iter().any(|(_, relay)| relay.traffic().over) {
        assert!(ticks < 20_000, "the example still runs after {ticks} ticks");
        for (gate, _) in devices {
            gate.advance(1);
        }
        for (gate, relay) in devices {
            let tick = gate.passed() - 1;
            relay.wait(&format!("the example's answer to tick {tick}"), |t| {
                t.over || t.answered == Some(tick)
            });
        }
        ticks += 1;
    }
    waiter.join().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// The states of the last second of `states`, by device time.
fn last_second(states: &[StateSample]) -> Vec<StateSample> {
    let end = states.last().expect("states").time;
    states
        .iter()
        .filter(|s| s.time > end - 1.0)
        .copied()
        .collect()
}

/// A field of vertical gravity: uniform 0.12 kg over ±80 mm.
fn vertical_field() -> MassGrid {
    MassGrid::uniform(
        0.12,
        G,
        Vector3::z(),
        Vector3::new(-0.08, -0.08, -0.08),
        0.04,
        [5, 5, 5],
    )
}

#[test]
fn the_c_wall_holds_a_probe_mass_at_its_weight_over_the_stiffness() {
    c_examples(); // built before the daemon starts, whose gated device gives up after GATE_WAIT
    let (running, gate) = start(&vertical_field());
    let relay = Relay::start(running.dir.path(), &running.socket);
    // 0.5 N/mm at the handle's height: the 30 g probe sinks to m_p g / k = 0.589 mm.
    let k = 500.0;
    let output = lock_step(
        &[(&gate, &relay)],
        c_wall_on(
            &relay.path,
            &["--stiffness", "0.5", "--height", "0", "--duration", "3"],
        ),
    );
    stop(running, &gate);
    let stdout = text(&output.stdout);
    assert!(output.status.success(), "{output:?}");
    let states = relay.traffic().states.clone();
    assert!(states.len() >= 3000, "{} states", states.len());
    let last = last_second(&states);
    let penetration = last.iter().map(|s| -s.position[2]).sum::<f64>() / last.len() as f64;
    let expected = PROBE_KG * G / k;
    assert!(
        (penetration - expected).abs() < 0.02 * expected,
        "penetration {:.4} mm, m_p g / k = {:.4} mm",
        penetration * 1e3,
        expected * 1e3
    );
    // The wall's force is the probe's weight: the output's z minus the compensation.
    let force_z = last.iter().map(|s| s.force[2]).sum::<f64>() / last.len() as f64;
    let compensation = 0.12 * G;
    assert!(
        (force_z - compensation - PROBE_KG * G).abs() < 0.02 * PROBE_KG * G,
        "the wall pushes {:.4} N, the probe weighs {:.4} N",
        force_z - compensation,
        PROBE_KG * G
    );
    // The example measured the same thing from the same states.
    let printed: f64 = stdout
        .strip_prefix("mean penetration over the last second: ")
        .and_then(|rest| rest.trim().strip_suffix(" mm"))
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("the example's summary: {stdout:?}"));
    assert!(
        (printed - penetration * 1e3).abs() < 0.01,
        "the example printed {printed} mm, the states say {:.4} mm",
        penetration * 1e3
    );
}

/// One row of the trial's CSV.
struct Row {
    phase: String,
    tick: u64,
    position: Vector3<f64>,
    velocity: Vector3<f64>,
    force: Vector3<f64>,
    offset: Vector3<f64>,
}

fn read_trial(path: &Path) -> Vec<Row> {
    let csv = std::fs::read_to_string(path).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some(
            "phase,tick,time_s,x_m,y_m,z_m,vx_m_s,vy_m_s,vz_m_s,fx_n,fy_n,fz_n,ox_n,oy_n,oz_n,\
             flags,offset_seq"
        )
    );
    lines
        .map(|line| {
            let f: Vec<&str> = line.split(',').collect();
            let n = |i: usize| f[i].parse::<f64>().unwrap();
            let v = |i: usize| Vector3::new(n(i), n(i + 1), n(i + 2));
            Row {
                phase: f[0].to_string(),
                tick: f[1].parse().unwrap(),
                position: v(3),
                velocity: v(6),
                force: v(9),
                offset: v(12),
            }
        })
        .collect()
}

fn mean(vectors: impl Iterator<Item = Vector3<f64>>) -> Vector3<f64> {
    let (sum, n) = vectors.fold((Vector3::zeros(), 0.0), |(s, n), v| (s + v, n + 1.0));
    sum / n
}

#[test]
fn the_python_trial_holds_still_then_its_spring_balances_a_probe_mass() {
    // Gravity tilted 3.3° off −z and a scrambled mass field, compensated exactly: the 30 g probe
    // is the only load, along −v_G.
    let truth = truth_field_27();
    let (running, gate) = start(&truth);
    let relay = Relay::start(running.dir.path(), &running.socket);
    let out = tempfile::tempdir().unwrap();
    let csv = out.path().join("trial.csv");
    let k = 200.0;
    let output = lock_step(
        &[(&gate, &relay)],
        python_trial_on(
            &relay.path,
            &[
                "--csv",
                csv.to_str().unwrap(),
                "--stiffness",
                "0.2",
                "--duration",
                "3",
            ],
        ),
    );
    stop(running, &gate);
    assert!(output.status.success(), "{output:?}");
    let rows = read_trial(&csv);
    // Every state the relay sent is in the example's CSV, in order, but for those still on
    // their way when the example's duration ran out (it stops reading then: once 3545 of 3546).
    let ticks: Vec<u64> = relay.traffic().states.iter().map(|s| s.tick).collect();
    assert!(
        rows.iter()
            .map(|r| r.tick)
            .eq(ticks.iter().copied().take(rows.len()))
            && ticks.len() - rows.len() <= 10,
        "the CSV has {} rows, the relay sent {} states",
        rows.len(),
        ticks.len()
    );
    // Hold, then stimulus; the hold ended with the handle still (under 5 mm/s for 0.3 s).
    let holds = rows.iter().take_while(|r| r.phase == "hold").count();
    assert!(holds > 300, "{holds} hold samples");
    assert!(rows[holds..].iter().all(|r| r.phase == "stimulus"));
    assert!(rows[holds - 300..holds]
        .iter()
        .all(|r| r.velocity.norm() < 5e-3));
    // Over the stimulus's last second the spring holds the probe: k Δx = m_p g v_G.
    let anchor = rows[0].position;
    // The last row is the trial's end, answered with zero force.
    let last: Vec<&Row> = rows[rows.len() - 1001..rows.len() - 1].iter().collect();
    let weight = PROBE_KG * G * tilted_v_g();
    let spring = mean(last.iter().map(|r| r.offset));
    assert!(
        (spring - weight).norm() < 0.02 * weight.norm(),
        "spring force {spring:?} N, probe weight {weight:?} N"
    );
    let displacement = mean(last.iter().map(|r| r.position - anchor));
    assert!(
        (displacement + weight / k).norm() < 0.02 * weight.norm() / k,
        "displacement {:?} mm, expected {:?} mm",
        displacement * 1e3,
        -weight / k * 1e3
    );
    // The CSV's force is what the device received: the spring plus the compensation there.
    let compensation = mean(last.iter().map(|r| truth.gravity_force(&r.position)));
    let sent = mean(last.iter().map(|r| r.force));
    assert!(
        (sent - spring - compensation).norm() < 1e-3,
        "sent {sent:?} N, spring {spring:?} N + compensation {compensation:?} N"
    );
}

/// A daemon at a new socket in `dir` that reads the hello, runs `serve` on the connection, then
/// waits for the client to go.
fn fake_daemon_serving(dir: &Path, serve: impl FnOnce(&UnixStream) + Send + 'static) -> PathBuf {
    static MADE: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = MADE.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let path = dir.join(format!("fake-{n}.sock"));
    let listener = UnixListener::bind(&path).unwrap();
    std::thread::spawn(move || {
        let (stream, _) = listener.accept().unwrap();
        let mut lines = BufReader::new(stream.try_clone().unwrap()).lines();
        let _hello = lines.next();
        serve(&stream);
        for _ in lines {}
    });
    path
}

/// A daemon that answers the hello with `replies`, then waits for the client to go.
fn fake_daemon(dir: &Path, replies: &[&str]) -> PathBuf {
    let text: String = replies.iter().map(|r| format!("{r}\n")).collect();
    fake_daemon_serving(dir, move |mut stream| {
        let _ = stream.write_all(text.as_bytes());
    })
}

const WELCOME: &str = r#"{"type":"welcome","version":1,"role":"control","client_id":1,"device":"sim:point-mass","device_id":"sim-point-mass","rate_hz":1000.0,"max_force_n":8.0}"#;
const NOT_JSON: &[&str] = &["this is not JSON"];
const BAD_STATE: &[&str] = &[WELCOME, r#"{"type":"state","tick":"soon"}"#];

/// The example failed with exit status 1 and one line of stderr containing every one of `parts`.
fn assert_one_line_error(output: &Output, parts: &[&str]) {
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{output:?}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    for part in parts {
        assert!(stderr.contains(part), "{part:?} not in {stderr:?}");
    }
}

#[test]
fn the_c_client_names_a_reply_it_does_not_understand() {
    let dir = tempfile::tempdir().unwrap();
    let output = c_wall_on(&fake_daemon(dir.path(), NOT_JSON), &[])
        .output()
        .unwrap();
    assert_one_line_error(
        &output,
        &[
            "virtual_wall: taking the force: hgcd_take_ownership: ",
            "the daemon sent something this client does not understand",
            "this is not JSON",
        ],
    );
    let output = c_wall_on(&fake_daemon(dir.path(), BAD_STATE), &[])
        .output()
        .unwrap();
    assert_one_line_error(
        &output,
        &[
            "virtual_wall: reading the state: hgcd_newest_state: ",
            "does not understand",
            "\"soon\"",
        ],
    );
}

#[test]
fn the_python_client_names_a_reply_it_does_not_understand() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("t.csv");
    let args = ["--csv", csv.to_str().unwrap()];
    let output = python_trial_on(&fake_daemon(dir.path(), NOT_JSON), &args)
        .output()
        .unwrap();
    assert_one_line_error(
        &output,
        &[
            "spring_trial: the daemon sent something this client does not understand",
            "this is not JSON",
        ],
    );
    let output = python_trial_on(&fake_daemon(dir.path(), BAD_STATE), &args)
        .output()
        .unwrap();
    assert_one_line_error(
        &output,
        &["spring_trial: the daemon's state has no valid 'tick': 'soon'"],
    );
    let output = python_trial_on(&dir.path().join("nobody.sock"), &args)
        .output()
        .unwrap();
    assert_one_line_error(
        &output,
        &[
            "spring_trial: cannot connect to the hgcd socket",
            "is `hgcd run` running?",
        ],
    );
}

/// `hgcd_client` in `python3 -c` on `socket`: what `script` prints.
fn python_module(socket: &Path, script: &str) -> Output {
    let python = tool(
        "python3",
        "the Python client tests run it (Debian: apt-get install python3)",
    );
    Command::new(python)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .env("PYTHONPATH", repo().join("clients/python"))
        .args(["-c", script])
        .arg(socket)
        .output()
        .unwrap()
}

#[test]
fn the_python_client_takes_the_force_limit_from_the_welcome_or_the_protocol() {
    const LIMITED: &[&str] = &[
        r#"{"type":"welcome","version":1,"role":"control","client_id":1,"device":"sim:point-mass","device_id":"sim-point-mass","rate_hz":1000.0,"max_force_n":3.5}"#,
    ];
    let dir = tempfile::tempdir().unwrap();
    let script = "import sys, hgcd_client\n\
                  with hgcd_client.connect(sys.argv[1]) as c:\n    \
                  print(c.take_ownership().max_force_n)";
    // A daemon from before the limit was published: the protocol's 8 N.
    const UNLIMITED: &[&str] = &[
        r#"{"type":"welcome","version":1,"role":"control","client_id":1,"device":"sim:point-mass","device_id":"sim-point-mass","rate_hz":1000.0}"#,
    ];
    for (replies, limit) in [(LIMITED, "3.5"), (UNLIMITED, "8.0")] {
        let output = python_module(&fake_daemon(dir.path(), replies), script);
        assert!(output.status.success(), "{output:?}");
        assert_eq!(text(&output.stdout).trim(), limit);
    }
}

/// A fake daemon at `dir/<device_id>.sock` that welcomes every connection as the device
/// `device` with id `device_id`.
fn fake_instance(dir: &Path, device: &str, device_id: &str) {
    let listener = UnixListener::bind(dir.join(format!("{device_id}.sock"))).unwrap();
    let welcome = format!(
        r#"{{"type":"welcome","version":1,"role":"observe","client_id":1,"device":"{device}","device_id":"{device_id}","rate_hz":1000.0,"max_force_n":8.0}}"#
    );
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(stream) = stream else { return };
            let mut lines = BufReader::new(stream.try_clone().unwrap()).lines();
            let _hello = lines.next();
            let _ = (&stream).write_all(format!("{welcome}\n").as_bytes());
            for _ in lines {}
        }
    });
}

#[test]
fn the_python_client_finds_a_daemon_by_device_and_says_when_it_cannot() {
    let dir = tempfile::tempdir().unwrap();
    fake_instance(dir.path(), "hid:1209:4847:SN1", "Omega-SN1");
    fake_instance(dir.path(), "sim:point-mass", "sim-point-mass-L");
    fake_instance(dir.path(), "sim:point-mass", "sim-point-mass-R");
    // A socket left by a daemon that was killed: skipped.
    drop(UnixListener::bind(dir.path().join("gone.sock")).unwrap());
    let script = "import hgcd_client as h\n\
                  print(' '.join(d.device_id for d in h.running()))\n\
                  print(h.find('hid:1209:4847').device_id)\n\
                  with h.connect(device='sim-point-mass-R') as c:\n    \
                  print(c.hello().device_id)\n\
                  for spec in (None, 'sim:point-mass', 'hid:1209:9999'):\n    \
                  try:\n        h.connect(device=spec)\n    \
                  except h.ConnectError as e:\n        print(e)";
    let output = Command::new(tool("python3", "the Python client tests run it"))
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .env("PYTHONPATH", repo().join("clients/python"))
        .env("RUNTIME_DIRECTORY", dir.path())
        .args(["-c", script])
        .output()
        .unwrap();
    assert!(output.status.success(), "{output:?}");
    let stdout = text(&output.stdout);
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(
        lines[..3],
        [
            "Omega-SN1 sim-point-mass-L sim-point-mass-R",
            "Omega-SN1",
            "sim-point-mass-R"
        ],
        "{stdout}"
    );
    assert!(
        lines[3].starts_with("3 hgcd daemons are running"),
        "{stdout}"
    );
    assert!(
        lines[4].starts_with("2 hgcd daemons are running"),
        "{stdout}"
    );
    assert!(
        lines[5].starts_with("no hgcd daemon for device 'hid:1209:9999'"),
        "{stdout}"
    );
    assert_eq!(lines.len(), 6, "{stdout}");
}

/// Start `example` on the daemon's own socket, wait until it owns the force, stop the daemon:
/// the example's output.
fn stop_under(example: impl FnOnce(&Path) -> Command, owner: &str) -> Output {
    let (running, gate) = start(&vertical_field());
    let child = example(&running.socket)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut observer = Client::connect(&running.socket, Role::Observe, "observer").unwrap();
    observer.set_read_timeout(Some(WAIT)).unwrap();
    wait_for(&format!("{owner} to own the force"), || {
        let status = observer.status().unwrap();
        (status.owner.as_deref() == Some(owner)).then_some(())
    });
    stop(running, &gate);
    child.wait_with_output().unwrap()
}

#[test]
fn the_c_client_says_when_the_daemon_goes_away() {
    c_examples(); // built before the daemon starts
    let output = stop_under(|socket| c_wall_on(socket, &[]), "virtual_wall.c");
    assert_one_line_error(
        &output,
        &["virtual_wall: ", "the daemon closed the connection"],
    );
}

#[test]
fn the_python_client_says_when_the_daemon_goes_away() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("t.csv");
    let output = stop_under(
        |socket| python_trial_on(socket, &["--csv", csv.to_str().unwrap()]),
        "spring_trial.py",
    );
    assert_one_line_error(
        &output,
        &["spring_trial: ", "the daemon closed the connection"],
    );
}

/// Every `hgcd_…` name the guide uses is in the header.
#[test]
fn the_guide_names_only_functions_the_c_header_has() {
    let header = std::fs::read_to_string(repo().join("clients/c/include/hgcd.h")).unwrap();
    let guide = std::fs::read_to_string(repo().join("docs/app-protocol.md")).unwrap();
    let mut names: Vec<&str> = guide
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .filter(|w| w.starts_with("hgcd_") || w.starts_with("HGCD_"))
        .collect();
    names.sort_unstable();
    names.dedup();
    assert!(names.len() > 5, "the guide names {names:?}");
    for name in names {
        assert!(
            header.contains(name),
            "docs/app-protocol.md names {name}, hgcd.h has no such thing"
        );
    }
}

/// [`WELCOME`] granting `observe`, what a hello asking for it gets.
fn observe_welcome() -> String {
    WELCOME.replace(r#""role":"control""#, r#""role":"observe""#)
}

/// Welcomes out of range: the field a client must name, and what replaces its value in
/// [`observe_welcome`].
const BAD_WELCOMES: &[(&str, &str, &str)] = &[
    ("version", r#""version":1"#, r#""version":2"#),
    ("role", r#""role":"observe""#, r#""role":"control""#),
    ("client_id", r#""client_id":1"#, r#""client_id":0"#),
    ("device", r#""device":"sim:point-mass""#, r#""device":"""#),
    (
        "device",
        r#""device":"sim:point-mass""#,
        r#""device":"sim:\u001b[2J""#,
    ),
    (
        "device_id",
        r#""device_id":"sim-point-mass""#,
        r#""device_id":"../etc/x""#,
    ),
    ("rate_hz", r#""rate_hz":1000.0"#, r#""rate_hz":0"#),
    ("rate_hz", r#""rate_hz":1000.0"#, r#""rate_hz":1e7"#),
    ("max_force_n", r#""max_force_n":8.0"#, r#""max_force_n":-1"#),
    ("max_force_n", r#""max_force_n":8.0"#, r#""max_force_n":51"#),
];

/// Welcomes with numbers that are not finite, which Python's JSON reads (Rust's refuses them).
const NOT_FINITE_WELCOMES: &[(&str, &str, &str)] = &[
    ("rate_hz", r#""rate_hz":1000.0"#, r#""rate_hz":Infinity"#),
    ("rate_hz", r#""rate_hz":1000.0"#, r#""rate_hz":1e999"#),
    (
        "max_force_n",
        r#""max_force_n":8.0"#,
        r#""max_force_n":NaN"#,
    ),
];

/// Each welcome of `table` (as [`BAD_WELCOMES`]), with its field.
fn bad_welcomes(
    table: &'static [(&str, &str, &str)],
) -> impl Iterator<Item = (&'static str, String)> {
    let welcome = observe_welcome();
    table.iter().map(move |(field, from, to)| {
        assert!(welcome.contains(from), "{from}");
        (*field, welcome.replace(from, to))
    })
}

/// A daemon that answers the hello with a welcome sent a byte every 0.3 s: about 50 s in all,
/// each byte well within 1 s of the one before.
fn trickling_daemon(dir: &Path) -> PathBuf {
    let welcome = observe_welcome();
    fake_daemon_serving(dir, move |mut stream| {
        for byte in welcome.bytes() {
            if stream.write_all(&[byte]).is_err() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(300));
        }
    })
}

/// A reply nested 50,000 deep, shorter than the longest reply.
fn deep_json() -> String {
    format!(r#"{{"type":"state","tick":{}"#, "[".repeat(50_000))
}

/// A welcome, a status whose owner carries a terminal escape, a refusal made of escapes.
fn escaping_replies() -> [String; 3] {
    [
        observe_welcome(),
        r#"{"type":"status","device":"sim:point-mass","device_id":"sim-point-mass","grid":null,"mode":"none","held_out_pct":null,"calibrating":false,"clients":1,"owner":"\u001b]0;pwned\u0007mallory","uptime_s":1.0,"ticks":1,"late":0,"missed":0,"overruns":0,"garbled":0,"watchdog_faults":0,"worst_compute_us":1.0,"worst_period_us":1.0,"late_wakeups":0,"worst_lateness_us":0.0}"#.into(),
        r#"{"type":"error","message":"\u001b[2J\u001b[31mboom\u001b[0m","fatal":true}"#.into(),
    ]
}

/// `Client::connect` asking for `observe` on `path`: the message of the protocol error it must
/// give.
fn rust_protocol_error(path: &Path) -> String {
    match Client::connect(path, Role::Observe, "t") {
        Err(ClientError::Protocol(message)) => message,
        Err(e) => panic!("not a protocol error: {e}"),
        Ok(c) => panic!("accepted: {} at {} Hz", c.device_id, c.rate_hz),
    }
}

#[test]
fn the_rust_client_refuses_a_welcome_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    for (field, welcome) in bad_welcomes(BAD_WELCOMES) {
        let message = rust_protocol_error(&fake_daemon(dir.path(), &[&welcome]));
        assert!(message.contains(field), "{welcome}: {message}");
        assert!(!message.chars().any(char::is_control), "{message:?}");
    }
    // The ranges are the daemon's configurable ones.
    let top = |key: &str| {
        let ranges = hgcd::config::RANGES;
        ranges.iter().find(|r| r.0 == key).unwrap().1.max
    };
    assert_eq!(top("servo.rate_hz"), protocol::MAX_RATE_HZ);
    assert_eq!(top("safety.max_force_n"), protocol::MAX_FORCE_N);
}

#[test]
fn the_rust_client_gives_a_reply_line_one_deadline_not_one_per_byte() {
    let dir = tempfile::tempdir().unwrap();
    let start = Instant::now();
    let message = rust_protocol_error(&trickling_daemon(dir.path()));
    let took = start.elapsed().as_secs_f64();
    assert!(took < 5.0, "{took} s");
    assert!(
        message.contains("within 1 s of its first byte"),
        "{message}"
    );
}

#[test]
fn the_rust_client_names_deeply_nested_json_in_one_short_line() {
    let dir = tempfile::tempdir().unwrap();
    let message = rust_protocol_error(&fake_daemon(dir.path(), &[&deep_json()]));
    assert!(message.len() < 400, "{} bytes: {message}", message.len());
    assert!(message.contains("recursion limit"), "{message}");
}

#[test]
fn the_rust_client_strips_control_characters_from_what_the_daemon_says() {
    let replies = escaping_replies();
    let replies: Vec<&str> = replies.iter().map(String::as_str).collect();
    let dir = tempfile::tempdir().unwrap();
    let path = fake_daemon(dir.path(), &replies);
    let mut client = Client::connect(&path, Role::Observe, "t").unwrap();
    assert_eq!(client.status().unwrap().owner.unwrap(), "]0;pwnedmallory");
    match client.next_reply() {
        Err(ClientError::Refused(message)) => assert_eq!(message, "[2J[31mboom[0m"),
        other => panic!("{other:?}"),
    }
}

/// What the Python client's `hello()` asking for `observe` on `path` raises as ProtocolError, as
/// it prints.
fn python_protocol_error(path: &Path) -> String {
    let output = python_module(
        path,
        "import sys, hgcd_client as h\n\
         try:\n    print('accepted', h.connect(sys.argv[1]).hello())\n\
         except h.ProtocolError as e:\n    print(e)",
    );
    assert!(output.status.success(), "{output:?}");
    let stdout = text(&output.stdout);
    assert_eq!(stdout.lines().count(), 1, "{stdout}");
    stdout.trim_end().to_string()
}

#[test]
fn the_python_client_refuses_a_welcome_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    for (field, welcome) in bad_welcomes(BAD_WELCOMES).chain(bad_welcomes(NOT_FINITE_WELCOMES)) {
        let message = python_protocol_error(&fake_daemon(dir.path(), &[&welcome]));
        assert!(
            message.contains(&format!("'{field}'")),
            "{welcome}: {message}"
        );
        assert!(!message.chars().any(char::is_control), "{message:?}");
    }
    // Its limits are the protocol's.
    let output = python_module(
        Path::new("-"),
        "import hgcd_client as h\n\
         print(h.MAX_RATE_HZ, h.MAX_FORCE_N, h.MAX_REPLY_LEN, h.LINE_COMPLETION_S)",
    );
    assert_eq!(
        text(&output.stdout).trim_end(),
        format!(
            "{:?} {:?} {} {:?}",
            protocol::MAX_RATE_HZ,
            protocol::MAX_FORCE_N,
            protocol::MAX_REPLY_LEN,
            protocol::REPLY_LINE_TIME.as_secs_f64()
        )
    );
}

#[test]
fn the_python_client_gives_a_reply_line_one_deadline_not_one_per_byte() {
    let dir = tempfile::tempdir().unwrap();
    // The alarm ends a client that waits byte by byte (about 50 s) sooner.
    let output = python_module(
        &trickling_daemon(dir.path()),
        "import signal, sys, time, hgcd_client as h\n\
         signal.alarm(20)\n\
         c = h.connect(sys.argv[1])\n\
         start = time.monotonic()\n\
         try:\n    c.hello()\n\
         except h.ProtocolError as e:\n    print(time.monotonic() - start)\n    print(e)",
    );
    assert!(output.status.success(), "{output:?}");
    let stdout = text(&output.stdout);
    let lines: Vec<&str> = stdout.lines().collect();
    let took: f64 = lines[0].parse().unwrap();
    assert!(took < 5.0, "{took} s");
    assert!(
        lines[1].contains("within 1 s of its first byte"),
        "{stdout}"
    );
}

#[test]
fn the_python_client_names_deeply_nested_json_in_one_short_line() {
    let dir = tempfile::tempdir().unwrap();
    let message = python_protocol_error(&fake_daemon(dir.path(), &[&deep_json()]));
    assert!(message.len() < 400, "{} bytes: {message}", message.len());
    assert!(message.contains("does not understand"), "{message}");
}

#[test]
fn the_python_client_strips_control_characters_from_what_the_daemon_says() {
    let replies = escaping_replies();
    let replies: Vec<&str> = replies.iter().map(String::as_str).collect();
    let dir = tempfile::tempdir().unwrap();
    let output = python_module(
        &fake_daemon(dir.path(), &replies),
        "import sys, hgcd_client as h\n\
         with h.connect(sys.argv[1]) as c:\n    \
         c.hello()\n    \
         print(c.status().owner)\n    \
         try:\n        c.newest_state(wait=5.0)\n    \
         except h.RefusedError as e:\n        print(e)",
    );
    assert!(output.status.success(), "{output:?}");
    assert_eq!(
        text(&output.stdout),
        "]0;pwnedmallory\nthe daemon refused: [2J[31mboom[0m\n"
    );
}
