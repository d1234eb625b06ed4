//! `hgcd analyze` on 40 s, 1 kHz logs: wall time of the whole analysis (read, smooth, the
//! selection's fits, diagnostics, closed-loop simulations, report and figures), median and worst
//! of five runs, on two logs recorded in virtual time: the simulated point mass with Coulomb
//! friction hidden (the quick case), and `sim:phantom` with a 60 N/m spring beside a 6 ms force
//! delay (the slowest kind of log in the discrepancy sweep: the arm's 31-parameter nominal model,
//! a delay searched at every step, pairs tried because the residual stays above the floor).
//! `cargo bench --bench analyze`; the target is under 5 s on the project's 2-core VM
//! (docs/performance.md).

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

use nalgebra::Vector3;

use hgcd::calibrate::{self, CalibrateRequest};
use hgcd::config::Config;
use hgcd::discrepancy::{self, AnalyzeRequest, RecordRequest};
use hgcd::grid::{GridFile, MassGrid};
use hgcd::transport::Pacing;

fn main() {
    let dir = tempfile::tempdir().expect("a temporary directory");

    // The point mass: a uniform grid of its own mass, 0.05 N of Coulomb friction hidden.
    let grid = dir.path().join("point-mass.toml");
    let field = MassGrid::uniform(
        0.12,
        9.81,
        Vector3::z(),
        Vector3::repeat(-0.04),
        0.04,
        [3, 3, 3],
    );
    GridFile::from(field)
        .save_atomic(&grid)
        .expect("grid written");
    let mut config = bench_config();
    config.sim.coulomb_friction_n = 0.05;
    let log = record(&config, "sim:point-mass", &grid, dir.path());
    time_analysis(
        "sim:point-mass, 0.05 N Coulomb friction hidden",
        &grid,
        &log,
        &["coulomb_friction"],
        dir.path(),
    );

    // The PHANToM: calibrated clean (its arm model), then a spring and a delay hidden.
    let grid = dir.path().join("phantom.toml");
    calibrate::calibrate(
        &bench_config(),
        &CalibrateRequest {
            device: "sim:phantom".parse().expect("a spec"),
            pacing: Pacing::Virtual,
            output: Some(grid.clone()),
            state_dir: dir.path().to_path_buf(),
        },
        Arc::new(AtomicBool::new(false)),
        &mut |_| {},
    )
    .expect("the PHANToM calibrates");
    let mut config = bench_config();
    config.sim.spring_n_per_m = 60.0;
    config.sim.spring_anchor_mm = [30.0, -20.0, 50.0];
    config.sim.force_delay_ms = 6.0;
    let log = record(&config, "sim:phantom", &grid, dir.path());
    time_analysis(
        "sim:phantom, a 60 N/m spring beside a 6 ms force delay hidden",
        &grid,
        &log,
        &["spring", "time_delay"],
        dir.path(),
    );
}

fn bench_config() -> Config {
    let mut config = Config::default();
    config.servo.lock_memory = false;
    config
}

/// A 40 s log of `device` with `config`'s hidden effects, recorded in virtual time.
fn record(config: &Config, device: &str, grid: &Path, dir: &Path) -> PathBuf {
    let log = dir.join(format!("{}.csv", device.replace(':', "-")));
    let request = RecordRequest {
        device: device.parse().expect("a spec"),
        pacing: Pacing::Virtual,
        grid: Some(grid.to_path_buf()),
        out: log.clone(),
        duration: 40.0,
    };
    let recording = discrepancy::record(
        config,
        &request,
        Arc::new(AtomicBool::new(false)),
        &mut |_| {},
    )
    .expect("the recording runs");
    assert!(recording.softenings.is_empty(), "the excitation softened");
    log
}

/// Five analyses of `log`, each naming `expected` (sorted); their median and worst wall time.
fn time_analysis(what: &str, grid: &Path, log: &Path, expected: &[&str], dir: &Path) {
    let mut times = Vec::new();
    for run in 0..5 {
        let started = Instant::now();
        let analysis = discrepancy::analyze(
            &AnalyzeRequest {
                grid: grid.to_path_buf(),
                log: log.to_path_buf(),
                out: dir.join(format!("{}-{run}", log_stem(log))),
            },
            &mut |_| {},
        )
        .expect("the analysis runs");
        times.push(started.elapsed().as_secs_f64());
        let mut named: Vec<&str> = analysis.effects.iter().map(|e| e.name()).collect();
        named.sort_unstable();
        assert_eq!(named, expected, "{what}");
    }
    times.sort_by(f64::total_cmp);
    println!(
        "hgcd analyze, 40 s log ({what}): median {:.2} s, worst {:.2} s of wall time over {} runs (target: under 5 s)",
        times[times.len() / 2],
        times[times.len() - 1],
        times.len()
    );
}

fn log_stem(log: &Path) -> String {
    log.file_stem()
        .map_or_else(String::new, |s| s.to_string_lossy().into_owned())
}
