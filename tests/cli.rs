//! The `hgcd` binary as a user runs it.

mod common;
use common::hgcd;

fn empty_config() -> tempfile::NamedTempFile {
    tempfile::NamedTempFile::new().unwrap()
}

#[test]
fn run_on_a_simulated_device_prints_timing_statistics() {
    let cfg = empty_config();
    let out = hgcd()
        .args([
            "--config",
            cfg.path().to_str().unwrap(),
            "run",
            "--device",
            "sim:point-mass",
        ])
        .args(["--duration", "0.3", "--virtual-time"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("servo loop: 30"), "{stdout}");
    assert!(stdout.contains("period µs"), "{stdout}");
    assert!(stdout.contains("watchdog faults 0"), "{stdout}");
}

#[test]
fn bad_input_gets_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("bad.toml");
    std::fs::write(&cfg, "[safety]\nmax_force_n = 0.0\n").unwrap();
    let out = hgcd()
        .args([
            "--config",
            cfg.to_str().unwrap(),
            "run",
            "--duration",
            "0.1",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("safety.max_force_n"), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");

    let cfg = empty_config();
    let out = hgcd()
        .args([
            "--config",
            cfg.path().to_str().unwrap(),
            "run",
            "--device",
            "sim:nope",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("known: point-mass"));

    let out = hgcd()
        .args(["--config", "/nonexistent/hgcd.toml", "devices"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/hgcd.toml"));
}

#[test]
fn missing_hid_device_is_reported_clearly() {
    let cfg = empty_config();
    let out = hgcd()
        .args([
            "--config",
            cfg.path().to_str().unwrap(),
            "run",
            "--device",
            "hid:dead:beef",
        ])
        .args(["--duration", "0.1"])
        .output()
        .unwrap();
    // Exit status 3: the systemd unit does not restart on it (RestartPreventExitStatus=3).
    assert_eq!(out.status.code(), Some(3));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("hid:dead:beef"), "{stderr}");
    assert!(
        stderr.contains("hgcd devices") || stderr.contains("hidapi"),
        "{stderr}"
    );
}
