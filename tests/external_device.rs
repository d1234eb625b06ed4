//! A device someone else built: written in this file from `docs/hid-protocol.md` alone (every
//! byte by hand, none of hgcd's codec), served on `socket:` in lock-step, with a device-info
//! report that gives its serial number and a workspace 150 mm from the frame origin. hgcd (the
//! binary) calibrates inside that workspace, names each unit's grid after its serial, refuses a
//! grid calibrated on another unit, and runs a device that does not answer as before.

use std::io::{Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::Output;
use std::thread::JoinHandle;
use std::time::Duration;

use nalgebra::Vector3;

use hgcd::grid::{DeviceIdentity, GridFile, MassGrid};
use hgcd::protocol::DeviceInfo;

mod common;
use common::{hgcd, succeeded};

const MODEL: &str = "Test linkage";
/// Workspace centre and half-extents, m: the handle is 150 mm in front of the base, 60 mm up.
const CENTRE: [f64; 3] = [0.0, 0.150, 0.060];
const HALF: [f64; 3] = [0.080, 0.060, 0.060];
/// The handle's mass, kg, under g along −z, and the actuators' limit per axis, N.
const MASS: f64 = 0.1;
const G: f64 = 9.81;
const MAX_FORCE: f64 = 3.0;
/// Report period, µs, and the device watchdog, µs of device time.
const PERIOD_US: u32 = 1000;
const WATCHDOG_US: u32 = 50_000;

/// One unit of the device.
#[derive(Clone, Copy)]
struct Unit {
    serial: &'static str,
    /// Whether it knows the device-info request (an older firmware ignores it).
    answers_info: bool,
}

/// What the device saw of one host.
#[derive(Debug, Default)]
struct Session {
    /// Reports sent.
    reports: u32,
    /// The handle hit one of the workspace's stops.
    touched_stop: bool,
}

/// §5a: the device-info report, 64 bytes.
fn device_info(unit: Unit) -> Vec<u8> {
    let mut b = vec![0x03, 0x01, 0x01, 0x00]; // ID, version, LOCKSTEP, reserved
    b.extend_from_slice(&1_000_000u32.to_le_bytes()); // 1 kHz in mHz
    b.extend_from_slice(&((MAX_FORCE * 1e6) as u32).to_le_bytes()); // µN
    for v in CENTRE.iter().chain(&HALF) {
        b.extend_from_slice(&((v * 1e9).round() as i32).to_le_bytes()); // nm
    }
    for (text, len) in [(MODEL, 16), (unit.serial, 12)] {
        let mut field = text.as_bytes().to_vec();
        field.resize(len, 0);
        b.extend_from_slice(&field);
    }
    assert_eq!(b.len(), 64);
    b
}

/// §5: a valid output report's force and ENABLE bit, or None for a malformed one (§6.1).
fn output(bytes: &[u8]) -> Option<([f64; 3], bool)> {
    if bytes.len() != 20 || bytes[0] != 0x02 || bytes[1] != 0x01 {
        return None;
    }
    let mut force = [0.0; 3];
    for (axis, f) in force.iter_mut().enumerate() {
        let at = 4 + 4 * axis;
        let raw = i32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        if raw.unsigned_abs() > 100_000_000 {
            return None;
        }
        *f = f64::from(raw) * 1e-6;
    }
    (bytes[16] & !1 == 0 && bytes[17..].iter().all(|&b| b == 0)).then_some((force, bytes[16] == 1))
}

/// Serve `hosts` connections at `path`, each from power-on, in lock-step.
fn spawn_device(path: &Path, unit: Unit, hosts: usize) -> JoinHandle<Vec<Session>> {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let listener = UnixListener::bind(path).unwrap();
    std::thread::spawn(move || {
        (0..hosts)
            .map(|_| serve(listener.accept().unwrap().0, unit))
            .collect()
    })
}

fn serve(mut stream: UnixStream, unit: Unit) -> Session {
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    let mut session = Session::default();
    let (mut x, mut v) = (Vector3::from(CENTRE), Vector3::<f64>::zeros());
    let (mut sequence, mut clock_us, mut last_command_us) = (0u16, 0u32, 0u32);
    let (mut command, mut enabled, mut tripped, mut saturated) =
        (Vector3::<f64>::zeros(), false, false, false);
    loop {
        // §4: the input report.
        let status =
            u16::from(enabled && !tripped) | u16::from(saturated) << 3 | u16::from(tripped) << 4;
        let mut frame = vec![24, 0x01, 0x01];
        frame.extend_from_slice(&sequence.to_le_bytes());
        frame.extend_from_slice(&clock_us.to_le_bytes());
        for axis in 0..3 {
            frame.extend_from_slice(&((x[axis] * 1e9).round() as i32).to_le_bytes());
        }
        frame.extend_from_slice(&status.to_le_bytes());
        frame.extend_from_slice(&[0, 0]);
        if stream.write_all(&frame).is_err() {
            return session;
        }
        session.reports += 1;
        // §9, lock-step: wait for the host's reply; answer feature requests meanwhile.
        loop {
            let mut n = [0u8];
            if stream.read_exact(&mut n).is_err() || !(1..=64).contains(&n[0]) {
                return session;
            }
            let mut bytes = vec![0u8; n[0] as usize];
            if stream.read_exact(&mut bytes).is_err() {
                return session;
            }
            if bytes.len() == 1 {
                if bytes[0] == 0x03 && unit.answers_info {
                    let mut answer = vec![64];
                    answer.extend_from_slice(&device_info(unit));
                    stream.write_all(&answer).unwrap();
                }
                continue;
            }
            if let Some((force, enable)) = output(&bytes) {
                command = if enable {
                    force.into()
                } else {
                    Vector3::zeros()
                };
                enabled = enable;
                last_command_us = clock_us;
                tripped = false;
            }
            break;
        }
        // One period of physics under the command: watchdog, actuator limit, stops.
        if clock_us - last_command_us > WATCHDOG_US {
            tripped = true;
            command = Vector3::zeros();
        }
        let force = command.map(|f| f.clamp(-MAX_FORCE, MAX_FORCE));
        saturated = force != command;
        let dt = f64::from(PERIOD_US) * 1e-6 / 10.0;
        for _ in 0..10 {
            v += (force / MASS - Vector3::new(0.0, 0.0, G)) * dt;
            x += v * dt;
            for axis in 0..3 {
                let (lo, hi) = (CENTRE[axis] - HALF[axis], CENTRE[axis] + HALF[axis]);
                if x[axis] < lo || x[axis] > hi {
                    x[axis] = x[axis].clamp(lo, hi);
                    v[axis] = 0.0;
                    session.touched_stop = true;
                }
            }
        }
        clock_us = clock_us.wrapping_add(PERIOD_US);
        sequence = sequence.wrapping_add(1);
    }
}

/// The config of most runs here: normal scheduling.
const NORMAL_SCHEDULING: &str = "[servo]\nrealtime_priority = 0\nlock_memory = false\n";

/// `hgcd --log-level LEVEL ARGS --device socket:DEVICE` with the config `config` (written to the
/// test's directory), and a state directory and an application socket of the test's own.
fn hgcd_on(dir: &Path, config: &str, log_level: &str, args: &[&str], device: &Path) -> Output {
    let cfg = dir.join("hgcd.toml");
    std::fs::write(&cfg, config).unwrap();
    hgcd()
        .arg("--config")
        .arg(&cfg)
        .args(["--log-level", log_level])
        .arg("--state-dir")
        .arg(dir.join("state"))
        .arg("--socket")
        .arg(dir.join("app.sock"))
        .args(args)
        .args(["--device", &spec(device)])
        .output()
        .unwrap()
}

fn spec(path: &Path) -> String {
    format!("socket:{}", path.display())
}

/// Two units of the same model behind sockets of the same file name, `a/dev.sock` and
/// `b/dev.sock`.
fn two_units(dir: &Path) -> [(PathBuf, Unit); 2] {
    [("a", "A-0001"), ("b", "B-0002")].map(|(sub, serial)| {
        (
            dir.join(sub).join("dev.sock"),
            Unit {
                serial,
                answers_info: true,
            },
        )
    })
}

#[test]
fn hgcd_calibrates_each_unit_inside_its_declared_workspace_into_a_grid_named_after_its_serial() {
    let dir = tempfile::tempdir().unwrap();
    for (path, unit) in two_units(dir.path()) {
        let device = spawn_device(&path, unit, 1);
        let out = hgcd_on(
            dir.path(),
            NORMAL_SCHEDULING,
            "warn",
            &["calibrate", "--yes"],
            &path,
        );
        let sessions = device.join().unwrap();
        succeeded(&out);
        // The handle stayed inside the workspace: it never met a stop.
        assert!(!sessions[0].touched_stop, "{sessions:?}");
        let grid_path = dir
            .path()
            .join("state")
            .join(format!("Test_linkage-{}.toml", unit.serial));
        let file = GridFile::load(&grid_path).unwrap();
        let unit_record = file.unit().unwrap();
        assert_eq!(
            (unit_record.model.as_str(), unit_record.serial.as_str()),
            (MODEL, unit.serial)
        );
        // The paper's 27 vertices, 40 mm apart around the workspace's centre, every one inside.
        let grid = &file.grid;
        assert_eq!(grid.dims, [3, 3, 3]);
        assert!((grid.spacing - 0.04).abs() < 1e-12);
        let centre = Vector3::from(CENTRE);
        assert!((grid.origin - (centre - Vector3::repeat(0.04))).norm() < 1e-9);
        for (i, m) in grid.masses.iter().enumerate() {
            let at = grid.vertex_position(i % 3, (i / 3) % 3, i / 9);
            assert!(
                (0..3).all(|a| (at[a] - CENTRE[a]).abs() < HALF[a]),
                "vertex at {at:?}"
            );
            assert!((m / MASS - 1.0).abs() < 0.02, "{m} kg at {at:?}");
        }
        assert!(grid.gravity_direction.angle(&Vector3::z()).to_degrees() < 1.0);
    }
    // Same model, same socket file name, two serials: two grids.
    let mut names = common::file_names(&dir.path().join("state"));
    names.retain(|n| n.ends_with(".toml"));
    assert_eq!(
        names,
        ["Test_linkage-A-0001.toml", "Test_linkage-B-0002.toml"]
    );
}

#[test]
fn a_grid_calibrated_on_another_unit_is_refused_with_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let [(_, a), (b_path, b)] = two_units(dir.path());
    // Unit A's grid, copied to where unit B's grid goes.
    let identity = |unit: Unit, path: &Path| DeviceIdentity {
        spec: spec(path).parse().unwrap(),
        info: Some(DeviceInfo::decode(&device_info(unit)).unwrap()),
    };
    let mut grid = GridFile::from(MassGrid::uniform(
        MASS,
        G,
        Vector3::z(),
        Vector3::from(CENTRE) - Vector3::repeat(0.04),
        0.04,
        [3, 3, 3],
    ));
    identity(a, &dir.path().join("a/dev.sock")).stamp(&mut grid);
    let b_grid = dir.path().join("state/Test_linkage-B-0002.toml");
    std::fs::create_dir_all(b_grid.parent().unwrap()).unwrap();
    grid.save_atomic(&b_grid).unwrap();

    let device = spawn_device(&b_path, b, 1);
    let out = hgcd_on(
        dir.path(),
        NORMAL_SCHEDULING,
        "error",
        &["run", "--duration", "1"],
        &b_path,
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains(&format!(
            "grid {} was calibrated on another unit (Test linkage serial A-0001), not on this one \
             (Test linkage serial B-0002)",
            b_grid.display()
        )),
        "{stderr}"
    );
    // Refused before the loop ran: the device served the power-on report alone.
    assert_eq!(device.join().unwrap()[0].reports, 1);
}

#[test]
fn a_device_that_does_not_answer_the_device_info_request_runs_as_before_said_once() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("dev.sock");
    let device = spawn_device(
        &path,
        Unit {
            serial: "C-0003",
            answers_info: false,
        },
        1,
    );
    // Without the report hgcd cannot know it runs in lock-step: the watchdog is wall-clock time,
    // generous here so a loaded machine does not make it a fault.
    let out = hgcd_on(
        dir.path(),
        "[servo]\nwatchdog_ms = 1000\nrealtime_priority = 0\n",
        "warn",
        &["run", "--duration", "0.3"],
        &path,
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let said: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("gave no device-info report"))
        .collect();
    assert_eq!(said.len(), 1, "{stderr}");
    assert!(
        said[0].contains("did not answer within 500ms") && said[0].contains("(socket-dev_sock)"),
        "{stderr}"
    );
    assert!(device.join().unwrap()[0].reports > 1);
}
