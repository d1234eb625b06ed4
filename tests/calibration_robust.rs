//! Calibration that needs no tuning (issue 17, and issue 14 item 3): the default config on light,
//! heavy, over-balanced and weightless handles, gravity tilted, Coulomb friction as large as the
//! load, an obstacle, and the published PHANToM 1.5 arm. Every figure is judged against the
//! plant's own holding force ([`Plant::holding_force`]), never against calibration output; every
//! run is in virtual time.

use std::sync::atomic::AtomicBool;

use nalgebra::Vector3;

use hgcd::calibrate::persist::grid_file;
use hgcd::config::{Config, DeviceSpec, HoldPlan};
use hgcd::control::calibration::{
    Calibration, CalibrationEvent, CalibrationFailure, CalibrationParams, CalibrationResult,
};
use hgcd::control::compensation::{Compensation, ForceOffset, GravityModel};
use hgcd::control::{ControlOutput, Controller, DeviceState};
use hgcd::servo::{self, ExitReason, ServoOptions};
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::Pacing;

/// Which simulated device, and its config.
struct Device {
    model: &'static str,
    config: Config,
}

impl Device {
    /// The point mass of the default config with apparent mass `mass` (kg), Coulomb friction
    /// `friction` (N), gravity tilted `tilt` degrees about y, noise seed `seed`. Weightless and
    /// over-balanced handles get a 50 g moving mass (a counterweight moves too).
    fn point_mass(mass: f64, friction: f64, tilt: f64, seed: u64) -> Self {
        let mut config = Config::default();
        config.sim.mass_kg = mass;
        config.sim.coulomb_friction_n = friction;
        config.sim.seed = seed;
        config.sim.gravity_direction = tilted(tilt);
        if mass.abs() < 0.005 {
            config.sim.inertia_kg = Some(0.05);
        }
        Self {
            model: "point-mass",
            config,
        }
    }

    /// The PHANToM 1.5 with its published mechanics and joint friction, gravity tilted `tilt`
    /// degrees about y.
    fn phantom(tilt: f64, seed: u64) -> Self {
        let mut config = Config::default();
        config.sim.gravity_direction = tilted(tilt);
        config.sim.seed = seed;
        Self {
            model: "phantom",
            config,
        }
    }

    /// The linkage `model` (`phantom` or `delta`), unit `unit` with noise seed `unit`.
    fn linkage(model: &'static str, unit: u64) -> Self {
        let mut device = Self::phantom(0.0, unit);
        device.model = model;
        device.config.sim.unit_seed = unit;
        device
    }

    /// The WoodenHaptics arm behind its joint-space protocol, unit `unit`, with the validation
    /// config that ships for it (its encoders' step sets the velocity filter's bound).
    fn woodenhaptics(unit: u64) -> Self {
        let shipped = format!("config/validate-woodenhaptics-unit-{unit}.toml");
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(shipped);
        Self {
            model: "woodenhaptics",
            config: Config::load(&path).unwrap(),
        }
    }

    fn spec(&self) -> DeviceSpec {
        format!("sim:{}", self.model).parse().unwrap()
    }

    /// The device, its handle at rest at `start` (m).
    fn at(&self, start: &Vector3<f64>) -> SimDevice {
        let mut config = self.config.clone();
        config.sim.start_position_mm = (start * 1e3).into();
        SimDevice::from_config(self.model, &config).unwrap()
    }

    /// The plant's holding force at `x`: the ground truth.
    fn truth(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.at(x).plant().holding_force()
    }

    /// A calibration run in virtual time with the default parameters, and its events.
    fn calibrate(&self) -> (CalibrationResult, Vec<CalibrationEvent>) {
        self.calibrate_with(|_| {})
    }

    /// [`Device::calibrate`] with its parameters changed by `adjust`.
    fn calibrate_with(
        &self,
        adjust: impl FnOnce(&mut CalibrationParams),
    ) -> (CalibrationResult, Vec<CalibrationEvent>) {
        let device = SimDevice::from_config(self.model, &self.config).unwrap();
        let (tx, events) = crossbeam_channel::unbounded();
        // As `hgcd calibrate` holds the cube (its strokes along the profile's arm, if any).
        let mut config = self.config.clone();
        if config.calibration.holds == HoldPlan::Auto {
            config.calibration.holds = HoldPlan::All;
        }
        let mut params = CalibrationParams::for_device(&config, &self.spec());
        adjust(&mut params);
        let mut calibration = Calibration::new(params, Some(tx)).unwrap();
        run(device, &mut calibration, &self.config);
        let events: Vec<_> = events.try_iter().collect();
        match calibration.outcome() {
            Some(Ok(result)) => (result, events),
            other => panic!(
                "{} {:?}: {other:?}; last events {:?}",
                self.model,
                self.config.sim,
                &events[events.len().saturating_sub(3)..]
            ),
        }
    }

    /// The compensation the daemon would run with the grid of `result` (default mode).
    fn compensation(&self, result: &CalibrationResult) -> GravityModel {
        let file = grid_file(result, &self.config, &self.spec());
        let c = &self.config.compensation;
        GravityModel::configured(file, c.mode, c.outside_grid).unwrap()
    }

    /// Where a handle released at rest at `start` under `model` is 0.5 s later, m.
    fn released(&self, model: &GravityModel, start: &Vector3<f64>) -> Vector3<f64> {
        let mut compensation =
            Compensation::new(Some(Box::new(model.clone())), ForceOffset::new(0.05, 0.05));
        let mut limited = For {
            controller: &mut compensation,
            until: 0.5,
        };
        run(self.at(start), &mut limited, &self.config)
    }
}

/// v_G tilted `degrees` from +z toward +x.
fn tilted(degrees: f64) -> [f64; 3] {
    let t = degrees.to_radians();
    [t.sin(), 0.0, t.cos()]
}

/// Runs a controller until it is done, stopping as a fault would; where the handle ends, m.
fn run(device: SimDevice, controller: &mut dyn Controller, config: &Config) -> Vector3<f64> {
    let mut transport = SimTransport::new(device, Pacing::Virtual);
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    let report = servo::run(
        &mut transport,
        controller,
        &options,
        &AtomicBool::new(false),
        None,
    )
    .unwrap();
    assert_eq!(report.exit, ExitReason::ControllerDone);
    transport.device().plant().position()
}

/// A controller run for `until` seconds of device time.
struct For<'a> {
    controller: &'a mut dyn Controller,
    until: f64,
}

impl Controller for For<'_> {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        let out = self.controller.tick(s);
        if s.time >= self.until {
            ControlOutput::done(out.force)
        } else {
            out
        }
    }
}

/// Points across the ±40 mm cube: its 27 vertices' cells' centres and faces, 5 per axis.
fn cube_points() -> impl Iterator<Item = Vector3<f64>> {
    let c = [-0.04, -0.02, 0.0, 0.02, 0.04];
    c.into_iter().flat_map(move |x| {
        c.into_iter()
            .flat_map(move |y| c.into_iter().map(move |z| Vector3::new(x, y, z)))
    })
}

/// Worst errors of a calibration against the plant, N: of the whole force vector, of its
/// vertical part (along the plant's gravity), of the one-sided reading; and the plant's smallest
/// vertical force at a vertex.
struct Errors {
    vector: f64,
    vertical: f64,
    one_sided: f64,
    weight: f64,
}

fn errors(device: &Device, result: &CalibrationResult) -> Errors {
    let up = Vector3::from(device.config.sim.gravity_direction).normalize();
    let mut e = Errors {
        vector: 0.0,
        vertical: 0.0,
        one_sided: 0.0,
        weight: f64::INFINITY,
    };
    for v in result.vertices.iter().filter(|v| v.reached) {
        let truth = device.truth(&v.vertex.position);
        e.vector = e.vector.max((v.force - truth).norm());
        e.vertical = e.vertical.max((v.force - truth).dot(&up).abs());
        e.one_sided = e.one_sided.max((v.one_sided_force - truth).norm());
        e.weight = e.weight.min(truth.dot(&up).abs());
    }
    e
}

/// The point-mass matrix of issue 17 and issue 14 item 3, chosen to cover it without running
/// its every combination: 5 g to 500 g, over-balanced (−8 g) and weightless, gravity upright
/// and tilted 10°, Coulomb friction 0, 0.02, 0.04, 0.06 and 0.1 N, a different noise seed each
/// (each friction level meets several masses and seeds).
const MATRIX: &[(f64, f64, f64, u64)] = &[
    (0.005, 0.0, 10.0, 1),
    (0.005, 0.04, 0.0, 2),
    (0.005, 0.1, 10.0, 3),
    (0.02, 0.02, 10.0, 4),
    (0.02, 0.06, 0.0, 5),
    (0.12, 0.0, 0.0, 6),
    (0.12, 0.02, 10.0, 7),
    (0.12, 0.1, 0.0, 8),
    (0.5, 0.0, 10.0, 9),
    (0.5, 0.04, 10.0, 10),
    (0.5, 0.1, 0.0, 11),
    (-0.008, 0.0, 10.0, 12),
    (-0.008, 0.06, 10.0, 13),
    (0.0, 0.02, 0.0, 14),
    (0.0005, 0.1, 10.0, 15),
];

#[test]
fn the_default_config_calibrates_light_heavy_over_balanced_and_weightless_handles_with_friction() {
    for &(mass, friction, tilt, seed) in MATRIX {
        let device = Device::point_mass(mass, friction, tilt, seed);
        let (result, events) = device.calibrate();
        let case = format!("{mass} kg, {friction} N, {tilt}°, seed {seed}");
        // First try: every vertex reached, no vertex given up on.
        assert!(result.unreachable.is_empty(), "{case}");
        assert!(!events
            .iter()
            .any(|e| matches!(e, CalibrationEvent::VertexUnreachable { .. })));
        let e = errors(&device, &result);
        // Within 2 % of the vertical force, and never less than 1 mN (2 % of a 5 g handle's
        // weight; a weightless handle's 2 % would be nothing).
        let vertical_bound = (0.02 * e.weight).max(1e-3);
        assert!(
            e.vertical <= vertical_bound,
            "{case}: vertical error {} N",
            e.vertical
        );
        // The whole vector likewise.
        assert!(
            e.vector <= (0.02 * e.weight).max(1e-3),
            "{case}: error {} N",
            e.vector
        );
    }
}

/// Under dominant friction a vertex that three vertices measured before it predict
/// (docs/calibration.md §4.3, Move) is measured by its strokes alone: the bands at every vertex
/// took a quarter of the run. The frictional point mass's cube, against the same run with the
/// paper's start (Eq. 12) and bands at every vertex: far less time on bands and in all, and
/// every vertex as close to the plant's force (within 0.5 %).
#[test]
fn predicted_vertices_are_measured_by_their_strokes_alone_as_accurately_and_sooner() {
    let device = Device::point_mass(0.12, 0.04, 0.0, 1);
    let (predicted, _) = device.calibrate();
    let (banded, _) = device.calibrate_with(|p| p.predict_vertices = false);
    for result in [&predicted, &banded] {
        assert!(result.unreachable.is_empty());
        assert_every_vertex_within(&device, result, 0.005);
    }
    let (p, b) = (&predicted.time_spent, &banded.time_spent);
    println!(
        "bands {:.1} s, in all {:.1} s; with the paper's start {:.1} s, {:.1} s",
        p.bands, predicted.duration, b.bands, banded.duration
    );
    assert!(p.bands < 0.25 * b.bands, "{p:?} against {b:?}");
    assert!(
        predicted.duration < 0.85 * banded.duration,
        "{} s against {} s",
        predicted.duration,
        banded.duration
    );
}

#[test]
fn with_compensation_on_the_residual_is_under_10_mn_and_a_released_handle_stays_within_5_mm() {
    // Four of the matrix: the lightest frictionless handle drifts furthest for a given
    // residual (5 mm in 0.5 s is 0.2 mN on 5 g), the heaviest leaves the largest residual.
    for &(mass, friction, tilt, seed) in [MATRIX[0], MATRIX[4], MATRIX[8], MATRIX[12]].iter() {
        let device = Device::point_mass(mass, friction, tilt, seed);
        let (result, _) = device.calibrate();
        let model = device.compensation(&result);
        let case = format!("{mass} kg, {friction} N, {tilt}°");
        for x in cube_points() {
            let residual = (model.force(&x) - device.truth(&x)).norm();
            assert!(residual <= 0.01, "{case}: residual {residual} N at {x:?}");
        }
        for start in [
            Vector3::zeros(),
            Vector3::new(0.013, -0.027, 0.031),
            Vector3::new(-0.035, 0.02, -0.03),
        ] {
            let moved = (device.released(&model, &start) - start).norm();
            assert!(
                moved < 5e-3,
                "{case}: released at {start:?} moved {moved} m"
            );
        }
    }
}

#[test]
fn one_unreachable_vertex_is_marked_and_filled_and_the_other_26_are_kept() {
    // Issue 14, item 3: an obstacle covers the corner (+40, +40, +40) mm of the grid, with
    // 0.06 N of friction (a friction band yields to a push, an obstacle does not).
    let mut device = Device::point_mass(0.12, 0.06, 0.0, 1);
    device.config.sim.obstacle_min_mm = Some([30.0, 30.0, 30.0]);
    device.config.sim.obstacle_max_mm = Some([90.0, 90.0, 90.0]);
    let (result, events) = device.calibrate();
    let unreachable: Vec<_> = events
        .iter()
        .filter_map(|e| match e {
            CalibrationEvent::VertexUnreachable { at, distance, .. } => Some((at.index, *distance)),
            _ => None,
        })
        .collect();
    assert_eq!(unreachable.len(), 1, "{unreachable:?}");
    assert_eq!(unreachable[0].0, [1, 1, 1]);
    // The obstacle's nearest face is 10 mm from the vertex.
    assert!(unreachable[0].1 > 9e-3, "{unreachable:?}");
    assert_eq!(result.unreachable.len(), 1);
    let corner = &result.vertices[26];
    assert!(!corner.reached);
    // Filled as docs/grid-format.md §4 says: the mean of its three calibrated face neighbours.
    let neighbours = [25, 23, 17].map(|n| result.vertices[n].force);
    let mean = neighbours.iter().sum::<Vector3<f64>>() / 3.0;
    assert!((corner.force - mean).norm() < 1e-12);
    // The 26 others are kept, within 2 %.
    let e = errors(&device, &result);
    assert!(e.vector <= 0.02 * e.weight, "{}", e.vector);
    // And the grid file says which vertex was filled.
    let file = grid_file(&result, &device.config, &device.spec());
    let record = file.calibration.unwrap();
    assert_eq!(record.unreachable_vertices, Some(vec![[1, 1, 1]]));
}

#[test]
fn both_sides_of_the_friction_band_beat_the_papers_one_sided_reading() {
    // The one-sided rest (the paper's procedure) lands anywhere in the band: off by up to the
    // friction. The middle of the band is the load.
    let device = Device::point_mass(0.12, 0.1, 10.0, 21);
    let (result, _) = device.calibrate();
    let e = errors(&device, &result);
    assert!(e.one_sided > 0.05, "one-sided {}", e.one_sided);
    assert!(e.one_sided <= 0.1 + 0.005, "one-sided {}", e.one_sided);
    assert!(e.vector < 0.003, "two-sided {}", e.vector);
    // The friction found is the plant's, within what the slip detection adds.
    let f = result.initial.friction;
    assert!(f.iter().all(|&f| (0.08..0.13).contains(&f)), "{f}");
}

#[test]
fn the_published_phantom_calibrates_first_time_within_10_mn_and_stays_put_when_compensated() {
    // Issue 17's Must show on sim:phantom: published mechanics and joint friction, gravity
    // upright and tilted 10°.
    for (tilt, seed) in [(0.0, 1), (10.0, 2)] {
        let device = Device::phantom(tilt, seed);
        let (result, _) = device.calibrate();
        assert!(result.unreachable.is_empty(), "{tilt}°");
        let e = errors(&device, &result);
        assert!(
            e.vector <= 0.01,
            "{tilt}°: force vector off by {} N",
            e.vector
        );
        // The paper's one-sided reading is off by the friction band, about 0.1 N.
        assert!(e.one_sided > 0.05, "{tilt}°: one-sided {}", e.one_sided);
        let model = device.compensation(&result);
        for x in cube_points() {
            let residual = (model.force(&x) - device.truth(&x)).norm();
            assert!(residual <= 0.01, "{tilt}°: residual {residual} N at {x:?}");
        }
        for start in [
            Vector3::zeros(),
            Vector3::new(0.03, -0.03, 0.03),
            Vector3::new(-0.035, 0.02, -0.03),
        ] {
            let moved = (device.released(&model, &start) - start).norm();
            assert!(
                moved < 5e-3,
                "{tilt}°: released at {start:?} moved {moved} m"
            );
        }
    }
}

/// Issue 8 on the linkages with their joint friction: every vertex's holding force within 2 % in
/// magnitude and 1° in direction of the plant's own, on three units of each (the nominal one
/// and unit seeds 1 and 2) and with gravity tilted 10°. On the PHANToM 2 % is 1.5 mN of its
/// 0.075 N at the lightest vertex, against some 0.065 N of friction; on the delta the stick
/// region is a parallelepiped skewed so far at the bottom corners of the cube that chords along
/// the axes leave it through faces of different joints.
#[test]
fn linkages_with_joint_friction_are_calibrated_within_2_percent_and_1_degree() {
    for model in ["phantom", "delta"] {
        for (unit_seed, tilt) in [(0, 0.0), (1, 0.0), (2, 0.0), (0, 10.0)] {
            let mut device = Device::phantom(tilt, 1);
            device.model = model;
            device.config.sim.unit_seed = unit_seed;
            let (result, _) = device.calibrate();
            let case = format!("{model} unit {unit_seed}, {tilt}°");
            assert!(result.unreachable.is_empty(), "{case}");
            let (mut worst_magnitude, mut worst_angle) = (0.0f64, 0.0f64);
            for v in &result.vertices {
                let truth = device.truth(&v.vertex.position);
                let magnitude = (v.force.norm() - truth.norm()).abs() / truth.norm();
                let angle = v.force.angle(&truth).to_degrees();
                assert!(
                    magnitude <= 0.02 && angle <= 1.0,
                    "{case}, vertex {:?}: {:.2} % and {angle:.2}° off",
                    v.vertex.index,
                    100.0 * magnitude
                );
                worst_magnitude = worst_magnitude.max(magnitude);
                worst_angle = worst_angle.max(angle);
            }
            println!(
                "{case}: worst {:.2} % and {worst_angle:.2}°",
                100.0 * worst_magnitude
            );
        }
    }
}

/// Issue 14 item 3 on the linkages: their friction is in the joints, so it is scaled
/// (`sim.friction_scale`) until the largest stick band the initialisation finds at the handle
/// spans the range, about 0, 0.02, 0.04, 0.06 and 0.1 N (the PHANToM's published
/// friction gives 0.065 N at its home pose, the delta's nominal 0.154 N). Two units each; every
/// run must reach every vertex at the first try and come within 2 % of the plant's vertical
/// holding force at every vertex. At 0.1 N (1.54 times its published friction) the PHANToM's
/// bands at X_C are misread on some units and seeds, and the survey strokes must catch it
/// (docs/calibration.md §6.1): three units there. The WoodenHaptics arm (its estimated friction gives 0.094 N)
/// is frictionless at 0: its 43–65 µm encoder steps then flicker at rest, which the
/// initialisation must not take for chatter.
#[test]
fn linkages_calibrate_within_2_percent_vertically_with_friction_from_0_to_0_1_n() {
    let levels: [(&str, f64, &[f64]); 3] = [
        ("phantom", 0.065, &[0.0, 0.02, 0.04, 0.06, 0.1]),
        ("delta", 0.154, &[0.0, 0.02, 0.04, 0.06, 0.1]),
        ("woodenhaptics", 0.094, &[0.0, 0.02, 0.04, 0.06, 0.1]),
    ];
    for (model, nominal, bands) in levels {
        for &band in bands {
            let units: &[u64] = if model == "phantom" && band >= 0.1 {
                &[1, 2, 3]
            } else {
                &[1, 2]
            };
            for &unit_seed in units {
                let mut device = if model == "woodenhaptics" {
                    Device::woodenhaptics(unit_seed)
                } else {
                    Device::linkage(model, unit_seed)
                };
                device.config.sim.friction_scale = band / nominal;
                let (result, _) = device.calibrate();
                let found = result.initial.friction.max();
                let case = format!("{model} unit {unit_seed}, {band} N (found {found:.3} N)");
                assert!(result.unreachable.is_empty(), "{case}");
                let up = Vector3::from(device.config.sim.gravity_direction).normalize();
                let mut worst: f64 = 0.0;
                for v in &result.vertices {
                    let truth = device.truth(&v.vertex.position).dot(&up);
                    let error = (v.force.dot(&up) - truth) / truth;
                    assert!(
                        error.abs() <= 0.02,
                        "{case}, vertex {:?}: {:.2} % off vertically",
                        v.vertex.index,
                        100.0 * error
                    );
                    worst = worst.max(error.abs());
                }
                println!("{case}: worst {:.2} % vertically", 100.0 * worst);
            }
        }
    }
}

/// docs/calibration.md §6's table: on each simulated device, the worst error of the one-sided
/// reading (the paper's procedure: the force at the first rest near the vertex) and of the
/// force hgcd measures (the strokes through the vertex), with the compensation's worst residual
/// over the cube and the furthest a released handle moves in 0.5 s. Run with
/// `cargo test --release --test calibration_robust side_by_side -- --ignored --nocapture`.
#[test]
#[ignore]
fn side_by_side() {
    let mut delta = Device::phantom(0.0, 1);
    delta.model = "delta";
    let mut delta_tilted = Device::phantom(10.0, 1);
    delta_tilted.model = "delta";
    let devices = [
        (
            "point-mass 120 g, no friction",
            Device::point_mass(0.12, 0.0, 0.0, 1),
        ),
        (
            "point-mass 120 g, 0.05 N",
            Device::point_mass(0.12, 0.05, 0.0, 1),
        ),
        (
            "point-mass 5 g, 0.1 N, 10°",
            Device::point_mass(0.005, 0.1, 10.0, 1),
        ),
        (
            "point-mass −8 g, 0.06 N, 10°",
            Device::point_mass(-0.008, 0.06, 10.0, 1),
        ),
        ("phantom, published", Device::phantom(0.0, 1)),
        ("phantom, published, 10°", Device::phantom(10.0, 1)),
        ("delta, nominal", delta),
        ("delta, nominal, 10°", delta_tilted),
    ];
    println!(
        "| device | friction found at X_C, N | paper (one-sided), worst error N | hgcd, \
         worst error N | worst vertical error | residual, N | released, mm | device time, s |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- |");
    for (name, device) in devices {
        let (result, _) = device.calibrate();
        let e = errors(&device, &result);
        let model = device.compensation(&result);
        let residual = cube_points()
            .map(|x| (model.force(&x) - device.truth(&x)).norm())
            .fold(0.0, f64::max);
        let released = [
            Vector3::zeros(),
            Vector3::new(0.013, -0.027, 0.031),
            Vector3::new(-0.035, 0.02, -0.03),
        ]
        .iter()
        .map(|start| (device.released(&model, start) - start).norm())
        .fold(0.0, f64::max);
        let f = result.initial.friction;
        println!(
            "| {name} | {:.3}, {:.3}, {:.3} | {:.4} | {:.4} | {:.2} % | {:.4} | {:.2} | {:.0} |",
            f.x,
            f.y,
            f.z,
            e.one_sided,
            e.vector,
            100.0 * e.vertical / e.weight,
            residual,
            released * 1e3,
            result.duration
        );
    }
}

/// docs/calibration.md §6.1, the PHANToM at 0.1 N on many seeds: its joint friction scaled to a
/// 0.1 N band at the handle, units 1 to 3 with noise seeds 1 to 8, every vertex within 2 % of
/// the plant's vertical holding force. About 90 s; run with
/// `cargo test --release --test calibration_robust phantom_at_0_1_n_on_many_seeds -- --ignored --nocapture`.
#[test]
#[ignore]
fn phantom_at_0_1_n_on_many_seeds() {
    let mut worst_of_all: f64 = 0.0;
    for seed in 1..=8 {
        for unit_seed in 1..=3 {
            let mut device = Device::phantom(0.0, seed);
            device.config.sim.unit_seed = unit_seed;
            device.config.sim.friction_scale = 0.1 / 0.065;
            let (result, _) = device.calibrate();
            let case = format!("unit {unit_seed}, noise seed {seed}");
            assert!(result.unreachable.is_empty(), "{case}");
            let worst = worst_vertical(&device, &result);
            println!("{case}: worst {:.2} % vertically", 100.0 * worst);
            assert_within_2_percent(&case, worst);
            worst_of_all = worst_of_all.max(worst);
        }
    }
    println!("worst of all: {:.2} %", 100.0 * worst_of_all);
}

/// The worst vertical error of `device`'s calibration against its plant's holding force, with
/// handle-side Coulomb friction `handle` (N) on top of its joint friction scaled by `scale`.
fn worst_vertical_with_handle_friction(mut device: Device, scale: f64, handle: f64) -> f64 {
    device.config.sim.friction_scale = scale;
    device.config.sim.coulomb_friction_n = handle;
    let (result, _) = device.calibrate();
    let case = format!(
        "{} at {scale} × joint friction, {handle} N at the handle",
        device.model
    );
    assert!(result.unreachable.is_empty(), "{case}");
    let worst = worst_vertical(&device, &result);
    println!("{case}: worst {:.2} % vertically", 100.0 * worst);
    worst
}

/// Every vertex within 2 % of the plant's vertical holding force.
fn assert_within_2_percent(case: &str, worst: f64) {
    assert!(
        worst <= 0.02,
        "{case}: {:.2} % off vertically",
        100.0 * worst
    );
}

/// Every vertex's force within `share` of the plant's, |F − F_plant| / |F_plant|.
fn assert_every_vertex_within(device: &Device, result: &CalibrationResult, share: f64) {
    for v in &result.vertices {
        let truth = device.truth(&v.vertex.position);
        let error = (v.force - truth).norm() / truth.norm();
        assert!(error <= share, "{}: {:.2} % off", v.vertex, 100.0 * error);
    }
}

/// The largest relative error of a vertex's vertical force against the plant's.
fn worst_vertical(device: &Device, result: &CalibrationResult) -> f64 {
    let up = Vector3::from(device.config.sim.gravity_direction).normalize();
    result
        .vertices
        .iter()
        .map(|v| {
            let truth = device.truth(&v.vertex.position).dot(&up);
            ((v.force.dot(&up) - truth) / truth).abs()
        })
        .fold(0.0, f64::max)
}

/// Issue 14 item 3 read literally: Coulomb friction at the handle (`sim.coulomb_friction_n`, a
/// ball of that radius, not the joints' polytope) on the linkages, their joints frictionless,
/// and once on top of the PHANToM's published joint friction. Every vertex within 2 %
/// vertically. The delta: `delta_calibrates_within_2_percent_with_handle_side_friction`.
#[test]
fn phantom_and_woodenhaptics_calibrate_within_2_percent_with_handle_side_friction() {
    for (device, scale, handle) in [
        (Device::linkage("phantom", 1), 0.0, 0.04),
        (Device::linkage("phantom", 2), 0.0, 0.1),
        (Device::linkage("phantom", 1), 1.0, 0.02),
        (Device::woodenhaptics(1), 0.0, 0.06),
        (Device::woodenhaptics(2), 0.0, 0.1),
        (woodenhaptics_seed_13(), 0.0, 0.02),
    ] {
        let case = format!("{} at {scale} × joint friction, {handle} N", device.model);
        let worst = worst_vertical_with_handle_friction(device, scale, handle);
        assert_within_2_percent(&case, worst);
    }
}

/// A handle whose friction follows the push (the point mass's ball of Coulomb friction) is read
/// by one stroke along (1, 1, 1) a vertex, where three along the diagonals took three times as
/// long: the 27-vertex cube at 0.04 N and 0.08 N in under 120 s of device time (284 s with
/// three strokes), every vertex within 0.05 % of the plant's force: 2.75 s of strokes a vertex.
/// A linkage without an arm profile whose first bands show joint friction keeps the three (9 s
/// a vertex): `sim:delta` as a Cartesian device. (The PHANToM near its home pose, whose joints
/// move the handle nearly along the axes, may not show it: its bands' slips came within 20° of
/// their push in a run that then took one stroke a vertex, 112 s, every vertex within 0.10 %.)
#[test]
fn a_handle_whose_friction_follows_the_push_is_read_by_one_stroke_a_vertex() {
    for friction in [0.04, 0.08] {
        let device = Device::point_mass(0.12, friction, 0.0, 1);
        let (result, _) = device.calibrate();
        assert!(result.unreachable.is_empty());
        assert_every_vertex_within(&device, &result, 0.0005);
        assert!(
            result.duration < 120.0,
            "{friction} N: {} s",
            result.duration
        );
        let per_vertex = result.time_spent.strokes / 27.0;
        assert!(
            per_vertex < 3.0,
            "{friction} N: {per_vertex} s of strokes a vertex"
        );
    }
    let mut cartesian = Device::linkage("delta", 1);
    cartesian.config.device.profile = "cartesian-v1".into();
    cartesian.config.sim.coulomb_friction_n = 0.04;
    let (result, _) = cartesian.calibrate();
    let per_vertex = result.time_spent.strokes / 27.0;
    assert!(per_vertex > 8.0, "{per_vertex} s of strokes a vertex");
}

/// PHANToM unit 2, noise seed 2, 0.04 N at the handle: the handle rests on one encoder
/// reading without flicker while it is caught, so no step shows and the slip threshold assumed
/// a fine encoder. A reading flipping by one step then passed for a slip: the bands read 6 mN
/// of friction where there are over 100, the moving mass 4.2 kg where it is about 50 g, and
/// the stiff hold built on it left vertices up to 200 % off (issue 35). The bands are measured
/// again once their slips have shown the step. Every vertex within 0.5 % of the plant's force.
#[test]
fn a_handle_resting_on_one_encoder_reading_is_measured_with_the_step_its_slips_show() {
    let mut device = Device::linkage("phantom", 2);
    device.config.sim.seed = 2;
    device.config.sim.coulomb_friction_n = 0.04;
    let (result, _) = device.calibrate();
    assert!(result.unreachable.is_empty());
    let i = &result.initial;
    assert!(i.friction.min() >= 0.04, "{i:?}");
    assert_every_vertex_within(&device, &result, 0.005);
}

/// PHANToM unit 2, noise seed 1, 0.02 N at the handle: the bands at X_C read the friction
/// along x and y 1.5 and 2 times as wide as the strokes slide against, and the middle along y
/// 47 mN off the strokes' force. The moving mass timed with that load read 925 g along z (about
/// 70 g), and the hold built on it left vertices up to 4 % off (issue 35). A band whose middle
/// is further from the strokes' force than a stroke is allowed to move F̂ was misread too: the
/// initialisation takes the strokes' load and times the moving mass again.
#[test]
fn bands_at_x_c_whose_middle_the_strokes_contradict_are_measured_again() {
    let mut device = Device::linkage("phantom", 2);
    device.config.sim.seed = 1;
    device.config.sim.coulomb_friction_n = 0.02;
    let (result, _) = device.calibrate();
    assert!(result.unreachable.is_empty());
    let i = &result.initial;
    assert!(i.inertia.max() < 0.2, "{i:?}");
    assert_every_vertex_within(&device, &result, 0.005);
}

/// The delta, unit 1, 0.04 N at the handle: strokes along the diagonals of the axes left one of
/// its arms turning slowly on every pass, stuck for part of it, and vertices 0.5–1.5 % off
/// (docs/calibration.md §7.1). Along the directions that turn its profile's three arms at the
/// same rate, every vertex is within 0.5 % of the plant's force.
#[test]
fn strokes_along_the_arms_own_joint_directions_hold_the_delta_within_half_a_percent() {
    let mut device = Device::linkage("delta", 1);
    device.config.sim.seed = 1;
    device.config.sim.coulomb_friction_n = 0.04;
    let (result, _) = device.calibrate();
    assert!(result.unreachable.is_empty());
    assert_every_vertex_within(&device, &result, 0.005);
}

/// `hgcd calibrate` says where the device time went: the kinds of step add up to the run's
/// duration; a frictionless handle needs no bands nor strokes, a frictional one both.
#[test]
fn the_time_spent_on_each_kind_of_step_adds_up_to_the_duration() {
    for friction in [0.0, 0.04] {
        let (result, _) = Device::point_mass(0.12, friction, 0.0, 3).calibrate();
        let t = result.time_spent;
        assert!((t.total() - result.duration).abs() < 0.002, "{result:?}");
        assert!(
            t.initialisation > 0.0 && t.moves > 0.0 && t.rests > 0.0,
            "{t:?}"
        );
        assert_eq!(t.exploration, 0.0);
        assert_eq!(t.bands > 0.0 && t.strokes > 0.0, friction > 0.0, "{t:?}");
    }
}

/// WoodenHaptics unit 2 with noise seed 13: at 0.02 N at the handle its band along x at X_C
/// reads 0.17 N, the hold along x is stiff (about 150 rad/s), and an undamped still hold on the
/// smoothed position once rang up from a slip to a 0.3 m excursion onto a joint stop, twice,
/// and the calibration timed out (docs/calibration.md §6.1).
fn woodenhaptics_seed_13() -> Device {
    let mut device = Device::woodenhaptics(2);
    device.config.sim.seed = 13;
    device
}

/// The delta with Coulomb friction at the handle on frictionless joints, every vertex within
/// 2 % vertically. At 0.02 N on unit 1 its bands' rounds, which read a ball of friction as
/// joints' faces (its mobility sends slips far off the push), once left vertex (−1, −1, −1)
/// 0.5 N off; the hold then kept the handle 3.5 mm off the strokes' windows, the strokes were
/// blocked and the rounds' force was kept, 47 % low. Blocked strokes now run again from the force
/// that holds the handle where it rests. Three cases here (about 40 s);
/// `handle_friction_on_every_linkage_and_seed` runs every level on every linkage.
#[test]
fn delta_calibrates_within_2_percent_with_handle_side_friction() {
    for (unit, handle) in [(1, 0.02), (2, 0.04), (2, 0.1)] {
        let worst =
            worst_vertical_with_handle_friction(Device::linkage("delta", unit), 0.0, handle);
        assert_within_2_percent(&format!("unit {unit}, {handle} N"), worst);
    }
}

/// Issue 35's time on the linkages: the 27-vertex cube at 0.04 N at the handle on top of the
/// joints' friction, every vertex held, in at most 120 s of device time, every vertex within
/// 0.5 % of the plant's force. Where the profile gives the arm, the arm's gravity fitted to the
/// vertices measured so far predicts the next, and one stroke along its joints measures it
/// (docs/calibration.md §4.3, §4.6). Units 1, and 2 for WoodenHaptics' shipped unit, noise seed 1
/// (§7.1 has the sweep over units, seeds and frictions).
#[test]
fn a_linkage_with_its_arm_calibrates_every_vertex_within_two_minutes() {
    for mut device in [
        Device::linkage("phantom", 1),
        Device::linkage("delta", 1),
        Device::woodenhaptics(2),
    ] {
        device.config.sim.seed = 1;
        device.config.sim.coulomb_friction_n = 0.04;
        let (result, _) = device.calibrate();
        assert!(result.unreachable.is_empty(), "{}", device.model);
        assert_every_vertex_within(&device, &result, 0.005);
        println!(
            "{}: {:.1} s, {:?}",
            device.model, result.duration, result.time_spent
        );
        assert!(
            result.duration <= 120.0,
            "{}: {:.1} s",
            device.model,
            result.duration
        );
    }
}

/// The delta, unit 1, noise seed 3, 0.02 N at the handle: at vertex (1, 1, −1) the rounds of
/// bands disagreed (joint friction read through a ball at the handle) and left F̂ 2.8 N off; the
/// hold kept the handle 4.5 mm from the vertex, the strokes were blocked, and the bands' force
/// was kept as a stop's would be: 264 % off (issue 35). A handle held off by more than friction
/// yields to is now measured again from beside the vertex. Every vertex within 2 %. Run as on a
/// delta without a profile (`cartesian-v1`: no arm, strokes along the axes' diagonals) and with
/// the strokes' second look as it was, where this happened; with its profile's arm, or the
/// second look as it is, the run goes another way. Since the strokes take out the handle's
/// momentum and the field's curvature (`Strokes` in `control/calibration/probe.rs`) that run
/// goes another way too, and unit 2, seed 2 meets the case (the one of units 1–3, seeds 1–20).
#[test]
fn a_force_estimate_that_holds_the_handle_far_off_is_measured_again_not_kept() {
    let mut device = Device::linkage("delta", 2);
    device.config.device.profile = "cartesian-v1".into();
    device.config.sim.seed = 2;
    device.config.sim.coulomb_friction_n = 0.02;
    // Strokes measured again after any 30 mN move of F̂, as when this was found: since, a move
    // of a tenth of the force is needed, and this run no longer meets the case.
    let mut params = CalibrationParams::for_device(&device.config, &device.spec());
    params.strokes_again_share = 0.0;
    // And every vertex's rounds of bands, as then: predicted from its neighbours (since), the
    // vertices where the rounds disagreed are measured by their strokes alone.
    params.predict_vertices = false;
    let (tx, events) = crossbeam_channel::unbounded();
    let mut calibration = Calibration::new(params, Some(tx)).unwrap();
    let model = SimDevice::from_config(device.model, &device.config).unwrap();
    run(model, &mut calibration, &device.config);
    let events: Vec<_> = events.try_iter().collect();
    let result = calibration.outcome().unwrap().unwrap();
    assert!(result.unreachable.is_empty());
    assert!(events.iter().any(|e| matches!(
        e,
        CalibrationEvent::VertexRetried {
            failure: Some(CalibrationFailure::HeldOff { .. }),
            ..
        }
    )));
    assert_every_vertex_within(&device, &result, 0.02);
}

/// Issue 14's levels of Coulomb friction at the handle (0.02, 0.04, 0.06 and 0.1 N; 0 is in
/// `linkages_calibrate_within_2_percent_vertically_with_friction_from_0_to_0_1_n`), on
/// frictionless joints, on every linkage: the PHANToM and the delta units 1–3, the WoodenHaptics
/// arm units 1, 2 and 2 again, with noise seeds 11–13. Every run calibrates at the first try
/// with every vertex within 2 % vertically. 0.54 % at worst, about 3 minutes; run with
/// `cargo test --release --test calibration_robust handle_friction_on_every_linkage -- --ignored --nocapture`.
#[test]
#[ignore]
fn handle_friction_on_every_linkage_and_seed() {
    let mut worst_of_all: f64 = 0.0;
    for model in ["phantom", "delta", "woodenhaptics"] {
        for handle in [0.02, 0.04, 0.06, 0.1] {
            for unit in 1..=3 {
                let mut device = if model == "woodenhaptics" {
                    Device::woodenhaptics(unit.min(2))
                } else {
                    Device::linkage(model, unit)
                };
                device.config.sim.seed = unit + 10;
                let worst = worst_vertical_with_handle_friction(device, 0.0, handle);
                assert_within_2_percent(&format!("{model} unit {unit}, {handle} N"), worst);
                worst_of_all = worst_of_all.max(worst);
            }
        }
    }
    println!("worst of all: {:.2} %", 100.0 * worst_of_all);
}

/// The moving mass the initialisation times at X_C (saved as `inertia_kg`; the daemon's payload
/// watch reads a released handle with it) against the plant's own 1 / (J H⁻¹ Jᵀ)_aa there:
/// within 30 % along each axis on each linkage (the force each pulse pushes with scatters it
/// by about ±25 %, docs/calibration.md §2.3: delta unit 2, seed 3 reads +23 % along y),
/// including PHANToM unit 2, seed 1, whose band
/// along z read 0.052 N of friction where the handle slides against 0.087 N, so that its pulse
/// pushed with a fifth of the force it meant to and timed 0.353 kg along z, where the arm's is
/// about 0.065 (docs/calibration.md §2.3). The survey strokes' load and sliding friction say
/// what each pulse pushed with.
#[test]
fn the_moving_mass_is_the_plants_where_a_band_was_misread() {
    let mut cases = Vec::new();
    for (model, unit, seed) in [("phantom", 2, 1), ("delta", 2, 3)] {
        let mut device = Device::linkage(model, unit);
        device.config.sim.seed = seed;
        cases.push(device);
    }
    cases.push(Device::woodenhaptics(2));
    for device in &mut cases {
        device.config.sim.coulomb_friction_n = 0.04;
        let (result, _) = device.calibrate();
        let truth = device.at(&result.rest_point).plant().moving_mass_per_axis();
        let measured = result.initial.inertia;
        println!(
            "{} unit {} seed {}: {:.3?} kg, the plant's {:.3?}",
            device.model,
            device.config.sim.unit_seed,
            device.config.sim.seed,
            measured.as_slice(),
            truth.as_slice()
        );
        for a in 0..3 {
            assert!(
                (measured[a] / truth[a] - 1.0).abs() < 0.3,
                "{} unit {} seed {}, axis {a}: {:.3} kg against {:.3}",
                device.model,
                device.config.sim.unit_seed,
                device.config.sim.seed,
                measured[a],
                truth[a]
            );
        }
    }
}
