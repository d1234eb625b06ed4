//! One servo tick's hot path: decode → FOAW state estimate → controller → safety → encode.
//!
//! `cargo bench --bench servo_tick`. Input reports come from the mock-HID device (a PD-held
//! simulated point mass, so positions and velocities are realistic); `core` times only what the
//! servo thread does per report with a PD hold, `daemon_controller` the same with the daemon's
//! compensation controller (mailbox: commands, newest offset, Eq. 15, state publishing),
//! `with_mock_device` adds the simulated firmware and plant.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::Vector3;

use hgcd::config::Config;
use hgcd::control::compensation::{
    Compensation, CompensationMode, ForceOffset, GravityModel, OutsideGrid,
};
use hgcd::control::pd::{LinearisedGains, PdHold};
use hgcd::daemon::controller::DaemonController;
use hgcd::grid::MassGrid;
use hgcd::mailbox::{mailbox, OffsetCommand, ServoCommand};
use hgcd::protocol::{INPUT_REPORT_LEN, MAX_REPORT_LEN};
use hgcd::servo::{ServoCore, ServoOptions};
use hgcd::sim::SimDevice;

fn hold() -> PdHold {
    PdHold {
        set_point: Vector3::new(0.01, 0.0, 0.02),
        gains: LinearisedGains::from_rise_time(0.1, 1.0),
        field: MassGrid::uniform(
            0.12,
            9.81,
            Vector3::z(),
            Vector3::new(-0.04, -0.04, -0.04),
            0.04,
            [3, 3, 3],
        ),
    }
}

fn bench_tick(c: &mut Criterion) {
    let config = Config::default();
    let options = ServoOptions::from_config(&config);
    let mut group = c.benchmark_group("servo_tick");
    group.measurement_time(Duration::from_secs(5));

    // Record 4096 input reports of a held, moving handle from the mock device.
    let mut device = SimDevice::from_config("point-mass", &config).unwrap();
    let mut core = ServoCore::new(&options).unwrap();
    let mut controller = hold();
    let mut reports = Vec::with_capacity(4096);
    for k in 0..4096 {
        let mut report = [0u8; MAX_REPORT_LEN];
        let n = device.input_report(&mut report);
        assert_eq!(n, INPUT_REPORT_LEN);
        reports.push(report);
        core.tick(&report[..n], k as f64 * 1e-3, &mut controller, None)
            .unwrap();
        device.receive_output(core.output()).unwrap();
        device.advance();
    }

    let mut core = ServoCore::new(&options).unwrap();
    let mut k = 0usize;
    group.bench_function("core", |b| {
        b.iter(|| {
            let report = &reports[k % reports.len()];
            k += 1;
            let report = &report[..INPUT_REPORT_LEN];
            let outcome = core.tick(black_box(report), k as f64 * 1e-3, &mut controller, None);
            let _ = black_box((outcome, core.output()));
        })
    });

    let mut core = ServoCore::new(&options).unwrap();
    let mut k = 0usize;
    group.bench_function("with_mock_device", |b| {
        b.iter(|| {
            let mut report = [0u8; MAX_REPORT_LEN];
            let n = device.input_report(&mut report);
            k += 1;
            let outcome = core.tick(&report[..n], k as f64 * 1e-3, &mut controller, None);
            device.receive_output(core.output()).unwrap();
            device.advance();
            black_box(outcome)
        })
    });
    // The daemon's controller: compensation (Eq. 15) with its mailbox and state publishing.
    let (commands_tx, offsets_tx, servo_mailbox, mut hub_mailbox) = mailbox();
    let model = GravityModel::new(
        hold().field.into(),
        CompensationMode::Scalar,
        OutsideGrid::HoldNearest,
    )
    .unwrap();
    let mut daemon = DaemonController::new(
        Compensation::new(Some(Box::new(model)), ForceOffset::new(0.05, 0.05)),
        servo_mailbox,
    );
    // Client 1 owns the force, so its offsets are applied.
    commands_tx
        .send(ServoCommand::SetOwner(Some(1)))
        .expect("an empty ring takes a command");
    let mut core = ServoCore::new(&options).unwrap();
    let mut k = 0usize;
    group.bench_function("daemon_controller", |b| {
        b.iter(|| {
            let report = &reports[k % reports.len()];
            k += 1;
            if k % 10 == 0 {
                offsets_tx.send(OffsetCommand {
                    client: 1,
                    seq: k as u64,
                    force: Vector3::new(0.1, 0.0, 0.0),
                });
            }
            let outcome = core.tick(black_box(report), k as f64 * 1e-3, &mut daemon, None);
            // Keep the state ring from filling, as the daemon's hub does.
            let _ = hub_mailbox.states.pop();
            let _ = black_box((outcome, core.output()));
        })
    });
    group.finish();
}

criterion_group!(benches, bench_tick);
criterion_main!(benches);
