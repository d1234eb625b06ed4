//! Helpers shared by the integration tests: known truth fields for the simulator, the binary
//! under test and its output, file listings, bounded waits, and the tap transport ([`tap`]).
#![allow(dead_code)]

pub mod daemon;
pub mod file_size;
pub mod tap;

use std::io::{BufRead, BufReader};
use std::os::unix::net::UnixListener;
use std::path::Path;
use std::process::{Child, ChildStderr, Command, Output, Stdio};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use hgcd::config::Config;
use hgcd::grid::{DeviceRecord, GridFile, MassGrid};
use hgcd::sim::{socket, SimDevice};

/// Gravity tilted about 3.3° away from −z (v_G = normalised (0.05, −0.03, 1)).
pub fn tilted_v_g() -> Vector3<f64> {
    Vector3::new(0.05, -0.03, 1.0).normalize()
}

/// Mass of vertex (i, j, k) of the 3×3×3 calibration grid: 27 distinct values spread evenly over
/// 0.05–0.25 kg in scrambled order, so neighbours differ by up to a factor of five.
pub fn scrambled_mass(i: usize, j: usize, k: usize) -> f64 {
    let q = i + 3 * (j + 3 * k);
    0.05 + 0.2 * ((q * 10) % 27) as f64 / 26.0
}

/// The 3×3×3 truth field on the paper's grid (L = 40 mm, ±40 mm), gravity tilted.
pub fn truth_field_27() -> MassGrid {
    MassGrid::uniform(
        0.1,
        9.81,
        tilted_v_g(),
        Vector3::new(-0.04, -0.04, -0.04),
        0.04,
        [3, 3, 3],
    )
    .with_masses(scrambled_mass)
}

/// The same field on a 5×5×5 lattice (±80 mm): the inner 27 vertices as in [`truth_field_27`],
/// the outer shell 0.15 kg, so moves beyond the calibration grid stay physical.
pub fn truth_field_125() -> MassGrid {
    let (inner, shell) = (1..4, 0.15);
    MassGrid::uniform(
        shell,
        9.81,
        tilted_v_g(),
        Vector3::new(-0.08, -0.08, -0.08),
        0.04,
        [5, 5, 5],
    )
    .with_masses(|i, j, k| {
        if [i, j, k].iter().all(|n| inner.contains(n)) {
            scrambled_mass(i - 1, j - 1, k - 1)
        } else {
            shell
        }
    })
}

/// A grid file of `grid` made for the device with id `id`.
pub fn with_device_id(grid: MassGrid, id: &str) -> GridFile {
    let mut file = GridFile::from(grid);
    file.device = Some(DeviceRecord {
        id: id.into(),
        spec: None,
        model: None,
        serial: None,
    });
    file
}

/// A grid file of `sim:phantom`'s paper cube with an arm model, as a calibration on the
/// nominal unit writes it: the published arm's parameters, the plant's own force at each vertex
/// (the arm model's plus 2 mN a vertex, for the residual lattice to hold), "arm-residual" chosen.
pub fn phantom_arm_grid() -> GridFile {
    use hgcd::arm::ArmGravity;
    use hgcd::grid::{ArmRecord, HeldOutRecord, ModelRecord};
    let arm = hgcd::profile::Profile::built_in("phantom_1_5")
        .unwrap()
        .gravity_arm()
        .unwrap();
    let p = hgcd::sim::phantom::Phantom::published();
    let upper = p.m_a * p.l1 + p.m_c * p.c_along_upper_arm + p.m_be * p.l5;
    let fore = p.m_a * p.a_along_forearm + p.m_c * p.l3 - p.m_df * p.l6;
    let gravity = ArmGravity {
        arm,
        parameters: [upper, 0.0, fore, 0.0, 0.0, 0.0, 0.0],
        up: Vector3::z(),
        g: 9.81,
    };
    let grid = MassGrid::uniform(
        0.0,
        9.81,
        Vector3::z(),
        Vector3::new(-0.04, -0.04, -0.04),
        0.04,
        [3, 3, 3],
    );
    let forces = (0..27)
        .map(|n| {
            let (i, j, k) = grid.coordinates(n);
            let f = gravity.force(&grid.vertex_position(i, j, k));
            (f + Vector3::new(0.002, 0.0, 0.0)).into()
        })
        .collect();
    let mut file = GridFile::from(grid);
    file.vertices.force_vectors = forces;
    file.arm = Some(ArmRecord::new("phantom_1_5", &gravity));
    file.model = Some(ModelRecord {
        chosen: "arm-residual".into(),
        held_out_holds: 7,
        held_out_pct: HeldOutRecord::default(),
        warning: None,
    });
    file
}

/// The `hgcd` binary, run from the temporary directory so no installed config is picked up.
pub fn hgcd() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_hgcd"));
    c.current_dir(std::env::temp_dir());
    c
}

/// `hgcd` arguments for a short run: half a second of virtual time on the simulated point mass.
pub const BRIEF_RUN: [&str; 6] = [
    "run",
    "--device",
    "sim:point-mass",
    "--virtual-time",
    "--duration",
    "0.5",
];

/// The stdout of a command that must have succeeded (its stderr fails the test otherwise).
pub fn succeeded(out: &Output) -> String {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Run `command` to its end; its stdout (it must succeed, as in [`succeeded`]).
pub fn stdout_of(command: &mut Command) -> String {
    succeeded(&command.output().unwrap())
}

/// Run `command` to its end; its stderr (it must fail, as in [`failed`]).
pub fn stderr_of(command: &mut Command) -> String {
    failed(&command.output().unwrap())
}

/// The stderr of a command that must have failed.
pub fn failed(out: &Output) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "{stderr}");
    stderr
}

/// The distance in mm an example printed as `<distance> mm at <at>` (the two-handle examples:
/// "at the start", "at the end").
pub fn distance_mm(stdout: &str, at: &str) -> f64 {
    let before = stdout
        .split(&format!(" mm at {at}"))
        .next()
        .unwrap_or_else(|| panic!("no distance at {at}: {stdout}"));
    before.rsplit(' ').next().unwrap().parse().unwrap()
}

/// Run `command` to its end with its output captured; one still going after `limit` is killed
/// and fails the test.
pub fn output_within(mut command: Command, limit: Duration) -> Output {
    let program = command.get_program().to_string_lossy().into_owned();
    let child = spawn(command.stdout(Stdio::piped()).stderr(Stdio::piped()));
    let pid = child.id() as i32;
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || tx.send(child.wait_with_output()));
    match rx.recv_timeout(limit) {
        Ok(out) => out.unwrap(),
        Err(_) => {
            // SAFETY: kill(2) on our own child, which has not been reaped (its waiter is stuck).
            unsafe { libc::kill(pid, libc::SIGKILL) };
            panic!("{program} did not end within {limit:?}");
        }
    }
}

/// Spawn `command`. A program this process has just written (a copy of the binary) may be
/// busy for a moment: a child another test thread forked while the copy was open for writing
/// holds that descriptor until its own exec, and exec'ing the copy meanwhile fails with ETXTBSY
/// ("Text file busy"). Try again then, for up to a second.
pub fn spawn(command: &mut Command) -> Child {
    for _ in 0..100 {
        match command.spawn() {
            Err(e) if e.kind() == std::io::ErrorKind::ExecutableFileBusy => {
                std::thread::sleep(std::time::Duration::from_millis(10));
            }
            other => return other.unwrap(),
        }
    }
    command.spawn().unwrap()
}

/// Spawn `command` with its stderr piped and read that until it says `ready` (failing the test
/// if it ends first): the child, the rest of its stderr, and what it has said so far.
pub fn spawn_until(command: &mut Command, ready: &str) -> (Child, BufReader<ChildStderr>, String) {
    let mut child = spawn(command.stderr(Stdio::piped()));
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut log = String::new();
    while !log.contains(ready) {
        assert!(stderr.read_line(&mut log).unwrap() > 0, "{log}");
    }
    (child, stderr, log)
}

/// Names of the entries of `dir`, sorted.
pub fn file_names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    names
}

/// How long [`wait_for`] polls before it fails the test.
pub const WAIT: Duration = Duration::from_secs(30);

/// Poll `poll` until it gives a value; fail the test, naming `what` was awaited, after [`WAIT`].
/// For conditions another thread brings about in its own time (a disconnect noticed, a file
/// reloaded), each poll a round trip that blocks by itself.
pub fn wait_for<T>(what: &str, mut poll: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + WAIT;
    loop {
        if let Some(value) = poll() {
            return value;
        }
        assert!(Instant::now() < deadline, "waited {WAIT:?} for {what}");
    }
}

static SERIAL: Mutex<()> = Mutex::new(());

/// Tests that run a device in real time hold this, so they do not compete for the two cores
/// with each other or with virtual-time runs (which use a core flat out).
pub fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// A feedback-linearised PD hold 5 mm above the origin, on a uniform 0.12 kg model.
pub fn pd_hold() -> hgcd::control::pd::PdHold {
    hgcd::control::pd::PdHold {
        set_point: Vector3::new(0.0, 0.0, 0.005),
        gains: hgcd::control::pd::LinearisedGains::from_rise_time(0.1, 1.0),
        field: MassGrid::uniform(0.12, 9.81, Vector3::z(), Vector3::zeros(), 0.1, [2, 2, 2]),
    }
}

/// The simulated `sim:MODEL` of `config` serving one host in lock-step on a new socket at
/// `path`: the flag that stops it, and its thread, which gives the device back.
pub fn serve_one_host(
    path: &Path,
    config: &Config,
    model: &'static str,
) -> (Arc<AtomicBool>, JoinHandle<SimDevice>) {
    let listener = UnixListener::bind(path).unwrap();
    let config = config.clone();
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let device = std::thread::spawn(move || {
        let mut device = SimDevice::from_config(model, &config).unwrap();
        let host = socket::accept(&listener, &flag).unwrap().unwrap();
        socket::serve_host(host, &mut device, true, &flag).unwrap();
        device
    });
    (stop, device)
}

/// Runs `.0` and ends the run after `.1` ticks.
pub struct Ticks<C>(pub C, pub u64);

impl<C: hgcd::control::Controller> hgcd::control::Controller for Ticks<C> {
    fn tick(&mut self, s: &hgcd::control::DeviceState) -> hgcd::control::ControlOutput {
        let out = self.0.tick(s);
        if s.tick + 1 >= self.1 {
            hgcd::control::ControlOutput::done(out.force)
        } else {
            out
        }
    }
}

/// The comma-separated values of the environment variable `key`, or `default` (the ignored
/// sweeps' narrowing variables).
pub fn env_list<T: std::str::FromStr + Clone>(key: &str, default: &[T]) -> Vec<T> {
    match std::env::var(key) {
        Ok(v) => v
            .split(',')
            .map(|s| {
                s.trim()
                    .parse()
                    .unwrap_or_else(|_| panic!("{key}: cannot read {s:?}"))
            })
            .collect(),
        Err(_) => default.to_vec(),
    }
}
