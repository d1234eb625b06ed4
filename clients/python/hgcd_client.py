"""Python client of hgcd, the gravity-compensation daemon for 3-DoF haptic devices.

One module, standard library only (Python 3.8+): copy it next to your script. It speaks the
application protocol v1 (docs/app-protocol.md) over the daemon's Unix socket. Units are SI
(m, m/s, N, s), vectors are (x, y, z) in the device frame.

    import hgcd_client

    with hgcd_client.connect() as client:  # the only daemon running; or device=, or path=
        welcome = client.take_ownership("my-experiment")
        client.subscribe(welcome.rate_hz)
        while True:
            state = client.newest_state(wait=1.0)
            if state is None:
                raise RuntimeError("the daemon sends no state")
            client.set_force((0.0, 0.0, 0.0))  # your rendering here, one offset per sample

Errors are exceptions derived from HgcdError, each saying what went wrong: ConnectError,
ClosedError (the daemon went away), ProtocolError (a reply this module does not understand),
RefusedError (the daemon closed the connection after a fatal error), NotOwnerError,
OrderError (a call out of order); bad arguments raise ValueError.

One daemon runs per device, each on its own socket in the runtime directory ($RUNTIME_DIRECTORY,
else /run/hgcd) named after its device id; connect(device=SPEC) picks one by device id or spec,
running() lists them.

A Client is not thread-safe: use one per thread.
"""

from __future__ import annotations

import enum
import json
import math
import os
import re
import select
import socket
import sys
import time
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

__all__ = [
    "PROTOCOL_VERSION", "DEFAULT_RUNTIME_DIR", "DEFAULT_MAX_FORCE_N", "Vector",
    "FLAG_MOTORS_ENABLED", "FLAG_FAULT", "FLAG_BUTTON", "FLAG_FORCE_SATURATED",
    "FLAG_DEVICE_WATCHDOG", "Role", "Mode", "Welcome", "State", "Status",
    "HgcdError", "ConnectError", "ClosedError", "ProtocolError", "RefusedError",
    "NotOwnerError", "OrderError", "Client", "Daemon", "connect", "running", "find",
]

PROTOCOL_VERSION = 1
#: Where daemons listen, one socket per device, when $RUNTIME_DIRECTORY is not set.
DEFAULT_RUNTIME_DIR = "/run/hgcd"
#: The per-axis force limit protocol v1 documents (safety.max_force_n by default), N. A daemon
#: configured otherwise closes a client that sends a component above its own limit.
DEFAULT_MAX_FORCE_N = 8.0
#: Longest reply line accepted, bytes.
MAX_REPLY_LEN = 64 * 1024
#: How long a reply may take from its first byte to its end, s (the daemon writes it at once).
LINE_COMPLETION_S = 1.0
#: How long hello() waits for the welcome, s.
WELCOME_WAIT_S = 5.0
#: The largest welcome rate_hz accepted, Hz (the top of the daemon's servo.rate_hz range).
MAX_RATE_HZ = 10_000.0
#: The largest welcome max_force_n accepted, N (the top of the daemon's safety.max_force_n range).
MAX_FORCE_N = 50.0
#: The longest welcome device (a spec) and device_id accepted, characters.
MAX_DEVICE_LEN = 4096
MAX_DEVICE_ID_LEN = 255

# State flags (docs/hid-protocol.md section 4).
FLAG_MOTORS_ENABLED = 0x1
FLAG_FAULT = 0x2
FLAG_BUTTON = 0x4
FLAG_FORCE_SATURATED = 0x8
FLAG_DEVICE_WATCHDOG = 0x10

Vector = Tuple[float, float, float]


class HgcdError(Exception):
    """Anything that went wrong talking to the daemon."""


class ConnectError(HgcdError):
    """Nobody listens on the socket."""


class ClosedError(HgcdError):
    """The daemon closed the connection (it stopped, or closed this client)."""


class ProtocolError(HgcdError):
    """The daemon sent something this module does not understand."""


class RefusedError(HgcdError):
    """The daemon refused a request with a fatal error and closed the connection."""


class NotOwnerError(HgcdError):
    """Another client owns the force, or this one observes."""


class OrderError(HgcdError):
    """A call out of order: a request before hello, or a second hello."""


class Role(str, enum.Enum):
    CONTROL = "control"  # render forces (one client at a time)
    OBSERVE = "observe"  # read state and status only


class Mode(str, enum.Enum):
    NONE = "none"  # no grid: the daemon renders the applications' forces only
    SCALAR = "scalar"  # M(X) g v_G from the grid's masses
    VECTOR = "vector"  # the grid's per-vertex holding forces, interpolated
    ARM = "arm"  # the arm model fitted at calibration
    ARM_RESIDUAL = "arm_residual"  # the arm model plus the lattice of what it left over


@dataclass(frozen=True)
class Welcome:
    role: Role  # granted: OBSERVE when another client owns the force
    client_id: int
    device: str
    device_id: str
    rate_hz: float  # servo rate, Hz
    #: Largest force component set_force may send, N: the daemon's safety.max_force_n when its
    #: welcome gives it, else DEFAULT_MAX_FORCE_N.
    max_force_n: float = DEFAULT_MAX_FORCE_N


@dataclass(frozen=True)
class State:
    """The device at one servo tick."""

    tick: int
    time: float  # device time, s
    position: Vector  # m
    velocity: Vector  # m/s (FOAW estimate)
    force: Vector  # N sent to the device: your offset plus compensation, after the safety layer
    flags: int  # FLAG_* bits
    offset_seq: int  # set_force number the servo applied on this tick (0: none)

    @property
    def button(self) -> bool:
        return bool(self.flags & FLAG_BUTTON)


@dataclass(frozen=True)
class Status:
    device: str
    device_id: str
    grid: Optional[str]
    mode: Mode
    calibrating: bool
    clients: int
    owner: Optional[str]
    uptime_s: float
    ticks: int
    late: int
    missed: int
    overruns: int
    garbled: int
    watchdog_faults: int
    worst_compute_us: float
    worst_period_us: float
    late_wakeups: int
    worst_lateness_us: float


def _shown(value: Any) -> str:
    """`value` for a message: its repr (control characters escaped), at most 200 characters."""
    text = repr(value)
    return text if len(text) <= 200 else text[:200] + "..."


def _printable(text: str) -> str:
    """`text` without control characters (terminal escapes among them)."""
    return "".join(c for c in text if not (ord(c) < 0x20 or 0x7F <= ord(c) < 0xA0))


#: What a value of each kind of field must be: integers unsigned 64-bit, numbers finite.
_KINDS = {
    bool: lambda v: isinstance(v, bool),
    str: lambda v: isinstance(v, str),
    int: lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**64,
    float: lambda v: (isinstance(v, (int, float)) and not isinstance(v, bool)
                      and abs(v) <= sys.float_info.max),
}
_MISSING = object()


def _field(reply: Dict[str, Any], name: str, kind: Any, default: Any = _MISSING) -> Any:
    """`reply[name]`, a `kind` (`default` when absent, if given); a float for a number."""
    if default is not _MISSING and name not in reply:
        return default
    value = reply.get(name)
    if not _KINDS[kind](value):
        raise ProtocolError(f"the daemon's {reply['type']} has no valid {name!r}: {_shown(value)}")
    return float(value) if kind is float else value


def _ranged(reply: Dict[str, Any], name: str, kind: Any, valid: Any, rule: str,
            default: Any = _MISSING) -> Any:
    """`reply[name]` as _field gives it, if `valid` holds for it, else a ProtocolError saying
    the `rule`."""
    value = _field(reply, name, kind, default)
    if not valid(value):
        raise ProtocolError(f"the daemon's {reply['type']} has {name!r} {_shown(value)}: {rule}")
    return value


def _optional(reply: Dict[str, Any], name: str) -> Optional[str]:
    value = reply.get(name)
    if value is not None and not isinstance(value, str):
        raise ProtocolError(f"the daemon's {reply['type']} has no valid {name!r}: {_shown(value)}")
    return None if value is None else _printable(value)


def _vector(reply: Dict[str, Any], name: str) -> Vector:
    value = reply.get(name)
    if not (isinstance(value, list) and len(value) == 3 and all(map(_KINDS[float], value))):
        raise ProtocolError(f"the daemon's {reply['type']} has no valid {name!r}: {_shown(value)}")
    return (float(value[0]), float(value[1]), float(value[2]))


def _welcome(reply: Dict[str, Any], asked: Role) -> Welcome:
    """The welcome `reply` to a hello asking for `asked`, each field in its range
    (docs/app-protocol.md section 5)."""
    _ranged(reply, "version", int, lambda v: v == PROTOCOL_VERSION,
            f"this client speaks {PROTOCOL_VERSION}")
    role = _ranged(reply, "role", str, lambda v: v in (asked.value, Role.OBSERVE.value),
                   f"granted to a hello asking for {asked.value}")
    return Welcome(
        role=Role(role),
        client_id=_ranged(reply, "client_id", int, lambda v: v >= 1, "ids start at 1"),
        device=_ranged(reply, "device", str,
                       lambda v: 0 < len(v) <= MAX_DEVICE_LEN and v == _printable(v),
                       f"a spec has 1 to {MAX_DEVICE_LEN} characters, none a control character"),
        device_id=_ranged(reply, "device_id", str,
                          re.compile(f"[A-Za-z0-9_-]{{1,{MAX_DEVICE_ID_LEN}}}").fullmatch,
                          f"an id has 1 to {MAX_DEVICE_ID_LEN} ASCII letters, digits, '-' and '_'"),
        rate_hz=_ranged(reply, "rate_hz", float, lambda v: 0 < v <= MAX_RATE_HZ,
                        f"the servo rate is above 0 and at most {MAX_RATE_HZ:g} Hz"),
        max_force_n=_ranged(reply, "max_force_n", float, lambda v: 0 < v <= MAX_FORCE_N,
                            f"the limit is above 0 and at most {MAX_FORCE_N:g} N",
                            DEFAULT_MAX_FORCE_N),
    )


def _state(reply: Dict[str, Any]) -> State:
    return State(
        tick=_field(reply, "tick", int),
        time=_field(reply, "time", float),
        position=_vector(reply, "position"),
        velocity=_vector(reply, "velocity"),
        force=_vector(reply, "force"),
        flags=_field(reply, "flags", int),
        offset_seq=_field(reply, "offset_seq", int),
    )


def _status(reply: Dict[str, Any]) -> Status:
    try:
        mode = Mode(reply.get("mode"))
    except ValueError:
        raise ProtocolError(f"the daemon's status has an unknown mode: {_shown(reply.get('mode'))}")
    return Status(
        device=_printable(_field(reply, "device", str)),
        device_id=_printable(_field(reply, "device_id", str)),
        grid=_optional(reply, "grid"),
        mode=mode,
        calibrating=_field(reply, "calibrating", bool),
        clients=_field(reply, "clients", int),
        owner=_optional(reply, "owner"),
        uptime_s=_field(reply, "uptime_s", float),
        **{name: _field(reply, name, int) for name in (
            "ticks", "late", "missed", "overruns", "garbled", "watchdog_faults")},
        worst_compute_us=_field(reply, "worst_compute_us", float),
        worst_period_us=_field(reply, "worst_period_us", float),
        late_wakeups=_field(reply, "late_wakeups", int, 0),
        worst_lateness_us=_field(reply, "worst_lateness_us", float, 0.0),
    )


class Client:
    """One connection to the daemon. Make it with connect(); use it as a context manager."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self._buf = bytearray()
        self._began = 0.0  # when the first byte in _buf arrived (monotonic s)
        self._seq = 0
        self._pending: Optional[State] = None
        self.welcome: Optional[Welcome] = None

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection; the daemon removes this client's force offset at once."""
        self._sock.close()

    # Requests

    def hello(self, role: Role = Role.OBSERVE, name: str = "") -> Welcome:
        """Say hello asking for `role` under `name` (shown as the owner in status; empty:
        client-<id>), once and first. Asking for control while another client owns the force
        is granted OBSERVE: check the welcome's role, or use take_ownership()."""
        if self.welcome is not None:
            raise OrderError("this client already said hello: a client's role is fixed for its "
                             "connection, connect again to change it")
        self._send({"type": "hello", "version": PROTOCOL_VERSION, "role": Role(role).value,
                    "name": name})
        reply = self._reply(time.monotonic() + WELCOME_WAIT_S)
        if reply is None:
            raise ProtocolError(f"no welcome from the daemon within {WELCOME_WAIT_S:g} s")
        if reply["type"] != "welcome":
            raise ProtocolError(f"expected a welcome, got: {_shown(reply)}")
        self.welcome = _welcome(reply, Role(role))
        return self.welcome

    def take_ownership(self, name: str = "") -> Welcome:
        """Say hello asking for control and raise NotOwnerError unless it was granted (the
        protocol fixes a client's role at its hello). After NotOwnerError the client observes."""
        welcome = self.hello(Role.CONTROL, name)
        if welcome.role is not Role.CONTROL:
            raise NotOwnerError("another client owns the force; this client may observe")
        return welcome

    def set_force(self, force: Sequence[float]) -> int:
        """Render `force` (N) on top of gravity compensation until the next call; its number.
        Send one per state sample, and at least every 50 ms (app.stale_offset_ms), or it ramps
        to zero. Each component must be at most welcome.max_force_n, or the daemon closes the
        connection."""
        self._greeted()
        if self.welcome is None or self.welcome.role is not Role.CONTROL:
            raise NotOwnerError("this client does not own the force (it observes)")
        fx, fy, fz = (float(f) for f in force)
        if not all(math.isfinite(f) for f in (fx, fy, fz)):
            raise ValueError(f"force ({fx}, {fy}, {fz}) N is not finite")
        self._seq += 1
        self._write(f'{{"type":"set_force","seq":{self._seq},"force":[{fx!r},{fy!r},{fz!r}]}}\n')
        return self._seq

    def subscribe(self, rate_hz: float) -> None:
        """Stream state samples at `rate_hz` (at most the welcome's rate_hz; 0 stops it). Read
        them continuously with newest_state(): a client that stops reading is disconnected."""
        self._greeted()
        rate_hz = float(rate_hz)
        if not (math.isfinite(rate_hz) and rate_hz >= 0.0):
            raise ValueError(f"rate_hz is {rate_hz}: give 0 to the servo rate")
        self._send({"type": "subscribe", "rate_hz": rate_hz})

    def newest_state(self, wait: float = 0.0) -> Optional[State]:
        """The newest state sample that arrived since the last call, reading everything that
        has arrived without waiting; if none has, wait up to `wait` s for one (None if none
        came). Older samples, non-fatal errors and calibration events are skipped."""
        self._greeted()
        if wait < 0.0:
            raise ValueError(f"wait is {wait}: give 0 or more seconds")
        newest, self._pending = self._pending, None
        deadline = time.monotonic() + wait
        until = time.monotonic()
        while True:
            reply = self._reply(until)
            if reply is None:
                if newest is None and until < deadline:
                    until = deadline
                    continue
                return newest
            if reply["type"] == "state":
                newest = _state(reply)
                until = time.monotonic()

    def status(self, timeout: float = 5.0) -> Status:
        """Ask for the daemon's status and wait up to `timeout` s for it. State samples that
        arrive meanwhile are kept for newest_state()."""
        self._greeted()
        self._send({"type": "status"})
        deadline = time.monotonic() + timeout
        while True:
            reply = self._reply(deadline)
            if reply is None:
                raise HgcdError(f"no status from the daemon within {timeout} s")
            if reply["type"] == "status":
                return _status(reply)
            if reply["type"] == "state":
                self._pending = _state(reply)

    # The connection

    def _greeted(self) -> None:
        if self.welcome is None:
            raise OrderError("say hello first (hello() or take_ownership())")

    def _send(self, request: Dict[str, Any]) -> None:
        self._write(json.dumps(request, separators=(",", ":")) + "\n")

    def _write(self, line: str) -> None:
        try:
            self._sock.sendall(line.encode())
        except (BrokenPipeError, ConnectionResetError) as e:
            raise ClosedError(f"the daemon closed the connection ({e})") from e
        except OSError as e:
            raise HgcdError(f"socket error: {e}") from e

    def _reply(self, deadline: float) -> Optional[Dict[str, Any]]:
        """The next reply if one begins to arrive before `deadline` (monotonic s), else None.
        A fatal error from the daemon raises RefusedError."""
        line = self._line(deadline)
        if line is None:
            return None
        try:
            reply = json.loads(line.decode("utf-8"))
        except (ValueError, RecursionError):  # UnicodeDecodeError is a ValueError
            raise ProtocolError(
                f"the daemon sent something this client does not understand: {bytes(line)[:200]!r}"
            ) from None
        if not (isinstance(reply, dict) and isinstance(reply.get("type"), str)):
            raise ProtocolError(f"the daemon sent a reply without a type: {bytes(line)[:200]!r}")
        if reply["type"] == "error" and reply.get("fatal") is True:
            raise RefusedError(f"the daemon refused: {_printable(str(reply.get('message')))}")
        return reply

    def _line(self, deadline: float) -> Optional[bytes]:
        while True:
            end = self._buf.find(b"\n")
            if end >= 0:
                line = bytes(self._buf[:end])
                del self._buf[: end + 1]
                return line
            if len(self._buf) > MAX_REPLY_LEN:
                raise ProtocolError(f"the daemon sent a line longer than {MAX_REPLY_LEN} bytes")
            if self._buf:  # a reply has begun: read it to its end, however its bytes trickle in
                deadline = self._began + LINE_COMPLETION_S
            if not self._readable(max(0.0, deadline - time.monotonic())):
                if self._buf:
                    raise ProtocolError(
                        f"the daemon did not end a line within {LINE_COMPLETION_S:g} s of its "
                        f"first byte: {bytes(self._buf)[:200]!r}")
                return None
            try:
                chunk = self._sock.recv(65536)
            except ConnectionResetError as e:
                raise ClosedError(f"the daemon closed the connection ({e})") from e
            except OSError as e:
                raise HgcdError(f"socket error: {e}") from e
            if not chunk:
                if self._buf:
                    raise ClosedError("the daemon closed the connection in the middle of a line")
                raise ClosedError("the daemon closed the connection")
            if not self._buf or b"\n" in chunk:  # the line left unfinished begins in this chunk
                self._began = time.monotonic()
            self._buf += chunk

    def _readable(self, timeout: float) -> bool:
        while True:
            try:
                readable, _, _ = select.select([self._sock], [], [], timeout)
                return bool(readable)
            except InterruptedError:
                continue


@dataclass(frozen=True)
class Daemon:
    """A daemon found listening in the runtime directory, as its welcome describes it."""

    socket: str
    device: str  # the spec it opened its device with
    device_id: str  # its device's grid id, which names the socket

    def matches(self, spec: str) -> bool:
        """Whether `spec` names this daemon's device: its device id, its spec, or its spec
        without the parts the daemon filled in (hid:1209:4847 for hid:1209:4847:SN1)."""
        return spec in (self.device_id, self.device) or self.device.startswith(spec + ":")


def runtime_dir() -> str:
    """The directory daemons' sockets are in: the first entry of $RUNTIME_DIRECTORY, else
    DEFAULT_RUNTIME_DIR."""
    dirs = [d for d in os.environ.get("RUNTIME_DIRECTORY", "").split(":") if d]
    return dirs[0] if dirs else DEFAULT_RUNTIME_DIR


def running(directory: Optional[str] = None) -> List[Daemon]:
    """Every daemon listening in `directory` (default: runtime_dir()), by socket name; sockets
    nobody listens on are skipped."""
    directory = directory or runtime_dir()
    try:
        names = sorted(n for n in os.listdir(directory) if n.endswith(".sock"))
    except FileNotFoundError:
        return []
    found = []
    for name in names:
        path = os.path.join(directory, name)
        try:
            client = _open(path)
        except ConnectError as e:
            if isinstance(e.__cause__, (ConnectionRefusedError, FileNotFoundError)):
                continue
            raise
        with client:
            welcome = client.hello(Role.OBSERVE, "hgcd lookup")
        found.append(Daemon(path, welcome.device, welcome.device_id))
    return found


def find(device: Optional[str] = None, directory: Optional[str] = None) -> Daemon:
    """The one daemon of `device` (a device id or spec), or with None the only one running.
    ConnectError says so when there is none, or several and `device` does not say which."""
    directory = directory or runtime_dir()
    every = running(directory)
    if not every:
        raise ConnectError(f"no hgcd daemon is running (no live socket in {directory}): start "
                           "one, or give its socket's path")
    matching = [d for d in every if device is None or d.matches(device)]
    if len(matching) == 1:
        return matching[0]
    names = ", ".join(f"{d.device_id} ({d.device})" for d in (matching or every))
    if not matching:
        raise ConnectError(f"no hgcd daemon for device {device!r}; running: {names}")
    raise ConnectError(f"{len(matching)} hgcd daemons are running: {names}; say which with "
                       "device=SPEC (a device id or spec)")


def connect(path: Optional[str] = None, device: Optional[str] = None) -> Client:
    """Connect to the daemon's socket at `path`, else to the daemon of `device` (a device id or
    spec), else to the only daemon running; say hello next (hello() or take_ownership()),
    within the daemon's app.hello_timeout_ms (5 s)."""
    return _open(path if path is not None else find(device).socket)


def _open(path: str) -> Client:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(path)
    except OSError as e:
        sock.close()
        raise ConnectError(
            f"cannot connect to the hgcd socket {path}: {e.strerror or e} (is `hgcd run` running?)"
        ) from e
    return Client(sock)
