//! Two devices on one host, as systemd runs them: two `hgcd run` processes, one per simulated
//! device, with nothing set but `$RUNTIME_DIRECTORY` and `$STATE_DIRECTORY`, which the two share.
//! Each device is a unit of its own (`sim.serial`), so each daemon finds its own socket and grid.
//! The devices run in virtual time: nothing here waits on a 1 kHz loop.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

use hgcd::app::endpoint;
use hgcd::client::{Client, Compensating, Role};
use hgcd::grid::GridFile;

mod common;
use common::{hgcd, wait_for, WAIT};

/// The shared directories of the host.
struct Host {
    dir: tempfile::TempDir,
}

impl Host {
    fn new() -> Self {
        let host = Self {
            dir: tempfile::tempdir().unwrap(),
        };
        std::fs::create_dir_all(host.run()).unwrap();
        std::fs::create_dir_all(host.state()).unwrap();
        host
    }

    fn run(&self) -> PathBuf {
        self.dir.path().join("run")
    }

    fn state(&self) -> PathBuf {
        self.dir.path().join("state")
    }

    /// `hgcd ARGS` as a unit's or a user's command on this host.
    fn hgcd(&self, args: &[&str]) -> Command {
        let mut c = hgcd();
        c.env("RUNTIME_DIRECTORY", self.run())
            .env("STATE_DIRECTORY", self.state())
            .env_remove("RUST_LOG")
            .args(args);
        c
    }

    /// Start the daemon of the simulated unit `serial`, its log to `<serial>.log`.
    fn start(&self, serial: &str) -> Daemon {
        let config = self.dir.path().join(format!("{serial}.toml"));
        std::fs::write(
            &config,
            format!("[sim]\nserial = \"{serial}\"\n[servo]\nlock_memory = false\n"),
        )
        .unwrap();
        let log = self.dir.path().join(format!("{serial}.log"));
        let child = self
            .hgcd(&["--config", config.to_str().unwrap()])
            .args(["run", "--device", "sim:point-mass", "--virtual-time"])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        Daemon {
            child,
            log,
            id: format!("sim-point-mass-{serial}"),
        }
    }

    /// The daemons listening, by device id, once `ids` are all among them.
    fn wait_for_daemons(&self, ids: &[&str]) -> Vec<endpoint::Instance> {
        wait_for(&format!("daemons {ids:?}"), || {
            let running = endpoint::running(&self.run()).unwrap();
            if ids
                .iter()
                .all(|id| running.iter().any(|i| i.device_id == *id))
            {
                Some(running)
            } else {
                std::thread::sleep(std::time::Duration::from_millis(50));
                None
            }
        })
    }
}

/// A daemon process, killed if the test ends before it stops it.
struct Daemon {
    child: Child,
    log: PathBuf,
    id: String,
}

impl Daemon {
    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// SIGTERM, as `systemctl stop` sends it; the daemon ends with status 0.
    fn stop(mut self) {
        // SAFETY: kill(2) on our own child, not yet reaped.
        assert_eq!(
            unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) },
            0
        );
        let status = self.child.wait().unwrap();
        assert_eq!(status.code(), Some(0), "{}", self.log());
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn text(out: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `command`'s output, once it succeeded.
fn succeeds(mut command: Command) -> String {
    let out = command.output().unwrap();
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}{stderr}");
    stdout
}

/// `command`'s one-line error, once it failed with status 1.
fn fails(mut command: Command) -> String {
    let out = command.output().unwrap();
    let (stdout, stderr) = text(&out);
    assert_eq!(out.status.code(), Some(1), "{stdout}{stderr}");
    assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    stderr
}

fn grid_id(path: &Path) -> String {
    let grid = GridFile::load(path).unwrap();
    grid.device.expect("the grid names its device").id
}

#[test]
fn two_daemons_on_two_devices_serve_side_by_side_and_each_calibrates_its_own() {
    let host = Host::new();
    let (left, right) = (host.start("L"), host.start("R"));
    let (l, r) = (left.id.clone(), right.id.clone());
    // Both serve, each on the socket named after its device.
    let found = host.wait_for_daemons(&[&l, &r]);
    let sockets: Vec<PathBuf> = found.iter().map(|i| i.socket.clone()).collect();
    assert_eq!(
        sockets,
        [&l, &r].map(|id| endpoint::socket_path(&host.run(), id)),
        "{}{}",
        left.log(),
        right.log()
    );

    // `hgcd status` lists both; naming one shows that one.
    let both = succeeds(host.hgcd(&["status"]));
    for id in [&l, &r] {
        assert!(both.contains(&format!("sim:point-mass ({id})")), "{both}");
    }
    assert_eq!(both.matches("compensation  none").count(), 2, "{both}");
    let one = succeeds(host.hgcd(&["status", "--device", &r]));
    assert!(one.contains(&r) && !one.contains(&l), "{one}");

    // Two running: a command that must pick one says which are there; an unknown device is named.
    let several = fails(host.hgcd(&["calibrate", "--via-daemon", "--yes"]));
    assert!(
        several.contains("2 daemons are running")
            && several.contains(&l)
            && several.contains(&r)
            && several.contains("--device"),
        "{several}"
    );
    let unknown = fails(host.hgcd(&["status", "--device", "hid:1209:4847"]));
    assert!(
        unknown.contains("no daemon for device `hid:1209:4847` is running") && unknown.contains(&l),
        "{unknown}"
    );

    // Each calibration lands in its own daemon's grid, and each daemon then uses its own.
    for id in [&l, &r] {
        let said = succeeds(host.hgcd(&["calibrate", "--via-daemon", "--yes", "--device", id]));
        let grid = host.state().join(format!("{id}.toml"));
        assert!(
            said.contains(&format!("now uses {}", grid.display())),
            "{said}"
        );
        assert_eq!(grid_id(&grid), *id);
    }
    let mut names = common::file_names(&host.state());
    names.retain(|n| n.ends_with(".toml"));
    assert_eq!(names, [format!("{l}.toml"), format!("{r}.toml")]);

    // A client of the right-hand daemon, then the left-hand one stops.
    let mut client = Client::connect(&sockets[1], Role::Control, "right hand").unwrap();
    client.set_read_timeout(Some(WAIT)).unwrap();
    left.stop();
    assert!(
        !sockets[0].exists(),
        "the stopped daemon removes its socket"
    );
    assert!(sockets[1].exists(), "and leaves the other's alone");
    // The other's client is untouched: it still owns the force and gets answers.
    let status = client.status().unwrap();
    assert_eq!(status.device_id, r);
    assert_eq!(status.owner.as_deref(), Some("right hand"));
    assert_eq!(status.mode, Compensating::Vector);
    let after = succeeds(host.hgcd(&["status"]));
    assert!(after.contains(&r) && !after.contains(&l), "{after}");
    drop(client);
    right.stop();
    let none = fails(host.hgcd(&["status"]));
    assert!(none.contains("no daemon is running"), "{none}");
}
