//! The discrepancy workflow (`hgcd record`, `hgcd analyze`) on logs of the simulated point mass
//! and PHANToM, and on logs a test writes as other software would, with physical effects hidden
//! in the plant (none, one, two, or in no candidate): the effects are named and measured against
//! the simulator's own parameters, never against what the code printed; what is left is said to
//! be unexplained; bad logs get one line. `cargo test --release --test discrepancy --
//! --nocapture` prints the tables of docs/discrepancy.md §6.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use nalgebra::Vector3;

use hgcd::config::Config;
use hgcd::control::compensation::GravityModel;
use hgcd::discrepancy::analysis::{self, Signals};
use hgcd::discrepancy::effects::ArmInertia;
use hgcd::discrepancy::{self, AnalyzeRequest, Effect, RecordRequest};
use hgcd::grid::{GridFile, MassGrid};
use hgcd::transport::Pacing;

mod common;
use common::hgcd;

/// The nominal model: the simulator's own field, uniform 120 g under gravity along −z, on the
/// ±40 mm cube (the calibration would find it within 1 %: tests/calibration.rs).
fn nominal_grid(dir: &Path) -> PathBuf {
    let path = dir.join("grid.toml");
    let grid = MassGrid::uniform(
        0.12,
        9.81,
        Vector3::z(),
        Vector3::repeat(-0.04),
        0.04,
        [3, 3, 3],
    );
    GridFile::from(grid).save_atomic(&path).unwrap();
    path
}

/// A hidden effect: what the plant gets, and the truth of the parameter analyze must find.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Hidden {
    None,
    Payload(f64),
    Coulomb(f64),
    Viscous(f64),
    /// Degrees, about x (false) or y (true).
    Tilt(f64, bool),
    /// N/m, anchor mm.
    Spring(f64, [f64; 3]),
    /// The actuators render the force late, ms.
    Delay(f64),
    /// The position is reported late, ms.
    SensingDelay(f64),
    /// Outside the library: motor cogging, N and pitch mm.
    Cogging(f64, f64),
    /// Outside the library: the x actuator renders this share of its command.
    ScaleX(f64),
    /// Outside the library: the table vibrates, N at Hz.
    Vibration(f64, f64),
}

impl Hidden {
    /// The effect `hgcd analyze` names for it (None: none in its library).
    fn effect(self) -> Option<Effect> {
        Some(match self {
            Hidden::None => Effect::None,
            Hidden::Payload(_) => Effect::Payload,
            Hidden::Coulomb(_) => Effect::CoulombFriction,
            Hidden::Viscous(_) => Effect::ViscousDamping,
            Hidden::Tilt(..) => Effect::GravityTilt,
            Hidden::Spring(..) => Effect::Spring,
            Hidden::Delay(_) | Hidden::SensingDelay(_) => Effect::TimeDelay,
            Hidden::Cogging(..) | Hidden::ScaleX(_) | Hidden::Vibration(..) => return None,
        })
    }

    fn apply(self, config: &mut Config) {
        let sim = &mut config.sim;
        match self {
            Hidden::None => {}
            Hidden::Payload(kg) => sim.probe_mass_kg = kg,
            Hidden::Coulomb(n) => sim.coulomb_friction_n = n,
            Hidden::Viscous(b) => sim.damping_n_s_per_m = b,
            Hidden::Tilt(deg, about_y) => {
                let (s, c) = deg.to_radians().sin_cos();
                sim.gravity_direction = if about_y { [s, 0.0, c] } else { [0.0, -s, c] };
            }
            Hidden::Spring(k, anchor) => {
                sim.spring_n_per_m = k;
                sim.spring_anchor_mm = anchor;
            }
            Hidden::Delay(ms) => sim.force_delay_ms = ms,
            Hidden::SensingDelay(ms) => sim.position_delay_ms = ms,
            Hidden::Cogging(n, pitch) => {
                sim.cogging_n = n;
                sim.cogging_pitch_mm = pitch;
            }
            Hidden::ScaleX(share) => sim.force_scale = [share, 1.0, 1.0],
            Hidden::Vibration(n, hz) => {
                sim.vibration_n = n;
                sim.vibration_hz = hz;
            }
        }
    }

    /// (the parameter's name in summary.json, its true value in SI units)
    fn truth(self) -> Option<(&'static str, f64)> {
        match self {
            Hidden::None | Hidden::Cogging(..) | Hidden::ScaleX(_) | Hidden::Vibration(..) => None,
            Hidden::Payload(kg) => Some(("mass_kg", kg)),
            Hidden::Coulomb(n) => Some(("force_n", n)),
            Hidden::Viscous(b) => Some(("damping_n_s_per_m", b)),
            Hidden::Tilt(deg, _) => Some(("angle_deg", deg)),
            Hidden::Spring(k, _) => Some(("stiffness_n_per_m", k)),
            Hidden::Delay(ms) | Hidden::SensingDelay(ms) => Some(("delay_s", ms * 1e-3)),
        }
    }
}

/// Record 40 s of the point mass with `hidden` and noise seed `seed`, analyse it against the
/// nominal grid; the summary.
fn record_and_analyze(dir: &Path, grid: &Path, hidden: &[Hidden], seed: u64) -> serde_json::Value {
    record_and_analyze_on("point-mass", dir, grid, hidden, seed)
}

/// [`record_and_analyze`] on `sim:MODEL`.
fn record_and_analyze_on(
    model: &str,
    dir: &Path,
    grid: &Path,
    hidden: &[Hidden],
    seed: u64,
) -> serde_json::Value {
    let recording = record_on(model, dir, grid, hidden, seed).unwrap();
    assert!(!recording.interrupted);
    // Only a loop delay rings the excitation's loop (docs/discrepancy.md §1).
    let delayed = hidden
        .iter()
        .any(|h| matches!(h, Hidden::Delay(_) | Hidden::SensingDelay(_)));
    assert!(delayed || recording.softenings.is_empty(), "{hidden:?}");
    analyze(dir, grid, &dir.join("log.csv"))
}

/// `hgcd record` of 40 s on `sim:MODEL` with `hidden` in the plant, into `dir/log.csv`.
fn record_on(
    model: &str,
    dir: &Path,
    grid: &Path,
    hidden: &[Hidden],
    seed: u64,
) -> Result<discrepancy::Recording, discrepancy::RecordError> {
    let mut config = Config::default();
    config.sim.seed = seed;
    for h in hidden {
        h.apply(&mut config);
    }
    record_with(config, model, dir, grid)
}

/// `hgcd record` of 40 s on `sim:MODEL` configured by `config`, into `dir/log.csv`.
fn record_with(
    mut config: Config,
    model: &str,
    dir: &Path,
    grid: &Path,
) -> Result<discrepancy::Recording, discrepancy::RecordError> {
    config.servo.lock_memory = false;
    let log = dir.join("log.csv");
    // `hgcd record` never replaces a file: the previous case's log goes first.
    let _ = std::fs::remove_file(&log);
    let request = RecordRequest {
        device: format!("sim:{model}").parse().unwrap(),
        pacing: Pacing::Virtual,
        grid: Some(grid.to_path_buf()),
        out: log.clone(),
        duration: 40.0,
    };
    discrepancy::record(
        &config,
        &request,
        Arc::new(AtomicBool::new(false)),
        &mut |_| {},
    )
}

/// `hgcd analyze` of `log` against `grid` into `dir/analysis`; the summary. In a release build
/// every analysis of the suite (each log at most 40 s at 1 kHz) must take at most
/// [`ANALYZE_SECONDS`] of this thread's CPU time: issue 41's bound, checked on the work done
/// and not on the wall clock, which a loaded machine stretches (`cargo bench --bench analyze`
/// gives the wall time, docs/performance.md).
fn analyze(dir: &Path, grid: &Path, log: &Path) -> serde_json::Value {
    let out = dir.join("analysis");
    let _ = std::fs::remove_dir_all(&out);
    let start = thread_cpu_seconds();
    discrepancy::analyze(
        &AnalyzeRequest {
            grid: grid.to_path_buf(),
            log: log.to_path_buf(),
            out: out.clone(),
        },
        &mut |_| {},
    )
    .unwrap();
    let used = thread_cpu_seconds() - start;
    assert!(
        cfg!(debug_assertions) || used <= ANALYZE_SECONDS,
        "hgcd analyze of {} took {used:.2} s of CPU time (bound {ANALYZE_SECONDS} s)",
        log.display()
    );
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

/// The most CPU time one analysis of a 40 s, 1 kHz log may take, s (release build).
const ANALYZE_SECONDS: f64 = 5.0;

/// CPU time this thread has used so far, s (`hgcd analyze` runs on its caller's thread).
fn thread_cpu_seconds() -> f64 {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes the timespec it is given, nothing else.
    assert_eq!(
        unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) },
        0
    );
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// The names in `summary.json`'s `effects`.
fn named(summary: &serde_json::Value) -> Vec<String> {
    summary["effects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["name"].as_str().unwrap().to_string())
        .collect()
}

/// One line for a case's summary.
fn line(hidden: &[Hidden], seed: u64, summary: &serde_json::Value) -> String {
    format!(
        "{hidden:?}, seed {seed}: named {:?}, {:.4} → {:.4} N, floor {:.4} N (position part \
         {:.4} N), unexplained {} (by {}), limits {}; {}",
        named(summary),
        summary["error_before"].as_f64().unwrap(),
        summary["error_after"].as_f64().unwrap(),
        summary["noise_floor_n"].as_f64().unwrap(),
        summary["noise_floor"]["from_position_n"].as_f64().unwrap(),
        summary["unexplained"],
        summary["unexplained_where"]["by"],
        summary["limits"]
            .as_array()
            .unwrap()
            .iter()
            .map(|l| format!(
                "{}: {}",
                l["check"].as_str().unwrap(),
                l["message"].as_str().unwrap()
            ))
            .collect::<Vec<_>>()
            .join(" | "),
        summary["parameters"]
    )
}

/// Every candidate alone at two magnitudes (small and large for a lab device) and two noise
/// seeds, and five clean logs.
fn suite() -> Vec<(Hidden, u64)> {
    let hidden = [
        Hidden::Payload(0.01),
        Hidden::Payload(0.05),
        Hidden::Coulomb(0.02),
        Hidden::Coulomb(0.08),
        Hidden::Viscous(0.5),
        Hidden::Viscous(3.0),
        Hidden::Tilt(2.0, true),
        Hidden::Tilt(8.0, false),
        Hidden::Spring(10.0, [0.0, 0.0, 0.0]),
        Hidden::Spring(60.0, [30.0, -20.0, 50.0]),
        Hidden::Delay(2.0),
        Hidden::Delay(8.0),
    ];
    let mut cases: Vec<(Hidden, u64)> = hidden.iter().flat_map(|&h| [(h, 1), (h, 2)]).collect();
    cases.extend((1..=5).map(|seed| (Hidden::None, seed)));
    cases
}

#[test]
fn each_hidden_effect_is_named_measured_and_removed_and_clean_logs_name_none() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let names: Vec<&str> = std::iter::once(Effect::None)
        .chain(Effect::CANDIDATES)
        .map(Effect::name)
        .collect();
    // confusion[hidden][named]
    let mut confusion = vec![vec![0usize; names.len()]; names.len()];
    let (mut hidden_cases, mut named_right) = (0, 0);
    for (hidden, seed) in suite() {
        let summary = record_and_analyze(dir.path(), &grid, &[hidden], seed);
        let named = summary["effect"].as_str().unwrap();
        let (before, after) = (
            summary["error_before"].as_f64().unwrap(),
            summary["error_after"].as_f64().unwrap(),
        );
        let truth = hidden.effect().unwrap().name();
        let row = names.iter().position(|n| *n == truth).unwrap();
        let column = names.iter().position(|n| *n == named).unwrap();
        confusion[row][column] += 1;
        let case = format!("{hidden:?}, seed {seed}: named {named}, {before:.4} → {after:.4} N");
        println!("{case}");
        if hidden == Hidden::None {
            // Clean: nothing named, nothing unexplained, the residual at the log's own floor.
            assert_eq!(named, "none", "{case}");
            assert_eq!(summary["effects"], serde_json::json!([]), "{case}");
            assert_eq!(summary["unexplained"], false, "{case}");
            let floor = summary["noise_floor_n"].as_f64().unwrap();
            assert!(after <= 2.0 * floor, "{case}: floor {floor} N");
            continue;
        }
        hidden_cases += 1;
        if named != truth {
            continue;
        }
        named_right += 1;
        // Held-out error at least halved.
        assert!(after <= 0.5 * before, "{case}");
        let (key, value) = hidden.truth().unwrap();
        let fitted = summary["parameters"][key].as_f64().unwrap();
        assert!(
            (fitted / value - 1.0).abs() <= 0.2,
            "{case}: {key} = {fitted}, truth {value}"
        );
    }
    println!("\n| hidden \\ named | {} |", names.join(" | "));
    println!("| --- |{}", " --- |".repeat(names.len()));
    for (name, row) in names.iter().zip(&confusion) {
        let cells: Vec<String> = row.iter().map(|n| n.to_string()).collect();
        println!("| {name} | {} |", cells.join(" | "));
    }
    assert!(
        named_right as f64 >= 0.95 * hidden_cases as f64,
        "{named_right} of {hidden_cases} named right"
    );
}

#[test]
fn a_tilt_is_measured_about_the_right_axis_and_the_gap_shrinks_in_position_too() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let summary = record_and_analyze(dir.path(), &grid, &[Hidden::Tilt(5.0, true)], 3);
    assert_eq!(summary["effect"], "gravity_tilt");
    // Gravity turned from −z toward −x: a rotation about y.
    let axis: Vec<f64> =
        serde_json::from_value(summary["parameters"]["rotation_axis"].clone()).unwrap();
    assert!(axis[1].abs() > 0.99, "{axis:?}");
    // The closed-loop simulation of the run tracks the measured position better with the tilt.
    let before = summary["position_error_before_m"].as_f64().unwrap();
    let after = summary["position_error_after_m"].as_f64().unwrap();
    assert!(after < 0.5 * before, "{before} → {after} m");
    // Everything the report links to is there.
    let out = dir.path().join("analysis");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    for name in [
        "residual_velocity",
        "residual_position",
        "residual_lagged_command",
        "residual_spectrum",
        "before_after",
    ] {
        assert!(report.contains(&format!("({name}.svg)")), "{name}");
        for ext in ["svg", "png"] {
            let bytes = std::fs::metadata(out.join(format!("{name}.{ext}")))
                .unwrap()
                .len();
            assert!(bytes > 5_000, "{name}.{ext}: {bytes} bytes");
        }
    }
    let model = std::fs::read_to_string(out.join("model.toml")).unwrap();
    assert!(model.contains("name = \"gravity_tilt\""), "{model}");
    GridFile::load(&out.join("grid.toml")).unwrap();
}

/// `hgcd analyze` on `log` (text) against `grid`: exit status and stderr.
fn analyze_cli(dir: &Path, grid: &Path, log: &str) -> (bool, String) {
    let path = dir.join("bad.csv");
    std::fs::write(&path, log).unwrap();
    let out = hgcd()
        .args(["--log-level", "warn", "analyze", "--grid"])
        .arg(grid)
        .arg("--log")
        .arg(&path)
        .arg("--out")
        .arg(dir.join("bad-out"))
        .output()
        .unwrap();
    let stderr: String = String::from_utf8_lossy(&out.stderr)
        .lines()
        .filter(|l| !l.starts_with("analyze: "))
        .map(|l| format!("{l}\n"))
        .collect();
    (out.status.success(), stderr)
}

#[test]
fn bad_logs_get_one_clear_line_and_no_report() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let rows = |n: usize, f: &dyn Fn(usize) -> String| -> String {
        let mut s = String::from("t,x,y,z,fx,fy,fz\n");
        for k in 0..n {
            s += &f(k);
        }
        s
    };
    let good = |k: usize| {
        let t = k as f64 * 1e-3;
        format!("{t},{},0,0,0,0,1.18\n", 0.01 * (6.0 * t).sin())
    };
    for (log, says) in [
        ("t,x,y,z,fx,fy\n0,0,0,0,0,0\n".to_string(), "no column `fz`"),
        (
            rows(20_000, &|k| {
                if k == 500 {
                    "0.5,0,0,0,0,0,NaN\n".into()
                } else {
                    good(k)
                }
            }),
            "line 502: `fz` is NaN",
        ),
        (
            rows(20_000, &|k| if k == 700 { good(699) } else { good(k) }),
            "repeats the row before",
        ),
        (
            rows(20_000, &|k| if k == 900 { good(100) } else { good(k) }),
            "goes back",
        ),
        (rows(3000, &good), "3.0 s of data"),
        (
            rows(20_000, &|k| {
                format!("{},0.5,0,0,0,0,1.18\n", k as f64 * 1e-3)
            }),
            "lie outside the grid",
        ),
        (
            rows(20_000, &|k| format!("{},0,0,0,0,0,1.18\n", k as f64 * 1e-3)),
            "does not excite the model",
        ),
        (
            format!("# device = sim-other-unit\n{}", rows(20_000, &good)),
            "recorded on sim-other-unit",
        ),
        // Issue 40: one absurd row became "effect: spring" with k = −1.9e298, or "the handle
        // hardly moved"; absurd gains and a half reference were accepted.
        (
            rows(20_000, &|k| {
                if k == 4000 {
                    "4,0,0,0,1e300,0,1.18\n".into()
                } else {
                    good(k)
                }
            }),
            "line 4002: `fx` is 1e300: beyond ±1000 N",
        ),
        (
            rows(20_000, &|k| {
                if k == 4000 {
                    "4,1e308,0,0,0,0,1.18\n".into()
                } else {
                    good(k)
                }
            }),
            "line 4002: `x` is 1e308: beyond ±10 m",
        ),
        (
            format!("# stiffness_n_per_m = nan\n{}", rows(20_000, &good)),
            "line 1: `stiffness_n_per_m` is `nan`: expected a number above 0, up to 100000",
        ),
        (
            format!("# damping_n_s_per_m = -1e300\n{}", rows(20_000, &good)),
            "`damping_n_s_per_m` is `-1e300`: expected a number from 0 to 1000",
        ),
        (
            "t,x,y,z,fx,fy,fz,fz\n0,0,0,0,0,0,0,0\n".to_string(),
            "the header names `fz` twice (columns 7 and 8)",
        ),
        (
            "t,x,y,z,fx,fy,fz,xr\n0,0,0,0,0,0,0,0\n".to_string(),
            "has some of `xr,yr,zr` but not all three",
        ),
    ] {
        let mut foreign = GridFile::load(&grid).unwrap();
        if says.contains("other-unit") {
            foreign.device = Some(hgcd::grid::DeviceRecord {
                id: "sim-point-mass".into(),
                spec: None,
                model: None,
                serial: None,
            });
        }
        let grid_here = dir.path().join("grid-here.toml");
        foreign.save_atomic(&grid_here).unwrap();
        let (ok, stderr) = analyze_cli(dir.path(), &grid_here, &log);
        assert!(!ok, "{says}");
        assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
        assert!(stderr.contains(says), "{stderr}");
        assert!(!dir.path().join("bad-out/summary.json").exists(), "{says}");
    }
}

#[test]
fn hgcd_run_compensates_a_named_payload_or_spring_and_leaves_friction_alone() {
    use hgcd::config::DeviceSpec;
    use hgcd::grid::DeviceIdentity;
    use hgcd::sim::SimDevice;
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let device = DeviceIdentity {
        spec: "sim:point-mass".parse::<DeviceSpec>().unwrap(),
        info: None,
    };
    let points = [
        Vector3::new(0.0, 0.0, 0.0),
        Vector3::new(0.03, -0.02, 0.01),
        Vector3::new(-0.035, 0.03, -0.025),
    ];
    for hidden in [
        vec![Hidden::Payload(0.03)],
        vec![Hidden::Spring(40.0, [10.0, 0.0, -20.0])],
        vec![Hidden::Coulomb(0.05)],
        // Two at once: the payload's weight turned with the grid's force.
        vec![Hidden::Payload(0.03), Hidden::Tilt(3.0, true)],
        vec![
            Hidden::Spring(40.0, [10.0, 0.0, -20.0]),
            Hidden::Coulomb(0.05),
        ],
    ] {
        let summary = record_and_analyze(dir.path(), &grid, &hidden, 1);
        let mut got = named(&summary);
        got.sort();
        assert_eq!(got, expected(&hidden, false).0, "{hidden:?}");
        let mut config = Config::default();
        config.compensation.effect_file = Some(dir.path().join("analysis/model.toml"));
        let model = hgcd::daemon::load_model(&config, &device, &grid)
            .unwrap()
            .unwrap();
        for x in points {
            // What holds the plant with the hidden effect still at x (friction holds nothing).
            let mut plant = Config::default();
            plant.sim.start_position_mm = (x * 1e3).into();
            for h in &hidden {
                h.apply(&mut plant);
            }
            let truth = SimDevice::from_config("point-mass", &plant)
                .unwrap()
                .plant()
                .holding_force();
            let error = (model.force(&x) - truth).norm();
            assert!(error < 2e-3, "{hidden:?} at {x:?}: off by {error} N");
        }
    }
}

#[test]
fn a_recording_stopped_early_leaves_a_valid_shorter_log() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let mut config = Config::default();
    config.servo.lock_memory = false;
    let log = dir.path().join("log.csv");
    let request = RecordRequest {
        device: "sim:point-mass".parse().unwrap(),
        pacing: Pacing::Virtual,
        grid: Some(grid),
        out: log.clone(),
        duration: 40.0,
    };
    // Ctrl-C (the stop flag) once a third is recorded.
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let recording = discrepancy::record(&config, &request, stop, &mut |share| {
        if share > 0.3 {
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
        }
    })
    .unwrap();
    assert!(recording.interrupted);
    let written = hgcd::discrepancy::log::Log::load(&log).unwrap();
    assert!(
        written.duration() > 10.0 && written.duration() < 39.0,
        "{} s",
        written.duration()
    );
    assert_eq!(written.len(), recording.log.len());

    // Stopped before the first tick: one line, and no empty log left behind.
    let error = discrepancy::record(
        &config,
        &RecordRequest {
            out: dir.path().join("never.csv"),
            ..request
        },
        Arc::new(AtomicBool::new(true)),
        &mut |_| {},
    )
    .unwrap_err();
    assert!(
        matches!(error, discrepancy::RecordError::NothingRecorded(false)),
        "{error}"
    );
    assert!(!dir.path().join("never.csv").exists());
}

/// Why `hgcd record` on the simulated point mass, recording `duration` s with `grid` into `out`,
/// refuses to start; the device must not move.
fn refused_recording(grid: &Path, out: &Path, duration: f64) -> discrepancy::RecordError {
    let mut config = Config::default();
    config.servo.lock_memory = false;
    let request = RecordRequest {
        device: "sim:point-mass".parse().unwrap(),
        pacing: Pacing::Virtual,
        grid: Some(grid.to_path_buf()),
        out: out.to_path_buf(),
        duration,
    };
    discrepancy::record(
        &config,
        &request,
        Arc::new(AtomicBool::new(false)),
        &mut |_| panic!("the device must not move"),
    )
    .unwrap_err()
}

/// `hgcd record --out` onto the grid it compensates with, onto another log or onto anything
/// else that is there is refused before the device moves, and the file is left as it was
/// (issue 40: `--grid G --out G` replaced the grid with a log and exited 0).
#[test]
fn a_recording_never_replaces_a_file_that_is_there() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let other = dir.path().join("old-log.csv");
    std::fs::write(&other, "t,x,y,z,fx,fy,fz\n").unwrap();
    for out in [&grid, &other] {
        let before = std::fs::read(out).unwrap();
        let refused = refused_recording(&grid, out, 10.0);
        assert!(
            matches!(&refused, discrepancy::RecordError::OutExists(p) if p == out),
            "{refused}"
        );
        assert!(
            refused.to_string().contains("choose another --out"),
            "{refused}"
        );
        assert_eq!(std::fs::read(out).unwrap(), before);
    }
}

/// A recording longer than the rows `hgcd analyze` reads is refused before the device moves
/// (issue 40: a 3600 s log at 1 kHz could be recorded but not analysed).
#[test]
fn a_recording_longer_than_analyze_reads_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("log.csv");
    let refused = refused_recording(&nominal_grid(dir.path()), &out, 1001.0);
    assert_eq!(
        refused.to_string(),
        "--duration 1001 s at 1000 Hz gives more than the 1000000 rows hgcd analyze reads: \
         record at most 1000 s"
    );
    assert!(!out.exists());
}

/// The seven effects of the pair table, at a small and a large magnitude for a lab device.
fn library(large: bool) -> [Hidden; 7] {
    let pick = |small: Hidden, big: Hidden| if large { big } else { small };
    [
        pick(Hidden::Payload(0.01), Hidden::Payload(0.04)),
        pick(Hidden::Tilt(2.0, true), Hidden::Tilt(6.0, false)),
        pick(
            Hidden::Spring(15.0, [0.0; 3]),
            Hidden::Spring(50.0, [30.0, -20.0, 50.0]),
        ),
        pick(Hidden::Coulomb(0.02), Hidden::Coulomb(0.06)),
        pick(Hidden::Viscous(0.5), Hidden::Viscous(2.0)),
        pick(Hidden::Delay(2.0), Hidden::Delay(6.0)),
        pick(Hidden::SensingDelay(2.0), Hidden::SensingDelay(6.0)),
    ]
}

/// What `hgcd analyze` must answer for `hidden`: the effects named (sorted), the parameters
/// and their truth, and the effects a `confounded` limit must name instead. A payload's weight
/// or a tilt beside a spring on a uniform field is a constant force the spring's anchor takes
/// (docs/discrepancy.md §3); the two delays add up (§2). On an arm a tilt turns its links'
/// weights, a force that changes with the pose, which a spring's anchor does not take: with
/// `tilt_told` it must then be named beside the spring and measured.
fn expected(
    hidden: &[Hidden],
    tilt_told: bool,
) -> (
    Vec<&'static str>,
    Vec<(&'static str, f64)>,
    Vec<&'static str>,
) {
    let spring = hidden.iter().any(|h| matches!(h, Hidden::Spring(..)));
    let mut names = Vec::new();
    let mut truths: Vec<(&'static str, f64)> = Vec::new();
    let mut confounded = Vec::new();
    for h in hidden {
        let (Some(effect), Some((key, value))) = (h.effect(), h.truth()) else {
            continue;
        };
        let told = tilt_told && matches!(h, Hidden::Tilt(..));
        if spring && !told && matches!(h, Hidden::Payload(_) | Hidden::Tilt(..)) {
            confounded.push(effect.name());
            continue;
        }
        match truths.iter_mut().find(|(k, _)| *k == key) {
            // Both delays: their sum.
            Some((_, v)) => *v += value,
            None => {
                names.push(effect.name());
                truths.push((key, value));
            }
        }
    }
    names.sort();
    (names, truths, confounded)
}

/// Checks one case's summary against what it hides; the failures, as lines. A tilt beside a
/// spring may be reported confounded or, on an arm (`arm`), named and measured.
fn check(hidden: &[Hidden], summary: &serde_json::Value, arm: bool) -> Vec<String> {
    let mut got = named(summary);
    got.sort();
    let told = arm && expected(hidden, true).0 == got;
    let (names, truths, confounded) = expected(hidden, told);
    let mut failures = Vec::new();
    if got != names {
        failures.push(format!("named {got:?}, hidden {names:?}"));
        return failures;
    }
    for (key, value) in truths {
        let fitted = summary["parameters"][key].as_f64().unwrap();
        if (fitted / value - 1.0).abs() > 0.2 {
            failures.push(format!("{key} = {fitted}, truth {value}"));
        }
    }
    let limits = summary["limits"].as_array().unwrap();
    for effect in confounded {
        let said = limits.iter().any(|l| {
            l["check"] == "confounded" && l["effects"].as_array().unwrap().contains(&effect.into())
        });
        if !said {
            failures.push(format!("no `confounded` limit for {effect}"));
        }
    }
    let (before, after) = (
        summary["error_before"].as_f64().unwrap(),
        summary["error_after"].as_f64().unwrap(),
    );
    // Halved above the log's noise floor (on the point mass, the floor is a tenth of any gap).
    let floor = summary["noise_floor_n"].as_f64().unwrap();
    let above = |e: f64| (e * e - floor * floor).max(0.0).sqrt();
    if !names.is_empty() && above(after) > 0.5 * above(before) {
        failures.push(format!(
            "held-out error {before} → {after} N, not halved above the floor {floor} N"
        ));
    }
    if summary["unexplained"] != false {
        failures.push("unexplained".into());
    }
    failures
}

/// Every pair of the seven effects, hidden together at the small magnitudes (one seed; the
/// ignored `every_pair_at_two_magnitudes_and_two_seeds` runs the whole table): the named set is
/// the hidden set, each parameter within 20 %, the held-out error at least halved, nothing
/// unexplained.
#[test]
fn every_pair_of_effects_is_named_as_a_set_and_measured() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let effects = library(false);
    let mut failures = Vec::new();
    for i in 0..effects.len() {
        for j in i + 1..effects.len() {
            let hidden = [effects[i], effects[j]];
            let summary = record_and_analyze(dir.path(), &grid, &hidden, 1);
            println!("{}", line(&hidden, 1, &summary));
            for f in check(&hidden, &summary, false) {
                failures.push(format!("{hidden:?}: {f}"));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The table of docs/discrepancy.md §6: each effect alone and every pair, at two magnitudes and
/// two seeds. `cargo test --release --test discrepancy -- --ignored --nocapture every_pair_at`
#[test]
#[ignore]
fn every_pair_at_two_magnitudes_and_two_seeds() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let failures = sweep("point-mass", dir.path(), &grid, library);
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Each effect of `library(large)` alone and every pair of them, small and large, two seeds,
/// on `sim:MODEL` against `grid`; a line per case and a summary printed; the failures.
fn sweep(model: &str, dir: &Path, grid: &Path, library: fn(bool) -> [Hidden; 7]) -> Vec<String> {
    let (mut cases, mut failures) = (0, Vec::new());
    let started = std::time::Instant::now();
    let mut slowest: f64 = 0.0;
    for large in [false, true] {
        let effects = library(large);
        let mut sets: Vec<Vec<Hidden>> = effects.iter().map(|e| vec![*e]).collect();
        for i in 0..effects.len() {
            for j in i + 1..effects.len() {
                sets.push(vec![effects[i], effects[j]]);
            }
        }
        for hidden in &sets {
            for seed in [1, 2] {
                let summary = record_and_analyze_on(model, dir, grid, hidden, seed);
                slowest = slowest.max(summary["wall_time_s"].as_f64().unwrap());
                cases += 1;
                let f = check(hidden, &summary, model != "point-mass");
                println!(
                    "{}{}",
                    line(hidden, seed, &summary),
                    if f.is_empty() {
                        String::new()
                    } else {
                        format!(" FAILED {f:?}")
                    }
                );
                failures.extend(
                    f.into_iter()
                        .map(|f| format!("{hidden:?} seed {seed}: {f}")),
                );
            }
        }
    }
    println!(
        "{cases} cases, {} failed; slowest analysis {slowest:.2} s; {:.0} s in all",
        failures.len(),
        started.elapsed().as_secs_f64()
    );
    failures
}

/// A payload beside a spring has no least-squares answer: its weight is a constant force, which
/// the spring's anchor takes, and its inertia is the handle's mass (an arm's) or the moving
/// mass's. The fit refuses that set: on the delta, rounding left its pivot some 1e-14 of its
/// norm and the fit answered with parameters of any size. The spring is named and the payload
/// reported `confounded` with it.
#[test]
fn a_payload_beside_a_spring_is_never_fitted_together_and_is_reported_confounded() {
    let dir = tempfile::tempdir().unwrap();
    let grid = calibrated("delta", dir.path());
    let hidden = [Hidden::Payload(0.03), Hidden::Spring(30.0, [0.0; 3])];
    record_on("delta", dir.path(), &grid, &hidden, 1).unwrap();
    let log_path = dir.path().join("log.csv");
    let log = discrepancy::log::Log::load(&log_path).unwrap();
    let file = GridFile::load(&grid).unwrap();
    let arm = file.arm.as_ref().map(|a| a.geometry.arm().unwrap());
    let outside = Config::default().compensation.outside_grid;
    let model = GravityModel::configured(file, None, outside).unwrap();
    let mut signals = Signals::new(&log, &model, arm.as_ref());
    assert!(signals.arm);
    // As `hgcd analyze` fits it: the delta's arms' inertia constant (its platform the handle's
    // mass).
    analysis::nominal(&mut signals).unwrap();
    assert_eq!(signals.arm_inertia(), ArmInertia::Constant);
    assert!(analysis::fit(&[Effect::Spring], &signals).is_some());
    assert!(analysis::fit(&[Effect::Spring, Effect::Payload], &signals).is_none());
    let summary = analyze(dir.path(), &grid, &log_path);
    assert_eq!(named(&summary), ["spring"], "{summary}");
    let confounded = summary["limits"].as_array().unwrap().iter().any(|l| {
        l["check"] == "confounded" && l["message"].as_str().unwrap().starts_with("payload")
    });
    assert!(confounded, "{}", summary["limits"]);
}

/// Effects in no candidate (motor cogging: a force of the position; a table's vibration: a
/// force of time) are never covered by a wrong name: `unexplained` with nothing named, or with
/// the library effect beside them named, and the residual ordered by what makes it.
#[test]
fn a_force_in_no_candidate_is_unexplained_and_never_named() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    for (hidden, names, by) in [
        (vec![Hidden::Cogging(0.05, 5.0)], vec![], "position"),
        (vec![Hidden::Vibration(0.05, 7.0)], vec![], "frequency"),
        (
            vec![Hidden::Cogging(0.05, 5.0), Hidden::Payload(0.02)],
            vec!["payload"],
            "position",
        ),
        (
            vec![Hidden::Vibration(0.05, 7.0), Hidden::Spring(20.0, [0.0; 3])],
            vec!["spring"],
            "frequency",
        ),
    ] {
        let summary = record_and_analyze(dir.path(), &grid, &hidden, 1);
        let case = line(&hidden, 1, &summary);
        println!("{case}");
        assert_eq!(named(&summary), names, "{case}");
        assert_eq!(summary["unexplained"], true, "{case}");
        assert_eq!(summary["unexplained_where"]["by"], by, "{case}");
        assert_eq!(
            summary["effect"],
            names.first().copied().unwrap_or("none"),
            "{case}"
        );
    }
    // An actuator gain of 0.9 along x, the axis without gravity, is a moving mass of m/0.9
    // along x to the analysis (docs/discrepancy.md §3): nothing to name, nothing left.
    let hidden = [Hidden::ScaleX(0.9)];
    let summary = record_and_analyze(dir.path(), &grid, &hidden, 1);
    let case = line(&hidden, 1, &summary);
    assert_eq!(named(&summary), Vec::<String>::new(), "{case}");
    assert_eq!(summary["unexplained"], false, "{case}");
    let along_x = summary["parameters"]["moving_mass_kg"][0].as_f64().unwrap();
    assert!((along_x / (0.12 / 0.9) - 1.0).abs() < 0.03, "{case}");
}

/// A log written the way other software would (docs/log-format.md): its own point mass (120 g
/// under gravity, with `payload` kg more and viscous damping `damping`), its own PD controller
/// (K = 150 N/m, D = 5 N·s/m, velocity from a 5-sample difference) on its own reference, at
/// 500 Hz, positions quantised to 5 µm with 2 µm of noise; no reference columns, no comments.
/// `reference(t)` is the trajectory it tracks.
fn foreign_log(
    path: &Path,
    payload: f64,
    damping: f64,
    duration: f64,
    reference: &dyn Fn(f64) -> Vector3<f64>,
) {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let noise = Normal::new(0.0, 2e-6).unwrap();
    let (period, substeps) = (2e-3, 20);
    let (m0, g) = (0.12, 9.81);
    let mass = m0 + payload;
    let (mut x, mut v) = (reference(0.0), Vector3::zeros());
    let mut measured: Vec<Vector3<f64>> = Vec::new();
    let mut text = String::from("t,x,y,z,fx,fy,fz\n");
    let steps = (duration / period) as usize;
    for k in 0..steps {
        let t = k as f64 * period;
        let xm = x.map(|c| ((c + noise.sample(&mut rng)) / 5e-6).round() * 5e-6);
        measured.push(xm);
        let back = measured.len().saturating_sub(6);
        let velocity =
            (xm - measured[back]) / (((measured.len() - 1 - back).max(1)) as f64 * period);
        let r = reference(t);
        let r_dot = (reference(t + 1e-3) - reference(t - 1e-3)) / 2e-3;
        let force = Vector3::new(0.0, 0.0, m0 * g) + (r - xm) * 150.0 + (r_dot - velocity) * 5.0;
        text += &format!(
            "{t:.6},{:.9},{:.9},{:.9},{:.6},{:.6},{:.6}\n",
            xm.x, xm.y, xm.z, force.x, force.y, force.z
        );
        let dt = period / f64::from(substeps);
        for _ in 0..substeps {
            let a = (force - Vector3::new(0.0, 0.0, mass * g) - v * damping) / mass;
            v += a * dt;
            x += v * dt;
        }
    }
    std::fs::write(path, text).unwrap();
}

/// Logs of other software with a slower excitation than `hgcd record`'s: the same answers where
/// the log shows the effects, and the log's limits named where it cannot.
#[test]
fn logs_of_other_software_with_a_slower_excitation_get_the_same_answers_or_their_limits() {
    let dir = tempfile::tempdir().unwrap();
    let grid = nominal_grid(dir.path());
    let log = dir.path().join("foreign.csv");
    // Slow sweeps up to 1.6 Hz with a 1 s hold every 5 s, 60 s.
    let slow = |t: f64| -> Vector3<f64> {
        // The trajectory's own time stops for the hold.
        let t = 4.0 * (t / 5.0).floor() + (t % 5.0).min(4.0);
        let w = std::f64::consts::TAU;
        Vector3::new(
            0.012 * (w * 0.23 * t).sin() + 0.004 * (w * 1.1 * t).sin(),
            0.012 * (w * 0.31 * t + 1.0).sin() + 0.004 * (w * 1.3 * t).sin(),
            0.012 * (w * 0.37 * t + 2.0).sin() + 0.004 * (w * 1.6 * t).sin(),
        )
    };
    foreign_log(&log, 0.02, 1.0, 60.0, &slow);
    let summary = analyze(dir.path(), &grid, &log);
    let case = line(&[Hidden::Payload(0.02), Hidden::Viscous(1.0)], 0, &summary);
    println!("{case}");
    let mut got = named(&summary);
    got.sort();
    assert_eq!(got, ["payload", "viscous_damping"], "{case}");
    let p = &summary["parameters"];
    assert!(
        (p["mass_kg"].as_f64().unwrap() / 0.02 - 1.0).abs() < 0.2,
        "{case}"
    );
    assert!(
        (p["damping_n_s_per_m"].as_f64().unwrap() - 1.0).abs() < 0.2,
        "{case}"
    );
    assert_eq!(summary["unexplained"], false, "{case}");

    // Only slow motion along x: no delay can show (not tried), nor a spring along y or z.
    let _ = std::fs::remove_file(&log);
    foreign_log(&log, 0.02, 0.0, 60.0, &|t| {
        Vector3::new(0.015 * (std::f64::consts::TAU * 0.2 * t).sin(), 0.0, 0.0)
    });
    let summary = analyze(dir.path(), &grid, &log);
    let case = line(&[Hidden::Payload(0.02)], 0, &summary);
    println!("{case}");
    assert_eq!(named(&summary), ["payload"], "{case}");
    let checks: Vec<&str> = summary["limits"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["check"].as_str().unwrap())
        .collect();
    for check in ["fast_motion", "travel_y", "travel_z", "holds"] {
        assert!(checks.contains(&check), "{check}: {case}");
    }
    let tried: Vec<&str> = summary["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["effect"].as_str().unwrap())
        .collect();
    assert!(!tried.contains(&"time_delay"), "{tried:?}");
}

/// A clean calibration of `sim:MODEL` (default configuration) into the fresh `dir`: its grid.
fn calibrated(model: &str, dir: &Path) -> PathBuf {
    let out = hgcd()
        .args([
            "--config",
            "/dev/null",
            "--log-level",
            "warn",
            "--state-dir",
        ])
        .arg(dir)
        .args(["calibrate", "--device", &format!("sim:{model}")])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The grid is named after the device's id (sim-phantom, woodenhaptics_v2015): the one
    // .toml the calibration wrote into the fresh `dir`.
    let grids: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    assert_eq!(grids.len(), 1, "{grids:?}");
    grids[0].clone()
}

/// The seven effects at magnitudes a linkage's noise floor lets show (sim:phantom: about
/// 0.025 N), small and large.
fn linkage_library(large: bool) -> [Hidden; 7] {
    if large {
        [
            Hidden::Payload(0.06),
            Hidden::Tilt(5.0, true),
            Hidden::Spring(60.0, [30.0, -20.0, 50.0]),
            Hidden::Coulomb(0.1),
            Hidden::Viscous(3.0),
            Hidden::Delay(6.0),
            Hidden::SensingDelay(6.0),
        ]
    } else {
        [
            Hidden::Payload(0.03),
            Hidden::Tilt(3.0, true),
            Hidden::Spring(30.0, [0.0; 3]),
            Hidden::Coulomb(0.06),
            Hidden::Viscous(2.0),
            Hidden::Delay(5.0),
            Hidden::SensingDelay(5.0),
        ]
    }
}

/// A clean log of `model` recorded and analysed: its summary and its line; the line goes into
/// `failures` if anything is named, `unexplained` is said, or more than twice the floor or
/// twice its position part is left. That part, the position's noise through the model's
/// derivatives, is what a model that holds the device's physics leaves; the floor's other
/// part, the command's noise, overestimates it here (docs/discrepancy.md, Limitations).
fn clean_log_on(
    model: &str,
    dir: &Path,
    grid: &Path,
    seed: u64,
    failures: &mut Vec<String>,
) -> (serde_json::Value, String) {
    let summary = record_and_analyze_on(model, dir, grid, &[Hidden::None], seed);
    let case = line(&[Hidden::None], seed, &summary);
    println!("{case}");
    let floor = summary["noise_floor_n"].as_f64().unwrap();
    let position_part = summary["noise_floor"]["from_position_n"].as_f64().unwrap();
    let after = summary["error_after"].as_f64().unwrap();
    if !named(&summary).is_empty()
        || summary["unexplained"] != false
        || after > 2.0 * floor
        || after > 2.0 * position_part
    {
        failures.push(case.clone());
    }
    (summary, case)
}

/// The PHANToM, calibrated clean: its nominal model is its arm's (inertia, joint friction,
/// gravity model), so a clean log names nothing and stays within twice its noise floor (five
/// seeds; it leaves less than the floor, which this device's quantised command overestimates),
/// its inertia varies with the pose where nothing else hides that, and each effect alone is
/// named and measured against the simulator's truth.
#[test]
fn on_the_phantom_a_clean_log_names_nothing_and_each_effect_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let grid = calibrated("phantom", dir.path());
    let mut failures = Vec::new();
    for seed in 1..=5 {
        let (summary, case) = clean_log_on("phantom", dir.path(), &grid, seed, &mut failures);
        // The nominal model's own joint friction is the plant's: 0.01 N m of Coulomb friction
        // on each joint (src/sim/phantom.rs, the published drives).
        let joints: Vec<f64> =
            serde_json::from_value(summary["parameters"]["joint_coulomb_friction_n_m"].clone())
                .unwrap();
        if joints.iter().any(|f| (f / 0.01 - 1.0).abs() > 0.2) {
            failures.push(format!(
                "{case}: joint Coulomb friction {joints:?} N m, truth 0.01"
            ));
        }
    }
    // A serial arm's inertia changes with its pose: with neither friction nor position noise
    // (the encoders' steps only) the inertia first order in the pose wins by more than the
    // margin; with the joints' friction the constant one generalises better (above).
    let mut ideal = Config::default();
    ideal.sim.friction_scale = 0.0;
    ideal.sim.noise_mm = 0.0;
    record_with(ideal, "phantom", dir.path(), &grid).unwrap();
    let summary = analyze(dir.path(), &grid, &dir.path().join("log.csv"));
    let inertia = &summary["parameters"]["joint_inertia_in_pose"];
    if inertia != "first_order" {
        failures.push(format!("frictionless, noiseless: inertia {inertia}"));
    }
    for hidden in linkage_library(false) {
        let summary = record_and_analyze_on("phantom", dir.path(), &grid, &[hidden], 1);
        println!("{}", line(&[hidden], 1, &summary));
        for f in check(&[hidden], &summary, true) {
            failures.push(format!("{hidden:?}: {f}"));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The delta, a parallel linkage, takes the PHANToM's path (its arm's nominal model): a clean
/// log names nothing and stays within twice its floor (two seeds), and its nominal model finds
/// the plant's platform and joint friction; a spring, a payload and a 10° tilt are each named
/// alone and measured. (Leaving the samples where a joint rests out of the fit, not only
/// scoring them for the torque beyond its friction, names a 72 g payload beside the spring
/// here: its inertia takes up what the arm's inertia, first order in the pose, leaves.)
#[test]
fn on_the_delta_a_clean_log_names_nothing_and_a_spring_a_payload_or_a_tilt_is_named_alone() {
    let dir = tempfile::tempdir().unwrap();
    let grid = calibrated("delta", dir.path());
    let mut failures = Vec::new();
    for seed in 1..=2 {
        let (summary, case) = clean_log_on("delta", dir.path(), &grid, seed, &mut failures);
        // The nominal unit's platform and grip, 45 g, with half of each leg's 10 g
        // parallelogram, and 0.004 N m of Coulomb friction on each joint (src/sim/delta.rs,
        // docs/simulated-devices.md). Its arms turn about fixed axes: a constant inertia.
        let parameters = &summary["parameters"];
        let handle = parameters["handle_mass_kg"].as_f64().unwrap();
        let joints: Vec<f64> =
            serde_json::from_value(parameters["joint_coulomb_friction_n_m"].clone()).unwrap();
        if (handle / 0.060 - 1.0).abs() > 0.1
            || joints.iter().any(|f| (f / 0.004 - 1.0).abs() > 0.2)
            || parameters["joint_inertia_in_pose"] != "constant"
        {
            failures.push(format!(
                "{case}: handle {handle} kg (truth 0.060), joint Coulomb friction {joints:?} \
                 N m (truth 0.004), inertia {}",
                parameters["joint_inertia_in_pose"]
            ));
        }
    }
    for (hidden, seed) in [
        (Hidden::Spring(30.0, [0.0; 3]), 1),
        (Hidden::Payload(0.03), 2),
        (Hidden::Tilt(10.0, true), 1),
    ] {
        let summary = record_and_analyze_on("delta", dir.path(), &grid, &[hidden], seed);
        println!("{}", line(&[hidden], seed, &summary));
        for f in check(&[hidden], &summary, true) {
            failures.push(format!("{hidden:?}: {f}"));
        }
        // The arm's gravity turned whole, not to first order (which left −(δ²/2) F_G, taken up
        // by a payload of −1.4 g beside a 10.17° tilt).
        if let Hidden::Tilt(degrees, _) = hidden {
            let found = summary["parameters"]["angle_deg"].as_f64();
            if found.is_none_or(|found| (found / degrees - 1.0).abs() >= 0.01) {
                failures.push(format!("tilt {found:?}°, truth {degrees}°"));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// A loop delay the excitation's PD cannot damp: on the PHANToM (a handle of a few tens of
/// grams), 5 ms on each side rings the default loop (K = 200 N/m, D = 9 N·s/m) into the 8 N
/// force limit within half a second. `hgcd record` halves the damping, holds the handle still
/// and records again from the start: the log stays under half the limit, its comments give the
/// gains it was recorded with, and the analysis finds the loop's 10 ms (the sum,
/// docs/discrepancy.md §2.2) within 20 %, nothing else named. A delay no gains damp stops the
/// run.
#[test]
fn a_loop_delay_that_rings_into_the_force_limit_softens_the_excitation() {
    let dir = tempfile::tempdir().unwrap();
    let grid = calibrated("phantom", dir.path());
    let hidden = [Hidden::Delay(5.0), Hidden::SensingDelay(5.0)];
    let recording = record_on("phantom", dir.path(), &grid, &hidden, 1).unwrap();
    let softened: Vec<_> = recording
        .softenings
        .iter()
        .map(|s| (s.to.stiffness, s.to.damping))
        .collect();
    assert_eq!(softened, [(200.0, 4.5)], "{:?}", recording.softenings);
    let log = &recording.log;
    let saved = std::fs::read_to_string(dir.path().join("log.csv")).unwrap();
    assert!(
        saved.contains("# stiffness_n_per_m = 200\n")
            && saved.contains("# damping_n_s_per_m = 4.5\n"),
        "the log's comments give the gains it was recorded with"
    );
    assert!(log.duration() > 39.9, "the whole run, recorded again");
    let largest = log.force.iter().map(|f| f.norm()).fold(0.0, f64::max);
    // Far from the safety layer's limit: under half of it. (A ringing loop's peak is chaotic:
    // 1.97 N on this log before the strokes read the joints' friction where each pass held the
    // handle, 2.05 N after, from a calibration a fraction of a millinewton apart.)
    let limit = Config::default().safety.max_force_n;
    assert!(
        largest < 0.5 * limit,
        "the softened loop pushed {largest} N (limit {limit} N)"
    );
    let summary = analyze(dir.path(), &grid, &dir.path().join("log.csv"));
    let case = line(&hidden, 1, &summary);
    assert_eq!(named(&summary), ["time_delay"], "{case}");
    let delay = summary["parameters"]["delay_ms"].as_f64().unwrap();
    assert!((delay / 10.0 - 1.0).abs() < 0.2, "{case}");

    // A loop delay no gains of the excitation's damp (20 ms each side): the run softens as far
    // as it goes, then stops with one clear error, and no log is written.
    let hidden = [Hidden::Delay(20.0), Hidden::SensingDelay(20.0)];
    let error = record_on("phantom", dir.path(), &grid, &hidden, 1).unwrap_err();
    // The softest gains: K / 4 and D / 4.
    assert!(
        matches!(error, discrepancy::RecordError::Unstable(e, _)
            if (e.stiffness, e.damping) == (50.0, 2.25)),
        "{error}"
    );
    let message = error.to_string();
    assert!(
        message.contains("stayed unstable") && message.contains("no log was written"),
        "{message}"
    );
    assert!(!dir.path().join("log.csv").exists());
}

/// On the PHANToM, what `hgcd analyze` finds is what `hgcd run` then compensates: a payload on
/// a tilted table turns the arm model's gravity and adds the payload's weight turned with it;
/// the force matches the plant's own holding force where the calibration measured.
#[test]
fn on_the_phantom_hgcd_run_compensates_a_named_payload_on_a_tilted_table() {
    use hgcd::config::DeviceSpec;
    use hgcd::grid::DeviceIdentity;
    use hgcd::sim::SimDevice;
    let dir = tempfile::tempdir().unwrap();
    let grid = calibrated("phantom", dir.path());
    let hidden = [Hidden::Payload(0.03), Hidden::Tilt(3.0, true)];
    let summary = record_and_analyze_on("phantom", dir.path(), &grid, &hidden, 1);
    let mut got = named(&summary);
    got.sort();
    assert_eq!(
        got,
        ["gravity_tilt", "payload"],
        "{}",
        line(&hidden, 1, &summary)
    );
    let device = DeviceIdentity {
        spec: "sim:phantom".parse::<DeviceSpec>().unwrap(),
        info: None,
    };
    let without = hgcd::daemon::load_model(&Config::default(), &device, &grid)
        .unwrap()
        .unwrap();
    let mut config = Config::default();
    config.compensation.effect_file = Some(dir.path().join("analysis/model.toml"));
    let model = hgcd::daemon::load_model(&config, &device, &grid)
        .unwrap()
        .unwrap();
    let file = GridFile::load(&grid).unwrap();
    let centre = file.grid.origin + file.grid.far_corner();
    for offset in [
        Vector3::zeros(),
        Vector3::new(0.015, -0.015, 0.01),
        Vector3::new(-0.015, 0.015, -0.01),
    ] {
        let x = centre / 2.0 + offset;
        let mut plant = Config::default();
        plant.sim.start_position_mm = (x * 1e3).into();
        for h in &hidden {
            h.apply(&mut plant);
        }
        let truth = SimDevice::from_config("phantom", &plant)
            .unwrap()
            .plant()
            .holding_force();
        let (error, before) = (
            (model.force(&x) - truth).norm(),
            (without.force(&x) - truth).norm(),
        );
        println!("at {x:?}: {before:.4} N without the effects, {error:.4} N with them");
        assert!(
            error < 5e-3 && error < 0.1 * before,
            "at {x:?}: {before} → {error} N"
        );
    }
}

/// [`sweep`] of [`linkage_library`] on `sim:MODEL`, calibrated clean first: the failures.
fn sweep_calibrated(model: &str) -> Vec<String> {
    let dir = tempfile::tempdir().unwrap();
    let grid = calibrated(model, dir.path());
    sweep(model, dir.path(), &grid, linkage_library)
}

/// Every pair on the PHANToM at two magnitudes and two seeds, as on the point mass
/// (docs/discrepancy.md §6). `cargo test --release --test discrepancy -- --ignored --nocapture
/// every_pair_on_the_phantom`
#[test]
#[ignore]
fn every_pair_on_the_phantom() {
    let failures = sweep_calibrated("phantom");
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Every pair on the delta, as on the PHANToM (docs/discrepancy.md §6). `cargo test --release
/// --test discrepancy -- --ignored --nocapture every_pair_on_the_delta`
#[test]
#[ignore]
fn every_pair_on_the_delta() {
    let failures = sweep_calibrated("delta");
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Every pair on WoodenHaptics, as on the PHANToM (docs/discrepancy.md §6): all 112 pass.
/// `cargo test --release --test discrepancy -- --ignored --nocapture every_pair_on_woodenhaptics`
#[test]
#[ignore]
fn every_pair_on_woodenhaptics() {
    let failures = sweep_calibrated("woodenhaptics");
    assert!(failures.is_empty(), "{failures:#?}");
}
