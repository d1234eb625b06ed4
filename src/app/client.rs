//! Client library for applications (`hgcd::client`): connect to the daemon, render a force offset
//! Z_E, read the device state, ask for status or a calibration. Blocking, one connection per
//! `Client`; see `examples/virtual_wall.rs`, and `examples/two_handles.rs` for two daemons.

use std::collections::VecDeque;
use std::io::{ErrorKind, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use super::endpoint::{self, FindError};
pub use super::protocol::{
    CalibrationStage, Compensating, ModelStale, Reply, Role, StaleEvidence, StateSample, Status,
};
use super::protocol::{
    Request, APP_PROTOCOL_VERSION, MAX_DEVICE_ID_LEN, MAX_DEVICE_LEN, MAX_FORCE_N, MAX_RATE_HZ,
    MAX_REPLY_LEN, REPLY_LINE_TIME,
};
use crate::sys::wait_readable;

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("cannot connect to the hgcd socket {path} ({hint})")]
    Connect {
        path: String,
        /// What to do about it.
        hint: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("socket I/O: {0}")]
    Io(#[from] std::io::Error),
    #[error("the daemon closed the connection")]
    Closed,
    #[error("the daemon sent something this client does not understand: {0}")]
    Protocol(String),
    #[error("the daemon refused: {0}")]
    Refused(String),
    #[error("no welcome from the daemon within {} s", WELCOME_WAIT.as_secs())]
    NoWelcome,
}

/// How long [`Client::hello`] waits for the welcome to begin.
pub const WELCOME_WAIT: Duration = Duration::from_secs(5);

/// What to do when connecting to the socket failed with `e`.
fn connect_hint(e: &std::io::Error) -> &'static str {
    match e.kind() {
        std::io::ErrorKind::PermissionDenied => {
            "this user may not connect: join group hgcd (docs/install.md §3), or give a socket you \
             may use with --socket PATH"
        }
        _ => {
            "is `hgcd run` running? A daemon listening on another socket is reached with --socket \
             PATH"
        }
    }
}

/// One connection to the daemon.
pub struct Client {
    stream: UnixStream,
    /// Reply lines read, without their newlines, not yet returned.
    lines: VecDeque<Vec<u8>>,
    /// The bytes read after the last newline: the start of the next reply line.
    partial: Vec<u8>,
    /// When the first byte of `partial` arrived.
    began: Instant,
    seq: u64,
    /// Role granted by the daemon.
    pub role: Role,
    pub client_id: u64,
    pub device: String,
    pub device_id: String,
    /// Servo rate, Hz.
    pub rate_hz: f64,
    /// The largest force component the daemon accepts, N (see [`Client::within_limit`]).
    pub max_force: f64,
}

impl Client {
    /// Connect to the socket at `path` and say hello asking for `role`: [`Client::open`] then
    /// [`Client::hello`]. The granted role may be `Observe` when another client already owns the
    /// force.
    ///
    /// Errors: [`ClientError::Connect`] when nobody listens there, then as [`Client::hello`].
    pub fn connect(path: &Path, role: Role, name: &str) -> Result<Self, ClientError> {
        let mut client = Self::open(path)?;
        client.hello(role, name)?;
        Ok(client)
    }

    /// Connect to the daemon of `device` (a device id or spec; None: the only daemon running) in
    /// the runtime directory ([`endpoint::find`]) and say hello asking for `role`.
    ///
    /// Errors: [`FindError::NoDaemon`], `NoneFor` or `Several` when no single daemon fits, else
    /// as [`Client::connect`] (in `FindError::Client`).
    pub fn connect_to(device: Option<&str>, role: Role, name: &str) -> Result<Self, FindError> {
        let found = endpoint::find(&endpoint::runtime_dir(), device)?;
        Ok(Self::connect(&found.socket, role, name)?)
    }

    /// Connect to the socket at `path` without saying hello: the daemon refuses every request
    /// but [`Client::hello`], which must follow within `app.hello_timeout_ms`.
    ///
    /// Errors: [`ClientError::Connect`] when nobody listens there.
    pub fn open(path: &Path) -> Result<Self, ClientError> {
        let stream = UnixStream::connect(path).map_err(|source| ClientError::Connect {
            path: path.display().to_string(),
            hint: connect_hint(&source),
            source,
        })?;
        Ok(Self {
            stream,
            lines: VecDeque::new(),
            partial: Vec::new(),
            began: Instant::now(),
            seq: 0,
            role: Role::Observe,
            client_id: 0,
            device: String::new(),
            device_id: String::new(),
            rate_hz: 0.0,
            max_force: 0.0,
        })
    }

    /// Say hello asking for `role` (once, first, on a connection from [`Client::open`]) and
    /// fill in `role` (check it), `client_id`, `device`, `device_id`, `rate_hz` and `max_force`
    /// from the welcome.
    ///
    /// Errors: `Refused` when the daemon refuses the hello (a second one included), `NoWelcome`
    /// when none begins within [`WELCOME_WAIT`], `Protocol` for a welcome with a field out of
    /// its range (docs/app-protocol.md §5), `Closed` or `Io` when the conversation breaks.
    pub fn hello(&mut self, role: Role, name: &str) -> Result<(), ClientError> {
        self.send(&Request::Hello {
            version: APP_PROTOCOL_VERSION,
            role,
            name: name.to_string(),
        })?;
        let welcome = self
            .next_reply_within(WELCOME_WAIT)?
            .ok_or(ClientError::NoWelcome)?;
        let Reply::Welcome {
            version,
            role: granted,
            client_id,
            device,
            device_id,
            rate_hz,
            max_force_n,
        } = welcome
        else {
            return Err(ClientError::Protocol(format!(
                "expected welcome, got {}",
                shown(&format!("{welcome:?}"))
            )));
        };
        let problem = if version != APP_PROTOCOL_VERSION {
            Some(format!(
                "version {version}: this client speaks {APP_PROTOCOL_VERSION}"
            ))
        } else if !(granted == role || granted == Role::Observe) {
            Some(format!(
                "role {granted:?} granted to a hello asking for {role:?}"
            ))
        } else if client_id == 0 {
            Some("client_id 0: ids start at 1".into())
        } else if !(1..=MAX_DEVICE_LEN).contains(&device.chars().count())
            || device.chars().any(char::is_control)
        {
            Some(format!(
                "device {:?}: a spec has 1 to {MAX_DEVICE_LEN} characters, none a control \
                 character",
                shown(&device)
            ))
        } else if !(1..=MAX_DEVICE_ID_LEN).contains(&device_id.len())
            || !device_id
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
        {
            Some(format!(
                "device_id {:?}: an id has 1 to {MAX_DEVICE_ID_LEN} ASCII letters, digits, '-' \
                 and '_'",
                shown(&device_id)
            ))
        } else if !(rate_hz > 0.0 && rate_hz <= MAX_RATE_HZ) {
            Some(format!(
                "rate_hz {rate_hz}: the servo rate is above 0 and at most {MAX_RATE_HZ} Hz"
            ))
        } else if !(max_force_n > 0.0 && max_force_n <= MAX_FORCE_N) {
            Some(format!(
                "max_force_n {max_force_n}: the limit is above 0 and at most {MAX_FORCE_N} N"
            ))
        } else {
            None
        };
        if let Some(problem) = problem {
            return Err(ClientError::Protocol(format!("a welcome with {problem}")));
        }
        self.role = granted;
        self.client_id = client_id;
        self.device = device;
        self.device_id = device_id;
        self.rate_hz = rate_hz;
        self.max_force = max_force_n;
        Ok(())
    }

    fn send(&mut self, request: &Request) -> Result<(), ClientError> {
        let mut line = serde_json::to_string(request).expect("requests always serialise");
        line.push('\n');
        (&self.stream).write_all(line.as_bytes())?;
        Ok(())
    }

    /// Render `force` (N) on top of gravity compensation until the next call. Send it at least
    /// every 50 ms (the daemon's default `stale_offset_ms`), or it ramps to zero.
    ///
    /// Errors: [`ClientError::Io`] when the daemon is gone. A refusal (not the owner, out of
    /// range) arrives later as a `Reply::Error`.
    pub fn set_force(&mut self, force: Vector3<f64>) -> Result<(), ClientError> {
        self.seq += 1;
        let seq = self.seq;
        self.send(&Request::SetForce {
            seq,
            force: force.into(),
        })
    }

    /// `force` (N) scaled down, its direction kept, to a magnitude of at most the daemon's limit
    /// [`Client::max_force`]. The daemon refuses (fatally) a component beyond the limit, and its
    /// safety layer clamps the magnitude of the total force to it anyway: an application whose
    /// force law can ask for more (a stiff wall deep inside) sends this instead.
    pub fn within_limit(&self, force: Vector3<f64>) -> Vector3<f64> {
        let norm = force.norm();
        if norm > self.max_force {
            force * (self.max_force / norm)
        } else {
            force
        }
    }

    /// Sequence number of the last `set_force` sent.
    pub fn last_seq(&self) -> u64 {
        self.seq
    }

    /// Stream the device state at `rate_hz` (0 stops it).
    ///
    /// Errors: [`ClientError::Io`] when the daemon is gone.
    pub fn subscribe(&mut self, rate_hz: f64) -> Result<(), ClientError> {
        self.send(&Request::Subscribe { rate_hz })
    }

    /// Ask the daemon to calibrate; progress arrives as `Reply::Calibration`.
    ///
    /// Errors: [`ClientError::Io`] when the daemon is gone.
    pub fn request_calibration(&mut self) -> Result<(), ClientError> {
        self.send(&Request::Calibrate {})
    }

    /// Ask the daemon to check its device against its grid (`hgcd check --via-daemon`), taking
    /// a payload and tilt found into the grid with `apply`; progress arrives as
    /// `Reply::Calibration`, the answer as `Reply::Checked`.
    ///
    /// Errors: [`ClientError::Io`] when the daemon is gone.
    pub fn request_check(&mut self, apply: bool) -> Result<(), ClientError> {
        self.send(&Request::Check { apply })
    }

    /// Ask the daemon to put back the model kept beside its grid, without waiting: a
    /// `Reply::Reverted` follows, or a `Reply::Error`.
    ///
    /// Errors: [`ClientError::Io`] when the daemon is gone.
    pub fn request_revert(&mut self) -> Result<(), ClientError> {
        self.send(&Request::Revert {})
    }

    /// Ask for the daemon's status without waiting for it: it arrives as a `Reply::Status`.
    ///
    /// Errors: [`ClientError::Io`] when the daemon is gone.
    pub fn request_status(&mut self) -> Result<(), ClientError> {
        self.send(&Request::Status {})
    }

    /// Limit how long the next reads may block waiting for a reply to begin (None: forever).
    ///
    /// Errors: [`ClientError::Io`] for a zero duration (as `std` refuses it).
    pub fn set_read_timeout(&mut self, timeout: Option<Duration>) -> Result<(), ClientError> {
        self.stream.set_read_timeout(timeout)?;
        Ok(())
    }

    /// The next reply of any kind, control characters (terminal escapes among them) removed
    /// from its text. A fatal error from the daemon is returned as `Refused`.
    ///
    /// Errors: `Protocol` for a line that is not a reply (not UTF-8, not protocol JSON, longer
    /// than [`MAX_REPLY_LEN`], or not ended within [`REPLY_LINE_TIME`] of its first byte),
    /// `Closed`, or `Io` (a read timeout is one of kind `WouldBlock`/`TimedOut`).
    pub fn next_reply(&mut self) -> Result<Reply, ClientError> {
        let line = self.next_line()?;
        let line = std::str::from_utf8(&line).map_err(|_| {
            ClientError::Protocol(format!(
                "a line that is not UTF-8: {}",
                shown(&String::from_utf8_lossy(&line))
            ))
        })?;
        let mut reply: Reply = serde_json::from_str(line)
            .map_err(|e| ClientError::Protocol(format!("{e}: {}", shown(line))))?;
        let texts: Vec<&mut String> = match &mut reply {
            Reply::Error { message, .. } | Reply::Calibration { message, .. } => vec![message],
            Reply::Status(s) => [&mut s.device, &mut s.device_id]
                .into_iter()
                .chain(s.grid.as_mut())
                .chain(s.owner.as_mut())
                .collect(),
            Reply::Reverted(r) => r
                .applied_now
                .iter_mut()
                .chain(r.applied_before.iter_mut())
                .filter_map(|a| a.hgcd_version.as_mut())
                .collect(),
            Reply::Welcome { .. } | Reply::State(_) | Reply::Checked(_) => Vec::new(),
        };
        for text in texts {
            text.retain(|c| !c.is_control());
        }
        let paths: Vec<&mut std::path::PathBuf> = match &mut reply {
            Reply::Checked(found) => std::iter::once(&mut found.grid)
                .chain(found.applied.as_mut())
                .collect(),
            Reply::Reverted(r) => vec![&mut r.grid],
            _ => Vec::new(),
        };
        for path in paths {
            let mut text = path.to_string_lossy().into_owned();
            text.retain(|c| !c.is_control());
            *path = text.into();
        }
        match reply {
            Reply::Error {
                message,
                fatal: true,
            } => Err(ClientError::Refused(message)),
            other => Ok(other),
        }
    }

    /// The next reply line, without its newline. The wait for it to begin is the read timeout's;
    /// once begun it must end within [`REPLY_LINE_TIME`] of its first byte.
    fn next_line(&mut self) -> Result<Vec<u8>, ClientError> {
        let mut chunk = [0; 8192];
        loop {
            if let Some(line) = self.lines.pop_front() {
                return Ok(line);
            }
            if !self.partial.is_empty() {
                let left = (self.began + REPLY_LINE_TIME).saturating_duration_since(Instant::now());
                if !wait_readable(&self.stream, left)? {
                    if left.is_zero() {
                        return Err(ClientError::Protocol(format!(
                            "a line not ended within {} s of its first byte: {}",
                            REPLY_LINE_TIME.as_secs_f64(),
                            shown(&String::from_utf8_lossy(&self.partial))
                        )));
                    }
                    continue; // interrupted
                }
            }
            let n = match (&self.stream).read(&mut chunk) {
                Ok(0) => return Err(ClientError::Closed),
                Ok(n) => n,
                Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                Err(e) => return Err(e.into()),
            };
            let mut rest = &chunk[..n];
            if self.partial.is_empty() || rest.contains(&b'\n') {
                self.began = Instant::now();
            }
            while let Some(end) = rest.iter().position(|&b| b == b'\n') {
                let mut line = std::mem::take(&mut self.partial);
                line.extend_from_slice(&rest[..end]);
                self.lines.push_back(line);
                rest = &rest[end + 1..];
            }
            self.partial.extend_from_slice(rest);
            if self
                .lines
                .iter()
                .chain([&self.partial])
                .any(|l| l.len() > MAX_REPLY_LEN)
            {
                return Err(ClientError::Protocol(format!(
                    "a line longer than {MAX_REPLY_LEN} bytes"
                )));
            }
        }
    }

    /// The next reply if one begins to arrive within `timeout` (`Duration::ZERO`: only one
    /// already here), else `None`; a reply that has begun to arrive is read to its end. A fatal
    /// error from the daemon is returned as `Refused`. Unlike a read timeout, running out of
    /// time never cuts a reply in half.
    ///
    /// Errors: as [`Client::next_reply`].
    pub fn next_reply_within(&mut self, timeout: Duration) -> Result<Option<Reply>, ClientError> {
        let deadline = Instant::now() + timeout;
        while self.lines.is_empty() && self.partial.is_empty() {
            let left = deadline.saturating_duration_since(Instant::now());
            if wait_readable(&self.stream, left)? {
                break;
            }
            if left.is_zero() {
                return Ok(None);
            }
        }
        self.next_reply().map(Some)
    }

    /// The next state sample. Other replies in between (non-fatal errors such as "does not own
    /// the force", calibration progress) are skipped: use [`Client::next_reply`] to see them.
    pub fn next_state(&mut self) -> Result<StateSample, ClientError> {
        loop {
            if let Reply::State(s) = self.next_reply()? {
                return Ok(s);
            }
        }
    }

    /// Ask for and wait for the daemon's status (state samples in between are skipped).
    ///
    /// Errors: [`ClientError::Refused`] for a refusal, else as [`Client::next_reply`].
    pub fn status(&mut self) -> Result<Status, ClientError> {
        self.request_status()?;
        loop {
            if let Reply::Status(s) = self.next_reply()? {
                return Ok(*s);
            }
        }
    }
}

/// Daemon text fit for a message: control characters removed, at most 200 characters.
fn shown(text: &str) -> String {
    let mut chars = text.chars().filter(|c| !c.is_control());
    let mut shown: String = chars.by_ref().take(200).collect();
    if chars.next().is_some() {
        shown.push('…');
    }
    shown
}
