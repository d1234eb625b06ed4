//! The arm model against the simulated plants' own holding force (`Plant::holding_force`): with
//! the published masses it is the plant's force everywhere the handle can go; fitted to the
//! plant's exact holds at the paper's cube it extrapolates to the whole workspace; a tilted base
//! is found; the wrong arm is caught.

use hgcd::arm::{Arm, ArmGravity, ArmTable, MAX_PARAMETERS};
use hgcd::config::{CompensationMode, Config};
use hgcd::fit::{choose, fit_arm, fit_arm_and_geometry, GeometryTolerances, Hold, LatticeHolds};
use hgcd::profile::Profile;
use hgcd::sim::delta::Delta;
use hgcd::sim::phantom::Phantom;
use hgcd::validate::sweep::{reachable_truth, TruePoint};
use nalgebra::Vector3;

fn profile_arm(model: &str, config: &Config) -> Arm {
    let spec = format!("sim:{model}").parse().unwrap();
    Profile::for_device(&spec, config)
        .unwrap()
        .gravity_arm()
        .expect("an arm")
}

/// p95 of |F_true − F| / |F_true| over `truth`, %.
fn p95(truth: &[TruePoint], model: impl Fn(&Vector3<f64>) -> Vector3<f64>) -> f64 {
    let mut r: Vec<f64> = truth
        .iter()
        .map(|t| 100.0 * (t.holding_force - model(&t.position)).norm() / t.holding_force.norm())
        .collect();
    r.sort_by(f64::total_cmp);
    r[(0.95 * r.len() as f64).ceil() as usize - 1]
}

#[test]
fn with_the_published_masses_the_arm_model_is_the_plants_force_everywhere() {
    let config = Config::default();
    let p = Phantom::published();
    // Σ m p of each body, written on the upper arm's and the forearm's directions.
    let upper = p.m_a * p.l1 + p.m_c * p.c_along_upper_arm + p.m_be * p.l5;
    let fore = p.m_a * p.a_along_forearm + p.m_c * p.l3 - p.m_df * p.l6;
    let d = Delta::nominal();
    let along = d.m_arm * d.arm_com + 0.5 * d.m_rods * d.arm;
    let platform = d.m_platform + 1.5 * d.m_rods;
    let cases = [
        ("phantom", [upper, 0.0, fore, 0.0, 0.0, 0.0, 0.0]),
        ("delta", [along, 0.0, along, 0.0, along, 0.0, platform]),
    ];
    for (model, parameters) in cases {
        let gravity = ArmGravity {
            arm: profile_arm(model, &config),
            parameters,
            up: Vector3::z(),
            g: config.sim.g,
        };
        let truth = reachable_truth(model, &config, 500, 7).unwrap();
        for t in &truth {
            let f = gravity.force(&t.position);
            assert!(
                (f - t.holding_force).norm() < 1e-6 + 1e-4 * t.holding_force.norm(),
                "{model} at {:?}: {f:?} against {:?}",
                t.position,
                t.holding_force
            );
        }
    }
}

/// The plant's exact holds at the vertices of the paper's default cube (±40 mm).
fn cube_holds(model: &str, config: &Config) -> LatticeHolds {
    let mut positions = Vec::new();
    let mut holds = Vec::new();
    for n in 0..27 {
        let i = Vector3::new((n % 3) as f64, ((n / 3) % 3) as f64, (n / 9) as f64);
        let x = (i.add_scalar(-1.0)) * 0.04;
        let mut placed = config.clone();
        placed.sim.start_position_mm = (x * 1e3).into();
        let device = hgcd::sim::SimDevice::from_config(model, &placed).unwrap();
        holds.push(Some(Hold::new(x, device.plant().holding_force())));
        positions.push(x);
    }
    LatticeHolds {
        dims: [3, 3, 3],
        positions,
        measured: holds.clone(),
        holds,
        up: Vector3::z(),
        g: config.sim.g,
        linear_fill: false,
    }
}

/// p95 of |F_true − F| over `truth`, mN.
fn p95_mn(truth: &[TruePoint], model: impl Fn(&Vector3<f64>) -> Vector3<f64>) -> f64 {
    let mut r: Vec<f64> = truth
        .iter()
        .map(|t| 1e3 * (t.holding_force - model(&t.position)).norm())
        .collect();
    r.sort_by(f64::total_cmp);
    r[(0.95 * r.len() as f64).ceil() as usize - 1]
}

/// A delta unit's links are up to 0.5 % and its home up to 1 mm off the profile's. From the
/// plant's holds at the cube's eight corners, each off by up to 0.15 % (about what the strokes
/// along the arm leave, docs/calibration.md §7.1), the fit estimates the unit's own geometry,
/// and the arm model then holds the whole workspace within 5 mN at p95 where the profile's
/// geometry leaves 6–9 mN. On the nominal unit, from its exact holds, the profile's geometry is
/// kept: its holds ask for no move.
#[test]
fn the_units_own_geometry_is_estimated_from_its_holds() {
    use rand::{Rng, SeedableRng};
    const CORNERS: [usize; 8] = [0, 2, 6, 8, 18, 20, 24, 26];
    for unit in [1u64, 2, 3] {
        let mut config = Config::default();
        config.sim.unit_seed = unit;
        let arm = profile_arm("delta", &config);
        let cube = cube_holds("delta", &config);
        let truth = reachable_truth("delta", &config, 1000, 1).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(unit);
        let holds: Vec<Hold> = CORNERS
            .iter()
            .map(|&n| {
                let h = cube.holds[n].unwrap();
                let off = Vector3::from_fn(|_, _| rng.gen_range(-1.0..1.0));
                Hold::new(h.position, h.force + off * 0.0015 * h.force.norm())
            })
            .collect();
        let g = config.sim.g;
        let profile = fit_arm(&arm, &holds, g, &[arm.up()]).unwrap();
        let (fitted, shift) =
            fit_arm_and_geometry(&arm, &holds, g, &[arm.up()], &GeometryTolerances::DEFAULT)
                .unwrap();
        let shift = shift.expect("the geometry moved");
        let before = p95_mn(&truth, |x| profile.gravity.force(x));
        let after = p95_mn(&truth, |x| fitted.gravity.force(x));
        println!(
            "delta unit {unit}: p95 {before:.2} → {after:.2} mN; residual {:.2} → {:.2} mN; {}",
            shift.profile_rms_residual * 1e3,
            fitted.rms_residual * 1e3,
            shift.describe()
        );
        assert!(
            before > 5.0,
            "unit {unit}: the profile's geometry gives {before} mN"
        );
        assert!(
            after < 5.0,
            "unit {unit}: the unit's geometry gives {after} mN"
        );
        assert!(
            fitted.rms_residual < 0.6 * shift.profile_rms_residual,
            "unit {unit}"
        );
    }
    let config = Config::default();
    let arm = profile_arm("delta", &config);
    let cube = cube_holds("delta", &config);
    let holds: Vec<Hold> = cube.holds.iter().flatten().copied().collect();
    let (_, shift) = fit_arm_and_geometry(
        &arm,
        &holds,
        config.sim.g,
        &[arm.up()],
        &GeometryTolerances::DEFAULT,
    )
    .unwrap();
    assert_eq!(shift, None, "the nominal unit's holds ask for no move");
}

/// A profile's `[geometry_tolerances]` bound what the fit may move: all 0 keeps the profile's
/// geometry (the fit is the profile's own), a tolerance of 0 keeps that part, and the rest still
/// moves. Delta unit 1, from the plant's exact holds at the cube's 27 vertices.
#[test]
fn geometry_tolerances_of_zero_keep_the_profiles_geometry() {
    let mut config = Config::default();
    config.sim.unit_seed = 1;
    let arm = profile_arm("delta", &config);
    let cube = cube_holds("delta", &config);
    let holds: Vec<Hold> = cube.holds.iter().flatten().copied().collect();
    let g = config.sim.g;
    let profile = fit_arm(&arm, &holds, g, &[arm.up()]).unwrap();
    let exact = GeometryTolerances {
        origin: 0.0,
        length: 0.0,
        radius: 0.0,
    };
    let (fit, shift) = fit_arm_and_geometry(&arm, &holds, g, &[arm.up()], &exact).unwrap();
    assert!(shift.is_none());
    assert_eq!(fit.gravity, profile.gravity);
    let lengths_only = GeometryTolerances {
        origin: 0.0,
        radius: 0.0,
        ..GeometryTolerances::DEFAULT
    };
    let (fit, shift) = fit_arm_and_geometry(&arm, &holds, g, &[arm.up()], &lengths_only).unwrap();
    let shift = shift.expect("the lengths move");
    assert_eq!(shift.origin, Vector3::zeros());
    assert_eq!(shift.radius, Some(0.0));
    assert!(
        shift.lengths.iter().any(|(_, l)| l.abs() > 1e-4),
        "{shift:?}"
    );
    assert!(fit.rms_residual < profile.rms_residual, "{shift:?}");
}

/// Fitted to the plant's exact holds at the cube's 27 vertices, the arm model holds the whole
/// workspace, level or tilted 10°, and finds the tilt: on the nominal unit (the profile's
/// geometry exactly) within 0.2 % and 0.05°; on unit 2, whose link lengths are up to 0.5 % and
/// whose home is up to 1 mm off the profile's, within 5 %, the tilt absorbing part of the
/// geometry's error.
#[test]
fn fitted_to_the_cubes_exact_holds_it_holds_the_whole_workspace_level_or_tilted() {
    for model in ["phantom", "delta", "woodenhaptics"] {
        for (unit, within_pct, within_deg) in [(0, 0.2, 0.05), (2, 5.0, 1.0)] {
            for tilt_deg in [0.0f64, 10.0] {
                let mut config = Config::default();
                config.sim.unit_seed = unit;
                let (s, c) = tilt_deg.to_radians().sin_cos();
                config.sim.gravity_direction = [s * 0.6, s * 0.8, c];
                let arm = profile_arm(model, &config);
                let lattice = cube_holds(model, &config);
                let holds: Vec<Hold> = lattice.holds.iter().flatten().copied().collect();
                let fit = fit_arm(&arm, &holds, config.sim.g, &[arm.up()]).unwrap();
                let truth = reachable_truth(model, &config, 1000, 3).unwrap();
                let whole = p95(&truth, |x| fit.gravity.force(x));
                let up = Vector3::from(config.sim.gravity_direction).normalize();
                let off = fit.gravity.up.angle(&up).to_degrees();
                let case = format!("{model} unit {unit} tilted {tilt_deg}°");
                println!(
                    "{case}: whole-workspace p95 {whole:.3} %, v_G off by {off:.4}°, rank {}, \
                     condition {:.0}, unidentified {:?}, residual/noise {:.3}",
                    fit.rank, fit.condition, fit.unidentified, fit.normalised_residual
                );
                assert!(whole < within_pct, "{case}: p95 {whole} %");
                assert!(off < within_deg, "{case}: v_G off by {off}°");
                let choice = choose(&lattice, Some(&arm), &GeometryTolerances::DEFAULT);
                assert!(
                    matches!(
                        choice.mode,
                        CompensationMode::Arm | CompensationMode::ArmResidual
                    ),
                    "{case}: {choice:?}"
                );
            }
        }
    }
}

/// A serial arm's base moments act only through a tilt of its base. On a base a hundredth of a
/// degree off level, from corner holds off by up to 0.15 %, they would fit the holds' noise
/// (kilogram-millimetres, which a later 5° tilt turns into millinewtons at the handle): they
/// are left out and reported unidentified. Where a 10° tilt shows them, they are fitted.
#[test]
fn a_serial_arms_base_moments_are_fitted_only_where_a_tilt_shows_them() {
    use rand::{Rng, SeedableRng};
    const CORNERS: [usize; 8] = [0, 2, 6, 8, 18, 20, 24, 26];
    let base = ["base, radial", "base, lateral"];
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let mut noisy = |holds: Vec<Hold>| -> Vec<Hold> {
        holds
            .into_iter()
            .map(|h| {
                let off = Vector3::from_fn(|_, _| rng.gen_range(-1.0..1.0));
                Hold::new(h.position, h.force + off * 0.0015 * h.force.norm())
            })
            .collect()
    };
    // The plant (its base moments are nil), 0.02° off level.
    let mut config = Config::default();
    let (s, c) = 0.02f64.to_radians().sin_cos();
    config.sim.gravity_direction = [s * 0.6, s * 0.8, c];
    let arm = profile_arm("phantom", &config);
    let cube = cube_holds("phantom", &config);
    let level = noisy(CORNERS.iter().map(|&n| cube.holds[n].unwrap()).collect());
    let fit = fit_arm(&arm, &level, config.sim.g, &[arm.up()]).unwrap();
    assert_eq!(fit.gravity.parameters[4..6], [0.0, 0.0], "{fit:?}");
    assert!(base.iter().all(|b| fit.unidentified.contains(b)), "{fit:?}");
    // Base moments of 0.002 and −0.001 kg m under a base tilted 10°.
    let (s, c) = 10f64.to_radians().sin_cos();
    let truth = ArmGravity {
        arm,
        parameters: [-0.0017, 0.0, -0.0075, 0.0, 0.002, -0.001, 0.0],
        up: Vector3::new(s * 0.6, s * 0.8, c),
        g: config.sim.g,
    };
    let tilted = noisy(
        CORNERS
            .iter()
            .map(|&n| cube.positions[n])
            .map(|x| Hold::new(x, truth.force(&x)))
            .collect(),
    );
    let fit = fit_arm(&arm, &tilted, config.sim.g, &[arm.up()]).unwrap();
    for k in 4..6 {
        let (got, want) = (fit.gravity.parameters[k], truth.parameters[k]);
        assert!(
            (got - want).abs() < 0.1 * want.abs(),
            "{k}: {got} kg m, {want} kg m"
        );
    }
    assert!(fit.unidentified.is_empty(), "{fit:?}");
}

#[test]
fn the_wrong_arm_is_caught_by_its_held_out_score() {
    let config = Config::default();
    let lattice = cube_holds("phantom", &config);
    let wrong = profile_arm("delta", &config);
    let choice = choose(&lattice, Some(&wrong), &GeometryTolerances::DEFAULT);
    println!("{:?}", choice.scores);
    assert!(
        matches!(
            choice.mode,
            CompensationMode::Vector | CompensationMode::Scalar
        ),
        "{choice:?}"
    );
    assert!(choice.warning().is_some());
    let _ = MAX_PARAMETERS;
}

/// A calibration of `sim:MODEL` with `config`, held as `hgcd calibrate` holds it (the device's
/// profile decides the holds), in virtual time.
fn calibrated(model: &str, config: &Config) -> hgcd::control::calibration::CalibrationResult {
    use hgcd::control::calibration::{Calibration, CalibrationParams};
    use hgcd::servo::{self, ServoOptions};
    use hgcd::transport::sim::SimTransport;
    use hgcd::transport::Pacing;
    let spec = format!("sim:{model}").parse().unwrap();
    let device = hgcd::sim::SimDevice::from_config(model, config).unwrap();
    let mut transport = SimTransport::new(device, Pacing::Virtual);
    let mut calibration =
        Calibration::new(CalibrationParams::for_device(config, &spec), None).unwrap();
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    let stop = std::sync::atomic::AtomicBool::new(false);
    servo::run(&mut transport, &mut calibration, &options, &stop, None).unwrap();
    calibration.outcome().unwrap().unwrap()
}

/// The plant's holding force at `x` (the handle placed there at rest).
fn plant_force(model: &str, config: &Config, x: &Vector3<f64>) -> Vector3<f64> {
    let mut placed = config.clone();
    placed.sim.start_position_mm = (x * 1e3).into();
    hgcd::sim::SimDevice::from_config(model, &placed)
        .unwrap()
        .plant()
        .holding_force()
}

#[test]
#[ignore = "diagnostic: prints each hold against the plant's force"]
fn holds_against_the_plant() {
    // "model,unit,friction,holds[,seed[,joint friction scale]];…"
    let cases: Vec<(&str, u64, f64, &str, u64, f64)> = std::env::var("HOLDS_CASES")
        .map(|v| {
            v.split(';')
                .map(|c| {
                    let f: Vec<&str> = c.split(',').collect();
                    let leak =
                        |s: &str| -> &'static str { Box::leak(s.to_string().into_boxed_str()) };
                    (
                        leak(f[0]),
                        f[1].parse().unwrap(),
                        f[2].parse().unwrap(),
                        leak(f[3]),
                        f.get(4).map_or(0, |seed| seed.parse().unwrap()),
                        f.get(5).map_or(1.0, |scale| scale.parse().unwrap()),
                    )
                })
                .collect()
        })
        .unwrap_or_else(|_| vec![("phantom", 2, 0.04, "auto", 0, 1.0)]);
    for (model, unit, friction, holds, seed, scale) in cases {
        let mut config = Config::default();
        config.calibration.holds = toml::Value::String(holds.into()).try_into().unwrap();
        config.sim.unit_seed = unit;
        config.sim.seed = seed;
        config.sim.coulomb_friction_n = friction;
        config.sim.friction_scale = scale;
        let result = calibrated(model, &config);
        println!(
            "{model} unit {unit} seed {seed} at {friction} N, joint friction × {scale}: {} s",
            result.duration
        );
        for v in result.vertices.iter().filter(|v| v.reached) {
            let truth = plant_force(model, &config, &v.measured_at);
            println!(
                "  at {:?} mm: held {:?}, plant {:?}: off {:.2} mN ({:.2} %)",
                (v.measured_at * 1e3)
                    .map(|c| (c * 10.0).round() / 10.0)
                    .as_slice(),
                v.held_force.as_slice(),
                truth.as_slice(),
                (v.held_force - truth).norm() * 1e3,
                100.0 * (v.held_force - truth).norm() / truth.norm()
            );
        }
    }
}

/// `sim:MODEL`'s unit `unit` as the whole-workspace sweeps run it: the default config (the
/// shipped one for WoodenHaptics), noise seed `seed`, 0.04 N of friction at the handle.
fn shipped_config(model: &str, unit: u64, seed: u64) -> Config {
    let mut config = Config::default();
    if model == "woodenhaptics" {
        let shipped = format!("config/validate-woodenhaptics-unit-{unit}.toml");
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(shipped);
        config = Config::load(&path).unwrap();
    }
    config.sim.unit_seed = unit;
    config.sim.seed = seed;
    config.sim.coulomb_friction_n = 0.04;
    config
}

/// The sweep of the Must show: on each arm, units 1 and 2, 0.04 N at the handle, level and
/// tilted 10°, a default calibration (the cube's corners held, the model chosen by held-out
/// score) against the plant's own force at 1000 random points of the whole reachable workspace.
/// Its table is docs/calibration.md §13.3; rerun with
/// `cargo test --release --test arm_model -- --ignored --nocapture whole_workspace`
/// (`WHOLE_WORKSPACE_HOLDS=all`: every vertex of the cube held, §13.2's comparison;
/// `WHOLE_WORKSPACE_SEEDS=10`: noise seeds 1–10, each run's row and then, per case, the median
/// and the worst p95 over the seeds, §13.3's second table; `WHOLE_WORKSPACE_FRICTION=0`: no
/// friction at the handle, only the joints'; `WHOLE_WORKSPACE_TOLERANCES=2`: each arm's profile
/// with its geometry tolerances twice the defaults, a prior half as strong).
#[test]
#[ignore = "about ten seconds a noise seed: the tables of docs/calibration.md §13.3"]
fn whole_workspace_after_a_default_calibration_on_every_arm() {
    use hgcd::calibrate::persist::grid_file;
    use hgcd::control::compensation::GravityModel;
    use hgcd::validate::sweep::{GridSweep, SweptGrid};
    let seeds: u64 = std::env::var("WHOLE_WORKSPACE_SEEDS").map_or(1, |n| n.parse().unwrap());
    let mut summary = Vec::new();
    println!(
        "| device | unit | tilt | noise seed | device time | model | held-out | p50 | p95 | p95 | max |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for model in ["phantom", "delta", "woodenhaptics"] {
        for unit in [1, 2] {
            for tilt_deg in [0.0f64, 10.0] {
                let (mut p95_mn, mut longest) = (Vec::new(), 0.0f64);
                for seed in 1..=seeds {
                    let mut config = shipped_config(model, unit, seed);
                    if std::env::var("WHOLE_WORKSPACE_HOLDS").is_ok_and(|h| h == "all") {
                        config.calibration.holds = hgcd::config::HoldPlan::All;
                    }
                    if let Ok(friction) = std::env::var("WHOLE_WORKSPACE_FRICTION") {
                        config.sim.coulomb_friction_n = friction.parse().unwrap();
                    }
                    if let Ok(factor) = std::env::var("WHOLE_WORKSPACE_TOLERANCES") {
                        config.device.profile = scaled_tolerances(model, &config, &factor);
                    }
                    let (s, c) = tilt_deg.to_radians().sin_cos();
                    config.sim.gravity_direction = [s * 0.6, s * 0.8, c];
                    let result = calibrated(model, &config);
                    let spec = format!("sim:{model}").parse().unwrap();
                    let file = grid_file(&result, &config, &spec);
                    let chosen = file.model.clone().unwrap();
                    let gravity =
                        GravityModel::configured(file.clone(), None, Default::default()).unwrap();
                    let truth = reachable_truth(model, &config, 1000, 1).unwrap();
                    let sweep = GridSweep::new(&SweptGrid::new(gravity, &file), &truth);
                    let score = chosen.held_out_pct.of(chosen.chosen.parse().unwrap());
                    println!(
                        "| sim:{model} | {unit} | {tilt_deg}° | {seed} | {:.0} s | {} | {:.2} % | \
                         {:.2} % | {:.2} % | {:.2} mN | {:.1} % |",
                        result.duration,
                        sweep.model,
                        score.unwrap_or(f64::NAN),
                        sweep.residual_pct.p50,
                        sweep.residual_pct.p95,
                        sweep.residual_mn.p95,
                        sweep.residual_pct.max
                    );
                    p95_mn.push(sweep.residual_mn.p95);
                    longest = longest.max(result.duration);
                }
                p95_mn.sort_by(f64::total_cmp);
                summary.push(format!(
                    "| sim:{model} | {unit} | {tilt_deg}° | {:.2} mN | {:.2} mN | {:.2} mN | {} of {seeds} | {longest:.0} s |",
                    p95_mn[0],
                    p95_mn[p95_mn.len() / 2],
                    p95_mn[p95_mn.len() - 1],
                    p95_mn.iter().filter(|&&p| p > 5.0).count(),
                ));
            }
        }
    }
    if seeds > 1 {
        println!(
            "\n| device | unit | tilt | p95, best seed | median | worst | over 5 mN | device time, longest |"
        );
        println!("| --- | --- | --- | --- | --- | --- | --- | --- |");
        summary.iter().for_each(|row| println!("{row}"));
    }
}

/// A copy of `sim:MODEL`'s built-in profile whose `[geometry_tolerances]` are `factor` times
/// the defaults, in a scratch directory; its path.
fn scaled_tolerances(model: &str, config: &Config, factor: &str) -> String {
    let spec = format!("sim:{model}").parse().unwrap();
    let name = Profile::for_device(&spec, config).unwrap().name;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join(format!("config/profiles/{name}.toml"))).unwrap();
    let k: f64 = factor.parse().unwrap();
    let d = hgcd::arm::GeometryTolerances::DEFAULT;
    let dir = std::env::temp_dir().join(format!("hgcd-tolerances-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(format!("{name}.toml"));
    let scaled = format!(
        "{text}\n[geometry_tolerances]\norigin_m = {}\nlength_share = {}\npivot_radius_m = {}\n",
        k * d.origin,
        k * d.length,
        k * d.radius
    );
    std::fs::write(&path, scaled).unwrap();
    path.display().to_string()
}

/// Which eight holds: from one calibration of all 27 vertices (the same measured holds for
/// every choice), the arm and the unit's geometry fitted to eight of them, chosen four ways:
/// the cube's corners (what `calibration.holds = "auto"` holds), the eight that maximise the
/// determinant of the base parameters' information Σ Gᵀ G (greedy; G the force regressor at the
/// arm's up, which needs no parameter and so could be chosen before any hold), the eight that
/// maximise it for the base parameters, v_G and the geometry together (their derivatives need
/// the parameters: taken from the fit to all 27, the best a calibration choosing as it goes
/// could do), and eight at random (the median of 20 draws). Each scored by p95 of |F_true − F|
/// over the whole reachable workspace. docs/calibration.md §13.2 ("An identifiability search");
/// rerun with `cargo test --release --test arm_model -- --ignored --nocapture which_eight`.
#[test]
#[ignore = "about a minute: a question docs/calibration.md §13.2 answers"]
fn which_eight_holds() {
    use hgcd::arm::ArmGravity;
    use hgcd::fit::geometry::{offsets, placed};
    use nalgebra::{DMatrix, Dyn, OMatrix, U3};
    use rand::{seq::SliceRandom, SeedableRng};
    type Rows = OMatrix<f64, U3, Dyn>;
    // The greedy choice of `n` of `rows` (each hold's weighted derivatives) maximising
    // log det(ε I + Σ rowsᵀ rows).
    fn greedy(rows: &[Option<Rows>], n: usize) -> Vec<usize> {
        let columns = rows.iter().flatten().next().unwrap().ncols();
        let mut information = DMatrix::<f64>::identity(columns, columns) * 1e-9;
        let mut chosen = Vec::new();
        for _ in 0..n {
            let gain = |i: usize| {
                let r = rows[i].as_ref().unwrap();
                (&information + r.transpose() * r).determinant().ln()
            };
            let best = (0..rows.len())
                .filter(|&i| rows[i].is_some() && !chosen.contains(&i))
                .max_by(|&a, &b| gain(a).total_cmp(&gain(b)))
                .unwrap();
            let r = rows[best].as_ref().unwrap();
            information += r.transpose() * r;
            chosen.push(best);
        }
        chosen
    }
    println!("| device | unit | noise seed | corners | base parameters' D-optimal | with v_G and geometry | random, median |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for model in ["phantom", "delta", "woodenhaptics"] {
        for unit in [1, 2] {
            for seed in 1..=4 {
                let mut config = shipped_config(model, unit, seed);
                config.calibration.holds = hgcd::config::HoldPlan::All;
                let spec = format!("sim:{model}").parse().unwrap();
                let profile = Profile::for_device(&spec, &config).unwrap();
                let arm = profile.gravity_arm().unwrap();
                let tolerances = profile.geometry_tolerances;
                let result = calibrated(model, &config);
                let holds: Vec<Hold> = result
                    .vertices
                    .iter()
                    .filter(|v| v.reached)
                    .map(|v| Hold::new(v.measured_at, v.held_force))
                    .collect();
                let truth = reachable_truth(model, &config, 1000, 1).unwrap();
                let g = config.sim.g;
                let p95_of = |chosen: &[usize]| {
                    let eight: Vec<Hold> = chosen.iter().map(|&i| holds[i]).collect();
                    let (fit, _) =
                        fit_arm_and_geometry(&arm, &eight, g, &[arm.up()], &tolerances).unwrap();
                    p95_mn(&truth, |x| fit.gravity.force(x))
                };
                let centre = config.calibration.centre();
                let corners: Vec<usize> = (0..holds.len())
                    .filter(|&i| {
                        let d = result.vertices[i].vertex.position - centre;
                        d.iter().all(|c| c.abs() > 1e-3)
                    })
                    .collect();
                let base: Vec<Option<Rows>> = holds
                    .iter()
                    .map(|h| {
                        let r = arm.force_regressor(&h.position, &arm.up(), g)?;
                        Some(r.columns(0, arm.parameter_count()).into_owned())
                    })
                    .collect();
                // ∂F/∂(θ, v_G, geometry) at the fit to all 27, each hold weighted by its noise;
                // the geometry in its tolerances, v_G in milliradians, θ per unit.
                let (all, _) =
                    fit_arm_and_geometry(&arm, &holds, g, &[arm.up()], &tolerances).unwrap();
                let k = arm.parameter_count();
                let unknowns = k + 2 + offsets(&arm);
                let perturbed = |j: usize, step: f64| {
                    let mut model: ArmGravity = all.gravity;
                    if j < k {
                        model.parameters[j] += step;
                    } else if j < k + 2 {
                        let tilt = if j == k { Vector3::x() } else { Vector3::y() };
                        model.up = (model.up + tilt * step * 1e-3).normalize();
                    } else {
                        let mut p = vec![0.0; offsets(&arm)];
                        p[j - k - 2] = step;
                        model.arm = placed(&model.arm, &p, &tolerances);
                    }
                    model
                };
                let full: Vec<Option<Rows>> = holds
                    .iter()
                    .map(|h| {
                        let mut rows = Rows::zeros(unknowns);
                        for j in 0..unknowns {
                            let (plus, minus) = (perturbed(j, 1e-3), perturbed(j, -1e-3));
                            if !plus.arm.reaches(&h.position) || !minus.arm.reaches(&h.position) {
                                return None;
                            }
                            let d = (plus.force(&h.position) - minus.force(&h.position)) / 2e-3;
                            rows.set_column(j, &(d / h.noise));
                        }
                        Some(rows)
                    })
                    .collect();
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
                let mut random: Vec<f64> = (0..20)
                    .map(|_| {
                        let mut all: Vec<usize> = (0..holds.len()).collect();
                        all.shuffle(&mut rng);
                        p95_of(&all[..8])
                    })
                    .collect();
                random.sort_by(f64::total_cmp);
                let (base, full) = (greedy(&base, 8), greedy(&full, 8));
                let shared =
                    |chosen: &[usize]| chosen.iter().filter(|i| corners.contains(i)).count();
                println!(
                    "| sim:{model} | {unit} | {seed} | {:.2} mN | {:.2} mN ({} corners) | \
                     {:.2} mN ({} corners) | {:.2} mN |",
                    p95_of(&corners),
                    p95_of(&base),
                    shared(&base),
                    p95_of(&full),
                    shared(&full),
                    random[10],
                );
            }
        }
    }
}

/// A profile that names the wrong arm (the delta's on the PHANToM, `device.profile`) is caught
/// when the calibration is saved: the lattice is chosen with a warning naming the failed model,
/// and nothing crashes.
#[test]
fn a_profile_naming_the_wrong_arm_leaves_the_lattice_with_a_warning() {
    use hgcd::calibrate::persist::grid_file;
    use hgcd::control::compensation::GravityModel;
    let mut config = Config::default();
    config.device.profile = "falcon_delta".into();
    config.calibration.holds = hgcd::config::HoldPlan::All;
    let result = calibrated("phantom", &config);
    let spec = "sim:phantom".parse().unwrap();
    let file = grid_file(&result, &config, &spec);
    let model = file.model.clone().expect("a model record");
    assert!(
        model.chosen == "vector" || model.chosen == "scalar",
        "{model:?}"
    );
    let warning = model.warning.expect("a warning");
    assert!(warning.contains("arm model"), "{warning}");
    let gravity = GravityModel::configured(file, None, Default::default()).unwrap();
    assert_eq!(gravity.mode.to_string(), model.chosen);
    println!("{warning}\n{:?}", model.held_out_pct);
}

/// `device.profile` naming a profile file whose `[geometry_tolerances]` are all 0: the saved
/// arm keeps the profile's geometry, where the built-in profile's tolerances let the same
/// calibration (delta unit 1) estimate the unit's own.
#[test]
fn a_profile_with_exact_geometry_keeps_it_through_calibration() {
    use hgcd::calibrate::persist::grid_file;
    let dir = tempfile::tempdir().unwrap();
    let exact = dir.path().join("falcon_exact.toml");
    let shipped = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/profiles/falcon_delta.toml"),
    )
    .unwrap();
    std::fs::write(
        &exact,
        format!(
            "{shipped}\n[geometry_tolerances]\norigin_m = 0.0\nlength_share = 0.0\n\
             pivot_radius_m = 0.0\n"
        ),
    )
    .unwrap();
    let spec = "sim:delta".parse().unwrap();
    let mut config = Config::default();
    config.sim.unit_seed = 1;
    let arm_of = |config: &Config| {
        let file = grid_file(&calibrated("delta", config), config, &spec);
        let model = file.model.expect("a model record");
        assert_eq!(model.chosen, "arm", "{model:?}");
        file.arm.expect("an arm record")
    };
    let estimated = arm_of(&config);
    assert!(estimated.geometry_change.is_some(), "{estimated:?}");
    config.device.profile = exact.display().to_string();
    let kept = arm_of(&config);
    assert_eq!(kept.geometry_change, None);
    assert_eq!(
        kept.geometry,
        ArmTable::of(&profile_arm("delta", &Config::default()))
    );
}

/// Could the fit identify the unit's geometry too (where its frame sits, its link lengths), and
/// so take the delta's whole-workspace residual under 5 mN? A Levenberg–Marquardt search over
/// the frame's origin and the lengths around the arm fit, from the plant's exact holds and from
/// holds off by 0.13 % (what one stroke along the arm leaves, §7.1) and by up to 0.7 % (what
/// three strokes left): fitted freely (this test's own search) or as the calibration fits it,
/// held to the units' tolerances by a prior (`fit::geometry`). Its table is
/// docs/calibration.md §13.4; rerun with
/// `cargo test --release --test arm_model -- --ignored --nocapture the_geometry`.
#[test]
#[ignore = "about a minute: a question docs/calibration.md §13.4 answers"]
fn the_geometry_from_the_holds_only_with_holds_far_better_than_frictions() {
    use hgcd::arm::ArmGeometry;
    use nalgebra::{DMatrix, DVector};
    use rand::{Rng, SeedableRng};
    // Frame origin x, y, z (mm), two lengths (‰) and, for the delta, its base radius (mm).
    let placed = |arm: &Arm, p: &[f64]| {
        let mut a = *arm;
        a.frame.origin += Vector3::new(p[0], p[1], p[2]) * 1e-3;
        match &mut a.geometry {
            ArmGeometry::Delta(d) => {
                d.arm *= 1.0 + p[3] * 1e-3;
                d.rod *= 1.0 + p[4] * 1e-3;
                d.base_radius += p[5] * 1e-3;
            }
            ArmGeometry::Serial(s) => {
                s.upper *= 1.0 + p[3] * 1e-3;
                s.fore *= 1.0 + p[4] * 1e-3;
            }
        }
        a
    };
    // The holds' weighted residuals after the arm fit.
    let residual = |arm: &Arm, p: &[f64], holds: &[Hold]| {
        let arm = placed(arm, p);
        let fit = fit_arm(&arm, holds, 9.81, &[arm.up()]).ok()?;
        let r: Vec<f64> = holds
            .iter()
            .flat_map(|h| {
                let r = (h.force - fit.gravity.force(&h.position)) / h.noise;
                [r.x, r.y, r.z]
            })
            .collect();
        Some(DVector::from_vec(r))
    };
    let fitted = |arm: &Arm, n: usize, holds: &[Hold]| {
        let mut p = vec![0.0; n];
        let mut current = residual(arm, &p, holds).unwrap();
        let mut damping = 1e-2;
        for _ in 0..30 {
            let mut jacobian = DMatrix::zeros(current.len(), n);
            for k in 0..n {
                let (mut plus, mut minus) = (p.clone(), p.clone());
                plus[k] += 1e-3;
                minus[k] -= 1e-3;
                let (a, b) = (residual(arm, &plus, holds), residual(arm, &minus, holds));
                jacobian.set_column(k, &((a.unwrap() - b.unwrap()) / 2e-3));
            }
            let jtj = jacobian.transpose() * &jacobian;
            let jtr = jacobian.transpose() * &current;
            let mut improved = false;
            for _ in 0..8 {
                let mut lhs = jtj.clone();
                for k in 0..n {
                    lhs[(k, k)] += damping * (1.0 + jtj[(k, k)]);
                }
                let step = lhs.lu().solve(&-&jtr).unwrap();
                let next: Vec<f64> = p.iter().zip(step.iter()).map(|(a, b)| a + b).collect();
                match residual(arm, &next, holds) {
                    Some(r) if r.norm() < current.norm() => {
                        (p, current, improved) = (next, r, true);
                        damping *= 0.3;
                        break;
                    }
                    _ => damping *= 10.0,
                }
            }
            if !improved {
                break;
            }
        }
        placed(arm, &p)
    };
    println!("| device | unit | holds | hold error | profile's geometry | fitted, free | fitted, within the spread |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for model in ["delta", "phantom"] {
        for unit in [1u64, 2, 3] {
            let mut config = Config::default();
            config.sim.unit_seed = unit;
            let arm = profile_arm(model, &config);
            let cube = cube_holds(model, &config);
            let truth = reachable_truth(model, &config, 1000, 1).unwrap();
            let n = if model == "delta" { 6 } else { 5 };
            for corners in [true, false] {
                for error in [0.0, 0.0013, 0.007] {
                    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(unit);
                    let holds: Vec<Hold> = (0..27)
                        .filter(|n| !corners || [0, 2, 6, 8, 18, 20, 24, 26].contains(n))
                        .map(|n| {
                            let h = cube.holds[n].unwrap();
                            let off = Vector3::from_fn(|_, _| rng.gen_range(-1.0..1.0));
                            Hold::new(h.position, h.force + off * error * h.force.norm())
                        })
                        .collect();
                    let p95_mn = |fit: &hgcd::fit::ArmFit| {
                        let mut r: Vec<f64> = truth
                            .iter()
                            .map(|t| {
                                1e3 * (t.holding_force - fit.gravity.force(&t.position)).norm()
                            })
                            .collect();
                        r.sort_by(f64::total_cmp);
                        r[949]
                    };
                    println!(
                        "| sim:{model} | {unit} | {} | {:.2} % | {:.1} mN | {:.1} mN | {:.1} mN |",
                        if corners { "8 corners" } else { "27 vertices" },
                        100.0 * error,
                        p95_mn(&fit_arm(&arm, &holds, 9.81, &[arm.up()]).unwrap()),
                        p95_mn(&{
                            let free = fitted(&arm, n, &holds);
                            fit_arm(&free, &holds, 9.81, &[free.up()]).unwrap()
                        }),
                        p95_mn(
                            &fit_arm_and_geometry(
                                &arm,
                                &holds,
                                9.81,
                                &[arm.up()],
                                &GeometryTolerances::DEFAULT
                            )
                            .unwrap()
                            .0
                        ),
                    );
                }
            }
        }
    }
}

/// Issue 36's sweep after `hgcd check --apply`: on each arm (unit 1, 0.04 N at the handle), a
/// default calibration, then 30 g on the handle and the table tilted 5°: the stale model, the
/// model `hgcd check --apply` changed, and a fresh calibration of the changed device, each
/// against the changed plant's own force at 1000 random points of the whole reachable
/// workspace. Its table is docs/calibration.md §2.2; rerun with
/// `cargo test --release --test arm_model -- --ignored --nocapture whole_workspace_after_check`.
#[test]
#[ignore = "about a minute: the table of docs/calibration.md §2.2"]
fn whole_workspace_after_check_apply_on_every_arm() {
    use hgcd::calibrate::check::{self, CheckRequest, Verdict};
    use hgcd::calibrate::persist::grid_file;
    use hgcd::calibrate::{calibrate, CalibrateRequest};
    use hgcd::control::compensation::GravityModel;
    use hgcd::grid::GridFile;
    use hgcd::transport::Pacing;
    use hgcd::validate::sweep::{GridSweep, SweptGrid};
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    let sim = |extra: &str| {
        let text = format!("[sim]\ncoulomb_friction_n = 0.04\n{extra}");
        Config::from_toml_str(&text, std::path::Path::new("test")).unwrap()
    };
    let (base, changed) = (
        sim(""),
        sim("probe_mass_kg = 0.03\ngravity_direction = [0.0871557427, 0.0, 0.9961946981]\n"),
    );
    println!(
        "| device | model | stale p95 | applied p50 / p95 / p95 / max | the true change folded in \
         | fresh p50 / p95 / p95 / max |"
    );
    println!("| --- | --- | --- | --- | --- | --- |");
    for model in ["phantom", "delta", "woodenhaptics"] {
        let spec: hgcd::config::DeviceSpec = format!("sim:{model}").parse().unwrap();
        let state = tempfile::tempdir().unwrap();
        let no_stop = || Arc::new(AtomicBool::new(false));
        let request = CalibrateRequest {
            device: spec.clone(),
            pacing: Pacing::Virtual,
            output: None,
            state_dir: state.path().to_path_buf(),
        };
        calibrate(&base, &request, no_stop(), &mut |_| {}).unwrap();
        let request = CheckRequest {
            device: spec.clone(),
            pacing: Pacing::Virtual,
            grid: None,
            state_dir: state.path().to_path_buf(),
        };
        let mut found = check::check(&changed, &request, no_stop(), &mut |_| {}).unwrap();
        assert_eq!(found.verdict, Verdict::Apply, "{model}: {found:?}");
        check::apply(&mut found).unwrap();
        // The serial arms' base moments act under the tilt; the delta has none.
        assert_eq!(
            found.warning.is_some(),
            model != "delta",
            "{model}: {found:?}"
        );
        let truth = reachable_truth(model, &changed, 1000, 1).unwrap();
        let swept = |file: GridFile| {
            let gravity = GravityModel::configured(file.clone(), None, Default::default()).unwrap();
            GridSweep::new(&SweptGrid::new(gravity, &file), &truth)
        };
        let stale = swept(GridFile::load(found.applied.as_ref().unwrap()).unwrap());
        let applied = swept(GridFile::load(&found.grid).unwrap());
        // The change as the simulator made it, folded in the same way: what the fold itself
        // leaves, apart from what the check's two holds measured of the change.
        let exact = hgcd::grid::Change {
            payload_kg: 0.03,
            tilt: Vector3::y() * 5f64.to_radians(),
        };
        let stale_file = GridFile::load(found.applied.as_ref().unwrap()).unwrap();
        let folded = swept(
            stale_file
                .with_change(
                    &exact,
                    GridFile::load(&found.grid).unwrap().applied[0].clone(),
                )
                .unwrap(),
        );
        let fresh = swept(grid_file(&calibrated(model, &changed), &changed, &spec));
        let row = |s: &GridSweep| {
            format!(
                "{:.2} % / {:.2} % / {:.1} mN / {:.1} %",
                s.residual_pct.p50, s.residual_pct.p95, s.residual_mn.p95, s.residual_pct.max
            )
        };
        println!(
            "| sim:{model} | {} | {:.1} % | {} | {} | {} |",
            applied.model,
            stale.residual_pct.p95,
            row(&applied),
            row(&folded),
            row(&fresh)
        );
        assert!(
            stale.residual_pct.p95 > 3.0 * applied.residual_pct.p95,
            "{model}"
        );
    }
}
