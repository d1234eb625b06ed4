//! One servo tick's hot path: decode → FOAW state estimate → controller → safety → encode.
//!
//! `cargo bench --bench servo_tick`. Input reports come from the mock-HID device (a PD-held
//! simulated point mass, so positions and velocities are realistic); `core` times only what the
//! servo thread does per report with a PD hold, `daemon_controller` the same with the daemon's
//! compensation controller (mailbox: commands, newest offset, Eq. 15, state publishing),
//! `with_mock_device` adds the simulated firmware and plant. `gravity_model/*` times one
//! evaluation of each gravity model: the lattices and a PHANToM's arm models.

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
    // The daemon's controller: compensation (Eq. 15) with its mailbox and state publishing,
    // with the scalar lattice and with a PHANToM's arm + residual model.
    let scalar = GravityModel::new(
        hold().field.into(),
        CompensationMode::Scalar,
        OutsideGrid::HoldNearest,
    )
    .unwrap();
    bench_daemon(&mut group, "daemon_controller", scalar, &reports, &options);
    let arm = phantom_arm_model().with_mode(CompensationMode::ArmResidual);
    bench_daemon(
        &mut group,
        "daemon_controller_arm_residual",
        arm,
        &reports,
        &options,
    );
    group.finish();

    // The gravity model alone, as compensation evaluates it once a tick, at positions across
    // the cube and beyond it: the lattices, and the arm models of a PHANToM (inverse kinematics,
    // J⁻ᵀ τ, and for arm + residual the residual lattice).
    let mut group = c.benchmark_group("gravity_model");
    group.measurement_time(Duration::from_secs(3));
    let positions: Vec<Vector3<f64>> = (0..1000)
        .map(|n| {
            let t = n as f64 * 0.0123;
            Vector3::new(
                0.06 * t.sin(),
                0.06 * (1.3 * t).cos(),
                0.05 * (0.7 * t).sin(),
            )
        })
        .collect();
    let arm_model = phantom_arm_model();
    let mut models = vec![(
        "scalar",
        GravityModel::new(
            hold().field.into(),
            CompensationMode::Scalar,
            OutsideGrid::HoldNearest,
        )
        .unwrap(),
    )];
    for (name, mode) in [
        ("vector", CompensationMode::Vector),
        ("arm", CompensationMode::Arm),
        ("arm_residual", CompensationMode::ArmResidual),
    ] {
        models.push((name, arm_model.with_mode(mode)));
    }
    for (name, model) in &models {
        let mut k = 0usize;
        group.bench_function(*name, |b| {
            b.iter(|| {
                k += 1;
                black_box(model.force(black_box(&positions[k % positions.len()])))
            })
        });
    }
    group.finish();
}

/// One tick of the daemon's controller compensating with `model`, an owner's offset every 10th
/// tick, on the recorded `reports`.
fn bench_daemon(
    group: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    name: &str,
    model: GravityModel,
    reports: &[[u8; MAX_REPORT_LEN]],
    options: &ServoOptions,
) {
    let (commands_tx, offsets_tx, servo_mailbox, mut hub_mailbox) = mailbox();
    let mut daemon = DaemonController::new(
        Compensation::new(Some(Box::new(model)), ForceOffset::new(0.05, 0.05)),
        servo_mailbox,
    );
    // Client 1 owns the force, so its offsets are applied.
    commands_tx
        .send(ServoCommand::SetOwner(Some(1)))
        .expect("an empty ring takes a command");
    let mut core = ServoCore::new(options).unwrap();
    let mut k = 0usize;
    group.bench_function(name, |b| {
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
            // The recorded report, not the whole buffer it sits in: a longer slice does not
            // decode, and the tick would end there.
            let report = &report[..INPUT_REPORT_LEN];
            let outcome = core.tick(black_box(report), k as f64 * 1e-3, &mut daemon, None);
            assert!(outcome.is_ok(), "{outcome:?}");
            // Keep the state ring from filling, as the daemon's hub does.
            let _ = hub_mailbox.states.pop();
            let _ = black_box((outcome, core.output()));
        })
    });
}

/// A grid file of `sim:phantom` over the paper's cube with an arm model: the published arm's
/// parameters and a residual of a few millinewtons at each vertex.
struct ArmFile(hgcd::grid::GridFile);

impl ArmFile {
    fn with_mode(&self, mode: CompensationMode) -> GravityModel {
        GravityModel::new(self.0.clone(), mode, OutsideGrid::HoldNearest).unwrap()
    }
}

fn phantom_arm_model() -> ArmFile {
    use hgcd::arm::ArmGravity;
    use hgcd::grid::{ArmRecord, GridFile};
    let arm = hgcd::profile::Profile::built_in("phantom_1_5")
        .unwrap()
        .gravity_arm()
        .unwrap();
    let parameters = [-0.0017, 0.0, -0.0075, 0.0, 0.0, 0.0, 0.0];
    let gravity = ArmGravity {
        arm,
        parameters,
        up: Vector3::z(),
        g: 9.81,
    };
    let grid = hold().field;
    let forces = (0..grid.vertex_count())
        .map(|n| {
            let (i, j, k) = grid.coordinates(n);
            let f = gravity.force(&grid.vertex_position(i, j, k));
            (f + Vector3::new(0.002, -0.001, 0.003)).into()
        })
        .collect();
    let mut file = GridFile::from(grid);
    file.vertices.force_vectors = forces;
    file.arm = Some(ArmRecord::new("phantom_1_5", &gravity));
    ArmFile(file)
}

criterion_group!(benches, bench_tick);
criterion_main!(benches);
