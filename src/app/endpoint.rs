//! Where each daemon listens, and how a client finds one. One daemon runs per device; its socket
//! is named after the device's grid id (`grid::DeviceIdentity::grid_id`: `<model>-<serial>`, or
//! the spec's id for a device that does not name itself) in the runtime directory all instances
//! share: `/run/hgcd/<device-id>.sock` under the shipped unit. A client names a daemon by device
//! (`--device SPEC`) or, with one daemon running, not at all. An explicit socket (`--socket`,
//! `app.socket`) bypasses all of this on both sides.

use std::path::{Path, PathBuf};

use thiserror::Error;

use super::client::{Client, ClientError, Role};

/// The runtime directory when `$RUNTIME_DIRECTORY` is not set (the shipped unit sets it to it).
pub const DEFAULT_RUNTIME_DIR: &str = "/run/hgcd";

/// The directory daemons' sockets live in: the first entry of `$RUNTIME_DIRECTORY` (systemd),
/// else [`DEFAULT_RUNTIME_DIR`].
pub fn runtime_dir() -> PathBuf {
    std::env::var("RUNTIME_DIRECTORY")
        .ok()
        .and_then(|dirs| dirs.split(':').find(|s| !s.is_empty()).map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from(DEFAULT_RUNTIME_DIR))
}

/// The socket of the daemon of the device with grid id `device_id`, in `dir`: the one place an
/// instance's endpoint is derived from its device.
pub fn socket_path(dir: &Path, device_id: &str) -> PathBuf {
    dir.join(format!("{device_id}.sock"))
}

/// A daemon found listening, as its welcome describes it.
#[derive(Clone, Debug, PartialEq)]
pub struct Instance {
    pub socket: PathBuf,
    /// The spec it opened its device with (`welcome.device`).
    pub device: String,
    /// Its device's grid id (`welcome.device_id`).
    pub device_id: String,
}

impl Instance {
    /// Whether `spec` names this daemon's device: its grid id, its spec, or its spec without
    /// the trailing parts the daemon filled in (`hid:1209:4847` for `hid:1209:4847:SN1`).
    pub fn matches(&self, spec: &str) -> bool {
        spec == self.device_id
            || spec == self.device
            || self
                .device
                .strip_prefix(spec)
                .is_some_and(|rest| rest.starts_with(':'))
    }
}

impl std::fmt::Display for Instance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({})", self.device_id, self.device)
    }
}

/// Why no single daemon was found.
#[derive(Debug, Error)]
pub enum FindError {
    #[error(
        "no daemon is running (no live socket in {}): start one (`hgcd run`, or `systemctl \
         start hgcd@DEVICE`), or name its socket with --socket PATH",
        dir.display()
    )]
    NoDaemon { dir: PathBuf },
    #[error("no daemon for device `{spec}` is running; running: {}", list(running))]
    NoneFor {
        spec: String,
        running: Vec<Instance>,
    },
    #[error(
        "{} daemons are running{}: {}; say which with --device SPEC (a device id or spec)",
        matching.len(),
        spec.as_ref().map(|s| format!(" for `{s}`")).unwrap_or_default(),
        list(matching)
    )]
    Several {
        spec: Option<String>,
        matching: Vec<Instance>,
    },
    #[error(
        "cannot list the runtime directory {} ({error}): {}",
        dir.display(),
        if error.kind() == std::io::ErrorKind::PermissionDenied {
            "join group hgcd (docs/install.md §3), or give a socket you may use with --socket PATH"
        } else {
            "give the daemon's socket with --socket PATH"
        }
    )]
    List { dir: PathBuf, error: std::io::Error },
    /// A socket there that cannot be asked (permission, a daemon that does not answer).
    #[error("asking {} which device it serves", socket.display())]
    Ask {
        socket: PathBuf,
        #[source]
        source: ClientError,
    },
    /// Connecting to the daemon found failed.
    #[error(transparent)]
    Client(#[from] ClientError),
}

fn list(instances: &[Instance]) -> String {
    let names: Vec<String> = instances.iter().map(Instance::to_string).collect();
    names.join(", ")
}

/// Every daemon listening in `dir`, by socket name. Sockets nobody listens on (left by a daemon
/// that was killed) are skipped.
///
/// Errors: [`FindError::List`] when `dir` cannot be read (a missing `dir` lists nothing), `Ask`
/// when a live socket cannot be asked (permission denied, no welcome within
/// [`WELCOME_WAIT`](super::client::WELCOME_WAIT)).
pub fn running(dir: &Path) -> Result<Vec<Instance>, FindError> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(error) => {
            return Err(FindError::List {
                dir: dir.to_path_buf(),
                error,
            })
        }
    };
    let mut sockets: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "sock"))
        .collect();
    sockets.sort();
    let mut found = Vec::new();
    for socket in sockets {
        let welcome = Client::connect(&socket, Role::Observe, "hgcd lookup");
        match welcome {
            Ok(client) => found.push(Instance {
                socket,
                device: client.device,
                device_id: client.device_id,
            }),
            Err(ClientError::Connect { source, .. })
                if matches!(
                    source.kind(),
                    std::io::ErrorKind::ConnectionRefused | std::io::ErrorKind::NotFound
                ) => {}
            Err(source) => return Err(FindError::Ask { socket, source }),
        }
    }
    Ok(found)
}

/// The one daemon in `dir` for the device `spec` ([`Instance::matches`]), or with `spec` None
/// the only one running.
///
/// Errors: [`FindError::NoDaemon`], `NoneFor`, `Several`, and as [`running`].
pub fn find(dir: &Path, spec: Option<&str>) -> Result<Instance, FindError> {
    let all = running(dir)?;
    if all.is_empty() {
        return Err(FindError::NoDaemon {
            dir: dir.to_path_buf(),
        });
    }
    let mut matching: Vec<Instance> = match spec {
        Some(s) => all.iter().filter(|i| i.matches(s)).cloned().collect(),
        None => all.clone(),
    };
    match (matching.len(), spec) {
        (1, _) => Ok(matching.remove(0)),
        (0, Some(s)) => Err(FindError::NoneFor {
            spec: s.to_string(),
            running: all,
        }),
        _ => Err(FindError::Several {
            spec: spec.map(str::to_string),
            matching,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn instance(device: &str, device_id: &str) -> Instance {
        Instance {
            socket: PathBuf::from(format!("/run/hgcd/{device_id}.sock")),
            device: device.into(),
            device_id: device_id.into(),
        }
    }

    #[test]
    fn a_device_is_named_by_its_id_its_spec_or_its_spec_without_the_serial() {
        let hid = instance("hid:1209:4847:SN1", "Omega-SN1");
        for spec in [
            "Omega-SN1",
            "hid:1209:4847:SN1",
            "hid:1209:4847",
            "hid:1209",
        ] {
            assert!(hid.matches(spec), "{spec}");
        }
        for spec in [
            "Omega",
            "hid:1209:484",
            "hid:1209:4847:SN",
            "sim:point-mass",
        ] {
            assert!(!hid.matches(spec), "{spec}");
        }
        let sim = instance("sim:point-mass", "sim-point-mass-L");
        assert!(sim.matches("sim:point-mass") && sim.matches("sim-point-mass-L"));
        assert!(!sim.matches("sim-point-mass"));
    }

    #[test]
    fn an_instance_socket_is_named_after_its_device() {
        assert_eq!(
            socket_path(Path::new("/run/hgcd"), "Omega-SN1"),
            Path::new("/run/hgcd/Omega-SN1.sock")
        );
    }

    #[test]
    fn an_empty_or_missing_directory_has_no_daemon_and_says_how_to_start_one() {
        let dir = tempfile::tempdir().unwrap();
        let none = find(&dir.path().join("missing"), None).unwrap_err();
        assert!(matches!(none, FindError::NoDaemon { .. }), "{none}");
        assert!(none.to_string().contains("--socket PATH"), "{none}");
        // A socket file nobody listens on is a daemon that was killed: skipped.
        drop(std::os::unix::net::UnixListener::bind(dir.path().join("dead.sock")).unwrap());
        assert_eq!(running(dir.path()).unwrap(), vec![]);
    }

    #[test]
    fn a_socket_that_is_not_a_daemon_is_named() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("other.sock");
        let listener = std::os::unix::net::UnixListener::bind(&path).unwrap();
        std::thread::spawn(move || {
            let (mut stream, _) = listener.accept().unwrap();
            let _ = stream.write_all(b"not json\n");
        });
        let e = find(dir.path(), None).unwrap_err();
        assert!(
            matches!(&e, FindError::Ask { socket, .. } if *socket == path),
            "{e}"
        );
        assert!(e.to_string().contains("other.sock"), "{e}");
    }
}
