//! Regressions from the attack on the daemon (issue "Hardening and structure"), one test per
//! finding on the servo path. Each failed before its fix.

use std::io::{ErrorKind, Read, Write};
use std::os::unix::net::UnixListener;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use hgcd::client::{Client, Role};
use hgcd::config::Config;
use hgcd::protocol::{INPUT_REPORT_LEN, MAX_REPORT_LEN, OUTPUT_REPORT_LEN};
use hgcd::servo::{self, ExitReason, ServoOptions};
use hgcd::sim::SimDevice;
use hgcd::transport::socket::SocketTransport;
use hgcd::transport::Speaks;

mod common;
use common::daemon::TestDaemon;
use common::{pd_hold, truth_field_27, with_device_id, Ticks};

/// A device that sends its reports in bursts of ten per exchange, nine valid and the newest
/// garbled (a flaky line or firmware), must still drive the loop from the newest valid report.
#[test]
fn a_burst_whose_newest_report_is_garbled_still_drives_the_loop() {
    const BURSTS: u64 = 300;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("device.sock");
    let listener = UnixListener::bind(&path).unwrap();
    let config = Config::default();
    let device_config = config.clone();
    let device = std::thread::spawn(move || {
        let (mut stream, _) = listener.accept().unwrap();
        // As long as the host's watchdog: on a loaded machine the host may take tens of ms to
        // answer, and a device that sent its next burst meanwhile would no longer be in step.
        stream
            .set_read_timeout(Some(Duration::from_secs(5)))
            .unwrap();
        let mut device = SimDevice::from_config("point-mass", &device_config).unwrap();
        let mut outputs = 0u64;
        for _ in 0..BURSTS {
            let mut frames = Vec::new();
            let mut report = [0u8; MAX_REPORT_LEN];
            for _ in 0..9 {
                device.advance();
                let n = device.input_report(&mut report);
                assert_eq!(n, INPUT_REPORT_LEN);
                frames.push(INPUT_REPORT_LEN as u8);
                frames.extend_from_slice(&report[..n]);
            }
            let garbled = &mut report[..INPUT_REPORT_LEN];
            garbled[1] = 0xee; // an unknown protocol version
            frames.push(INPUT_REPORT_LEN as u8);
            frames.extend_from_slice(garbled);
            if stream.write_all(&frames).is_err() {
                break;
            }
            // Lock-step: wait for the host's answer before the next burst.
            let mut frame = [0u8; OUTPUT_REPORT_LEN + 1];
            match stream.read_exact(&mut frame) {
                Ok(()) => {
                    outputs += 1;
                    let _ = device.receive_output(&frame[1..]);
                }
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(_) => break,
            }
        }
        // Stay connected until the host hangs up: its last report (zero force, motors off)
        // must not find the device gone.
        let _ = std::io::copy(&mut stream, &mut std::io::sink());
        outputs
    });
    let mut transport = SocketTransport::connect(&path, Speaks::default()).unwrap();
    let mut options = ServoOptions::from_config(&config);
    options.watchdog = 5.0; // wall clock: generous on a loaded machine
    let report = servo::run(
        &mut transport,
        &mut Ticks(pd_hold(), BURSTS),
        &options,
        &AtomicBool::new(false),
        None,
    );
    drop(transport);
    let answered = device.join().unwrap();
    let report = report.expect("the loop ran to its end");
    assert_eq!(report.exit, ExitReason::ControllerDone);
    assert_eq!(report.stats.ticks, BURSTS, "one tick per burst");
    assert_eq!(report.stats.garbled, BURSTS, "every garbled report counted");
    assert_eq!(
        report.stats.watchdog_faults, 0,
        "never mistaken for silence"
    );
    assert!(answered >= BURSTS - 1);
}

/// Clients see the force the device was sent, not the one requested: an offset of 8 N on every
/// axis (13.9 N) is clamped to `safety.max_force_n` before it leaves, and so is what is published.
#[test]
fn published_state_carries_the_force_sent_after_the_safety_layer() {
    let config = Config::default();
    let max_force = config.safety.max_force_n;
    let daemon = TestDaemon::new(config)
        .grid(Some(&with_device_id(truth_field_27(), "sim-point-mass")))
        .start();
    let mut client = Client::connect(&daemon.socket, Role::Control, "pushy").unwrap();
    client
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    client.subscribe(1000.0).unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut clamped = 0;
    while clamped < 200 {
        assert!(Instant::now() < deadline, "the offset never took effect");
        // Keep the offset fresh in device time, however fast the virtual device runs.
        client.set_force(Vector3::new(8.0, 8.0, 8.0)).unwrap();
        let s = client.next_state().unwrap();
        let sent = Vector3::from(s.force).norm();
        assert!(
            sent <= max_force + 1e-9,
            "published {sent:.3} N, more than the {max_force} N ever sent"
        );
        if s.offset_seq > 0 && (sent - max_force).abs() < 1e-6 {
            clamped += 1;
        }
    }
    drop(client);
    daemon.stop().unwrap();
}
