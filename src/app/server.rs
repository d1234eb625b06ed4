//! The application socket: a listener thread, and per client a reader thread (validates requests)
//! and a writer thread (sends replies). Force offsets go straight to the servo thread through a
//! bounded channel where the newest wins; everything else goes to the daemon's hub. A client that
//! misbehaves is closed with a logged reason and affects nobody else.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::{self, JoinHandle};
use std::time::Duration;

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
    Calibrate { client: u64 },
    Status { client: u64 },
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
    pub max_clients: usize,
    /// A client that has not said hello within this time is closed.
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

fn accept(stream: UnixStream, ctx: &Arc<ServerContext>) {
    let _ = stream.set_nonblocking(false);
    let (id, rx) = {
        let mut reg = lock(&ctx.registry);
        if reg.clients.len() >= ctx.max_clients {
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
                stream: clone,
            },
        );
        (id, rx)
    };
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
            let reason = serve_client(stream, id, &ctx2);
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

/// Read one line of at most `MAX_LINE_LEN` bytes. Ok(None) at end of stream.
fn read_line(reader: &mut impl BufRead) -> Result<Option<String>, String> {
    let mut buf = Vec::with_capacity(128);
    let n = reader
        .take(MAX_LINE_LEN as u64 + 1)
        .read_until(b'\n', &mut buf)
        .map_err(|e| match e.kind() {
            ErrorKind::WouldBlock | ErrorKind::TimedOut => "no hello within the time limit".into(),
            _ => format!("read error: {e}"),
        })?;
    if n == 0 {
        return Ok(None);
    }
    if buf.last() != Some(&b'\n') {
        return if buf.len() > MAX_LINE_LEN {
            Err(format!("line longer than {MAX_LINE_LEN} bytes"))
        } else {
            Err("connection closed in the middle of a line".into())
        };
    }
    buf.pop();
    String::from_utf8(buf)
        .map(Some)
        .map_err(|_| "line is not UTF-8".into())
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
fn serve_client(stream: UnixStream, id: u64, ctx: &ServerContext) -> String {
    // A client must say hello in time, or idle connections could hold every place.
    let _ = stream.set_read_timeout(Some(ctx.hello_timeout));
    let mut reader = BufReader::new(stream);
    let mut greeted = false;
    let mut last_seq: Option<u64> = None;
    loop {
        let line = match read_line(&mut reader) {
            Ok(Some(line)) => line,
            Ok(None) => return "disconnected".into(),
            Err(e) => return fatal(ctx, id, e),
        };
        let request = match parse_request(&line, ctx.max_force, ctx.rate_hz) {
            Ok(r) => r,
            Err(e) => return fatal(ctx, id, e.to_string()),
        };
        match request {
            Request::Hello {
                version,
                role,
                name,
            } => {
                if greeted {
                    return fatal(ctx, id, "hello sent twice".into());
                }
                if version != APP_PROTOCOL_VERSION {
                    return fatal(
                        ctx,
                        id,
                        format!("protocol version {version} not supported (daemon speaks {APP_PROTOCOL_VERSION})"),
                    );
                }
                greeted = true;
                let _ = reader.get_ref().set_read_timeout(None);
                let granted = {
                    let mut reg = lock(&ctx.registry);
                    let granted = if role == Role::Control && reg.owner.is_none() {
                        reg.owner = Some(id);
                        Role::Control
                    } else {
                        Role::Observe
                    };
                    if let Some(c) = reg.clients.get_mut(&id) {
                        if !name.is_empty() {
                            c.name = name.chars().take(64).collect();
                        }
                        c.role = granted;
                    }
                    granted
                };
                if granted == Role::Control {
                    send_command(ctx, ServoCommand::SetOwner(Some(id)));
                }
                reply(
                    ctx,
                    id,
                    Reply::Welcome {
                        version: APP_PROTOCOL_VERSION,
                        role: granted,
                        client_id: id,
                        device: ctx.device.clone(),
                        device_id: ctx.device_id.clone(),
                        rate_hz: ctx.rate_hz,
                    },
                );
                if role == Role::Control && granted != Role::Control {
                    reply(
                        ctx,
                        id,
                        Reply::Error {
                            message: "another client owns the force; you may observe".into(),
                            fatal: false,
                        },
                    );
                }
            }
            _ if !greeted => return fatal(ctx, id, "the first message must be hello".into()),
            Request::SetForce { seq, force } => {
                if lock(&ctx.registry).owner != Some(id) {
                    reply(
                        ctx,
                        id,
                        Reply::Error {
                            message: "this client does not own the force".into(),
                            fatal: false,
                        },
                    );
                    continue;
                }
                if last_seq.is_some_and(|last| seq <= last) {
                    return fatal(
                        ctx,
                        id,
                        format!(
                            "out-of-order set_force: seq {seq} after {}",
                            last_seq.unwrap_or(0)
                        ),
                    );
                }
                last_seq = Some(seq);
                ctx.offsets.send(OffsetCommand {
                    client: id,
                    seq,
                    force: Vector3::from(force),
                });
            }
            Request::Subscribe { rate_hz } => {
                let divider = if rate_hz <= 0.0 {
                    0
                } else {
                    (ctx.rate_hz / rate_hz).round().max(1.0) as u64
                };
                if let Some(c) = lock(&ctx.registry).clients.get_mut(&id) {
                    c.state_divider = divider;
                }
            }
            Request::Calibrate {} => {
                let owner = lock(&ctx.registry).owner;
                if owner.is_some_and(|o| o != id) {
                    reply(
                        ctx,
                        id,
                        Reply::Error {
                            message: "another client owns the force: only it may start a \
                                      calibration"
                                .into(),
                            fatal: false,
                        },
                    );
                    continue;
                }
                let _ = ctx.hub.send(HubRequest::Calibrate { client: id });
            }
            Request::Status {} => {
                let _ = ctx.hub.send(HubRequest::Status { client: id });
            }
        }
    }
}
