//! `hgcd check` (issue 36, item 1): after a calibration, a changed handle or table is told from
//! an unchanged device and from something else, on every simulated device, in virtual time. The
//! truths are the simulator's: the payload it carries (`sim.probe_mass_kg`), the gravity
//! direction it is given (`sim.gravity_direction`), the spring it is attached to.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use hgcd::calibrate::check::{self, check, Check, CheckRequest, Verdict};
use hgcd::calibrate::{calibrate, CalibrateRequest};
use hgcd::config::Config;
use hgcd::grid::GridFile;
use hgcd::transport::Pacing;
use hgcd::validate::{self, Mode, Reading, ValidateRequest};

mod common;
use common::{hgcd, stdout_of};

/// A config of the simulated device with `sim` keys added (0.04 N at the handle on a linkage).
fn config(model: &str, sim: &str) -> Config {
    let friction = if model == "point-mass" {
        ""
    } else {
        "coulomb_friction_n = 0.04\n"
    };
    Config::from_toml_str(&format!("[sim]\n{friction}{sim}"), Path::new("test")).unwrap()
}

/// Calibrate `sim:MODEL` into `state` as `hgcd calibrate` does.
fn calibrate_into(model: &str, state: &Path) {
    calibrate_with(model, state, "");
}

/// Calibrate `sim:MODEL` with `sim` keys changed into `state`.
fn calibrate_with(model: &str, state: &Path, sim: &str) {
    let request = CalibrateRequest {
        device: format!("sim:{model}").parse().unwrap(),
        pacing: Pacing::Virtual,
        output: None,
        state_dir: state.to_path_buf(),
    };
    calibrate(
        &config(model, sim),
        &request,
        Arc::new(AtomicBool::new(false)),
        &mut |_| {},
    )
    .unwrap_or_else(|e| panic!("{model}: {e}"));
}

/// `hgcd check` of `sim:MODEL` with `sim` keys changed since the calibration in `state`.
fn check_with(model: &str, state: &Path, sim: &str) -> Check {
    let request = CheckRequest {
        device: format!("sim:{model}").parse().unwrap(),
        pacing: Pacing::Virtual,
        grid: None,
        state_dir: state.to_path_buf(),
    };
    check(
        &config(model, sim),
        &request,
        Arc::new(AtomicBool::new(false)),
        &mut |_| {},
    )
    .unwrap_or_else(|e| panic!("{model}: {e}"))
}

/// 5° about y: the table tilted so that gravity leans toward −x in the device frame.
const TILTED: &str = "gravity_direction = [0.0871557427, 0.0, 0.9961946981]\n";
const PAYLOAD: &str = "probe_mass_kg = 0.03\n";

fn assert_payload(found: &Check, grams: f64, what: &str) {
    assert_eq!(found.verdict, Verdict::Apply, "{what}: {found:?}");
    assert!(
        (found.payload_g - grams).abs() <= 2.0,
        "{what}: {} g",
        found.payload_g
    );
}

fn assert_tilt(found: &Check, degrees: f64, what: &str) {
    assert!(
        (found.tilt_deg - degrees).abs() <= 0.3,
        "{what}: {}°",
        found.tilt_deg
    );
    if degrees > 0.0 {
        // About y, the axis the table turned about (either sense names it): the rotation found
        // is within 1° of the table's (its axis is the less certain part, docs/calibration.md §2).
        let axis = nalgebra::Vector3::from(found.tilt_axis);
        let found_rotation = axis * found.tilt_deg * axis.y.signum();
        let error = (found_rotation - nalgebra::Vector3::y() * degrees).norm();
        println!(
            "{what}: {:.2}° about {axis:?}, {error:.2}° off",
            found.tilt_deg
        );
        assert!(
            error <= 1.0,
            "{what}: {:.2}° about {axis:?}",
            found.tilt_deg
        );
    }
}

#[test]
fn a_payload_a_tilt_or_both_are_told_from_an_unchanged_device_on_every_simulated_device() {
    for model in ["point-mass", "phantom", "delta", "woodenhaptics"] {
        let dir = tempfile::tempdir().unwrap();
        calibrate_into(model, dir.path());
        let same = check_with(model, dir.path(), "");
        assert_eq!(same.verdict, Verdict::Unchanged, "{model}: {same:?}");
        let payload = check_with(model, dir.path(), PAYLOAD);
        assert_payload(&payload, 30.0, model);
        assert_tilt(&payload, 0.0, model);
        let tilted = check_with(model, dir.path(), TILTED);
        assert_eq!(tilted.verdict, Verdict::Apply, "{model}: {tilted:?}");
        assert!(tilted.payload_g.abs() <= 2.0, "{model}: {tilted:?}");
        assert_tilt(&tilted, 5.0, model);
        let mut both = check_with(model, dir.path(), &format!("{PAYLOAD}{TILTED}"));
        assert_payload(&both, 30.0, model);
        assert_tilt(&both, 5.0, model);
        // Taken in, the model agrees with the changed device again on every device. On the
        // serial arms the warning says that their base moments, which a level calibration cannot
        // see (it leaves them out), would now act if the arm had any (docs/calibration.md §2.2).
        // A payload alone is taken in on every device.
        check::apply(&mut both).unwrap_or_else(|e| panic!("{model}: {e}"));
        let after = check_with(model, dir.path(), &format!("{PAYLOAD}{TILTED}"));
        let serial = matches!(model, "phantom" | "woodenhaptics");
        assert_eq!(both.warning.is_some(), serial, "{model}: {both:?}");
        assert_eq!(after.verdict, Verdict::Unchanged, "{model}: {after:?}");
        let payload_only = tempfile::tempdir().unwrap();
        calibrate_into(model, payload_only.path());
        let mut payload = check_with(model, payload_only.path(), PAYLOAD);
        check::apply(&mut payload).unwrap_or_else(|e| panic!("{model}: {e}"));
        let after_payload = check_with(model, payload_only.path(), PAYLOAD);
        assert_eq!(
            after_payload.verdict,
            Verdict::Unchanged,
            "{model}: {after_payload:?}"
        );
        let times = [same, payload, tilted, both, after, after_payload].map(|c| c.device_time_s);
        println!("{model}: device time {times:.1?} s");
        // The check starts its holds from the saved calibration (docs/calibration.md §2.1).
        assert!(
            times.iter().all(|&t| t <= 30.0),
            "{model}: device time {times:?} s"
        );
    }
}

/// A grid written before calibration recorded the encoder's step (`step_mm`) is checked after
/// the full initialisation, with the same answer.
#[test]
fn a_grid_without_the_initialisations_record_is_checked_after_a_full_initialisation() {
    let dir = tempfile::tempdir().unwrap();
    calibrate_into("woodenhaptics", dir.path());
    let quick = check_with("woodenhaptics", dir.path(), PAYLOAD);
    let path = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "toml"))
        .expect("the calibrated grid");
    let mut file = GridFile::load(&path).unwrap();
    file.calibration.as_mut().unwrap().step_mm = None;
    file.save_atomic(&path).unwrap();
    let full = check_with("woodenhaptics", dir.path(), PAYLOAD);
    assert_payload(&full, 30.0, "without step_mm");
    println!(
        "device time {:.1} s from the record, {:.1} s without",
        quick.device_time_s, full.device_time_s
    );
    assert!(
        full.device_time_s > quick.device_time_s + 5.0,
        "{} s, {} s",
        quick.device_time_s,
        full.device_time_s
    );
}

#[test]
fn a_spring_is_not_taken_for_a_payload_or_a_tilt() {
    let dir = tempfile::tempdir().unwrap();
    calibrate_into("point-mass", dir.path());
    let found = check_with(
        "point-mass",
        dir.path(),
        "spring_n_per_m = 20.0\nspring_anchor_mm = [0.0, 0.0, 50.0]\n",
    );
    assert_eq!(found.verdict, Verdict::Recalibrate, "{found:?}");
}

#[test]
fn an_unchanged_device_is_unchanged_in_ten_checks_of_ten() {
    let dir = tempfile::tempdir().unwrap();
    calibrate_into("phantom", dir.path());
    for seed in 1..=10 {
        let found = check_with("phantom", dir.path(), &format!("seed = {}\n", 100 + seed));
        assert_eq!(found.verdict, Verdict::Unchanged, "seed {seed}: {found:?}");
    }
}

/// A state directory with `sim:point-mass` calibrated into it by `hgcd calibrate`.
fn calibrated_point_mass() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    stdout_of(
        hgcd()
            .args(["--config", "/dev/null", "--state-dir"])
            .arg(dir.path())
            .args(["calibrate", "--device", "sim:point-mass"]),
    );
    dir
}

#[test]
fn hgcd_check_says_its_verdict_in_its_exit_status_and_in_json() {
    let dir = calibrated_point_mass();
    let state = dir.path().to_str().unwrap();
    let text = stdout_of(hgcd().args([
        "--config",
        "/dev/null",
        "--state-dir",
        state,
        "check",
        "--device",
        "sim:point-mass",
    ]));
    assert!(
        text.starts_with("unchanged: the model fits both holds"),
        "{text}"
    );
    let heavier = dir.path().join("heavier.toml");
    std::fs::write(&heavier, format!("[sim]\n{PAYLOAD}")).unwrap();
    let out = hgcd()
        .args(["--log-level", "warn", "--config"])
        .arg(&heavier)
        .args([
            "--state-dir",
            state,
            "check",
            "--device",
            "sim:point-mass",
            "--json",
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(4), "{out:?}");
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["verdict"], "apply");
    assert!(
        (json["payload_g"].as_f64().unwrap() - 30.0).abs() <= 2.0,
        "{json}"
    );
    for key in ["tilt_deg", "tilt_axis", "device_time_s"] {
        assert!(!json[key].is_null(), "{key}: {json}");
    }
}

/// The grid calibration wrote into `state` (named after the unit where the device names one).
fn grid_in(state: &Path) -> std::path::PathBuf {
    std::fs::read_dir(state)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "toml"))
        .expect("a grid")
}

/// `hgcd validate` of `sim:MODEL` with `sim` keys changed, compensating with the grid in `state`:
/// the arm model's (or on the point mass the vector lattice's) two-sided mean penalty and its
/// worst point, as shares of the ideal m_p g / k.
fn validate_with(model: &str, state: &Path, sim: &str) -> (f64, f64) {
    let compensated = if model == "point-mass" {
        Mode::Vector
    } else {
        Mode::Arm
    };
    let request = ValidateRequest {
        device: format!("sim:{model}").parse().unwrap(),
        pacing: Pacing::Virtual,
        grid: Some(grid_in(state)),
        out: state.join("validation"),
        probe_mass: 0.03,
        stiffness: 1000.0,
        repetitions: 10,
        // The one mode read here: the others would only triple the experiment.
        modes: vec![compensated],
        sweep: None,
    };
    let mut config = config(model, sim);
    config.servo.lock_memory = false;
    if model == "woodenhaptics" {
        // Its encoders' 65 µm steps, as the shipped validation configs set them
        // (config/validate-woodenhaptics-unit-*.toml, docs/devices.md §5).
        config.estimate.noise_bound_mm = 0.035;
        config.validation.eps_s_mm = 0.2;
    }
    let run = validate::prepare(&config, &request)
        .unwrap()
        .run(Arc::new(AtomicBool::new(false)), &mut |_| {})
        .unwrap();
    let report = &run.report;
    let m = report.modes.iter().find(|m| m.mode == compensated).unwrap();
    let r = m.of(Reading::TwoSided);
    assert_eq!(r.unsettled, 0, "{model}");
    let worst = r
        .points
        .iter()
        .map(|p| (p.mean / report.ideal - 1.0).abs())
        .fold(0.0, f64::max);
    (r.mean / report.ideal - 1.0, worst)
}

/// Issue 36's must-show for `--apply`: a 30 g payload and a 5° tilt found on the PHANToM, taken
/// in, compensate as a fresh calibration does: `hgcd validate` on the changed device gives a mean
/// penalty within 2 % of the ideal and every point within 5 %. Uncorrected, the same model
/// misses by far more. The other devices: `check_apply_validates_on_every_device` (ignored).
#[test]
fn a_payload_and_tilt_applied_on_the_phantom_compensate_as_a_fresh_calibration() {
    let changed = format!("{PAYLOAD}{TILTED}");
    let dir = tempfile::tempdir().unwrap();
    calibrate_into("phantom", dir.path());
    let (stale, _) = validate_with("phantom", dir.path(), &changed);
    let mut found = check_with("phantom", dir.path(), &changed);
    check::apply(&mut found).unwrap();
    // A serial arm's base moments, measured on a level base, now act: the user is told
    // (the whole-workspace sweep of docs/calibration.md §2.2 shows why).
    let warning = found.warning.as_deref().unwrap_or_default();
    assert!(warning.contains("base moments"), "{found:?}");
    let (mean, worst) = validate_with("phantom", dir.path(), &changed);
    println!(
        "phantom: stale model {:+.1} %; applied {:+.1} %, worst point {:.1} %",
        stale * 1e2,
        mean * 1e2,
        worst * 1e2
    );
    assert!(stale.abs() > 0.2, "the stale model: {:+.1} %", stale * 1e2);
    assert!(mean.abs() <= 0.02, "mean {:+.1} %", mean * 1e2);
    assert!(worst <= 0.05, "worst point {:.1} %", worst * 1e2);
}

/// The same on every simulated device (0.04 N at the handle on the linkages), after a check
/// with both changes and `--apply`; beside each, a fresh calibration of the changed device
/// validated the same way. Summary in docs/calibration.md §2.2:
/// `cargo test --release --test check -- --ignored --nocapture check_apply_validates`.
#[test]
#[ignore = "about a minute: the four devices calibrated twice and validated twice"]
fn check_apply_validates_on_every_device() {
    let changed = format!("{PAYLOAD}{TILTED}");
    for model in ["point-mass", "phantom", "delta", "woodenhaptics"] {
        let dir = tempfile::tempdir().unwrap();
        calibrate_into(model, dir.path());
        let mut found = check_with(model, dir.path(), &changed);
        assert_eq!(found.verdict, Verdict::Apply, "{model}: {found:?}");
        check::apply(&mut found).unwrap();
        let (mean, worst) = validate_with(model, dir.path(), &changed);
        let fresh = tempfile::tempdir().unwrap();
        calibrate_with(model, fresh.path(), &changed);
        let (fresh_mean, fresh_worst) = validate_with(model, fresh.path(), &changed);
        println!(
            "{model}: applied {:+.2} %, worst point {:.1} %; fresh calibration {:+.2} %, worst \
             point {:.1} %; check {:.1} s of device time",
            mean * 1e2,
            worst * 1e2,
            fresh_mean * 1e2,
            fresh_worst * 1e2,
            found.device_time_s
        );
    }
}

/// `--apply` writes the change and keeps the model before beside it; `--revert` puts that back
/// and keeps the applied one in its turn; a verdict of "recalibrate" writes nothing.
#[test]
fn apply_keeps_the_model_before_and_revert_puts_it_back() {
    let dir = calibrated_point_mass();
    let state = dir.path().to_str().unwrap();
    let grid = dir.path().join("sim-point-mass.toml");
    let kept = dir.path().join("sim-point-mass.toml.bak");
    let calibrated = std::fs::read_to_string(&grid).unwrap();
    let sprung = dir.path().join("sprung.toml");
    std::fs::write(
        &sprung,
        "[sim]\nspring_n_per_m = 20.0\nspring_anchor_mm = [0.0, 0.0, 50.0]\n",
    )
    .unwrap();
    let check_cli = |config: &Path, extra: &[&str]| {
        hgcd()
            .args(["--log-level", "warn", "--config"])
            .arg(config)
            .args(["--state-dir", state, "check", "--device", "sim:point-mass"])
            .args(extra)
            .output()
            .unwrap()
    };
    let out = check_cli(&sprung, &["--apply"]);
    assert_eq!(out.status.code(), Some(5), "{out:?}");
    assert_eq!(std::fs::read_to_string(&grid).unwrap(), calibrated);
    assert!(!kept.exists());

    let heavier = dir.path().join("heavier.toml");
    std::fs::write(&heavier, format!("[sim]\n{PAYLOAD}")).unwrap();
    let out = check_cli(&heavier, &["--apply", "--json"]);
    assert_eq!(out.status.code(), Some(4), "{out:?}");
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["applied"], kept.to_str().unwrap(), "{json}");
    let applied = std::fs::read_to_string(&grid).unwrap();
    assert_eq!(std::fs::read_to_string(&kept).unwrap(), calibrated);
    let file = GridFile::load(&grid).unwrap();
    assert_eq!(file.applied.len(), 1);
    assert!((file.applied[0].payload_g - 30.0).abs() <= 2.0, "{applied}");
    assert!(file.applied[0].at.is_some());
    // Every vertex carries the payload's weight more (the point mass's lattice, upright).
    let before = GridFile::load(&kept).unwrap();
    for (m, m0) in file.grid.masses.iter().zip(&before.grid.masses) {
        assert!((m - m0 - file.applied[0].payload_g * 1e-3).abs() < 1e-9);
    }
    let out = check_cli(&heavier, &[]);
    assert_eq!(out.status.code(), Some(0), "{out:?}");

    let out = check_cli(&heavier, &["--revert"]);
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("no change applied since its calibration"),
        "{text}"
    );
    assert_eq!(std::fs::read_to_string(&grid).unwrap(), calibrated);
    assert_eq!(std::fs::read_to_string(&kept).unwrap(), applied);
    let out = check_cli(&heavier, &["--revert"]);
    assert!(out.status.success(), "{out:?}");
    assert_eq!(std::fs::read_to_string(&grid).unwrap(), applied);
}

/// A check stopped (Ctrl-C) with `--apply` asked for leaves the grid as it was and keeps no
/// backup: nothing is written before the measurement is whole. The stop is asked for before the
/// servo loop's first tick: a check of the point mass takes 3.5 s of device time, a few
/// milliseconds of wall time, over before a stop asked for at its first event could land.
#[test]
fn a_check_interrupted_leaves_the_model_untouched() {
    let dir = calibrated_point_mass();
    let grid = dir.path().join("sim-point-mass.toml");
    let calibrated = std::fs::read_to_string(&grid).unwrap();
    let request = CheckRequest {
        device: "sim:point-mass".parse().unwrap(),
        pacing: Pacing::Virtual,
        grid: None,
        state_dir: dir.path().to_path_buf(),
    };
    let stop = Arc::new(AtomicBool::new(true));
    let found = check(&config("point-mass", PAYLOAD), &request, stop, &mut |_| {});
    assert!(
        matches!(
            found,
            Err(check::CheckError::Measure(
                hgcd::calibrate::CalibrateError::Aborted
            ))
        ),
        "{found:?}"
    );
    assert_eq!(std::fs::read_to_string(&grid).unwrap(), calibrated);
    assert!(!dir.path().join("sim-point-mass.toml.bak").exists());
}

/// `hgcd check --via-daemon` (issue 36 item 1): the running daemon measures the two holds on its
/// own device; with `--apply` it takes the payload into its grid and compensates it at once, so a
/// second check finds the device unchanged. The daemon runs `sim:point-mass` in virtual time
/// with 30 g more than its calibration saw.
#[test]
fn a_running_daemon_checks_its_device_and_applies_what_it_finds() {
    let dir = calibrated_point_mass();
    let state = dir.path().to_str().unwrap();
    let elsewhere = tempfile::tempdir().unwrap();
    let heavier = elsewhere.path().join("heavier.toml");
    std::fs::write(&heavier, format!("[sim]\n{PAYLOAD}")).unwrap();
    let socket = elsewhere.path().join("hgcd.sock");
    let with_daemon = |level: &str, args: &[&str]| {
        let mut c = hgcd();
        c.args(["--log-level", level, "--config"])
            .arg(&heavier)
            .args(["--state-dir", state, "--socket"])
            .arg(&socket)
            .args(args);
        c
    };
    let (daemon, stderr, _) = common::spawn_until(
        &mut with_daemon(
            "info",
            &["run", "--device", "sim:point-mass", "--virtual-time"],
        ),
        "hgcd running on",
    );
    // Stopped however the test ends (it runs in virtual time until then).
    struct Killed(std::process::Child);
    impl Drop for Killed {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let daemon = Killed(daemon);
    // Its log, read so that it never blocks on a full pipe.
    let log = std::thread::spawn(move || std::io::read_to_string(stderr).unwrap_or_default());
    let check = |args: &[&str]| {
        let out = with_daemon(
            "warn",
            &[&["check", "--via-daemon", "--yes", "--json"], args].concat(),
        )
        .output()
        .unwrap();
        let json: serde_json::Value =
            serde_json::from_slice(&out.stdout).unwrap_or_else(|_| panic!("{out:?}"));
        (out.status.code(), json)
    };
    let (code, found) = check(&[]);
    assert_eq!(code, Some(4), "{found}");
    assert!(
        (found["payload_g"].as_f64().unwrap() - 30.0).abs() <= 2.0,
        "{found}"
    );
    let grid = grid_in(dir.path());
    let before = std::fs::read_to_string(&grid).unwrap();
    let (code, applied) = check(&["--apply"]);
    assert_eq!(code, Some(4), "{applied}");
    assert!(!applied["applied"].is_null(), "{applied}");
    assert!(
        applied["warning"].is_null(),
        "a point mass has no base: {applied}"
    );
    let after = GridFile::load(&grid).unwrap();
    assert_eq!(after.applied.len(), 1);
    assert_ne!(std::fs::read_to_string(&grid).unwrap(), before);
    // The daemon compensates the changed grid at once: the gravity force it renders is the
    // changed grid's, 30 g heavier than the one before, and a check finds nothing left.
    let config = Config::default();
    let model = |file: GridFile| {
        let c = &config.compensation;
        hgcd::control::compensation::GravityModel::configured(file, c.mode, c.outside_grid).unwrap()
    };
    let (changed, stale) = (
        model(after),
        model(GridFile::from_toml_str(&before, &grid).unwrap()),
    );
    let mut observer =
        hgcd::client::Client::connect(&socket, hgcd::client::Role::Observe, "observer").unwrap();
    observer.set_read_timeout(Some(common::WAIT)).unwrap();
    observer.subscribe(1000.0).unwrap();
    // The hub swaps the model in before it answers, and the servo thread takes it at its next
    // tick: until then it holds the handle where the check left it, rendering no gravity.
    let s = (0..10_000)
        .map(|_| observer.next_state().unwrap())
        .find(|s| s.gravity.is_some_and(|g| g != [0.0; 3]))
        .expect("the hold after the check ends");
    let (x, rendered) = (
        nalgebra::Vector3::from(s.position),
        nalgebra::Vector3::from(s.gravity.expect("the gravity force rendered")),
    );
    assert!((rendered - changed.force(&x)).norm() < 1e-9, "{s:?}");
    let added = (changed.force(&x) - stale.force(&x)).norm();
    assert!((added - 0.03 * 9.81).abs() < 0.003, "{added} N added");
    drop(observer);
    let (code, again) = check(&[]);
    assert_eq!(code, Some(0), "{again}");
    // `--revert --via-daemon` puts the calibration's model back, and the daemon compensates with
    // it at once: the force it renders is the stale model's again, and a check finds the 30 g.
    let out = with_daemon("warn", &["check", "--revert", "--via-daemon"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(said.contains("put back the model kept beside"), "{said}");
    assert!(
        said.contains("the daemon compensates with it now"),
        "{said}"
    );
    assert_eq!(std::fs::read_to_string(&grid).unwrap(), before);
    let mut observer =
        hgcd::client::Client::connect(&socket, hgcd::client::Role::Observe, "observer").unwrap();
    observer.set_read_timeout(Some(common::WAIT)).unwrap();
    observer.subscribe(1000.0).unwrap();
    let rendered_stale = (0..10_000)
        .map(|_| observer.next_state().unwrap())
        .any(|s| {
            let x = nalgebra::Vector3::from(s.position);
            s.gravity
                .is_some_and(|g| (nalgebra::Vector3::from(g) - stale.force(&x)).norm() < 1e-9)
        });
    assert!(rendered_stale, "the daemon renders the model put back");
    drop(observer);
    let (code, stale_again) = check(&[]);
    assert_eq!(code, Some(4), "{stale_again}");
    // Another client owning the force keeps a check from moving the handle, and a revert from
    // changing its force.
    let mut owner =
        hgcd::client::Client::connect(&socket, hgcd::client::Role::Control, "owner").unwrap();
    owner.set_read_timeout(Some(common::WAIT)).unwrap();
    let out = with_daemon("warn", &["check", "--via-daemon", "--yes"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("only it may start a check"),
        "{out:?}"
    );
    let out = with_daemon("warn", &["check", "--revert", "--via-daemon"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("only it may put back a model"),
        "{out:?}"
    );
    drop(owner);
    drop(daemon);
    let log = log.join().unwrap();
    assert!(log.contains("check: Apply"), "{log}");
}
