//! Client library for applications (`hgcd::client`): connect to the daemon, render a force offset
//! Z_E, read the device state, ask for status or a calibration. Blocking, one connection per
//! `Client`; see `examples/virtual_wall.rs`, and `examples/two_handles.rs` for two daemons.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::time::Duration;

use nalgebra::Vector3;

use super::endpoint::{self, FindError};
pub use super::protocol::{CalibrationStage, Compensating, Reply, Role, StateSample, Status};
use super::protocol::{Request, APP_PROTOCOL_VERSION, MAX_LINE_LEN};
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
}

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
    writer: UnixStream,
    reader: BufReader<UnixStream>,
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
    /// Errors: [`ClientError::Connect`] when nobody listens there, `Refused` when the daemon
    /// refuses the hello, `Closed`, `Io` or `Protocol` when the conversation breaks.
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
    /// Errors: [`ClientError::Connect`] when nobody listens there, `Io` when the socket cannot
    /// be shared between reader and writer.
    pub fn open(path: &Path) -> Result<Self, ClientError> {
        let stream = UnixStream::connect(path).map_err(|source| ClientError::Connect {
            path: path.display().to_string(),
            hint: connect_hint(&source),
            source,
        })?;
        let writer = stream.try_clone()?;
        Ok(Self {
            writer,
            reader: BufReader::new(stream),
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
    /// fill in `role` (check it), `client_id`, `device`, `device_id`, `rate_hz` and `max_force` from the
    /// welcome.
    ///
    /// Errors: `Refused` when the daemon refuses the hello (a second one included), `Closed`,
    /// `Io` or `Protocol` when the conversation breaks.
    pub fn hello(&mut self, role: Role, name: &str) -> Result<(), ClientError> {
        self.send(&Request::Hello {
            version: APP_PROTOCOL_VERSION,
            role,
            name: name.to_string(),
        })?;
        match self.next_reply()? {
            Reply::Welcome {
                role,
                client_id,
                device,
                device_id,
                rate_hz,
                max_force_n,
                ..
            } => {
                self.role = role;
                self.client_id = client_id;
                self.device = device;
                self.device_id = device_id;
                self.rate_hz = rate_hz;
                self.max_force = max_force_n;
                Ok(())
            }
            other => Err(ClientError::Protocol(format!(
                "expected welcome, got {other:?}"
            ))),
        }
    }

    fn send(&mut self, request: &Request) -> Result<(), ClientError> {
        let mut line = serde_json::to_string(request).expect("requests always serialise");
        line.push('\n');
        self.writer.write_all(line.as_bytes())?;
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

    /// Ask for the daemon's status without waiting for it: it arrives as a `Reply::Status`.
    ///
    /// Errors: [`ClientError::Io`] when the daemon is gone.
    pub fn request_status(&mut self) -> Result<(), ClientError> {
        self.send(&Request::Status {})
    }

    /// Limit how long the next reads may block (None: forever).
    ///
    /// Errors: [`ClientError::Io`] for a zero duration (as `std` refuses it).
    pub fn set_read_timeout(&mut self, timeout: Option<Duration>) -> Result<(), ClientError> {
        self.reader.get_ref().set_read_timeout(timeout)?;
        Ok(())
    }

    /// The next reply of any kind. A fatal error from the daemon is returned as `Refused`.
    pub fn next_reply(&mut self) -> Result<Reply, ClientError> {
        let mut line = String::new();
        let n =
            std::io::Read::take(&mut self.reader, 64 * MAX_LINE_LEN as u64).read_line(&mut line)?;
        if n == 0 {
            return Err(ClientError::Closed);
        }
        let reply: Reply = serde_json::from_str(line.trim_end())
            .map_err(|e| ClientError::Protocol(format!("{e}: {}", line.trim_end())))?;
        match reply {
            Reply::Error {
                message,
                fatal: true,
            } => Err(ClientError::Refused(message)),
            other => Ok(other),
        }
    }

    /// The next reply if one begins to arrive within `timeout` (`Duration::ZERO`: only one
    /// already here), else `None`; a reply that has begun to arrive is read to its end. A fatal
    /// error from the daemon is returned as `Refused`. Unlike a read timeout, running out of
    /// time never cuts a reply in half.
    ///
    /// Errors: as [`Client::next_reply`].
    pub fn next_reply_within(&mut self, timeout: Duration) -> Result<Option<Reply>, ClientError> {
        if self.reader.buffer().is_empty() && !wait_readable(self.reader.get_ref(), timeout)? {
            return Ok(None);
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
    /// Errors: [`ClientError::Refused`] for a refusal, `Closed`, `Io` or `Protocol` when the
    /// conversation breaks (a read timeout is an `Io` error of kind `WouldBlock`/`TimedOut`).
    pub fn status(&mut self) -> Result<Status, ClientError> {
        self.request_status()?;
        loop {
            if let Reply::Status(s) = self.next_reply()? {
                return Ok(*s);
            }
        }
    }
}
