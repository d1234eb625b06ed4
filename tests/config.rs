//! Configs built in code pass the same range checks as files, before anything runs.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use hgcd::calibrate::{calibrate, CalibrateRequest};
use hgcd::config::Config;
use hgcd::daemon::{Daemon, RunRequest, Signals};
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::Pacing;

/// Default config in a directory of its own, with `change` applied.
fn config_in(dir: &std::path::Path, change: impl FnOnce(&mut Config)) -> Config {
    let mut config = Config::default();
    config.paths.state_dir = Some(dir.to_path_buf());
    config.app.socket = Some(dir.join("hgcd.sock"));
    config.servo.lock_memory = false;
    change(&mut config);
    config
}

#[test]
fn the_daemon_refuses_an_out_of_range_watchdog_instead_of_panicking_its_servo_thread() {
    let dir = tempfile::tempdir().unwrap();
    let config = config_in(dir.path(), |c| c.servo.watchdog_ms = 1e308);
    let mut valid = config.clone();
    valid.servo.watchdog_ms = 10.0;
    // The device is built from the valid twin: only the daemon sees the bad value.
    let transport = Box::new(SimTransport::new(
        SimDevice::from_config("point-mass", &valid).unwrap(),
        Pacing::Virtual,
    ));
    let request = RunRequest {
        device: "sim:point-mass".parse().unwrap(),
        duration: Some(0.1),
        pacing: Pacing::Virtual,
        config_file: None,
    };
    let mut ready = false;
    let err = Daemon::new(config, &request)
        .run(transport, Signals::default(), &mut |_| ready = true)
        .unwrap_err();
    assert!(!ready, "refused before the socket listened");
    assert_eq!(
        err.to_string(),
        "config key `servo.watchdog_ms`: 1e308 is out of range (1 to 1000 ms)"
    );
}

#[test]
fn calibration_refuses_a_force_limit_that_would_turn_the_safety_layer_off() {
    let dir = tempfile::tempdir().unwrap();
    let config = config_in(dir.path(), |c| c.safety.max_force_n = 1e308);
    let output = dir.path().join("grid.toml");
    let request = CalibrateRequest {
        device: "sim:point-mass".parse().unwrap(),
        pacing: Pacing::Virtual,
        output: Some(output.clone()),
        state_dir: dir.path().to_path_buf(),
    };
    let stop = Arc::new(AtomicBool::new(false));
    let Err(err) = calibrate(&config, &request, stop, &mut |_| {}) else {
        panic!("calibrated with the safety limit off");
    };
    assert_eq!(
        err.to_string(),
        "config key `safety.max_force_n`: 1e308 is out of range (0.1 to 50 N)"
    );
    assert!(!output.exists());
}
