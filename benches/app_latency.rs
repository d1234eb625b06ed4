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
use hgcd::protocol::OutputReport;
use hgcd::protocol::MAX_REPORT_LEN;
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
    fn write_output(&mut self, report: &[u8]) -> Result<(), TransportError> {
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

/// A client that sends a block of offsets on its own schedule.
trait OffsetSender {
    /// Connect and own the force (the previous owner's connection may still be closing), send
    /// the offsets (n · 0.5 mN, 0, 0) for n in `first..first + delays.len()`, the k-th after
    /// sleeping `delays[k]` µs, and close; the time each was sent, ns. Nothing else happens on
    /// the client's side while it sends, as in an application's own loop.
    fn block(&mut self, first: u32, delays: &[u64]) -> Vec<u64>;
}

fn offset(n: u32) -> f64 {
    f64::from(n) * 5e-4
}

struct RustClient {
    socket: std::path::PathBuf,
}

impl RustClient {
    fn connect(socket: &Path) -> Client {
        loop {
            let client = Client::connect(socket, Role::Control, "bench-rust").unwrap();
            if client.role == Role::Control {
                return client;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

impl OffsetSender for RustClient {
    fn block(&mut self, first: u32, delays: &[u64]) -> Vec<u64> {
        let mut client = Self::connect(&self.socket);
        let mut sent = Vec::with_capacity(delays.len());
        for (k, delay) in delays.iter().enumerate() {
            std::thread::sleep(Duration::from_micros(*delay));
            sent.push(monotonic_ns());
            client
                .set_force(Vector3::new(offset(first + k as u32), 0.0, 0.0))
                .unwrap();
        }
        sent
    }
}

/// `python3` running [`PYTHON_DRIVER`]: one command per line in, one answer per line out.
struct PythonClient {
    child: Child,
    commands: ChildStdin,
    answers: BufReader<ChildStdout>,
}

/// On `block FIRST D1,D2,…`: connects with `hgcd_client`, sends the block as
/// [`OffsetSender::block`] says, closes, and answers with the send times.
const PYTHON_DRIVER: &str = r#"
import sys, time
sys.path.insert(0, sys.argv[2])
import hgcd_client
for line in sys.stdin:
    _, first, delays = line.split()
    first = int(first)
    while True:
        client = hgcd_client.connect(sys.argv[1])
        try:
            client.take_ownership("bench-python")
            break
        except hgcd_client.NotOwnerError:
            client.close()
            time.sleep(0.005)
    sent = []
    for k, delay in enumerate(delays.split(",")):
        time.sleep(int(delay) * 1e-6)
        sent.append(time.clock_gettime_ns(time.CLOCK_MONOTONIC))
        client.set_force(((first + k) * 5e-4, 0.0, 0.0))
    client.close()
    print(" ".join(map(str, sent)), flush=True)
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
}

impl OffsetSender for PythonClient {
    fn block(&mut self, first: u32, delays: &[u64]) -> Vec<u64> {
        let delays: Vec<String> = delays.iter().map(u64::to_string).collect();
        writeln!(self.commands, "block {first} {}", delays.join(",")).unwrap();
        let mut answer = String::new();
        self.answers.read_line(&mut answer).unwrap();
        assert!(!answer.is_empty(), "the Python client ended");
        answer
            .split_whitespace()
            .map(|t| t.parse().unwrap())
            .collect()
    }
}

/// Run one block of `client` on its own thread while this one takes the device's stamps; each
/// offset's latency to the first output report carrying it, µs, into `latencies`. Returns how
/// many offsets no report carried (a newer one replaced it first: the slot keeps the newest).
fn block<C: OffsetSender + Send + 'static>(
    client: C,
    first: u32,
    rng: &mut impl Rng,
    stamps: &Receiver<(u64, f64)>,
    latencies: &mut Vec<f64>,
) -> (C, usize) {
    // 1.5 to 2.5 ms apart: each offset meets a tick before the next replaces it, at a random
    // phase of the servo period.
    let delays: Vec<u64> = (0..BLOCK).map(|_| rng.gen_range(1500..2500)).collect();
    let sender = std::thread::spawn(move || {
        let mut client = client;
        let sent = client.block(first, &delays);
        (client, sent)
    });
    let mut carried = std::collections::HashMap::new();
    while carried.len() < BLOCK as usize {
        match stamps.recv_timeout(Duration::from_secs(2)) {
            Ok((at, fx)) => {
                let n = (fx / 5e-4).round() as i64 - i64::from(first);
                if (0..i64::from(BLOCK)).contains(&n) {
                    carried.entry(n as usize).or_insert(at);
                }
            }
            Err(_) if sender.is_finished() => break,
            Err(_) => {}
        }
    }
    let (client, sent) = sender.join().expect("the client's thread");
    for (n, at) in &carried {
        latencies.push(at.saturating_sub(sent[*n]) as f64 * 1e-3);
    }
    (client, BLOCK as usize - carried.len())
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
        config_file: None,
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
        socket: socket.clone(),
    };
    let mut python = PythonClient::start(&socket);
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let (mut rust_us, mut python_us) = (Vec::new(), Vec::new());
    let (mut rust_lost, mut python_lost) = (0, 0);
    for round in 0..OFFSETS / BLOCK {
        let first = 1 + 2 * round * BLOCK;
        let lost;
        (rust, lost) = block(rust, first, &mut rng, &stamps, &mut rust_us);
        rust_lost += lost;
        let lost;
        (python, lost) = block(python, first + BLOCK, &mut rng, &stamps, &mut python_us);
        python_lost += lost;
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
    println!(
        "  offsets replaced before a tick carried them: Rust {rust_lost}, Python {python_lost}"
    );
    println!("  p99 Python − Rust: {:.0} µs", python_p99 - rust_p99);
}
