//! What `hgcd` does with what it finds where a grid should be, and with a disk that has no room
//! for one (issue 7, items 8 and 9).

use std::os::unix::fs::{symlink, PermissionsExt};
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Duration;

mod common;
use common::file_size::limit_file_size;
use common::{
    failed, file_names, hgcd, output_within, serial, spawn_until, truth_field_27, with_device_id,
    BRIEF_RUN,
};

/// [`BRIEF_RUN`] (`hgcd run`, half a second of virtual time on the simulated device) with the
/// config file `config` and grids in `state`.
fn run_in(config: &Path, dir: &Path, state: &Path) -> Command {
    let mut c = hgcd();
    c.arg("--config")
        .arg(config)
        .args(["--log-level", "error", "--socket"])
        .arg(dir.join("s.sock"))
        .arg("--state-dir")
        .arg(state)
        .args(BRIEF_RUN);
    c
}

const NO_CONFIG: &str = "/dev/null";

/// [`run_in`] without a config file, in `dir` with grids there too, to its end.
fn run_without_config(dir: &Path) -> Output {
    output_within(run_in(Path::new(NO_CONFIG), dir, dir), DEADLINE)
}

/// How long a run may take before it is killed and fails the test (the FIFO used to block
/// `hgcd run` for ever).
const DEADLINE: Duration = Duration::from_secs(60);

/// The run failed with one line on stderr that contains `needle`.
fn refused_with(out: &Output, needle: &str) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(stderr.contains(needle), "{stderr}");
}

/// With `place` putting something at the path of the device's grid, [`run_without_config`] is
/// refused with a line that contains `needle`. Returns the directory, for more runs.
fn refused_when_the_grid_is(place: impl FnOnce(&Path), needle: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    place(&dir.path().join("sim-point-mass.toml"));
    let out = run_without_config(dir.path());
    refused_with(&out, needle);
    dir
}

#[test]
fn a_fifo_where_the_grid_should_be_is_refused_at_once() {
    let mkfifo = |grid: &Path| {
        let c = std::ffi::CString::new(grid.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: `c` is a valid NUL-terminated path for the duration of the call.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
    };
    refused_when_the_grid_is(mkfifo, "is a FIFO (named pipe), not a regular file");
}

#[test]
fn a_link_to_dev_zero_where_the_grid_should_be_is_refused_without_reading_it() {
    refused_when_the_grid_is(
        |grid| symlink("/dev/zero", grid).unwrap(),
        "is a character device, not a regular file",
    );
}

#[test]
fn a_dangling_link_is_not_taken_for_a_missing_grid() {
    let dir = refused_when_the_grid_is(
        |grid| symlink("moved-away.toml", grid).unwrap(),
        "is a symbolic link to moved-away.toml, which does not exist",
    );
    // Unless uncompensated running is allowed: then it runs.
    let allow = dir.path().join("allow.toml");
    std::fs::write(&allow, "[compensation]\nallow_uncompensated = true\n").unwrap();
    let out = output_within(run_in(&allow, dir.path(), dir.path()), DEADLINE);
    assert!(out.status.success(), "{out:?}");
}

#[test]
fn an_unsearchable_state_directory_is_not_taken_for_a_missing_grid() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    std::fs::create_dir(&state).unwrap();
    with_device_id(truth_field_27(), "sim-point-mass")
        .save_atomic(&state.join("sim-point-mass.toml"))
        .unwrap();
    std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o700)).unwrap();
    let mut command = run_in(Path::new(NO_CONFIG), dir.path(), &state);
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } == 0 {
        // Root searches any directory whatever its mode: run hgcd as user `nobody`, to whom the
        // root-owned 0700 directory is closed. The rest of the way must be open to it.
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o777)).unwrap();
        // SAFETY: only async-signal-safe calls between fork and exec.
        unsafe {
            command.pre_exec(|| {
                if libc::setgroups(0, std::ptr::null()) != 0
                    || libc::setgid(65534) != 0
                    || libc::setuid(65534) != 0
                {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    } else {
        std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o000)).unwrap();
    }
    let child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn();
    let out = match child {
        Ok(child) => child.wait_with_output().unwrap(),
        Err(e) => {
            eprintln!("skipped: cannot run hgcd as user nobody here ({e})");
            return;
        }
    };
    std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o700)).unwrap();
    refused_with(&out, "cannot read grid file");
    assert!(String::from_utf8_lossy(&out.stderr).contains("Permission denied"));
}

#[test]
fn without_room_for_the_grid_calibration_refuses_before_it_starts() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("hgcd.toml");
    std::fs::write(&cfg, "[sim]\nmass_grid = \"truth.toml\"\n").unwrap();
    let truth = with_device_id(truth_field_27(), "sim-point-mass");
    truth.save_atomic(&dir.path().join("truth.toml")).unwrap();
    // A previous grid and its backup.
    let out_file = dir.path().join("grid.toml");
    truth.save_atomic(&out_file).unwrap();
    truth.save_atomic(&out_file).unwrap();
    let read = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
    let (old, old_bak) = (read("grid.toml"), read("grid.toml.bak"));
    let mut command = hgcd();
    command
        .arg("--config")
        .arg(&cfg)
        .args(["calibrate", "--device", "sim:point-mass", "--output"])
        .arg(&out_file);
    // Files may grow to 2 KiB only: less than the grid needs. The room check of old (a 5-byte
    // probe) passed, the calibration ran to the end and failed at the write.
    limit_file_size(&mut command, 2048);
    let out = output_within(command, DEADLINE);
    let stderr = failed(&out);
    assert!(
        stderr.contains(&format!("grid file in {}", dir.path().display()))
            && stderr.contains("File too large"),
        "{stderr}"
    );
    assert!(
        !stderr.contains("calibrating"),
        "refused before starting: {stderr}"
    );
    assert_eq!(read("grid.toml"), old);
    assert_eq!(read("grid.toml.bak"), old_bak);
    assert_eq!(
        file_names(dir.path()),
        ["grid.toml", "grid.toml.bak", "hgcd.toml", "truth.toml"]
    );
}

#[test]
fn without_room_for_the_grid_the_daemon_refuses_a_calibration_and_runs_on() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("s.sock");
    let mut daemon = hgcd();
    daemon
        .args(["--config", "/dev/null", "--socket"])
        .arg(&socket)
        .arg("--state-dir")
        .arg(dir.path())
        .args(["run", "--device", "sim:point-mass"])
        .stdout(Stdio::null());
    limit_file_size(&mut daemon, 2048);
    let (mut daemon, mut stderr, log) = spawn_until(&mut daemon, "hgcd running on");
    // Keep draining the log, so the daemon never waits on a full pipe.
    let log = std::thread::spawn(move || {
        let mut rest = String::new();
        let _ = std::io::Read::read_to_string(&mut stderr, &mut rest);
        log + &rest
    });
    let mut calibrate = hgcd();
    calibrate
        .args(["--config", "/dev/null", "--socket"])
        .arg(&socket)
        .args(["calibrate", "--via-daemon", "--yes"]);
    let text = failed(&output_within(calibrate, DEADLINE));
    assert!(
        text.contains("calibration failed: cannot write a") && text.contains("File too large"),
        "{text}"
    );
    // The daemon is still up and answers.
    let mut status = hgcd();
    status
        .args(["--config", "/dev/null", "--socket"])
        .arg(&socket)
        .arg("status");
    let status = output_within(status, DEADLINE);
    assert!(status.status.success(), "{status:?}");
    // SAFETY: kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(daemon.id() as i32, libc::SIGTERM) }, 0);
    let log = log.join().unwrap();
    assert!(daemon.wait().unwrap().success(), "{log}");
    assert_eq!(file_names(dir.path()), Vec::<String>::new());
}
