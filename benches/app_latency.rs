//! Client-to-device latency: from an application's `set_force` to the output report that carries
//! the force, through the socket, the reader thread, the offset channel and one servo tick.
//!
//! `cargo bench --bench app_latency` runs a daemon on a real-time simulated device (1 kHz) and a
//! client that sends a new offset at a random phase of the servo period, 2000 times, and prints
//! p50/p99/max. The device side time-stamps each output report as the transport receives it.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use crossbeam_channel::Sender;
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

/// Time-stamps output reports whose x force changed.
struct Stamping {
    inner: SimTransport,
    last_fx: f64,
    stamps: Sender<(Instant, f64)>,
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
        let at = Instant::now();
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
    let mut client =
        Client::connect(&dir.path().join("hgcd.sock"), Role::Control, "bench").unwrap();
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let mut latencies = Vec::with_capacity(2000);
    for n in 1..=2000u32 {
        std::thread::sleep(Duration::from_micros(rng.gen_range(500..1500)));
        let fx = f64::from(n) * 1e-3;
        let sent = Instant::now();
        client.set_force(Vector3::new(fx, 0.0, 0.0)).unwrap();
        loop {
            let (at, got) = stamps
                .recv_timeout(Duration::from_secs(1))
                .expect("offset arrives");
            if (got - fx).abs() < 1e-6 {
                latencies.push(at.duration_since(sent).as_secs_f64() * 1e6);
                break;
            }
        }
    }
    signals.stop.store(true, Ordering::SeqCst);
    drop(client);
    daemon.join().unwrap().unwrap();
    latencies.sort_by(f64::total_cmp);
    let q = |p: f64| latencies[((latencies.len() as f64 * p) as usize).min(latencies.len() - 1)];
    println!(
        "client-to-device latency over {} offsets: p50 {:.0} µs, p99 {:.0} µs, max {:.0} µs",
        latencies.len(),
        q(0.5),
        q(0.99),
        latencies[latencies.len() - 1]
    );
}
