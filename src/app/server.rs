//! The application socket: a listener thread, and per client a reader thread (validates requests)
//! and a writer thread (sends replies). Force offsets go straight to the servo thread through a
//! bounded channel where the newest wins; everything else goes to the daemon's hub. A client that
//! misbehaves is closed with a logged reason and affects nobody else.
//!
//! Admission: up to `max_clients` connections are served in full. While they are all taken, one
//! more connection is admitted as a *status-only* connection (granted observe, may send `hello`
//! and `status` only), so `hgcd status` answers whoever holds the places; any further connection
//! is refused. Every connection must say hello within `hello_timeout` of being accepted (an
//! absolute deadline, however the bytes trickle in); a status-only connection is closed at that
//! deadline whatever it sends.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, ErrorKind, Write};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};
use nalgebra::Vector3;
use tracing::{info, warn};

use super::protocol::{
    encode_reply, parse_request, Reply, Request, Role, APP_PROTOCOL_VERSION, MAX_LINE_LEN,
};
use crate::mailbox::{CommandSender, OffsetCommand, OffsetSender, ServoCommand};

/// Stack of the listener and client threads. Small on purpose: with memory locked (mlockall with
/// MCL_FUTURE) every thread's stack counts against the memlock limit.
const CLIENT_STACK: usize = 256 * 1024;

/// One connected client, as the registry knows it.
pub struct ClientEntry {
    pub name: String,
    pub role: Role,
    /// Send every n-th servo state; 0: not subscribed.
    pub state_divider: u64,
    pub outbound: Sender<Reply>,
    /// Its welcome is queued: events for every client may follow it (never precede it).
    welcomed: bool,
    /// Admitted beyond `max_clients`: may only ask for status, closed at its hello deadline.
    status_only: bool,
    stream: UnixStream,
}

/// Who is connected and who owns the force.
#[derive(Default)]
pub struct Registry {
    pub clients: HashMap<u64, ClientEntry>,
    pub owner: Option<u64>,
    next_id: u64,
}

impl Registry {
    /// Name of the client owning the force.
    pub fn owner_name(&self) -> Option<String> {
        self.owner
            .and_then(|id| self.clients.get(&id))
            .map(|c| c.name.clone())
    }

    /// The queues of every welcomed client, for an event all of them get. A client still
    /// saying hello gets it only after its welcome, or not at all.
    pub fn welcomed_outbound(&self) -> Vec<Sender<Reply>> {
        self.clients
            .values()
            .filter(|c| c.welcomed)
            .map(|c| c.outbound.clone())
            .collect()
    }

    /// Close every connection (daemon shutdown).
    pub fn close_all(&self) {
        for c in self.clients.values() {
            let _ = c.stream.shutdown(std::net::Shutdown::Both);
        }
    }
}

pub type SharedRegistry = Arc<Mutex<Registry>>;

/// Lock the registry; a panic in another holder does not make its data unusable.
pub fn lock(registry: &SharedRegistry) -> MutexGuard<'_, Registry> {
    registry.lock().unwrap_or_else(|e| e.into_inner())
}

/// Requests the daemon's hub answers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HubRequest {
    Calibrate {
        client: u64,
    },
    /// `hgcd check --via-daemon`; `apply` takes what it finds into the grid.
    Check {
        client: u64,
        apply: bool,
    },
    /// `hgcd check --revert --via-daemon`: the model kept beside the grid put back.
    Revert {
        client: u64,
    },
    Status {
        client: u64,
    },
}

/// Everything client threads share.
pub struct ServerContext {
    pub registry: SharedRegistry,
    /// Commands to the servo thread.
    pub commands: CommandSender,
    /// Force offsets to the servo thread; the newest wins.
    pub offsets: OffsetSender,
    pub hub: Sender<HubRequest>,
    pub device: String,
    pub device_id: String,
    pub rate_hz: f64,
    pub max_force: f64,
    /// Connections served in full; one more may connect for status only.
    pub max_clients: usize,
    /// A client that has not said hello within this time of being accepted is closed; a
    /// status-only connection is closed at that deadline in any case.
    pub hello_timeout: Duration,
}

/// Bind the socket at `path` with permissions `mode`. A stale socket file (nobody listening) is
/// replaced; a live one means another daemon serves this path, which is an error.
pub fn bind(path: &Path, mode: u32) -> std::io::Result<UnixListener> {
    if path.exists() {
        use std::os::unix::fs::FileTypeExt;
        if !std::fs::symlink_metadata(path)?.file_type().is_socket() {
            return Err(std::io::Error::new(
                ErrorKind::AlreadyExists,
                format!(
                    "{} exists and is not a socket; not replacing it",
                    path.display()
                ),
            ));
        }
        match UnixStream::connect(path) {
            Ok(_) => {
                return Err(std::io::Error::new(
                    ErrorKind::AddrInUse,
                    format!("another hgcd daemon is listening on {}", path.display()),
                ))
            }
            Err(_) => std::fs::remove_file(path)?,
        }
    }
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir)?;
        }
    }
    let listener = UnixListener::bind(path)?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode))?;
    Ok(listener)
}

/// Accept clients until `stop` is set.
///
/// Errors: the `io::Error` of a thread that could not be started.
pub fn spawn_listener(
    listener: UnixListener,
    path: PathBuf,
    ctx: Arc<ServerContext>,
    stop: Arc<AtomicBool>,
) -> std::io::Result<JoinHandle<()>> {
    listener.set_nonblocking(true)?;
    thread::Builder::new()
        .name("hgcd-listener".into())
        .stack_size(CLIENT_STACK)
        .spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((stream, _)) => accept(stream, &ctx),
                    Err(e) if e.kind() == ErrorKind::WouldBlock => {
                        thread::sleep(Duration::from_millis(20))
                    }
                    Err(e) => {
                        warn!("application socket: accept failed: {e}");
                        thread::sleep(Duration::from_millis(100));
                    }
                }
            }
            lock(&ctx.registry).close_all();
            let _ = std::fs::remove_file(&path);
        })
}

/// What a status-only connection is told, and why its other requests are refused.
const STATUS_ONLY: &str =
    "the daemon has app.max_clients clients: this connection may only ask for status, and is \
     closed app.hello_timeout_ms after it connected";

fn accept(stream: UnixStream, ctx: &Arc<ServerContext>) {
    // The hello deadline counts from here, not from the last byte received.
    let deadline = Instant::now().checked_add(ctx.hello_timeout);
    let _ = stream.set_nonblocking(false);
    let (id, rx, status_only) = {
        let mut reg = lock(&ctx.registry);
        let full = reg.clients.values().filter(|c| !c.status_only).count() >= ctx.max_clients;
        if full && reg.clients.values().any(|c| c.status_only) {
            drop(reg);
            warn!("application socket: refused a client (max_clients reached)");
            let mut s = stream;
            let _ = s.write_all(
                encode_reply(&Reply::Error {
                    message: "too many clients".into(),
                    fatal: true,
                })
                .as_bytes(),
            );
            return;
        }
        let Ok(clone) = stream.try_clone() else {
            return;
        };
        reg.next_id += 1;
        let id = reg.next_id;
        let (tx, rx) = crossbeam_channel::bounded(256);
        reg.clients.insert(
            id,
            ClientEntry {
                name: format!("client-{id}"),
                role: Role::Observe,
                state_divider: 0,
                outbound: tx,
                welcomed: false,
                status_only: full,
                stream: clone,
            },
        );
        (id, rx, full)
    };
    if status_only {
        info!("application client {id} admitted for status only (max_clients reached)");
    }
    let Ok(write_half) = stream.try_clone() else {
        forget(ctx, id);
        return;
    };
    let ctx2 = ctx.clone();
    let spawned = thread::Builder::new()
        .name(format!("hgcd-client-{id}"))
        .stack_size(CLIENT_STACK)
        .spawn(move || {
            let writer = spawn_writer(write_half, rx, id);
            let reason = serve_client(stream, id, status_only, deadline, &ctx2);
            info!("application client {id} closed: {reason}");
            forget(&ctx2, id);
            if let Ok(w) = writer {
                let _ = w.join();
            }
        });
    if spawned.is_err() {
        forget(ctx, id);
    }
}

/// Remove a client; if it owned the force, its force goes at once.
fn forget(ctx: &ServerContext, id: u64) {
    let was_owner = {
        let mut reg = lock(&ctx.registry);
        reg.clients.remove(&id);
        if reg.owner == Some(id) {
            reg.owner = None;
            true
        } else {
            false
        }
    };
    if was_owner {
        send_command(ctx, ServoCommand::ClientGone(id));
    }
}

/// Hand a command to the servo thread; it takes its commands every tick, so a full queue means
/// the device is silent and the command is dropped (logged).
fn send_command(ctx: &ServerContext, command: ServoCommand) {
    if let Err(command) = ctx.commands.send(command) {
        warn!("servo loop not taking commands (device silent?): dropped {command:?}");
    }
}

fn spawn_writer(
    mut stream: UnixStream,
    replies: Receiver<Reply>,
    id: u64,
) -> std::io::Result<JoinHandle<()>> {
    let _ = stream.set_write_timeout(Some(Duration::from_millis(200)));
    thread::Builder::new()
        .name(format!("hgcd-client-{id}-w"))
        .stack_size(CLIENT_STACK)
        .spawn(move || {
            for reply in replies.iter() {
                let fatal = matches!(reply, Reply::Error { fatal: true, .. });
                if stream.write_all(encode_reply(&reply).as_bytes()).is_err() || fatal {
                    break;
                }
            }
            let _ = stream.shutdown(std::net::Shutdown::Both);
        })
}

/// Why no request line could be read.
#[derive(Debug, thiserror::Error)]
enum ReadError {
    #[error("the connection's time limit was reached")]
    Deadline,
    #[error("line longer than {MAX_LINE_LEN} bytes")]
    TooLong,
    #[error("connection closed in the middle of a line")]
    Unfinished,
    #[error("line is not UTF-8")]
    NotUtf8,
    #[error("read error: {0}")]
    Io(#[source] std::io::Error),
}

/// Read one line of at most `MAX_LINE_LEN` bytes (newline excluded). Ok(None) at end of stream.
/// With a `deadline`, every read is bounded by the time left until it, so a client that trickles
/// bytes cannot stretch the line past it.
fn read_line(
    reader: &mut BufReader<UnixStream>,
    deadline: Option<Instant>,
) -> Result<Option<String>, ReadError> {
    let mut line = Vec::with_capacity(128);
    loop {
        if let Some(deadline) = deadline {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(ReadError::Deadline);
            }
            reader
                .get_ref()
                .set_read_timeout(Some(left))
                .map_err(ReadError::Io)?;
        }
        let (taken, complete) = match reader.fill_buf() {
            Ok([]) if line.is_empty() => return Ok(None),
            Ok([]) => return Err(ReadError::Unfinished),
            Ok(chunk) => {
                let window = &chunk[..chunk.len().min(MAX_LINE_LEN + 1 - line.len())];
                match window.iter().position(|&b| b == b'\n') {
                    Some(end) => {
                        line.extend_from_slice(&window[..end]);
                        (end + 1, true)
                    }
                    None => {
                        line.extend_from_slice(window);
                        (window.len(), false)
                    }
                }
            }
            // A read timed out: the loop's head decides whether the deadline has passed.
            Err(e)
                if deadline.is_some()
                    && matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) =>
            {
                continue
            }
            Err(e) if e.kind() == ErrorKind::Interrupted => continue,
            Err(e) => return Err(ReadError::Io(e)),
        };
        reader.consume(taken);
        if complete {
            return String::from_utf8(line)
                .map(Some)
                .map_err(|_| ReadError::NotUtf8);
        }
        if line.len() > MAX_LINE_LEN {
            return Err(ReadError::TooLong);
        }
    }
}

/// How long a reply other than a state sample may wait for room in a client's queue.
pub const REPLY_WAIT: Duration = Duration::from_millis(100);

fn reply(ctx: &ServerContext, id: u64, r: Reply) {
    let outbound = lock(&ctx.registry)
        .clients
        .get(&id)
        .map(|c| c.outbound.clone());
    if let Some(tx) = outbound {
        let _ = tx.send_timeout(r, REPLY_WAIT);
    }
}

fn fatal(ctx: &ServerContext, id: u64, message: String) -> String {
    reply(
        ctx,
        id,
        Reply::Error {
            message: message.clone(),
            fatal: true,
        },
    );
    message
}

/// Serve one client until it leaves or breaks the protocol; returns the reason it ended.
/// `deadline`: when it must have said hello (a status-only connection: when it is closed); None
/// when the hello timeout is too long to represent.
fn serve_client(
    stream: UnixStream,
    id: u64,
    status_only: bool,
    mut deadline: Option<Instant>,
    ctx: &ServerContext,
) -> String {
    let mut reader = BufReader::new(stream);
    let mut session = Session {
        id,
        status_only,
        greeted: false,
        last_seq: None,
        ctx,
    };
    loop {
        let line = match read_line(&mut reader, deadline) {
            Ok(Some(line)) => line,
            Ok(None) => return "disconnected".into(),
            Err(ReadError::Deadline) if !session.greeted => {
                return fatal(ctx, id, "no hello within the time limit".into())
            }
            Err(ReadError::Deadline) => {
                return fatal(
                    ctx,
                    id,
                    "status-only connection: its time limit (app.hello_timeout_ms) was reached"
                        .into(),
                )
            }
            Err(e) => return fatal(ctx, id, e.to_string()),
        };
        let request = match parse_request(&line, ctx.max_force, ctx.rate_hz) {
            Ok(r) => r,
            Err(e) => return fatal(ctx, id, e.to_string()),
        };
        let handled = match request {
            Request::Hello {
                version,
                role,
                name,
            } => session.hello(version, role, &name).map(|()| {
                if !status_only {
                    // A greeted client may stay as long as it likes.
                    deadline = None;
                    let _ = reader.get_ref().set_read_timeout(None);
                }
            }),
            _ if !session.greeted => Err("the first message must be hello".into()),
            Request::Status {} => {
                let _ = ctx.hub.send(HubRequest::Status { client: id });
                Ok(())
            }
            _ if status_only => Err(STATUS_ONLY.into()),
            Request::SetForce { seq, force } => session.set_force(seq, force),
            Request::Subscribe { rate_hz } => {
                session.subscribe(rate_hz);
                Ok(())
            }
            Request::Calibrate {} => {
                session.calibrate(HubRequest::Calibrate { client: id });
                Ok(())
            }
            Request::Check { apply } => {
                session.calibrate(HubRequest::Check { client: id, apply });
                Ok(())
            }
            Request::Revert {} => {
                session.calibrate(HubRequest::Revert { client: id });
                Ok(())
            }
        };
        if let Err(reason) = handled {
            return fatal(ctx, id, reason);
        }
    }
}

/// One client's side of the conversation. Each request handler returns `Err(reason)` when the
/// client broke the protocol and must be closed.
struct Session<'a> {
    id: u64,
    status_only: bool,
    greeted: bool,
    /// `seq` of the last accepted `set_force` (they must increase).
    last_seq: Option<u64>,
    ctx: &'a ServerContext,
}

impl Session<'_> {
    fn refuse(&self, message: &str) {
        reply(
            self.ctx,
            self.id,
            Reply::Error {
                message: message.into(),
                fatal: false,
            },
        );
    }

    /// `hello`: check the version, grant a role (control only if nobody owns the force), welcome.
    fn hello(&mut self, version: u32, role: Role, name: &str) -> Result<(), String> {
        if self.greeted {
            return Err("hello sent twice".into());
        }
        if version != APP_PROTOCOL_VERSION {
            return Err(format!(
                "protocol version {version} not supported (daemon speaks {APP_PROTOCOL_VERSION})"
            ));
        }
        self.greeted = true;
        let ctx = self.ctx;
        let welcome = |granted| Reply::Welcome {
            version: APP_PROTOCOL_VERSION,
            role: granted,
            client_id: self.id,
            device: ctx.device.clone(),
            device_id: ctx.device_id.clone(),
            rate_hz: ctx.rate_hz,
            max_force_n: ctx.max_force,
        };
        // The welcome is queued under the registry's lock, with the client marked welcomed, so
        // that no event sent to every client can reach it first (its queue is empty: nothing
        // but a hello is answered before the welcome), and after the servo thread was told who
        // owns the force, so that the owner's first force cannot reach it first.
        let granted = {
            let mut reg = lock(&ctx.registry);
            let granted = if role == Role::Control && reg.owner.is_none() && !self.status_only {
                reg.owner = Some(self.id);
                send_command(ctx, ServoCommand::SetOwner(Some(self.id)));
                Role::Control
            } else {
                Role::Observe
            };
            if let Some(c) = reg.clients.get_mut(&self.id) {
                if !name.is_empty() {
                    c.name = name.chars().take(64).collect();
                }
                c.role = granted;
                c.welcomed = c.outbound.try_send(welcome(granted)).is_ok();
            }
            granted
        };
        if self.status_only {
            self.refuse(STATUS_ONLY);
        } else if role == Role::Control && granted != Role::Control {
            self.refuse("another client owns the force; you may observe");
        }
        Ok(())
    }

    /// `set_force`: only from the owner, in increasing `seq`; handed to the servo thread.
    fn set_force(&mut self, seq: u64, force: [f64; 3]) -> Result<(), String> {
        if lock(&self.ctx.registry).owner != Some(self.id) {
            self.refuse("this client does not own the force");
            return Ok(());
        }
        if let Some(last) = self.last_seq.filter(|&last| seq <= last) {
            return Err(format!("out-of-order set_force: seq {seq} after {last}"));
        }
        self.last_seq = Some(seq);
        self.ctx.offsets.send(OffsetCommand {
            client: self.id,
            seq,
            force: Vector3::from(force),
        });
        Ok(())
    }

    /// `subscribe`: every n-th tick's state (0 stops the stream).
    fn subscribe(&self, rate_hz: f64) {
        let divider = if rate_hz <= 0.0 {
            0
        } else {
            (self.ctx.rate_hz / rate_hz).round().max(1.0) as u64
        };
        if let Some(c) = lock(&self.ctx.registry).clients.get_mut(&self.id) {
            c.state_divider = divider;
        }
    }

    /// `calibrate`, `check` (both move the handle) and `revert` (changes the force the handle
    /// gets): refused while another client owns the force; otherwise the hub decides.
    fn calibrate(&self, request: HubRequest) {
        let owner = lock(&self.ctx.registry).owner;
        if owner.is_some_and(|o| o != self.id) {
            self.refuse(match request {
                HubRequest::Check { .. } => {
                    "another client owns the force: only it may start a check"
                }
                HubRequest::Revert { .. } => {
                    "another client owns the force: only it may put back a model"
                }
                _ => "another client owns the force: only it may start a calibration",
            });
            return;
        }
        let _ = self.ctx.hub.send(request);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A reader over `bytes`, then end of stream.
    fn reader_over(bytes: &[u8]) -> BufReader<UnixStream> {
        let (mut tx, rx) = UnixStream::pair().unwrap();
        tx.write_all(bytes).unwrap();
        BufReader::new(rx)
    }

    #[test]
    fn lines_are_split_bounded_and_checked() {
        let longest = "x".repeat(MAX_LINE_LEN);
        let mut r = reader_over(format!("a\n{longest}\n\nb").as_bytes());
        assert_eq!(read_line(&mut r, None).unwrap().as_deref(), Some("a"));
        assert_eq!(read_line(&mut r, None).unwrap(), Some(longest.clone()));
        assert_eq!(read_line(&mut r, None).unwrap().as_deref(), Some(""));
        assert!(matches!(
            read_line(&mut r, None),
            Err(ReadError::Unfinished)
        ));
        let mut r = reader_over(format!("{longest}x\n").as_bytes());
        assert!(matches!(read_line(&mut r, None), Err(ReadError::TooLong)));
        let mut r = reader_over(b"\xff\n");
        assert!(matches!(read_line(&mut r, None), Err(ReadError::NotUtf8)));
        let mut r = reader_over(b"");
        assert!(matches!(read_line(&mut r, None), Ok(None)));
    }

    #[test]
    fn a_trickling_writer_cannot_stretch_the_deadline() {
        let (mut tx, rx) = UnixStream::pair().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let trickler = thread::spawn({
            let stop = stop.clone();
            move || {
                // A byte every 10 ms, never a newline.
                while !stop.load(Ordering::Relaxed) && tx.write_all(b" ").is_ok() {
                    thread::sleep(Duration::from_millis(10));
                }
            }
        });
        let start = Instant::now();
        let result = read_line(
            &mut BufReader::new(rx),
            Some(start + Duration::from_millis(100)),
        );
        let took = start.elapsed();
        stop.store(true, Ordering::Relaxed);
        trickler.join().unwrap();
        assert!(matches!(result, Err(ReadError::Deadline)), "{result:?}");
        assert!(took >= Duration::from_millis(100), "{took:?}");
        // Generous: a loaded machine may wake late, but not by seconds.
        assert!(took < Duration::from_secs(5), "{took:?}");
    }

    /// An event sent to every client (the daemon's "the model no longer fits") reaches a client
    /// that is still saying hello only after its welcome: its hello would otherwise be answered
    /// by the event, and it would take the daemon for a stranger.
    #[test]
    fn an_event_for_every_client_never_precedes_a_welcome() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("hgcd.sock");
        let (commands, offsets, _servo, _hub_mailbox) = crate::mailbox::mailbox();
        let (hub, _hub_requests) = crossbeam_channel::unbounded();
        let registry = SharedRegistry::default();
        let ctx = Arc::new(ServerContext {
            registry: registry.clone(),
            commands,
            offsets,
            hub,
            device: "sim:point-mass".into(),
            device_id: "sim-point-mass".into(),
            rate_hz: 1000.0,
            max_force: 8.0,
            max_clients: 4,
            hello_timeout: Duration::from_secs(60),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let listener =
            spawn_listener(bind(&path, 0o600).unwrap(), path.clone(), ctx, stop.clone()).unwrap();
        let mut client = crate::app::client::Client::open(&path).unwrap();
        while lock(&registry).clients.is_empty() {
            thread::sleep(Duration::from_millis(1));
        }
        let event = Reply::Error {
            message: "for everyone".into(),
            fatal: false,
        };
        let everyone = lock(&registry).welcomed_outbound();
        assert!(everyone.is_empty(), "a client not yet welcomed");
        client.hello(Role::Observe, "late").unwrap();
        for tx in lock(&registry).welcomed_outbound() {
            tx.send(event.clone()).unwrap();
        }
        client
            .set_read_timeout(Some(Duration::from_secs(60)))
            .unwrap();
        assert_eq!(client.next_reply().unwrap(), event);
        stop.store(true, Ordering::Relaxed);
        drop(client);
        listener.join().unwrap();
    }

    /// What `read_line` must make of `bytes`, written out on its own: the lines, then how the
    /// stream ends (None: cleanly).
    fn expected_lines(bytes: &[u8]) -> (Vec<String>, Option<&'static str>) {
        let mut lines = Vec::new();
        let mut rest = bytes;
        while let Some(end) = rest.iter().position(|&b| b == b'\n') {
            if end > MAX_LINE_LEN {
                return (lines, Some("too long"));
            }
            match std::str::from_utf8(&rest[..end]) {
                Ok(line) => lines.push(line.to_string()),
                Err(_) => return (lines, Some("not UTF-8")),
            }
            rest = &rest[end + 1..];
        }
        let end = match rest.len() {
            0 => None,
            n if n > MAX_LINE_LEN => Some("too long"),
            _ => Some("unfinished"),
        };
        (lines, end)
    }

    /// Byte streams of short and long segments, with and without newlines between them.
    fn streams() -> impl Strategy<Value = Vec<u8>> {
        let segment = prop_oneof![
            4 => proptest::collection::vec(any::<u8>(), 0..40),
            1 => proptest::collection::vec(prop::sample::select(b"{}\"a:,1 \xff".to_vec()), 0..60),
            1 => (MAX_LINE_LEN - 2..MAX_LINE_LEN + 3).prop_map(|n| vec![b' '; n]),
        ];
        (proptest::collection::vec(segment, 0..6), any::<bool>()).prop_map(|(segments, last)| {
            let mut bytes = segments.join(&b'\n');
            if last {
                bytes.push(b'\n');
            }
            bytes
        })
    }

    proptest! {
        #![proptest_config(crate::protocol::fuzz::config())]

        #[test]
        fn any_stream_splits_into_the_lines_it_holds(bytes in streams()) {
            let mut reader = reader_over(&bytes);
            let mut lines = Vec::new();
            let end = loop {
                match read_line(&mut reader, None) {
                    Ok(Some(line)) => lines.push(line),
                    Ok(None) => break None,
                    Err(ReadError::TooLong) => break Some("too long"),
                    Err(ReadError::NotUtf8) => break Some("not UTF-8"),
                    Err(ReadError::Unfinished) => break Some("unfinished"),
                    Err(e) => panic!("{e}"),
                }
            };
            prop_assert_eq!((lines, end), expected_lines(&bytes));
        }
    }
}
