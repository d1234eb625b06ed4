//! The C ABI of hgcd's client library (`hgcd::client::Client`): `libhgcd_c.so` / `libhgcd_c.a`
//! and the header `include/hgcd.h`, generated from this file by cbindgen (`cbindgen.toml`).
//!
//! Every function returns `HGCD_OK` (0), `HGCD_NO_SAMPLE` (1, not an error) or a negative
//! `HGCD_ERR_*` code; after an error `hgcd_last_error()` gives one line saying what went wrong.
//! No panic crosses the boundary: each entry point runs under `catch_unwind` and turns a panic
//! into `HGCD_ERR_PANIC`.
//!
//! Threads: a handle may move between threads but is used by one at a time. It is guarded by a
//! lock that is never waited for: a call made while another thread is inside a call on the same
//! handle returns `HGCD_ERR_BUSY` at once, so a haptics thread never blocks behind a slow call.
//! Give each thread that talks to the daemon its own handle (the haptics thread one with
//! `control`, a user-interface thread one with `observe` for status). The last error is per
//! thread, like `errno`. `hgcd_close` must not race another call on the same handle.

#![allow(non_camel_case_types)]

use std::cell::RefCell;
use std::ffi::{c_char, c_int, CStr, CString, OsStr};
use std::os::unix::ffi::OsStrExt;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::ptr;
use std::sync::{Mutex, MutexGuard, TryLockError};
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use hgcd::app::endpoint::{self, FindError};
use hgcd::client::{Client, ClientError, Compensating, Reply, Role, StateSample, Status};
use hgcd_result::*;

/// What every call returns: `HGCD_OK`, `HGCD_NO_SAMPLE` (not an error) or a negative
/// `HGCD_ERR_*`, after which `hgcd_last_error()` says what went wrong.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum hgcd_result {
    /// Success.
    HGCD_OK = 0,
    /// `hgcd_newest_state`: no new state sample arrived within the wait (not an error).
    HGCD_NO_SAMPLE = 1,
    /// Nobody listens on the socket (is `hgcd run` running? is the path right?), or no single
    /// daemon runs for the device asked.
    HGCD_ERR_CONNECT = -1,
    /// The daemon closed the connection (it stopped, or closed this client after a fatal error).
    HGCD_ERR_CLOSED = -2,
    /// The daemon sent something this library does not understand.
    HGCD_ERR_PROTOCOL = -3,
    /// The daemon refused a request with a fatal error and closed the connection.
    HGCD_ERR_REFUSED = -4,
    /// `hgcd_take_ownership`: another client owns the force (this handle observes);
    /// `hgcd_set_force`: this handle does not own the force.
    HGCD_ERR_NOT_OWNER = -5,
    /// A socket error other than the daemon closing the connection.
    HGCD_ERR_IO = -6,
    /// A NULL pointer, a string that is not UTF-8, a value out of range.
    HGCD_ERR_ARGUMENT = -7,
    /// Called out of order: a request before `hgcd_hello`, or a second hello.
    HGCD_ERR_STATE = -8,
    /// Another thread is inside a call on this handle (see the threads rule in `hgcd.h`).
    HGCD_ERR_BUSY = -9,
    /// `hgcd_status`: no status reply within the wait; `hgcd_hello`: no welcome within 5 s.
    HGCD_ERR_TIMEOUT = -10,
    /// An internal error in this library (a bug: please report `hgcd_last_error()`).
    HGCD_ERR_PANIC = -11,
}

/// Role asked for in `hgcd_hello`: render forces (one client at a time).
pub const HGCD_ROLE_CONTROL: c_int = 0;
/// Role asked for in `hgcd_hello`: read state and status only.
pub const HGCD_ROLE_OBSERVE: c_int = 1;

/// `hgcd_daemon_status.mode`: no grid, the daemon renders the applications' forces only.
pub const HGCD_MODE_NONE: c_int = 0;
/// `hgcd_daemon_status.mode`: M(X) g v_G from the grid's masses (the paper's model).
pub const HGCD_MODE_SCALAR: c_int = 1;
/// `hgcd_daemon_status.mode`: the grid's per-vertex holding forces, interpolated.
pub const HGCD_MODE_VECTOR: c_int = 2;
/// `hgcd_daemon_status.mode`: the arm model fitted at calibration.
pub const HGCD_MODE_ARM: c_int = 3;
/// `hgcd_daemon_status.mode`: the arm model plus the lattice of what it left over.
pub const HGCD_MODE_ARM_RESIDUAL: c_int = 4;

/// `hgcd_state.flags`: motors enabled.
pub const HGCD_FLAG_MOTORS_ENABLED: u16 = 0x1;
/// `hgcd_state.flags`: the device reports a fault (the force is zero).
pub const HGCD_FLAG_FAULT: u16 = 0x2;
/// `hgcd_state.flags`: the handle's button is pressed.
pub const HGCD_FLAG_BUTTON: u16 = 0x4;
/// `hgcd_state.flags`: the device saturated the force.
pub const HGCD_FLAG_FORCE_SATURATED: u16 = 0x8;
/// `hgcd_state.flags`: the device's own watchdog zeroed the force.
pub const HGCD_FLAG_DEVICE_WATCHDOG: u16 = 0x10;

/// The per-axis force limit protocol v1 documents (`safety.max_force_n` by default), N. A
/// daemon configured otherwise closes a client that sends a component above its own limit.
pub const HGCD_DEFAULT_MAX_FORCE_N: f64 = 8.0;

/// One connection to the daemon (opaque). Made by `hgcd_connect`, freed by `hgcd_close`.
pub struct hgcd_client {
    session: Mutex<Session>,
}

struct Session {
    client: Client,
    greeted: bool,
    /// The welcome's strings, alive until `hgcd_close`.
    device: CString,
    device_id: CString,
    /// The last status's strings, alive until the next `hgcd_status`.
    status_strings: Vec<CString>,
    /// A state sample read while waiting for something else, not yet handed out.
    pending: Option<StateSample>,
}

/// What the daemon granted in its welcome. Strings belong to the handle: valid until
/// `hgcd_close`.
#[repr(C)]
pub struct hgcd_welcome {
    /// `HGCD_ROLE_CONTROL` or `HGCD_ROLE_OBSERVE` (another client owns the force).
    pub role: c_int,
    /// Unique for the daemon's lifetime, from 1.
    pub client_id: u64,
    /// Servo rate, Hz.
    pub rate_hz: f64,
    /// Device spec the daemon opened (`hid:VID:PID[:SERIAL]`, `sim:MODEL`, `socket:PATH`).
    pub device: *const c_char,
    /// Device id (the grid file is `<state_dir>/<device_id>.toml`).
    pub device_id: *const c_char,
}

/// The device at one servo tick. SI units, device frame.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct hgcd_state {
    /// Servo tick number, from 0.
    pub tick: u64,
    /// Device time since its first report, s.
    pub time: f64,
    /// End-effector position, m.
    pub position: [f64; 3],
    /// Velocity (FOAW estimate), m/s.
    pub velocity: [f64; 3],
    /// Force the output report carried on this tick, N: your offset plus gravity compensation,
    /// after the safety layer; zero during a fault.
    pub force: [f64; 3],
    /// `HGCD_FLAG_*` bits.
    pub flags: u16,
    /// Number of your `hgcd_set_force` call (from 1) the servo applied on this tick; 0: none.
    pub offset_seq: u64,
}

/// The daemon's status. Strings belong to the handle: valid until the next `hgcd_status` on it
/// or `hgcd_close`.
#[repr(C)]
pub struct hgcd_daemon_status {
    pub device: *const c_char,
    pub device_id: *const c_char,
    /// Grid file in use; NULL without a grid.
    pub grid: *const c_char,
    /// `HGCD_MODE_*`.
    pub mode: c_int,
    pub calibrating: bool,
    /// Open connections, the asking one included.
    pub clients: u64,
    /// Name of the client that owns the force; NULL when nobody does.
    pub owner: *const c_char,
    /// Since the daemon started serving, s.
    pub uptime_s: f64,
    /// Servo loop counters (refreshed every 500 ticks; see docs/app-protocol.md §5).
    pub ticks: u64,
    pub late: u64,
    pub missed: u64,
    pub overruns: u64,
    pub garbled: u64,
    pub watchdog_faults: u64,
    /// µs.
    pub worst_compute_us: f64,
    /// µs.
    pub worst_period_us: f64,
    pub late_wakeups: u64,
    /// µs.
    pub worst_lateness_us: f64,
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

/// An error on its way to C: its code and the line `hgcd_last_error` gives.
#[derive(Debug)]
struct Failure {
    code: hgcd_result,
    message: String,
}

fn fail(code: hgcd_result, message: impl Into<String>) -> Failure {
    Failure {
        code,
        message: message.into(),
    }
}

impl From<ClientError> for Failure {
    fn from(e: ClientError) -> Self {
        let code = match &e {
            ClientError::Connect { .. } => HGCD_ERR_CONNECT,
            ClientError::Closed => HGCD_ERR_CLOSED,
            ClientError::Io(io)
                if matches!(
                    io.kind(),
                    std::io::ErrorKind::BrokenPipe | std::io::ErrorKind::ConnectionReset
                ) =>
            {
                return fail(
                    HGCD_ERR_CLOSED,
                    format!("the daemon closed the connection ({io})"),
                )
            }
            ClientError::Io(_) => HGCD_ERR_IO,
            ClientError::Protocol(_) => HGCD_ERR_PROTOCOL,
            ClientError::Refused(_) => HGCD_ERR_REFUSED,
            ClientError::NoWelcome => HGCD_ERR_TIMEOUT,
        };
        fail(code, e.to_string())
    }
}

fn set_last_error(message: &str) {
    let line = CString::new(message.replace('\0', " ")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = line);
}

/// Run `body` as the entry point `function`: its code, or the failure's with the last error set
/// to `function: message`; a panic becomes `HGCD_ERR_PANIC`.
fn entry(function: &str, body: impl FnOnce() -> Result<hgcd_result, Failure>) -> hgcd_result {
    match catch_unwind(AssertUnwindSafe(body)) {
        Ok(Ok(code)) => code,
        Ok(Err(failure)) => {
            set_last_error(&format!("{function}: {}", failure.message));
            failure.code
        }
        Err(panic) => {
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            set_last_error(&format!(
                "{function}: internal error in the hgcd C library, please report it: {what}"
            ));
            HGCD_ERR_PANIC
        }
    }
}

/// The handle's session, without waiting for another thread.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` that stays open while the guard lives.
unsafe fn lock(client: *mut hgcd_client) -> Result<MutexGuard<'static, Session>, Failure> {
    // SAFETY: by this function's contract.
    let handle =
        unsafe { client.as_ref() }.ok_or_else(|| fail(HGCD_ERR_ARGUMENT, "the handle is NULL"))?;
    match handle.session.try_lock() {
        Ok(session) => Ok(session),
        Err(TryLockError::WouldBlock) => Err(fail(
            HGCD_ERR_BUSY,
            "another thread is inside a call on this handle: give each thread its own handle",
        )),
        Err(TryLockError::Poisoned(_)) => Err(fail(
            HGCD_ERR_PANIC,
            "this handle is unusable after an internal error: close it and connect again",
        )),
    }
}

/// The C string at `s` as UTF-8; `what` names it in the error.
///
/// # Safety
///
/// `s` is NULL or a NUL-terminated string that outlives `'a`.
unsafe fn utf8<'a>(s: *const c_char, what: &str) -> Result<Option<&'a str>, Failure> {
    if s.is_null() {
        return Ok(None);
    }
    // SAFETY: by this function's contract.
    unsafe { CStr::from_ptr(s) }
        .to_str()
        .map(Some)
        .map_err(|_| fail(HGCD_ERR_ARGUMENT, format!("{what} is not UTF-8")))
}

fn wait(ms: c_int) -> Result<Duration, Failure> {
    u64::try_from(ms).map(Duration::from_millis).map_err(|_| {
        fail(
            HGCD_ERR_ARGUMENT,
            format!("wait_ms is {ms}: give 0 or more milliseconds"),
        )
    })
}

impl Session {
    fn greeted(&self) -> Result<(), Failure> {
        if self.greeted {
            Ok(())
        } else {
            Err(fail(
                HGCD_ERR_STATE,
                "say hello first (hgcd_hello or hgcd_take_ownership)",
            ))
        }
    }

    /// The next reply, waiting until `deadline` for one to begin; state samples met on the way
    /// are kept for `hgcd_newest_state`.
    fn reply_before(&mut self, deadline: Instant) -> Result<Option<Reply>, Failure> {
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if let Some(reply) = self.client.next_reply_within(left)? {
                return Ok(Some(reply));
            }
            if left.is_zero() {
                return Ok(None);
            }
        }
    }

    fn hello(
        &mut self,
        role: Role,
        name: Option<&str>,
        out: *mut hgcd_welcome,
    ) -> Result<(), Failure> {
        if self.greeted {
            return Err(fail(
                HGCD_ERR_STATE,
                "this handle already said hello: a client's role is fixed for its connection, \
                 connect again to change it",
            ));
        }
        self.client.hello(role, name.unwrap_or(""))?;
        self.greeted = true;
        self.device = c_text(&self.client.device);
        self.device_id = c_text(&self.client.device_id);
        // SAFETY: `out` is NULL or points to a welcome the caller owns.
        if let Some(out) = unsafe { out.as_mut() } {
            *out = hgcd_welcome {
                role: role_code(self.client.role),
                client_id: self.client.client_id,
                rate_hz: self.client.rate_hz,
                device: self.device.as_ptr(),
                device_id: self.device_id.as_ptr(),
            };
        }
        Ok(())
    }
}

/// Text from the client as C: it has no control characters, NUL among them.
fn c_text(text: &str) -> CString {
    CString::new(text).unwrap_or_default()
}

fn role_code(role: Role) -> c_int {
    match role {
        Role::Control => HGCD_ROLE_CONTROL,
        Role::Observe => HGCD_ROLE_OBSERVE,
    }
}

impl From<StateSample> for hgcd_state {
    fn from(s: StateSample) -> Self {
        Self {
            tick: s.tick,
            time: s.time,
            position: s.position,
            velocity: s.velocity,
            force: s.force,
            flags: s.flags,
            offset_seq: s.offset_seq,
        }
    }
}

/// Connect to the daemon's socket at `socket_path` (NULL: the only daemon running, as
/// `hgcd_connect_device(NULL, out)`) and store the new handle in `*out`. Say hello next, within
/// the daemon's `app.hello_timeout_ms` (5 s).
///
/// Returns `HGCD_OK`, `HGCD_ERR_CONNECT` (nobody listens there), `HGCD_ERR_IO`,
/// `HGCD_ERR_ARGUMENT` (`out` NULL).
///
/// # Safety
///
/// `socket_path` is NULL or a NUL-terminated string; `out` is NULL or points to a
/// writable `hgcd_client *`.
#[no_mangle]
pub unsafe extern "C" fn hgcd_connect(
    socket_path: *const c_char,
    out: *mut *mut hgcd_client,
) -> hgcd_result {
    entry("hgcd_connect", || {
        if out.is_null() {
            return Err(fail(HGCD_ERR_ARGUMENT, "out is NULL"));
        }
        let path = if socket_path.is_null() {
            find(None)?
        } else {
            // SAFETY: a NUL-terminated string (the header's contract).
            PathBuf::from(OsStr::from_bytes(
                unsafe { CStr::from_ptr(socket_path) }.to_bytes(),
            ))
        };
        // SAFETY: `out` is non-NULL and writable (the header's contract).
        unsafe { open(&path, out) }
    })
}

/// Connect to the daemon of `device` (a device id such as `Omega-SN0042` or a spec such as
/// `hid:1209:4847`; NULL: the only daemon running), found in the runtime directory
/// (`$RUNTIME_DIRECTORY`, else `/run/hgcd`), and store the new handle in `*out`; then as
/// `hgcd_connect`.
///
/// Returns `HGCD_OK`, `HGCD_ERR_CONNECT` (no daemon for that device, or several and `device`
/// does not say which: `hgcd_last_error` names them), `HGCD_ERR_IO`, `HGCD_ERR_ARGUMENT`.
///
/// # Safety
///
/// `device` is NULL or a NUL-terminated string; `out` is NULL or points to a writable
/// `hgcd_client *`.
#[no_mangle]
pub unsafe extern "C" fn hgcd_connect_device(
    device: *const c_char,
    out: *mut *mut hgcd_client,
) -> hgcd_result {
    entry("hgcd_connect_device", || {
        if out.is_null() {
            return Err(fail(HGCD_ERR_ARGUMENT, "out is NULL"));
        }
        // SAFETY: NULL or a NUL-terminated string (the header's contract).
        let path = find(unsafe { utf8(device, "device") }?)?;
        // SAFETY: `out` is non-NULL and writable (the header's contract).
        unsafe { open(&path, out) }
    })
}

/// The socket of the daemon of `device`, or of the only one running.
fn find(device: Option<&str>) -> Result<PathBuf, Failure> {
    endpoint::find(&endpoint::runtime_dir(), device)
        .map(|found| found.socket)
        .map_err(|e| match e {
            FindError::Client(e) => e.into(),
            FindError::Ask { socket, source } => {
                let failure = Failure::from(source);
                let asking = format!("asking {} which device it serves", socket.display());
                fail(failure.code, format!("{asking}: {}", failure.message))
            }
            other => fail(HGCD_ERR_CONNECT, other.to_string()),
        })
}

/// Connect to `path` and store the new handle in `*out`.
///
/// # Safety
///
/// `out` points to a writable `hgcd_client *`.
unsafe fn open(path: &Path, out: *mut *mut hgcd_client) -> Result<hgcd_result, Failure> {
    let client = Client::open(path)?;
    let handle = Box::new(hgcd_client {
        session: Mutex::new(Session {
            client,
            greeted: false,
            device: CString::default(),
            device_id: CString::default(),
            status_strings: Vec::new(),
            pending: None,
        }),
    });
    // SAFETY: by this function's contract.
    unsafe { *out = Box::into_raw(handle) };
    Ok(HGCD_OK)
}

/// Say hello asking for `role` (`HGCD_ROLE_CONTROL` or `HGCD_ROLE_OBSERVE`) under `name`
/// (NULL: `client-<id>`; shown as the owner in status), once, before any other request, and fill
/// `*welcome` (may be NULL). Asking for control while another client owns the force is granted
/// observe: check `welcome->role`, or use `hgcd_take_ownership`.
///
/// Returns `HGCD_OK`, `HGCD_ERR_STATE` (hello already said), `HGCD_ERR_REFUSED`,
/// `HGCD_ERR_TIMEOUT` (no welcome within 5 s), `HGCD_ERR_CLOSED`, `HGCD_ERR_PROTOCOL` (a
/// welcome out of its ranges among others), `HGCD_ERR_IO`, `HGCD_ERR_ARGUMENT`, `HGCD_ERR_BUSY`.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` not yet closed; `name` is NULL or a
/// NUL-terminated string; `welcome` is NULL or points to a writable `hgcd_welcome`.
#[no_mangle]
pub unsafe extern "C" fn hgcd_hello(
    client: *mut hgcd_client,
    role: c_int,
    name: *const c_char,
    welcome: *mut hgcd_welcome,
) -> hgcd_result {
    entry("hgcd_hello", || {
        let role = match role {
            HGCD_ROLE_CONTROL => Role::Control,
            HGCD_ROLE_OBSERVE => Role::Observe,
            other => {
                return Err(fail(
                    HGCD_ERR_ARGUMENT,
                    format!("role {other} is neither HGCD_ROLE_CONTROL nor HGCD_ROLE_OBSERVE"),
                ))
            }
        };
        let name = utf8(name, "name")?;
        lock(client)?.hello(role, name, welcome)?;
        Ok(HGCD_OK)
    })
}

/// Say hello asking for control under `name` (as `hgcd_hello`) and succeed only if it was
/// granted: the protocol fixes a client's role at its hello, so this is how a client takes
/// ownership of the force. On `HGCD_ERR_NOT_OWNER` the handle stays open as an observer.
///
/// Returns `HGCD_OK`, `HGCD_ERR_NOT_OWNER` (another client owns the force), or what
/// `hgcd_hello` returns.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` not yet closed; `name` is NULL or
/// a NUL-terminated string; `welcome` is NULL or points to a writable `hgcd_welcome`.
#[no_mangle]
pub unsafe extern "C" fn hgcd_take_ownership(
    client: *mut hgcd_client,
    name: *const c_char,
    welcome: *mut hgcd_welcome,
) -> hgcd_result {
    entry("hgcd_take_ownership", || {
        let name = utf8(name, "name")?;
        let mut session = lock(client)?;
        session.hello(Role::Control, name, welcome)?;
        if session.client.role == Role::Control {
            Ok(HGCD_OK)
        } else {
            Err(fail(
                HGCD_ERR_NOT_OWNER,
                "another client owns the force; this handle may observe",
            ))
        }
    })
}

/// Render the force offset (`fx`, `fy`, `fz`) N on top of gravity compensation until the next
/// call. Send one per state sample, and at least every 50 ms (`app.stale_offset_ms`), or it
/// ramps to zero. Each component must be finite and at most the daemon's `safety.max_force_n`
/// (`HGCD_DEFAULT_MAX_FORCE_N` unless configured otherwise): the daemon closes a client that
/// sends more, and a later call returns `HGCD_ERR_REFUSED`.
///
/// Returns `HGCD_OK` (sent), `HGCD_ERR_NOT_OWNER`, `HGCD_ERR_ARGUMENT` (not finite),
/// `HGCD_ERR_STATE`, `HGCD_ERR_CLOSED`, `HGCD_ERR_IO`, `HGCD_ERR_BUSY`.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` not yet closed.
#[no_mangle]
pub unsafe extern "C" fn hgcd_set_force(
    client: *mut hgcd_client,
    fx: f64,
    fy: f64,
    fz: f64,
) -> hgcd_result {
    entry("hgcd_set_force", || {
        let mut session = lock(client)?;
        session.greeted()?;
        if session.client.role != Role::Control {
            return Err(fail(
                HGCD_ERR_NOT_OWNER,
                "this handle does not own the force (it observes)",
            ));
        }
        let force = Vector3::new(fx, fy, fz);
        if !force.iter().all(|f| f.is_finite()) {
            return Err(fail(
                HGCD_ERR_ARGUMENT,
                format!("force ({fx}, {fy}, {fz}) N is not finite"),
            ));
        }
        session.client.set_force(force)?;
        Ok(HGCD_OK)
    })
}

/// Stream state samples at `rate_hz` (at most `welcome.rate_hz`; 0 stops the stream), read with
/// `hgcd_newest_state`. Read continuously: a client that stops reading is disconnected.
///
/// Returns `HGCD_OK`, `HGCD_ERR_ARGUMENT` (negative or not finite), `HGCD_ERR_STATE`,
/// `HGCD_ERR_CLOSED`, `HGCD_ERR_IO`, `HGCD_ERR_BUSY`.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` not yet closed.
#[no_mangle]
pub unsafe extern "C" fn hgcd_subscribe(client: *mut hgcd_client, rate_hz: f64) -> hgcd_result {
    entry("hgcd_subscribe", || {
        if !(rate_hz.is_finite() && rate_hz >= 0.0) {
            return Err(fail(
                HGCD_ERR_ARGUMENT,
                format!("rate_hz is {rate_hz}: give 0 to the servo rate"),
            ));
        }
        let mut session = lock(client)?;
        session.greeted()?;
        session.client.subscribe(rate_hz)?;
        Ok(HGCD_OK)
    })
}

/// Store in `*out` the newest state sample that arrived since the last call, reading everything
/// that has arrived without waiting; if none has, wait up to `wait_ms` ms (0: do not wait) for
/// one. Older samples are skipped, as are non-fatal errors and calibration events.
///
/// Returns `HGCD_OK`, `HGCD_NO_SAMPLE` (none within the wait; `*out` untouched),
/// `HGCD_ERR_REFUSED` (a fatal error from the daemon), `HGCD_ERR_CLOSED`, `HGCD_ERR_PROTOCOL`,
/// `HGCD_ERR_IO`, `HGCD_ERR_STATE`, `HGCD_ERR_ARGUMENT`, `HGCD_ERR_BUSY`.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` not yet closed; `out` is NULL
/// or points to a writable `hgcd_state`.
#[no_mangle]
pub unsafe extern "C" fn hgcd_newest_state(
    client: *mut hgcd_client,
    wait_ms: c_int,
    out: *mut hgcd_state,
) -> hgcd_result {
    entry("hgcd_newest_state", || {
        if out.is_null() {
            return Err(fail(HGCD_ERR_ARGUMENT, "out is NULL"));
        }
        let deadline = Instant::now() + wait(wait_ms)?;
        let mut session = lock(client)?;
        session.greeted()?;
        let mut newest = session.pending.take();
        // Everything already here, then (if that held no sample) the first to come in time.
        let mut until = Instant::now();
        loop {
            match session.reply_before(until)? {
                Some(Reply::State(s)) => newest = Some(s),
                Some(_) => {}
                None if newest.is_none() && until < deadline => until = deadline,
                None => break,
            }
            if newest.is_some() {
                until = Instant::now();
            }
        }
        Ok(match newest {
            Some(s) => {
                // SAFETY: `out` is non-NULL and points to a state the caller owns.
                unsafe { *out = s.into() };
                HGCD_OK
            }
            None => HGCD_NO_SAMPLE,
        })
    })
}

/// Ask for the daemon's status and store it in `*out`, waiting up to `wait_ms` ms for it. State
/// samples that arrive meanwhile are kept for `hgcd_newest_state`.
///
/// Returns `HGCD_OK`, `HGCD_ERR_TIMEOUT`, `HGCD_ERR_REFUSED`, `HGCD_ERR_CLOSED`,
/// `HGCD_ERR_PROTOCOL`, `HGCD_ERR_IO`, `HGCD_ERR_STATE`, `HGCD_ERR_ARGUMENT`, `HGCD_ERR_BUSY`.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` not yet closed; `out` is NULL or
/// points to a writable `hgcd_daemon_status`.
#[no_mangle]
pub unsafe extern "C" fn hgcd_status(
    client: *mut hgcd_client,
    wait_ms: c_int,
    out: *mut hgcd_daemon_status,
) -> hgcd_result {
    entry("hgcd_status", || {
        if out.is_null() {
            return Err(fail(HGCD_ERR_ARGUMENT, "out is NULL"));
        }
        let deadline = Instant::now() + wait(wait_ms)?;
        let mut session = lock(client)?;
        session.greeted()?;
        session.client.request_status()?;
        let status = loop {
            match session.reply_before(deadline)? {
                Some(Reply::Status(status)) => break status,
                Some(Reply::State(s)) => session.pending = Some(s),
                Some(_) => {}
                None => {
                    return Err(fail(
                        HGCD_ERR_TIMEOUT,
                        format!("no status from the daemon within {wait_ms} ms"),
                    ))
                }
            }
        };
        let out_status = session.keep_status(*status);
        // SAFETY: `out` is non-NULL and points to a status the caller owns.
        unsafe { *out = out_status };
        Ok(HGCD_OK)
    })
}

impl Session {
    /// `status` for C, its strings kept in the session until the next status.
    fn keep_status(&mut self, status: Status) -> hgcd_daemon_status {
        self.status_strings = vec![c_text(&status.device), c_text(&status.device_id)];
        let mut optional = |s: &Option<String>| match s {
            Some(s) => {
                self.status_strings.push(c_text(s));
                self.status_strings
                    .last()
                    .map_or(ptr::null(), |c| c.as_ptr())
            }
            None => ptr::null(),
        };
        // A CString's bytes stay put when the vector holding it grows.
        let grid = optional(&status.grid);
        let owner = optional(&status.owner);
        let c = &status.servo;
        hgcd_daemon_status {
            device: self.status_strings[0].as_ptr(),
            device_id: self.status_strings[1].as_ptr(),
            grid,
            mode: match status.mode {
                Compensating::None => HGCD_MODE_NONE,
                Compensating::Scalar => HGCD_MODE_SCALAR,
                Compensating::Vector => HGCD_MODE_VECTOR,
                Compensating::Arm => HGCD_MODE_ARM,
                Compensating::ArmResidual => HGCD_MODE_ARM_RESIDUAL,
            },
            calibrating: status.calibrating,
            clients: status.clients as u64,
            owner,
            uptime_s: status.uptime_s,
            ticks: c.ticks,
            late: c.late,
            missed: c.missed,
            overruns: c.overruns,
            garbled: c.garbled,
            watchdog_faults: c.watchdog_faults,
            worst_compute_us: c.worst_compute_us,
            worst_period_us: c.worst_period_us,
            late_wakeups: c.late_wakeups,
            worst_lateness_us: c.worst_lateness_us,
        }
    }
}

/// Close the connection and free the handle (NULL: nothing). The daemon removes this client's
/// force offset at once. No other call on the handle may run or follow.
///
/// # Safety
///
/// `client` is NULL or a handle from `hgcd_connect` not yet closed, and no other
/// call on it runs or follows.
#[no_mangle]
pub unsafe extern "C" fn hgcd_close(client: *mut hgcd_client) {
    entry("hgcd_close", || {
        if !client.is_null() {
            // SAFETY: the handle came from `hgcd_connect` (Box::into_raw) and is closed once.
            drop(unsafe { Box::from_raw(client) });
        }
        Ok(HGCD_OK)
    });
}

/// The last error on this thread as one line (empty before any): what went wrong and, where
/// there is one, what to do. Valid until the next failing call on this thread.
#[no_mangle]
pub extern "C" fn hgcd_last_error() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

#[cfg(test)]
mod tests {
    use super::*;
    use hgcd::protocol::Status as Flags;
    use std::io::{BufRead, BufReader, Lines, Write};
    use std::os::unix::net::{UnixListener, UnixStream};
    use std::thread::JoinHandle;

    fn last_error() -> String {
        // SAFETY: hgcd_last_error returns a NUL-terminated string owned by this thread.
        unsafe { CStr::from_ptr(hgcd_last_error()) }
            .to_string_lossy()
            .into_owned()
    }

    #[test]
    fn a_panic_becomes_an_error_code_and_a_message() {
        let code = entry("hgcd_test", || panic!("boom"));
        assert_eq!(code, HGCD_ERR_PANIC);
        let message = last_error();
        assert!(
            message.starts_with("hgcd_test: internal error"),
            "{message}"
        );
        assert!(message.contains("boom"), "{message}");
    }

    #[test]
    fn null_and_bad_arguments_are_refused_with_a_message() {
        // SAFETY (all calls here): NULL is a valid argument everywhere.
        unsafe {
            assert_eq!(
                hgcd_set_force(ptr::null_mut(), 0.0, 0.0, 0.0),
                HGCD_ERR_ARGUMENT
            );
            assert_eq!(last_error(), "hgcd_set_force: the handle is NULL");
            assert_eq!(
                hgcd_connect(ptr::null(), ptr::null_mut()),
                HGCD_ERR_ARGUMENT
            );
            assert_eq!(
                hgcd_hello(ptr::null_mut(), 7, ptr::null(), ptr::null_mut()),
                HGCD_ERR_ARGUMENT
            );
            assert!(last_error().contains("role 7"), "{}", last_error());
            hgcd_close(ptr::null_mut());
        }
    }

    #[test]
    fn connecting_where_nobody_listens_says_so() {
        let mut handle = ptr::null_mut();
        let path = CString::new("/nonexistent/hgcd.sock").unwrap();
        // SAFETY: a C string and a pointer we own.
        let code = unsafe { hgcd_connect(path.as_ptr(), &mut handle) };
        assert_eq!(code, HGCD_ERR_CONNECT);
        assert!(handle.is_null());
        let message = last_error();
        assert!(
            message.contains("/nonexistent/hgcd.sock") && message.contains("hgcd run"),
            "{message}"
        );
    }

    const WELCOME: &str =
        "{\"type\":\"welcome\",\"version\":1,\"role\":\"observe\",\"client_id\":3,\
        \"device\":\"sim:point-mass\",\"device_id\":\"sim-point-mass\",\"rate_hz\":1000.0,\
        \"max_force_n\":8.0}";

    /// A fake daemon at a socket of its own, named after `test`, that runs `serve` on the one
    /// connection it accepts: its socket as a C string, its directory (for the caller to
    /// remove), its thread.
    fn fake_daemon(
        test: &str,
        serve: impl FnOnce(UnixStream) + Send + 'static,
    ) -> (CString, PathBuf, JoinHandle<()>) {
        let dir = std::env::temp_dir().join(format!("hgcd-c-{test}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("fake.sock");
        let _ = std::fs::remove_file(&path);
        let listener = UnixListener::bind(&path).unwrap();
        let server = std::thread::spawn(move || serve(listener.accept().unwrap().0));
        let path = CString::new(path.as_os_str().as_bytes()).unwrap();
        (path, dir, server)
    }

    /// Read the hello on `stream` and answer it with `welcome`; the lines after the hello.
    fn answer_hello(stream: &UnixStream, welcome: &str) -> Lines<BufReader<UnixStream>> {
        let mut lines = BufReader::new(stream.try_clone().unwrap()).lines();
        let hello = lines.next().unwrap().unwrap();
        assert!(hello.contains(r#""type":"hello""#), "{hello}");
        (&*stream)
            .write_all(format!("{welcome}\n").as_bytes())
            .unwrap();
        lines
    }

    /// A handle connected to `path`.
    fn connect(path: &CString) -> *mut hgcd_client {
        let mut handle = ptr::null_mut();
        // SAFETY: a C string and an out-pointer we own.
        assert_eq!(unsafe { hgcd_connect(path.as_ptr(), &mut handle) }, HGCD_OK);
        handle
    }

    #[test]
    fn requests_before_hello_and_a_second_hello_are_refused_here() {
        let (path, dir, server) = fake_daemon("order", |stream| {
            let mut lines = answer_hello(&stream, WELCOME);
            // Nothing else reaches the server: the library refuses the rest itself.
            assert!(lines.next().is_none());
        });
        let handle = connect(&path);
        // SAFETY: out-pointers we own; the handle is open until hgcd_close.
        unsafe {
            assert_eq!(hgcd_subscribe(handle, 100.0), HGCD_ERR_STATE);
            assert!(last_error().contains("say hello first"), "{}", last_error());
            let mut welcome = hgcd_welcome {
                role: -1,
                client_id: 0,
                rate_hz: 0.0,
                device: ptr::null(),
                device_id: ptr::null(),
            };
            assert_eq!(
                hgcd_take_ownership(handle, ptr::null(), &mut welcome),
                HGCD_ERR_NOT_OWNER
            );
            assert_eq!(
                (welcome.role, welcome.client_id, welcome.rate_hz),
                (HGCD_ROLE_OBSERVE, 3, 1000.0)
            );
            // The welcome's strings live until hgcd_close.
            let device = CStr::from_ptr(welcome.device);
            assert_eq!(device.to_str().unwrap(), "sim:point-mass");
            assert_eq!(hgcd_set_force(handle, 0.1, 0.0, 0.0), HGCD_ERR_NOT_OWNER);
            assert_eq!(
                hgcd_hello(handle, HGCD_ROLE_OBSERVE, ptr::null(), ptr::null_mut()),
                HGCD_ERR_STATE
            );
            let mut state = hgcd_state::from(StateSample::default());
            assert_eq!(hgcd_newest_state(handle, -1, &mut state), HGCD_ERR_ARGUMENT);
            hgcd_close(handle);
        }
        server.join().unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_welcome_out_of_range_is_a_protocol_error() {
        let welcome = WELCOME.replace("\"max_force_n\":8.0", "\"max_force_n\":-1");
        let (path, dir, server) = fake_daemon(
            "range",
            move |stream| {
                for _ in answer_hello(&stream, &welcome) {}
            },
        );
        let handle = connect(&path);
        // SAFETY: the handle is open until hgcd_close.
        unsafe {
            let code = hgcd_hello(handle, HGCD_ROLE_OBSERVE, ptr::null(), ptr::null_mut());
            assert_eq!(code, HGCD_ERR_PROTOCOL);
            assert!(last_error().contains("max_force_n -1"), "{}", last_error());
            hgcd_close(handle);
        }
        server.join().unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_daemon_that_never_welcomes_is_a_timeout() {
        let (path, dir, server) = fake_daemon("silent", |stream| {
            // Silent until the client goes, or 20 s (a client waiting forever sees it close).
            stream
                .set_read_timeout(Some(Duration::from_secs(20)))
                .unwrap();
            let mut lines = BufReader::new(stream).lines();
            while let Some(Ok(_)) = lines.next() {}
        });
        let handle = connect(&path);
        let start = Instant::now();
        // SAFETY: the handle is open until hgcd_close.
        unsafe {
            let code = hgcd_hello(handle, HGCD_ROLE_OBSERVE, ptr::null(), ptr::null_mut());
            assert_eq!(code, HGCD_ERR_TIMEOUT, "{}", last_error());
            assert!(start.elapsed() < Duration::from_secs(15));
            assert!(last_error().contains("no welcome"), "{}", last_error());
            hgcd_close(handle);
        }
        server.join().unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_line_trickling_in_is_cut_off_not_waited_for_byte_by_byte() {
        let (path, dir, server) = fake_daemon("trickle", |stream| {
            let _lines = answer_hello(&stream, WELCOME);
            // A state line, a byte every 0.3 s: about 40 s in all.
            let state = hgcd::app::protocol::encode_reply(&Reply::State(StateSample::default()));
            for byte in state.bytes() {
                if (&stream).write_all(&[byte]).is_err() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(300));
            }
        });
        let handle = connect(&path);
        // SAFETY: an out-pointer we own; the handle is open until hgcd_close.
        unsafe {
            let code = hgcd_hello(handle, HGCD_ROLE_OBSERVE, ptr::null(), ptr::null_mut());
            assert_eq!(code, HGCD_OK);
            let start = Instant::now();
            let mut state = hgcd_state::from(StateSample::default());
            assert_eq!(
                hgcd_newest_state(handle, 3000, &mut state),
                HGCD_ERR_PROTOCOL
            );
            assert!(start.elapsed() < Duration::from_secs(5));
            let message = last_error();
            assert!(
                message.contains("within 1 s of its first byte"),
                "{message}"
            );
            hgcd_close(handle);
        }
        server.join().unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_handle_in_use_by_another_thread_is_busy_not_shared() {
        let (path, dir, server) =
            fake_daemon("busy", |stream| for _ in BufReader::new(stream).lines() {});
        let handle = connect(&path);
        // SAFETY: the handle is open until hgcd_close.
        unsafe {
            // The guard stands for another thread inside a call.
            let guard = (*handle).session.lock().unwrap();
            assert_eq!(hgcd_set_force(handle, 0.0, 0.0, 0.0), HGCD_ERR_BUSY);
            assert!(last_error().contains("its own handle"), "{}", last_error());
            drop(guard);
            hgcd_close(handle);
        }
        server.join().unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_header_constants_are_the_protocol_values() {
        assert_eq!(HGCD_FLAG_MOTORS_ENABLED, Flags::MOTORS_ENABLED);
        assert_eq!(HGCD_FLAG_FAULT, Flags::FAULT);
        assert_eq!(HGCD_FLAG_BUTTON, Flags::BUTTON);
        assert_eq!(HGCD_FLAG_FORCE_SATURATED, Flags::FORCE_SATURATED);
        assert_eq!(HGCD_FLAG_DEVICE_WATCHDOG, Flags::DEVICE_WATCHDOG);
        assert_eq!(
            HGCD_DEFAULT_MAX_FORCE_N,
            hgcd::config::Config::default().safety.max_force_n
        );
    }
}
