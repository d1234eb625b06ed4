//! Exploration of a workspace of unknown shape (issue 11, `calibration.workspace = "explore"`):
//! the walk over the lattice meets every stop no faster than the documented bound, read from
//! the plant's own contact log; a wall the user did not declare is explored around; and the
//! explored grid is swept against the plant's own holding force beside the paper's cube and the
//! exact lattice. Every run is in virtual time.

use std::sync::atomic::AtomicBool;

use nalgebra::Vector3;

use hgcd::calibrate::persist::grid_file;
use hgcd::config::{Config, DeviceSpec, WorkspaceMode};
use hgcd::control::calibration::explore::{CONTACT_SPEED, MARGIN};
use hgcd::control::calibration::{
    Calibration, CalibrationEvent, CalibrationParams, CalibrationResult,
};
use hgcd::control::compensation::GravityModel;
use hgcd::servo::{self, ExitReason, ServoOptions};
use hgcd::sim::{ContactLog, SimDevice};
use hgcd::transport::sim::SimTransport;
use hgcd::transport::Pacing;
use hgcd::validate::sweep::{reachable_truth, ExactLattice, GridSweep, SweptGrid};

/// A finished calibration in virtual time, its events and the plant's contacts.
struct Run {
    /// The config the calibration ran with (the device's workspace filled in).
    config: Config,
    result: CalibrationResult,
    events: Vec<CalibrationEvent>,
    contacts: ContactLog,
}

/// Calibrate `sim:model` as `hgcd calibrate` would: with the workspace the device declares
/// where `config` gives none.
fn calibrate(model: &str, config: &Config) -> Run {
    let device = SimDevice::from_config(model, config).unwrap();
    let config = &config.for_device(Some(&device.device_info(false)));
    let (tx, events) = crossbeam_channel::unbounded();
    let mut calibration =
        Calibration::new(CalibrationParams::from_config(config), Some(tx)).unwrap();
    let mut transport = SimTransport::new(device, Pacing::Virtual);
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    let report = servo::run(
        &mut transport,
        &mut calibration,
        &options,
        &AtomicBool::new(false),
        None,
    )
    .unwrap();
    assert_eq!(report.exit, ExitReason::ControllerDone);
    let events: Vec<_> = events.try_iter().collect();
    let result = match calibration.outcome() {
        Some(Ok(result)) => result,
        other => panic!("{model}: {other:?}; last events {:?}", events.last()),
    };
    Run {
        config: config.clone(),
        result,
        events,
        contacts: transport.device().plant().contacts().clone(),
    }
}

fn exploring(mut config: Config) -> Config {
    config.calibration.workspace = WorkspaceMode::Explore;
    config
}

/// The exploration's moves, in order: from where, along which axis, how far (m), and whether
/// a stop ended it.
fn probes(events: &[CalibrationEvent]) -> Vec<(Vector3<f64>, Vector3<f64>, f64, bool)> {
    events
        .iter()
        .filter_map(|e| match e {
            CalibrationEvent::Probed {
                from,
                direction,
                run,
                stopped,
                ..
            } => Some((*from, *direction, *run, *stopped)),
            _ => None,
        })
        .collect()
}

/// The grid of `run` swept over `n` reachable points of `sim:model`.
fn sweep(model: &str, config: &Config, run: &Run, n: usize) -> GridSweep {
    let spec: DeviceSpec = format!("sim:{model}").parse().unwrap();
    let file = grid_file(&run.result, &run.config, &spec);
    let c = &config.compensation;
    let gravity = GravityModel::configured(file.clone(), c.mode, c.outside_grid).unwrap();
    let truth = reachable_truth(model, config, n, 1).unwrap();
    GridSweep::new(&SweptGrid::new(gravity, &file), &truth)
}

#[test]
fn a_wall_the_user_did_not_declare_is_explored_around_not_driven_into() {
    // A point mass of 120 g with 0.03 N of friction in the default ±70 mm box, and a wall at
    // x = +25 mm across all of it that no config key declares to calibration.
    let mut config = exploring(Config::default());
    config.calibration.spacing_mm = 20.0;
    config.sim.coulomb_friction_n = 0.03;
    config.sim.obstacle_min_mm = Some([25.0, -500.0, -500.0]);
    config.sim.obstacle_max_mm = Some([500.0, 500.0, 500.0]);
    let run = calibrate("point-mass", &config);

    // The lattice's vertices at x = +20 mm are reached; every move from them toward +x meets
    // the wall within 2 mm of it, and no other move meets anything or leaves the configured
    // box (the plant's ±80 mm stops, as the simulated device declares them).
    let (lo, hi) = run.config.device.workspace();
    assert_eq!((lo, hi), (Vector3::repeat(-0.08), Vector3::repeat(0.08)));
    let probes = probes(&run.events);
    let mut at_the_wall = 0;
    for (from, d, run, stopped) in &probes {
        let end = from + d * *run;
        if *stopped {
            assert!(d.x > 0.5, "{from:?} along {d:?} stopped at {end:?}");
            assert!((end.x - 0.025).abs() < 2e-3, "{from:?} stopped at {end:?}");
            at_the_wall += 1;
        } else {
            assert!(
                end.x < 0.025 && end.abs().max() < 0.08 + 1e-4,
                "{from:?}: {end:?}"
            );
        }
    }
    // Every vertex at x = +20 mm inside the box (−80 … 80 mm along y and z, less those that
    // X_C's few µm off the origin puts just outside) tried toward the wall.
    let centre = run.result.workspace.as_ref().expect("a map").centre;
    let inside = |a: usize| {
        (-4..=4)
            .filter(|&k| (centre[a] + 0.02 * f64::from(k)).abs() <= 0.08)
            .count()
    };
    assert_eq!(at_the_wall, inside(1) * inside(2));
    assert!(at_the_wall >= 64, "{at_the_wall} moves met the wall");
    // No vertex is planned behind the wall or within the margin of it, and none the calibration
    // went to was out of reach.
    let visited: Vec<_> = run
        .result
        .vertices
        .iter()
        .filter(|v| !run.result.extrapolated.contains(&v.vertex))
        .collect();
    assert!(visited.len() >= 100, "{} visited", visited.len());
    for v in &visited {
        assert!(
            v.vertex.position.x <= 0.025 - MARGIN + 1e-9,
            "{} planned at {:?}",
            v.vertex,
            v.vertex.position
        );
        assert!(v.reached, "{} not reached", v.vertex);
    }
    assert!(
        run.result.unreachable.is_empty(),
        "{:?}",
        run.result.unreachable
    );
    // The plant's log: every contact with the wall or the box was slow.
    assert!(
        run.contacts.count() >= 9,
        "{} contacts",
        run.contacts.count()
    );
    assert!(
        run.contacts.fastest() <= CONTACT_SPEED,
        "a contact at {} m/s",
        run.contacts.fastest()
    );
    // A point mass's holding force is the same everywhere, so the extrapolated vertices are as
    // good as the measured ones: within 2 % everywhere the handle can go.
    let swept = sweep("point-mass", &config, &run, 300);
    assert!(swept.residual_pct.max < 2.0, "{swept:?}");
}

/// What the explored grid of a linkage shows beside the paper's cube and the exact lattice
/// (the plant's own force at every vertex of the same spacing the handle can reach, the best
/// any grid of that spacing does), all swept over the same 1000 reachable points.
struct Explored {
    cube: GridSweep,
    explored: GridSweep,
    bound: GridSweep,
}

/// Calibrate `model` on the cube and exploring, and assert what holds on every linkage: no
/// contact of the exploring run faster than the bound (read from the plant's own log), some
/// moves ending on a stop, and every vertex the calibration measured within 4 % of the plant's
/// own holding force there, as a vector (the PHANToM's is light: 3 % of its smallest is 2 mN).
fn explored_beside_the_cube(model: &str, mut config: Config) -> Explored {
    // The lattices side by side: the arm model, which holds the whole workspace from the cube
    // alone, is tested in tests/arm_model.rs and tests/validate.rs.
    config.compensation.mode = Some(hgcd::config::CompensationMode::Vector);
    let cube = calibrate(model, &config);
    let config = exploring(config);
    let explored = calibrate(model, &config);
    let truth = reachable_truth(model, &config, 1000, 1).unwrap();
    let bound = ExactLattice::new(model, &config, &truth).unwrap().unwrap();
    let on = |run: &Run| {
        let spec: DeviceSpec = format!("sim:{model}").parse().unwrap();
        let file = grid_file(&run.result, &run.config, &spec);
        let c = &config.compensation;
        let gravity = GravityModel::configured(file.clone(), c.mode, c.outside_grid).unwrap();
        GridSweep::new(&SweptGrid::new(gravity, &file), &truth)
    };
    let shown = Explored {
        cube: on(&cube),
        explored: on(&explored),
        bound: bound.sweep,
    };
    eprintln!(
        "{model}: cube {:?}\nexplored {:?}\nexact lattice {:?}\ndevice time {} s, {} contacts, \
         fastest {} m/s",
        shown.cube,
        shown.explored,
        shown.bound,
        explored.result.duration,
        explored.contacts.count(),
        explored.contacts.fastest()
    );
    assert!(
        explored.contacts.fastest() <= CONTACT_SPEED,
        "{model}: a contact at {} m/s: {:?}",
        explored.contacts.fastest(),
        explored
            .contacts
            .contacts()
            .iter()
            .filter(|c| c.speed > CONTACT_SPEED)
            .collect::<Vec<_>>()
    );
    let moves = probes(&explored.events);
    let stopped = moves.iter().filter(|p| p.3).count();
    assert!(
        stopped >= 20 && stopped < moves.len(),
        "{model}: {stopped} of {} moves met a stop",
        moves.len()
    );
    // The vertices measured, against the plant's own force there.
    let mut placed = config.clone();
    let mut worst: f64 = 0.0;
    for v in explored.result.vertices.iter().filter(|v| v.reached) {
        placed.sim.start_position_mm = (v.vertex.position * 1e3).into();
        let plant = SimDevice::from_config(model, &placed).unwrap();
        let truth = plant.plant().holding_force();
        worst = worst.max((v.force - truth).norm() / truth.norm());
    }
    eprintln!("{model}: worst measured vertex {:.2} %", 100.0 * worst);
    assert!(
        worst <= 0.04,
        "{model}: a vertex {:.2} % off",
        100.0 * worst
    );
    shown
}

/// The PHANToM's explored grid covers many times the cube's share of its workspace, its p95
/// residual over the whole workspace is several times below the cube's and close to the exact
/// lattice's: what is left is the spacing's, not the calibration's (docs/calibration.md §12).
#[test]
fn the_explored_phantom_grid_nears_the_lattices_bound_and_no_stop_is_struck_hard() {
    let Explored {
        cube,
        explored,
        bound,
    } = explored_beside_the_cube("phantom", Config::default());
    assert!(
        explored.covered_fraction > 10.0 * cube.covered_fraction,
        "covered {} vs the cube's {}",
        explored.covered_fraction,
        cube.covered_fraction
    );
    assert!(
        explored.residual_pct.p95 < 0.25 * cube.residual_pct.p95,
        "p95 {} vs the cube's {}",
        explored.residual_pct.p95,
        cube.residual_pct.p95
    );
    assert!(
        explored.residual_pct.p95 < 1.5 * bound.residual_pct.p95,
        "p95 {} vs the exact lattice's {}",
        explored.residual_pct.p95,
        bound.residual_pct.p95
    );
}

/// The delta on 20 mm cells, as its validation configs calibrate it (its gravity force bends
/// too sharply near the top of its workspace for 40 mm cells): the explored grid covers more of
/// its bowl-shaped workspace than the paper's cube, with a lower p95 residual over all of it.
#[test]
fn the_explored_delta_grid_covers_more_than_the_cube_and_no_stop_is_struck_hard() {
    let mut config = Config::default();
    config.calibration.half_size = 2;
    config.calibration.spacing_mm = 20.0;
    let Explored {
        cube,
        explored,
        bound,
    } = explored_beside_the_cube("delta", config);
    assert!(
        explored.covered_fraction > cube.covered_fraction,
        "covered {} vs the cube's {}",
        explored.covered_fraction,
        cube.covered_fraction
    );
    assert!(
        explored.residual_pct.p95 < 0.75 * cube.residual_pct.p95,
        "p95 {} vs the cube's {}",
        explored.residual_pct.p95,
        cube.residual_pct.p95
    );
    assert!(explored.residual_pct.p95 > bound.residual_pct.p95);
}
