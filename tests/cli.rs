//! The `hgcd` binary as a user runs it.

mod common;
use common::{hgcd, serial, spawn_until, stderr_of, stdout_of, succeeded, BRIEF_RUN};

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

/// The number `text` gives right after the first `marker`, up to the next space.
fn number_after<T: std::str::FromStr>(text: &str, marker: &str) -> Option<T> {
    let rest = text.split(marker).nth(1)?;
    rest.split(' ').next()?.parse().ok()
}

/// `hgcd run` on `device` with the config file `cfg`.
fn run_on(cfg: &tempfile::NamedTempFile, device: &str) -> std::process::Command {
    let mut c = hgcd();
    c.arg("--config")
        .arg(cfg.path())
        .args(["run", "--device", device]);
    c
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
    let stdout = succeeded(&out);
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
    let stdout = stdout_of(hgcd_in(&cfg, &dir.path().join("s.sock"), dir.path()).args([
        "run",
        "--device",
        "sim:point-mass",
        "--duration",
        "20",
        "--virtual-time",
    ]));
    assert!(stdout.contains("servo loop: 2000"), "{stdout}");
    // 20 s of device time; only a sanity bound on the wall clock, not a performance claim.
    assert!(started.elapsed().as_secs_f64() < 20.0);
}

#[test]
fn sigterm_stops_the_daemon_with_status_0_and_status_works_while_it_runs() {
    use std::io::Read;
    let _serial = serial();
    let cfg = empty_config();
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("s.sock");
    let (child, mut stderr, mut log) = spawn_until(
        hgcd_in(&cfg, &socket, dir.path())
            .args(["run", "--device", "sim:point-mass"])
            .stdout(std::process::Stdio::piped()),
        "hgcd running on",
    );
    let text = stdout_of(
        hgcd()
            .args(["--config", cfg.path().to_str().unwrap(), "--socket"])
            .arg(&socket)
            .arg("status"),
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
    let stderr = stderr_of(hgcd().args([
        "--config",
        cfg.to_str().unwrap(),
        "run",
        "--duration",
        "0.1",
    ]));
    assert!(stderr.contains("safety.max_force_n"), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");

    let cfg = empty_config();
    assert!(stderr_of(&mut run_on(&cfg, "sim:nope")).contains("known: point-mass"));

    let stderr = stderr_of(hgcd().args(["--config", "/nonexistent/hgcd.toml", "status"]));
    assert!(stderr.contains("/nonexistent/hgcd.toml"));
}

#[test]
fn missing_hid_device_is_reported_clearly() {
    let cfg = empty_config();
    let out = run_on(&cfg, "hid:dead:beef")
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

/// `hgcd sim-device` serves one host after another, each from power-on, until it is stopped;
/// in lock-step `run --duration` counts the device's time, so each run is the same 0.5 s of
/// device time however fast the two processes exchange reports (before: wall time, several
/// seconds of device time, and the device exited after the first host).
#[test]
fn hgcd_sim_device_serves_host_after_host_and_run_duration_counts_its_time() {
    use std::io::Read;
    let _serial = serial();
    let cfg = empty_config();
    // The default 10 ms watchdog: in lock-step it counts device time, which a loaded machine
    // cannot stretch.
    std::fs::write(cfg.path(), "[sim]\nserial = \"SIM-0042\"\n").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let device = dir.path().join("device.sock");
    let (sim, mut stderr, mut log) = spawn_until(
        hgcd()
            .args([
                "--config",
                cfg.path().to_str().unwrap(),
                "sim-device",
                "--lockstep",
                "--listen",
            ])
            .arg(&device)
            .stdout(std::process::Stdio::piped()),
        "simulated device listening",
    );
    let spec = format!("socket:{}", device.display());
    for host in 1..=2 {
        let out = hgcd_in(&cfg, &dir.path().join("app.sock"), dir.path())
            .args(["run", "--device", &spec, "--duration", "0.5"])
            .output()
            .unwrap();
        let run_log = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{run_log}");
        assert!(
            run_log.contains("sim-point-mass serial SIM-0042")
                && run_log.contains("lock-step (the run counts device time)")
                && run_log.contains("grid id sim-point-mass-SIM-0042"),
            "{run_log}"
        );
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(stdout.contains("watchdog faults 0"), "{stdout}");
        // One tick per report from 0 to 500 ms of device time.
        let ticks: u64 =
            number_after(&stdout, "servo loop: ").unwrap_or_else(|| panic!("{stdout}"));
        assert!((500..=502).contains(&ticks), "host {host}: {ticks} ticks");
    }
    // Stopped, it says what it served: two hosts, each from power-on (its clock at 0 again).
    // SAFETY: kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(sim.id() as i32, libc::SIGTERM) }, 0);
    stderr.read_to_string(&mut log).unwrap();
    let served = sim.wait_with_output().unwrap();
    assert!(served.status.success(), "{log}");
    let text = String::from_utf8_lossy(&served.stdout);
    assert!(
        text.contains("served 2 host(s)") && text.contains("0 output reports rejected"),
        "{text}"
    );
    for host in 1..=2 {
        let line = log
            .lines()
            .find(|l| l.contains(&format!("host {host} left: ")))
            .unwrap_or_else(|| panic!("{log}"));
        let seconds: f64 = number_after(line, "left: ").unwrap_or_else(|| panic!("{line}"));
        assert!((0.5..0.51).contains(&seconds), "{line}");
    }
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
        status(&["check", "--yes", "--device", "hid:dead:beef"]),
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

/// A pipe whose reader has gone already: every write to it fails (EPIPE), as when `head` has
/// read what it wanted.
fn closed_pipe() -> std::process::Stdio {
    use std::os::fd::FromRawFd;
    let mut fds = [0; 2];
    // SAFETY: pipe2 fills `fds` with two new descriptors; the read end is closed at once and the
    // write end owned by the returned Stdio alone.
    unsafe {
        assert_eq!(libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC), 0);
        libc::close(fds[0]);
        std::process::Stdio::from(std::os::fd::OwnedFd::from_raw_fd(fds[1]))
    }
}

/// `command` run with stdout, stderr or both going to a pipe nobody reads any more, the other
/// one kept: its exit status and what it printed there.
fn with_reader_gone(
    mut command: std::process::Command,
    stdout: bool,
    stderr: bool,
) -> (Option<i32>, String) {
    use std::process::Stdio;
    command
        .stdin(Stdio::null())
        .stdout(if stdout {
            closed_pipe()
        } else {
            Stdio::piped()
        })
        .stderr(if stderr {
            closed_pipe()
        } else {
            Stdio::piped()
        })
        .env("RUST_BACKTRACE", "1");
    let out = command.output().unwrap();
    let kept = if stdout { &out.stderr } else { &out.stdout };
    (
        out.status.code(),
        String::from_utf8_lossy(kept).into_owned(),
    )
}

/// Send SIGTERM to this test's child process whose command line names `path`.
fn terminate_the_process_serving(path: &std::path::Path) {
    let wanted = path.as_os_str().as_encoded_bytes();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) else {
            continue;
        };
        if cmdline.split(|&b| b == 0).any(|arg| arg == wanted) {
            // SAFETY: kill(2) on a process started by this test.
            unsafe { libc::kill(pid, libc::SIGTERM) };
            return;
        }
    }
    panic!("no process serves {}", path.display());
}

#[test]
fn every_command_ends_quietly_when_its_reader_goes_away() {
    // Before: a write to a closed pipe panicked (exit status 101, and a message when stderr was
    // still there). Now the command does its work, drops what it cannot print and exits with the
    // status it would have had.
    let cfg = empty_config();
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("s.sock");
    let check = |args: &[&str], expected: i32| {
        for (stdout, stderr) in [(true, false), (false, true), (true, true)] {
            let mut command = hgcd_in(&cfg, &socket, dir.path());
            command.args(args);
            let (code, kept) = with_reader_gone(command, stdout, stderr);
            let gone = match (stdout, stderr) {
                (true, false) => "stdout",
                (false, true) => "stderr",
                _ => "stdout and stderr",
            };
            assert_eq!(code, Some(expected), "{args:?}, {gone} gone: {kept}");
            assert!(!kept.contains("panicked"), "{args:?}, {gone} gone: {kept}");
            assert!(
                !kept.contains("Broken pipe"),
                "{args:?}, {gone} gone: {kept}"
            );
        }
    };
    check(&["--help"], 0);
    check(&["devices"], 0);
    check(&["calibrate", "--device", "sim:point-mass"], 0);
    check(&BRIEF_RUN, 0);
    // Nobody listens: the error has nowhere to go either, the status says it.
    check(&["status"], 1);

    // The commands that talk to a daemon, with one running (flat out, in virtual time).
    let (mut daemon, mut log, _) = spawn_until(
        hgcd_in(&cfg, &socket, dir.path())
            .args(["run", "--device", "sim:point-mass", "--virtual-time"])
            .stdout(std::process::Stdio::null()),
        "hgcd running on",
    );
    // Keep the daemon's log flowing so it never blocks on it.
    let drain = std::thread::spawn(move || std::io::copy(&mut log, &mut std::io::sink()));
    check(&["status"], 0);
    check(&["calibrate", "--via-daemon", "--yes"], 0);
    // SAFETY: kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(daemon.id() as i32, libc::SIGTERM) }, 0);
    assert!(daemon.wait().unwrap().success());
    drain.join().unwrap().unwrap();

    // The simulated device served on a socket prints what it served when it is stopped.
    let device = dir.path().join("device.sock");
    let slow_watchdog = empty_config();
    std::fs::write(slow_watchdog.path(), "[servo]\nwatchdog_ms = 1000\n").unwrap();
    for (stdout, stderr) in [(true, false), (false, true), (true, true)] {
        let mut sim = hgcd();
        sim.args(["--config", slow_watchdog.path().to_str().unwrap()])
            .args(["sim-device", "--lockstep", "--listen"])
            .arg(&device);
        let sim = std::thread::spawn(move || with_reader_gone(sim, stdout, stderr));
        common::wait_for("the simulated device's socket", || {
            device.exists().then_some(())
        });
        let spec = format!("socket:{}", device.display());
        let mut host = hgcd_in(&slow_watchdog, &socket, dir.path());
        host.args(["run", "--device", &spec, "--duration", "0.2"]);
        let (code, kept) = with_reader_gone(host, stdout, stderr);
        assert_eq!(code, Some(0), "host: {kept}");
        // It serves host after host until told to stop.
        terminate_the_process_serving(&device);
        let (code, kept) = sim.join().unwrap();
        assert_eq!(code, Some(0), "sim-device: {kept}");
        assert!(!kept.contains("panicked"), "sim-device: {kept}");
    }
}

/// Runs as a user who may not write /var/lib/hgcd: as `nobody` when the tests run as root.
fn unprivileged(
    mut command: std::process::Command,
    home: &std::path::Path,
) -> std::process::Command {
    use std::os::unix::process::CommandExt;
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } == 0 {
        command.uid(65534).gid(65534);
    }
    command
        .env("HOME", home)
        .env_remove("XDG_STATE_HOME")
        .env_remove("STATE_DIRECTORY")
        .env_remove("RUNTIME_DIRECTORY");
    command
}

#[test]
fn a_normal_user_calibrates_and_runs_a_simulated_device_without_naming_a_state_dir() {
    use std::os::unix::fs::PermissionsExt;
    // SAFETY: geteuid and access have no preconditions; the path is a NUL-terminated literal.
    let (root, system_writable) = unsafe {
        (
            libc::geteuid() == 0,
            libc::access(c"/var/lib".as_ptr(), libc::W_OK) == 0,
        )
    };
    if !root && system_writable {
        eprintln!("skipped: this user may write /var/lib, where the grid would go");
        return;
    }
    // A home the unprivileged user may write, holding the config and the socket too.
    let home = tempfile::tempdir().unwrap();
    std::fs::set_permissions(home.path(), std::fs::Permissions::from_mode(0o777)).unwrap();
    let cfg = home.path().join("hgcd.toml");
    std::fs::write(&cfg, "").unwrap();
    std::fs::set_permissions(&cfg, std::fs::Permissions::from_mode(0o644)).unwrap();
    let socket = home.path().join("hgcd.sock");
    // A copy of the binary there too: the user may not be allowed into the build's directory.
    let exe = home.path().join("hgcd");
    std::fs::copy(env!("CARGO_BIN_EXE_hgcd"), &exe).unwrap();
    let hgcd_as_user = |args: &[&str]| {
        let mut c = std::process::Command::new(&exe);
        c.current_dir(home.path())
            .arg("--config")
            .arg(&cfg)
            .args(args);
        unprivileged(c, home.path())
    };
    // The daemon, flat out in virtual time until told to stop; its mode as `status` gives it, and
    // what it logged.
    let run_daemon = || {
        let mut daemon = hgcd_as_user(&["run", "--device", "sim:point-mass", "--virtual-time"]);
        let (mut daemon, mut stderr, mut log) = spawn_until(
            daemon
                .arg("--socket")
                .arg(&socket)
                .stdout(std::process::Stdio::null()),
            "hgcd running on",
        );
        let status = hgcd::client::Client::connect(&socket, hgcd::client::Role::Observe, "test")
            .unwrap()
            .status()
            .unwrap();
        // SAFETY: kill(2) on our own child.
        assert_eq!(unsafe { libc::kill(daemon.id() as i32, libc::SIGTERM) }, 0);
        std::io::Read::read_to_string(&mut stderr, &mut log).unwrap();
        assert!(daemon.wait().unwrap().success(), "{log}");
        (status, log)
    };

    // No grid yet: the daemon says which command calibrates this device.
    let (status, log) = run_daemon();
    assert_eq!(status.mode, hgcd::client::Compensating::None);
    let advice = "hgcd calibrate --device sim:point-mass";
    assert!(log.contains(&format!("`{advice}`")), "{log}");
    assert!(!log.contains("--via-daemon"), "{log}");

    // The advice, as given (with the daemon's --config): the grid goes to the user's state dir.
    let args: Vec<&str> = advice.split_whitespace().skip(1).collect();
    let out = hgcd_as_user(&args).output().unwrap();
    let stdout = succeeded(&out);
    let grid = home.path().join(".local/state/hgcd/sim-point-mass.toml");
    assert!(grid.is_file(), "{stdout}");

    // `hgcd run` finds it the same way.
    let (status, log) = run_daemon();
    assert_eq!(status.mode, hgcd::client::Compensating::Vector, "{log}");
    assert_eq!(
        status.grid.as_deref(),
        Some(grid.to_str().unwrap()),
        "{log}"
    );
}

#[test]
fn help_and_devices_show_what_a_newcomer_can_use() {
    // A subcommand's help lists only the options it uses.
    let help = |sub: &str| {
        let out = hgcd().args([sub, "--help"]).output().unwrap();
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    for (sub, shown, hidden) in [
        (
            "devices",
            &["--config", "--profile"][..],
            &["--socket", "--state-dir"][..],
        ),
        (
            "status",
            &["--config", "--socket"][..],
            &["--state-dir", "--profile"][..],
        ),
        (
            "sim-device",
            &["--config"][..],
            &["--socket", "--state-dir"][..],
        ),
        ("run", &["--config", "--socket", "--state-dir"][..], &[][..]),
        (
            "calibrate",
            &["--config", "--socket", "--state-dir"][..],
            &[][..],
        ),
    ] {
        let text = help(sub);
        for o in shown {
            assert!(text.contains(o), "{sub} --help lacks {o}: {text}");
        }
        for o in hidden {
            assert!(!text.contains(o), "{sub} --help shows {o}: {text}");
        }
    }
    // `devices` names the simulated devices too, and each spec it gives opens.
    let out = hgcd().arg("devices").output().unwrap();
    let listing = String::from_utf8_lossy(&out.stdout);
    let sims: Vec<&str> = listing
        .split_whitespace()
        .filter(|w| w.starts_with("sim:"))
        .collect();
    let models: Vec<String> = hgcd::config::SIM_MODELS
        .iter()
        .map(|m| format!("sim:{m}"))
        .collect();
    assert_eq!(sims, models, "{listing}");
    // Each with the profile it would be driven with.
    assert!(
        listing.contains("sim:woodenhaptics") && listing.contains("profile woodenhaptics_v2015"),
        "{listing}"
    );
    assert!(listing.contains("profile cartesian-v1"), "{listing}");
    let out = hgcd()
        .args(["--profile", "polhem_v1", "devices"])
        .output()
        .unwrap();
    let listing = String::from_utf8_lossy(&out.stdout);
    assert!(
        listing
            .lines()
            .any(|l| l.starts_with("sim:woodenhaptics") && l.contains("profile polhem_v1")),
        "{listing}"
    );
    let cfg = empty_config();
    let dir = tempfile::tempdir().unwrap();
    for spec in sims {
        let out = hgcd_in(&cfg, &dir.path().join("s.sock"), dir.path())
            .args([
                "run",
                "--device",
                spec,
                "--virtual-time",
                "--duration",
                "0.1",
            ])
            .output()
            .unwrap();
        succeeded(&out);
    }
    // Where the daemon is not, `status` says how to point at it.
    let out = hgcd()
        .args(["--config", cfg.path().to_str().unwrap(), "--socket"])
        .arg(dir.path().join("nothing.sock"))
        .arg("status")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("--socket"), "{stderr}");
}

/// Issue 40, item 2: SIGTERM ends hgcd at any point, even where it is blocked on something that
/// never answers (here writing `summary.json` into a FIFO nobody reads, after the experiment):
/// the stop flag is set at once, and the process ends within the grace of 3 s. Before, the
/// Ctrl-C thread only set the flag, and hgcd hung until SIGKILL.
#[test]
fn sigterm_ends_hgcd_even_where_it_is_blocked() {
    use std::time::{Duration, Instant};
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let fifo = std::ffi::CString::new(out.join("summary.json").to_str().unwrap()).unwrap();
    // SAFETY: mkfifo(3) on a NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o600) }, 0);
    let config =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/validate-point-mass.toml");
    let mut child = hgcd()
        .arg("--config")
        .arg(&config)
        .arg("--state-dir")
        .arg(dir.path())
        .args(["validate", "--device", "sim:point-mass", "--out"])
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The CSV is written just before summary.json, whose open then waits for a reader.
    let started = Instant::now();
    while !out.join("penalties.csv").exists() {
        assert!(child.try_wait().unwrap().is_none(), "hgcd ended early");
        assert!(started.elapsed() < Duration::from_secs(300), "no CSV");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(500));
    assert!(child.try_wait().unwrap().is_none(), "hgcd did not block");
    // SAFETY: kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    let signalled = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if signalled.elapsed() > Duration::from_secs(30) {
            let _ = child.kill();
            panic!("hgcd still running 30 s after SIGTERM");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("hgcd: stopped by a signal: what it was doing did not stop within 3 s"),
        "{stderr}"
    );
}

/// Issue 37: `hgcd --version` names the release, the commit it was built from and the HID
/// report protocol it speaks.
#[test]
fn version_names_the_release_the_git_commit_and_the_hid_protocol() {
    let commit = std::process::Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map_or("unknown".into(), |o| {
            String::from_utf8_lossy(&o.stdout).trim().to_string()
        });
    let want = format!(
        "hgcd {} (git {commit}, HID protocol v{})\n",
        env!("CARGO_PKG_VERSION"),
        hgcd::protocol::PROTOCOL_VERSION
    );
    for flag in ["--version", "-V"] {
        assert_eq!(succeeded(&hgcd().arg(flag).output().unwrap()), want);
    }
}

/// Issue 37: the man pages and completions the package ships come from the command line's own
/// definition: a page per subcommand a user sees, none for the generators themselves.
#[test]
fn man_pages_and_completions_are_generated_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    succeeded(
        &hgcd()
            .args(["man", "--out"])
            .arg(dir.path())
            .output()
            .unwrap(),
    );
    let mut pages: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    pages.sort();
    let want = [
        "hgcd-analyze.1",
        "hgcd-calibrate.1",
        "hgcd-check.1",
        "hgcd-devices.1",
        "hgcd-record.1",
        "hgcd-run.1",
        "hgcd-sim-device.1",
        "hgcd-status.1",
        "hgcd-validate.1",
        "hgcd.1",
    ];
    assert_eq!(pages, want);
    let run = std::fs::read_to_string(dir.path().join("hgcd-run.1")).unwrap();
    assert!(run.contains("virtual\\-time"), "{run}");
    // The global options a subcommand uses are on its page.
    assert!(run.contains("state\\-dir"), "{run}");
    let top = std::fs::read_to_string(dir.path().join("hgcd.1")).unwrap();
    assert!(top.contains("HID protocol v1"), "the version: {top}");
    for (shell, marker) in [
        ("bash", "complete -F _hgcd"),
        ("zsh", "#compdef hgcd"),
        ("fish", "complete -c hgcd"),
    ] {
        let script = succeeded(&hgcd().args(["completions", shell]).output().unwrap());
        assert!(script.contains(marker), "{shell}: {script}");
        assert!(script.contains("calibrate"), "{shell}: {script}");
        assert!(
            !script.contains("completions"),
            "{shell}: offers the generators"
        );
    }
    // The generators are for packagers: not in the help a user reads.
    let help = succeeded(&hgcd().arg("--help").output().unwrap());
    assert!(!help.contains("completions"), "{help}");
}

/// The completion scripts the package ships: shell, file name in packaging/generated/completions/
/// (the name each shell looks for; Cargo.toml's `[package.metadata.deb]` installs them).
const COMPLETION_FILES: [(&str, &str); 3] = [
    ("bash", "hgcd.bash"),
    ("zsh", "_hgcd"),
    ("fish", "hgcd.fish"),
];

/// Issue 37: the man pages and completions the package ships are committed in
/// packaging/generated/, so that a bare `cargo deb` finds them in a fresh clone, and are exactly
/// what this hgcd generates (`hgcd man`, `hgcd completions`): never edited by hand, never stale.
/// `HGCD_REFRESH_GENERATED=1 cargo test --release --test cli packaged` writes them afresh.
#[test]
fn the_packaged_man_pages_and_completions_are_what_hgcd_generates() {
    let committed = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("packaging/generated");
    let refresh = std::env::var_os("HGCD_REFRESH_GENERATED").is_some();
    let fresh = tempfile::tempdir().unwrap();
    let out = if refresh {
        // Pages of subcommands that are gone go too.
        for dir in ["man", "completions"] {
            if committed.join(dir).exists() {
                std::fs::remove_dir_all(committed.join(dir)).unwrap();
            }
        }
        committed.clone()
    } else {
        fresh.path().to_path_buf()
    };
    succeeded(
        &hgcd()
            .args(["man", "--out"])
            .arg(out.join("man"))
            .output()
            .unwrap(),
    );
    std::fs::create_dir_all(out.join("completions")).unwrap();
    for (shell, file) in COMPLETION_FILES {
        let script = succeeded(&hgcd().args(["completions", shell]).output().unwrap());
        std::fs::write(out.join("completions").join(file), script).unwrap();
    }
    if refresh {
        return;
    }
    // Each file of either tree that the other lacks or has with other contents.
    let files = |root: &std::path::Path| -> std::collections::BTreeSet<std::path::PathBuf> {
        ["man", "completions"]
            .iter()
            .flat_map(|dir| std::fs::read_dir(root.join(dir)).into_iter().flatten())
            .map(|entry| {
                let path = entry.unwrap().path();
                path.strip_prefix(root).unwrap().to_path_buf()
            })
            .collect()
    };
    let differ: Vec<String> = files(&committed)
        .union(&files(fresh.path()))
        .filter(|name| {
            std::fs::read(committed.join(name)).ok() != std::fs::read(fresh.path().join(name)).ok()
        })
        .map(|name| name.display().to_string())
        .collect();
    assert!(
        differ.is_empty(),
        "packaging/generated/ is not what this hgcd generates ({}): refresh it with \
         `HGCD_REFRESH_GENERATED=1 cargo test --release --test cli packaged` and commit the result",
        differ.join(", ")
    );
}
