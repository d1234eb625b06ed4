//! Algorithm 1 against the simulator's ground truth, and its failure paths.

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use nalgebra::Vector3;

use hgcd::calibrate::{calibrate, CalibrateRequest};
use hgcd::config::Config;
use hgcd::control::calibration::CalibrationEvent;
use hgcd::grid::{GridFile, MassGrid};
use hgcd::transport::Pacing;

mod common;
use common::{file_names, hgcd, serial, truth_field_125};

/// A config file (paper defaults) whose simulated device has the truth field; extra TOML appended.
fn setup(dir: &Path, extra: &str) -> (PathBuf, MassGrid) {
    let truth = truth_field_125();
    GridFile::from(truth.clone())
        .save_atomic(&dir.join("truth.toml"))
        .unwrap();
    let cfg = dir.join("hgcd.toml");
    std::fs::write(&cfg, format!("[sim]\nmass_grid = \"truth.toml\"\n{extra}")).unwrap();
    (cfg, truth)
}

/// `hgcd calibrate` on the simulated device, writing to `output`.
fn calibrate_to(cfg: &Path, output: &Path) -> std::process::Output {
    hgcd_with(cfg)
        .args(["calibrate", "--device", "sim:point-mass", "--output"])
        .arg(output)
        .output()
        .unwrap()
}

fn hgcd_with(cfg: &Path) -> Command {
    let mut c = hgcd();
    c.arg("--config").arg(cfg).arg("--log-level").arg("warn");
    c
}

#[test]
fn hgcd_calibrate_recovers_the_truth_within_1_percent_and_half_a_degree() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, truth) = setup(dir.path(), "");
    let state = dir.path().join("state");
    let out = hgcd_with(&cfg)
        .args(["calibrate", "--device", "sim:point-mass", "--state-dir"])
        .arg(&state)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let file = GridFile::load(&state.join("sim-point-mass.toml")).unwrap();
    let grid = &file.grid;
    assert_eq!(grid.dims, [3, 3, 3]);
    let angle = grid
        .gravity_direction
        .angle(&truth.gravity_direction)
        .to_degrees();
    assert!(angle < 0.5, "v_G off by {angle}°");
    let mut worst: f64 = 0.0;
    for k in 0..3 {
        for j in 0..3 {
            for i in 0..3 {
                let x = grid.vertex_position(i, j, k);
                let expected = truth.mass_at(&x);
                let got = grid.masses[grid.index(i, j, k)];
                let rel = (got / expected - 1.0).abs();
                worst = worst.max(rel);
                assert!(rel < 0.01, "vertex {x:?}: {got} kg, truth {expected} kg");
            }
        }
    }
    // The truth spans 0.05–0.25 kg at these vertices, so the test really spans that range.
    let (lo, hi) = grid
        .masses
        .iter()
        .fold((f64::MAX, 0.0f64), |(l, h), &m| (l.min(m), h.max(m)));
    assert!(lo < 0.051 && hi > 0.249, "range {lo}..{hi}");
    // The vector mode's holding forces equal the true gravity force M g v_G at each vertex.
    for (n, f) in file.vertices.force_vectors.iter().enumerate() {
        let (i, j, k) = (n % 3, (n / 3) % 3, n / 9);
        let x = grid.vertex_position(i, j, k);
        let expected = truth.gravity_force(&x);
        let err = (Vector3::from(*f) - expected).norm() / expected.norm();
        assert!(err < 0.01, "force vector at {x:?} off by {err}");
    }
    // Under a minute of device time (docs/performance.md).
    let duration = file.calibration.as_ref().unwrap().duration_s.unwrap();
    assert!(
        duration < 60.0,
        "calibration took {duration} s of device time"
    );
    eprintln!("worst relative mass error {worst:.2e}, v_G error {angle:.3}°, {duration:.1} s");
}

#[test]
fn ctrl_c_mid_run_aborts_and_leaves_the_old_grid_untouched() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = setup(dir.path(), "");
    let output = dir.path().join("dev.toml");
    let old = "format = \"hgcd-grid/1\"\n# the previous calibration\n";
    std::fs::write(&output, old).unwrap();
    // Real time, so the run is still going when the signal comes; the signal is sent once the
    // log says the second vertex has started (no sleeping on the wall clock).
    let mut child = hgcd()
        .arg("--config")
        .arg(&cfg)
        .args([
            "calibrate",
            "--device",
            "sim:point-mass",
            "--real-time",
            "--output",
        ])
        .arg(&output)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut log = String::new();
    loop {
        let mut line = String::new();
        assert!(
            stderr.read_line(&mut line).unwrap() > 0,
            "log ended early: {log}"
        );
        log.push_str(&line);
        if line.contains("vertex 2/27: moving") {
            break;
        }
    }
    // SAFETY: kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
    stderr.read_to_string(&mut log).unwrap();
    let status = child.wait().unwrap();
    assert!(!status.success());
    assert!(
        log.contains("calibration aborted; nothing was written"),
        "{log}"
    );
    assert_eq!(std::fs::read_to_string(&output).unwrap(), old);
    let names = file_names(dir.path());
    assert_eq!(names.len(), 3, "{names:?}"); // hgcd.toml, truth.toml, dev.toml
}

#[test]
fn a_device_that_goes_silent_mid_run_stops_the_calibration_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = setup(dir.path(), "stop_reporting_after_s = 5.0\n");
    let config = Config::load(&cfg).unwrap();
    let output = dir.path().join("dev.toml");
    let request = CalibrateRequest {
        device: "sim:point-mass".parse().unwrap(),
        pacing: Pacing::Virtual,
        output: Some(output.clone()),
        state_dir: PathBuf::from("/nonexistent"),
    };
    let mut vertices_done = 0;
    let err = calibrate(
        &config,
        &request,
        Arc::new(AtomicBool::new(false)),
        &mut |e| {
            if matches!(e, CalibrationEvent::VertexDone { .. }) {
                vertices_done += 1;
            }
        },
    )
    .unwrap_err();
    assert!(vertices_done > 0, "the fault came mid-run");
    assert!(
        err.to_string()
            .contains("stopped by a fault: device stopped reporting; nothing was written"),
        "{err}"
    );
    assert!(!output.exists());
}

#[test]
fn vertices_outside_the_workspace_are_left_out_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    // N = 2 at 40 mm spans ±80 mm: the outer shell lies on the simulated stops, outside the
    // configured safe box of ±60 mm.
    let (cfg, truth) = setup(
        dir.path(),
        "[calibration]\nhalf_size = 2\n[device]\nworkspace_min_mm = [-60.0, -60.0, -60.0]\n\
         workspace_max_mm = [60.0, 60.0, 60.0]\n",
    );
    let out_file = dir.path().join("grid.toml");
    let out = calibrate_to(&cfg, &out_file);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("98 vertices lie outside the workspace")
            && stderr.contains("vertex (-2, -2, -2) at (-80.0, -80.0, -80.0) mm"),
        "{stderr}"
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("left out (outside the workspace)"),
        "{stdout}"
    );
    let file = GridFile::load(&out_file).unwrap();
    let grid = &file.grid;
    assert_eq!(grid.dims, [3, 3, 3]);
    let left_out = file.calibration.unwrap().left_out_vertices.unwrap();
    assert_eq!(left_out.len(), 98);
    for (n, m) in grid.masses.iter().enumerate() {
        let x = grid.vertex_position(n % 3, (n / 3) % 3, n / 9);
        assert!((m / truth.mass_at(&x) - 1.0).abs() < 0.01);
    }
}

#[test]
fn a_vertex_behind_a_mechanical_stop_fails_with_its_name_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    // The simulated device's top stop is at +30 mm, but the config claims ±70 mm is safe: the
    // vertices at z = +40 mm cannot be reached.
    let (cfg, _) = setup(
        dir.path(),
        "workspace_max_mm = [80.0, 80.0, 30.0]\n[calibration]\nvertex_timeout_s = 8.0\n",
    );
    let out_file = dir.path().join("grid.toml");
    let out = calibrate_to(&cfg, &out_file);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    let last = stderr.trim().lines().last().unwrap();
    assert!(
        last.contains("vertex (-1, -1, 1) at (-40.0, -40.0, 40.0) mm could not be reached"),
        "{stderr}"
    );
    assert!(last.contains("nothing was written"), "{last}");
    assert!(!out_file.exists());
}

#[test]
fn unwritable_state_dir_fails_before_calibrating() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = setup(dir.path(), "");
    let blocker = dir.path().join("not-a-dir");
    std::fs::write(&blocker, "").unwrap();
    let out = hgcd_with(&cfg)
        .args(["calibrate", "--device", "sim:point-mass", "--state-dir"])
        .arg(blocker.join("state"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("cannot create the state directory") && stderr.contains("--state-dir"),
        "{stderr}"
    );
    assert!(
        !stderr.contains("vertex"),
        "failed before calibrating: {stderr}"
    );
}

#[test]
fn a_handle_too_light_to_sag_gets_a_message_that_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("hgcd.toml");
    // 10 g sags 0.2 mm on 0.5 N/mm: below the 0.3 mm (3 ε_init) that tells a free handle from a
    // held one.
    std::fs::write(
        &cfg,
        "[sim]\nmass_kg = 0.01\n[calibration]\nvertex_timeout_s = 2.0\n",
    )
    .unwrap();
    let out = calibrate_to(&cfg, &dir.path().join("grid.toml"));
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("sagged only 0.19") && stderr.contains("weighs less than 15 g"),
        "{stderr}"
    );
}

#[test]
fn a_vertex_that_does_not_converge_in_time_or_in_updates_fails_with_its_name() {
    let dir = tempfile::tempdir().unwrap();
    // The first vertex (−40, −40, −40) mm weighs 50 g after a 219 g start: it needs several
    // updates and over a second.
    for (extra, expected) in [
        (
            "[calibration]\nvertex_timeout_s = 1.0\n",
            "vertex (-1, -1, -1) at (-40.0, -40.0, -40.0) mm did not converge within 1 s",
        ),
        (
            "[calibration]\nmax_iterations = 2\n",
            "vertex (-1, -1, -1) at (-40.0, -40.0, -40.0) mm did not converge after 2 mass updates",
        ),
    ] {
        let (cfg, _) = setup(dir.path(), extra);
        let out_file = dir.path().join("grid.toml");
        let out = calibrate_to(&cfg, &out_file);
        assert!(!out.status.success());
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(expected), "{stderr}");
        assert!(stderr.contains("nothing was written"), "{stderr}");
        assert!(!out_file.exists());
    }
}
