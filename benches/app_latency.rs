//! Client-to-device latency: from an application's `set_force` to the output report that carries
//! the force, through the socket, the reader thread, the offset channel and one servo tick.
//!
//! `cargo bench --bench app_latency` runs a daemon on a real-time simulated device (1 kHz) and two
//! clients in turn, the Rust client (`hgcd::client`) in this process and the Python client
//! (`clients/python/hgcd_client.py`, run by `python3`), each sending a new offset at a random
//! phase of the servo period: 2000 each, in alternating blocks of 500 so both see the same load.
//! It prints p50/p99/max for each. Each client time-stamps its offset just before sending it and
//! the device side each output report as the transport receives it, both on CLOCK_MONOTONIC.

use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::sync::atomic::Ordering;
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

use hgcd::client::{Client, Role};
use hgcd::config::Config;
use hgcd::daemon::{Daemon, RunRequest, Signals};
use hgcd::protocol::MAX_REPORT_LEN;
use hgcd::protocol::{OutputReport, OUTPUT_REPORT_LEN};
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::{Pacing, Transport, TransportError};

/// Offsets per client, and per block.
const OFFSETS: u32 = 2000;
const BLOCK: u32 = 500;

/// CLOCK_MONOTONIC, ns: the clock Python's `time.clock_gettime_ns(time.CLOCK_MONOTONIC)` reads.
fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Time-stamps output reports whose x force changed.
struct Stamping {
    inner: SimTransport,
    last_fx: f64,
    stamps: Sender<(u64, f64)>,
}

impl Transport for Stamping {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        self.inner.read_input(buf, timeout)
    }
    fn write_output(&mut self, report: &[u8; OUTPUT_REPORT_LEN]) -> Result<(), TransportError> {
        let at = monotonic_ns();
        let fx = OutputReport::decode(report)
            .map(|r| r.force.x)
            .unwrap_or(0.0);
        if fx != self.last_fx {
            self.last_fx = fx;
            let _ = self.stamps.try_send((at, fx));
        }
        self.inner.write_output(report)
    }
    fn now(&self) -> f64 {
        self.inner.now()
    }
    fn describe(&self) -> String {
        "simulated device (real time, stamping)".into()
    }
}

/// A client that sends offsets when told to.
trait OffsetSender {
    /// Connect and own the force (the previous owner's connection may still be closing).
    fn connect(&mut self);
    /// Send the offset (`fx`, 0, 0) N; when it was sent, ns.
    fn send(&mut self, fx: f64) -> u64;
    fn close(&mut self);
}

struct RustClient<'a> {
    socket: &'a Path,
    client: Option<Client>,
}

impl OffsetSender for RustClient<'_> {
    fn connect(&mut self) {
        loop {
            let client = Client::connect(self.socket, Role::Control, "bench-rust").unwrap();
            if client.role == Role::Control {
                self.client = Some(client);
                return;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    fn send(&mut self, fx: f64) -> u64 {
        let client = self.client.as_mut().expect("connected");
        let sent = monotonic_ns();
        client.set_force(Vector3::new(fx, 0.0, 0.0)).unwrap();
        sent
    }
    fn close(&mut self) {
        self.client = None;
    }
}

/// `python3` running [`PYTHON_DRIVER`]: one command per line in, one answer per line out.
struct PythonClient {
    child: Child,
    commands: ChildStdin,
    answers: BufReader<ChildStdout>,
}

/// Connects with `hgcd_client` on `connect`, time-stamps and sends an offset on `f FX`.
const PYTHON_DRIVER: &str = r#"
import sys, time
sys.path.insert(0, sys.argv[2])
import hgcd_client
client = None
for line in sys.stdin:
    command = line.split()
    if command[0] == "connect":
        client = hgcd_client.connect(sys.argv[1])
        try:
            client.take_ownership("bench-python")
            answer = "control"
        except hgcd_client.NotOwnerError:
            client.close()
            answer = "observe"
    elif command[0] == "f":
        fx = float(command[1])
        sent = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        client.set_force((fx, 0.0, 0.0))
        answer = str(sent)
    else:
        client.close()
        answer = "closed"
    print(answer, flush=True)
"#;

impl PythonClient {
    fn start(socket: &Path) -> Self {
        let module = Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/python");
        let mut child = Command::new("python3")
            .args(["-c", PYTHON_DRIVER])
            .arg(socket)
            .arg(module)
            .env("PYTHONDONTWRITEBYTECODE", "1")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("python3 runs (the Python client's half of this benchmark needs it)");
        let commands = child.stdin.take().unwrap();
        let answers = BufReader::new(child.stdout.take().unwrap());
        Self {
            child,
            commands,
            answers,
        }
    }

    fn ask(&mut self, command: &str) -> String {
        writeln!(self.commands, "{command}").unwrap();
        let mut answer = String::new();
        self.answers.read_line(&mut answer).unwrap();
        assert!(!answer.is_empty(), "the Python client ended");
        answer.trim().to_string()
    }
}

impl OffsetSender for PythonClient {
    fn connect(&mut self) {
        while self.ask("connect") != "control" {
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    fn send(&mut self, fx: f64) -> u64 {
        self.ask(&format!("f {fx:?}")).parse().unwrap()
    }
    fn close(&mut self) {
        self.ask("close");
    }
}

/// Send `BLOCK` offsets from `client` at random phases, numbered from `first`; each one's
/// latency to the first output report carrying it, µs, into `latencies`.
fn block(
    client: &mut dyn OffsetSender,
    first: u32,
    rng: &mut impl Rng,
    stamps: &Receiver<(u64, f64)>,
    latencies: &mut Vec<f64>,
) {
    client.connect();
    for n in first..first + BLOCK {
        std::thread::sleep(Duration::from_micros(rng.gen_range(500..1500)));
        let fx = f64::from(n) * 5e-4;
        let sent = client.send(fx);
        loop {
            let (at, got) = stamps
                .recv_timeout(Duration::from_secs(1))
                .expect("offset arrives");
            if (got - fx).abs() < 1e-6 {
                latencies.push(at.saturating_sub(sent) as f64 * 1e-3);
                break;
            }
        }
    }
    client.close();
}

fn report(name: &str, latencies: &mut [f64]) -> f64 {
    latencies.sort_by(f64::total_cmp);
    let q = |p: f64| latencies[((latencies.len() as f64 * p) as usize).min(latencies.len() - 1)];
    println!(
        "  {name:<13} p50 {:.0} µs, p99 {:.0} µs, max {:.0} µs",
        q(0.5),
        q(0.99),
        latencies[latencies.len() - 1]
    );
    q(0.99)
}

fn main() {
    // `cargo test --benches` runs benches in test mode: skip the real measurement there.
    if std::env::args().any(|a| a == "--test") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::default();
    config.app.socket = Some(dir.path().join("hgcd.sock"));
    config.paths.state_dir = Some(dir.path().join("state"));
    config.sim.start_position_mm = [0.0, 0.0, -80.0]; // rest on the floor: no motion needed
    let (stamps_tx, stamps) = crossbeam_channel::bounded(4096);
    let transport = Box::new(Stamping {
        inner: SimTransport::new(
            SimDevice::from_config("point-mass", &config).unwrap(),
            Pacing::RealTime,
        ),
        last_fx: 0.0,
        stamps: stamps_tx,
    });
    let request = RunRequest {
        device: "sim:point-mass".parse().unwrap(),
        duration: None,
        pacing: Pacing::RealTime,
    };
    let signals = Signals::default();
    let s2 = signals.clone();
    let (ready_tx, ready_rx) = crossbeam_channel::bounded(1);
    let daemon = std::thread::spawn(move || {
        Daemon::new(config, &request).run(transport, s2, &mut |_| {
            let _ = ready_tx.send(());
        })
    });
    ready_rx.recv().unwrap();
    let socket = dir.path().join("hgcd.sock");
    let mut rust = RustClient {
        socket: &socket,
        client: None,
    };
    let mut python = PythonClient::start(&socket);
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let (mut rust_us, mut python_us) = (Vec::new(), Vec::new());
    for round in 0..OFFSETS / BLOCK {
        let first = 1 + 2 * round * BLOCK;
        block(&mut rust, first, &mut rng, &stamps, &mut rust_us);
        block(
            &mut python,
            first + BLOCK,
            &mut rng,
            &stamps,
            &mut python_us,
        );
    }
    drop(python.commands);
    python.child.wait().unwrap();
    signals.stop.store(true, Ordering::SeqCst);
    daemon.join().unwrap().unwrap();
    println!(
        "client-to-device latency, {OFFSETS} offsets per client in alternating blocks of {BLOCK}:"
    );
    let rust_p99 = report("Rust client", &mut rust_us);
    let python_p99 = report("Python client", &mut python_us);
    println!("  p99 Python − Rust: {:.0} µs", python_p99 - rust_p99);
}
