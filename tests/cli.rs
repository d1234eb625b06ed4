//! The `hgcd` binary as a user runs it.

mod common;
use common::{hgcd, serial};

/// `hgcd` with a config file, an application socket and a state directory of the test's own.
fn hgcd_in(
    cfg: &tempfile::NamedTempFile,
    socket: &std::path::Path,
    state_dir: &std::path::Path,
) -> std::process::Command {
    let mut c = hgcd();
    c.arg("--config")
        .arg(cfg.path())
        .arg("--socket")
        .arg(socket)
        .arg("--state-dir")
        .arg(state_dir);
    c
}

fn empty_config() -> tempfile::NamedTempFile {
    tempfile::NamedTempFile::new().unwrap()
}

#[test]
fn run_on_a_simulated_device_in_real_time_prints_timing_statistics() {
    let _serial = serial();
    let cfg = empty_config();
    let dir = tempfile::tempdir().unwrap();
    let started = std::time::Instant::now();
    let out = hgcd_in(&cfg, &dir.path().join("s.sock"), dir.path())
        .args(["run", "--device", "sim:point-mass", "--duration", "1"])
        .output()
        .unwrap();
    let elapsed = started.elapsed().as_secs_f64();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let count = |after: &str| -> u64 {
        let words: Vec<&str> = stdout.split_whitespace().collect();
        words
            .iter()
            .position(|w| *w == after)
            .and_then(|i| words.get(i + 1))
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no count after `{after}`: {stdout}"))
    };
    let (ticks, missed) = (count("loop:"), count("missed"));
    // One second of wall-clock time at 1 kHz, paced by the simulated device's reports. On a
    // loaded machine the loop may wake more than a period late; the device then drops the
    // reports it was not asked for, and the loop counts them as missed: every report the device
    // made in that second is either a tick or a missed report.
    assert!(elapsed >= 1.0, "real time: took {elapsed} s");
    assert!((990..=1010).contains(&(ticks + missed)), "{stdout}");
    assert!(ticks >= 500, "most reports drove a tick: {stdout}");
    assert!(stdout.contains("period µs"), "{stdout}");
    assert!(stdout.contains("lateness µs"), "{stdout}");
    assert!(stdout.contains("watchdog faults 0"), "{stdout}");
}

#[test]
fn virtual_time_runs_as_fast_as_the_cpu_allows() {
    let cfg = empty_config();
    let dir = tempfile::tempdir().unwrap();
    let started = std::time::Instant::now();
    let out = hgcd_in(&cfg, &dir.path().join("s.sock"), dir.path())
        .args([
            "run",
            "--device",
            "sim:point-mass",
            "--duration",
            "20",
            "--virtual-time",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("servo loop: 2000"), "{stdout}");
    // 20 s of device time; only a sanity bound on the wall clock, not a performance claim.
    assert!(started.elapsed().as_secs_f64() < 20.0);
}

#[test]
fn sigterm_stops_the_daemon_with_status_0_and_status_works_while_it_runs() {
    use std::io::{BufRead, BufReader, Read};
    let _serial = serial();
    let cfg = empty_config();
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("s.sock");
    let mut child = hgcd_in(&cfg, &socket, dir.path())
        .args(["run", "--device", "sim:point-mass"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut log = String::new();
    while !log.contains("hgcd running on") {
        assert!(stderr.read_line(&mut log).unwrap() > 0, "{log}");
    }
    let status = hgcd()
        .args(["--config", cfg.path().to_str().unwrap(), "--socket"])
        .arg(&socket)
        .arg("status")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&status.stdout);
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    assert!(text.contains("sim:point-mass (sim-point-mass)"), "{text}");
    assert!(text.contains("compensation  none"), "{text}");
    // SAFETY: kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    stderr.read_to_string(&mut log).unwrap();
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{log}");
    assert!(String::from_utf8_lossy(&out.stdout).contains("servo loop:"));
    assert!(log.contains("servo loop ended: Stopped"), "{log}");
    assert!(!socket.exists(), "socket removed on exit");
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

#[test]
fn the_socket_transport_runs_against_hgcd_sim_device() {
    use std::io::{BufRead, BufReader};
    let _serial = serial();
    // Real time is not what this tests: the device waits for each of the host's reports, and
    // the host's watchdog (wall clock) is as generous as the config allows, so a loaded machine
    // that holds either process back for a while does not make it a fault.
    let cfg = empty_config();
    std::fs::write(cfg.path(), "[servo]\nwatchdog_ms = 1000\n").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let device = dir.path().join("device.sock");
    let mut sim = hgcd()
        .args([
            "--config",
            cfg.path().to_str().unwrap(),
            "sim-device",
            "--lockstep",
            "--listen",
        ])
        .arg(&device)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(sim.stderr.take().unwrap());
    let mut log = String::new();
    while !log.contains("simulated device listening") {
        assert!(stderr.read_line(&mut log).unwrap() > 0, "{log}");
    }
    let spec = format!("socket:{}", device.display());
    let out = hgcd_in(&cfg, &dir.path().join("app.sock"), dir.path())
        .args(["run", "--device", &spec, "--duration", "0.5"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("watchdog faults 0"), "{stdout}");
    // The device side ends when the host disconnects, having rejected nothing.
    let served = sim.wait_with_output().unwrap();
    assert!(served.status.success());
    let text = String::from_utf8_lossy(&served.stdout);
    assert!(text.contains("0 output reports rejected"), "{text}");
    assert!(!device.exists());
}

/// Exit status and stderr of `command`, which must end within a generous deadline (before the
/// ranges were checked, `sim.substep_hz = 1e308` never ended).
fn finished(mut command: std::process::Command) -> (std::process::ExitStatus, String) {
    let child = command
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id() as i32;
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || tx.send(child.wait_with_output()));
    match rx.recv_timeout(std::time::Duration::from_secs(30)) {
        Ok(out) => {
            let out = out.unwrap();
            (
                out.status,
                String::from_utf8_lossy(&out.stderr).into_owned(),
            )
        }
        Err(_) => {
            // SAFETY: kill(2) on our own child, which has not been reaped (wait never returned).
            unsafe { libc::kill(pid, libc::SIGKILL) };
            panic!("hung: {command:?}");
        }
    }
}

#[test]
fn out_of_range_config_values_stop_run_and_calibrate_with_one_line() {
    // Before: a panicked servo thread, a panic at start-up, a hang, or a run without the limit.
    let dir = tempfile::tempdir().unwrap();
    for (section, key, value, range) in [
        ("servo", "watchdog_ms", "1e308", "(1 to 1000 ms)"),
        ("app", "hello_timeout_ms", "1e308", "(10 to 60000 ms)"),
        ("app", "hello_timeout_ms", "1e-9", "(10 to 60000 ms)"),
        ("sim", "substep_hz", "1e308", "(100 to 1000000 Hz)"),
        ("safety", "max_force_n", "1e308", "(0.1 to 50 N)"),
        ("app", "stale_offset_ms", "1e308", "(1 to 1000 ms)"),
        ("servo", "watchdog_ms", "nan", "(1 to 1000 ms)"),
    ] {
        let cfg = empty_config();
        std::fs::write(cfg.path(), format!("[{section}]\n{key} = {value}\n")).unwrap();
        let expected = format!("config key `{section}.{key}`: {value} is out of range {range}");
        for args in [
            &[
                "run",
                "--device",
                "sim:point-mass",
                "--duration",
                "0.2",
                "--virtual-time",
            ][..],
            &["calibrate", "--device", "sim:point-mass", "--output"][..],
        ] {
            let mut command = hgcd_in(&cfg, &dir.path().join("s.sock"), dir.path());
            command.args(args);
            if args[0] == "calibrate" {
                command.arg(dir.path().join("grid.toml"));
            }
            let (status, stderr) = finished(command);
            assert!(!status.success(), "{args:?} with {key} = {value}: {stderr}");
            assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
            assert!(stderr.contains(&expected), "{stderr}");
        }
    }
    assert!(!dir.path().join("grid.toml").exists());
}

/// One exit status per error family: 3 when the device cannot be opened or goes away (the
/// systemd unit does not restart on it; udev starts it again on plug-in), 1 for everything else.
#[test]
fn exit_status_says_whether_the_device_is_gone() {
    let cfg = empty_config();
    let dir = tempfile::tempdir().unwrap();
    let status = |args: &[&str]| {
        hgcd()
            .args(["--config", cfg.path().to_str().unwrap()])
            .args(["--state-dir", dir.path().to_str().unwrap()])
            .args(args)
            .output()
            .unwrap()
            .status
            .code()
    };
    // Cannot be opened: a HID device that is not plugged in, a socket nobody serves.
    let gone = dir.path().join("nobody.sock");
    let gone = format!("socket:{}", gone.display());
    assert_eq!(
        status(&["calibrate", "--yes", "--device", "hid:dead:beef"]),
        Some(3)
    );
    assert_eq!(
        status(&["run", "--duration", "1", "--device", &gone]),
        Some(3)
    );
    // Goes away while running: the device side accepts, then hangs up.
    let path = dir.path().join("dev.sock");
    let listener = std::os::unix::net::UnixListener::bind(&path).unwrap();
    let device = std::thread::spawn(move || drop(listener.accept()));
    let spec = format!("socket:{}", path.display());
    assert_eq!(
        status(&["run", "--duration", "30", "--device", &spec]),
        Some(3)
    );
    device.join().unwrap();
    // A simulated device whose plant cannot be built is one that cannot be opened; the OS's
    // reason reaches the user.
    let sim_cfg = dir.path().join("missing-grid.toml");
    std::fs::write(&sim_cfg, "[sim]\nmass_grid = \"/nonexistent/truth.toml\"\n").unwrap();
    let out = hgcd()
        .args(["--config", sim_cfg.to_str().unwrap()])
        .args(["run", "--duration", "1", "--device", "sim:point-mass"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains("/nonexistent/truth.toml") && stderr.contains("no grid file"),
        "{stderr}"
    );
    // A device side that breaks the socket framing is a fault of the link, not a lost device.
    let path = dir.path().join("garbler.sock");
    let listener = std::os::unix::net::UnixListener::bind(&path).unwrap();
    let device = std::thread::spawn(move || {
        use std::io::Write;
        let (mut stream, _) = listener.accept().unwrap();
        stream.write_all(&[200, 1, 2, 3]).unwrap();
        let mut sink = Vec::new();
        let _ = std::io::Read::read_to_end(&mut stream, &mut sink);
    });
    let spec = format!("socket:{}", path.display());
    assert_eq!(
        status(&["run", "--duration", "30", "--device", &spec]),
        Some(1)
    );
    device.join().unwrap();
    // Anything else: a bad device spec, a bad value on the command line; a malformed command
    // line is clap's usage error, 2.
    assert_eq!(status(&["run", "--device", "usb:1:2"]), Some(1));
    assert_eq!(status(&["run", "--duration", "0"]), Some(1));
    assert_eq!(status(&["run", "--duration", "-1"]), Some(2));
}
