//! The application socket: a scripted session checked against its golden transcript
//! (`tests/golden/app-session.txt`, the example of `docs/app-protocol.md`), and slow and idle
//! clients (the hello deadline, the status slot). Daemons here run the simulated device in
//! virtual time; only the clients keep wall-clock time.

use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::thread;
use std::time::{Duration, Instant};

use hgcd::client::{CalibrationStage, Client, Compensating, Reply, Role, Status};
use hgcd::config::Config;
use hgcd::grid::GridFile;

mod common;
use common::daemon::{Running, TestDaemon};
use common::{hgcd, serial, stdout_of, truth_field_27, with_device_id};

/// A daemon serving the simulated point mass in virtual time, with its own socket and state dir.
fn start(config: Config, grid: Option<&GridFile>) -> Running {
    TestDaemon::new(config).grid(grid).start()
}

/// A daemon on the simulated device that serves at most `max_clients` connections and closes one
/// that has not said hello within `hello_timeout_ms`.
fn start_limited(max_clients: usize, hello_timeout_ms: f64) -> Running {
    let mut config = Config::default();
    config.app.max_clients = max_clients;
    config.app.hello_timeout_ms = hello_timeout_ms;
    start(config, None)
}

/// A raw connection to `daemon`'s socket.
fn connect(daemon: &Running) -> UnixStream {
    UnixStream::connect(&daemon.socket).unwrap()
}

/// Stop `daemon`, which must end cleanly.
fn stop(daemon: Running) {
    daemon.stop().unwrap();
}

/// Everything the daemon sends on `stream` until it closes the connection (bounded by `limit`).
fn read_until_closed(mut stream: UnixStream, limit: Duration) -> String {
    stream.set_read_timeout(Some(limit)).unwrap();
    let mut out = String::new();
    let _ = stream.read_to_string(&mut out);
    out
}

/// The next reply on a raw connection.
fn next_reply(replies: &mut BufReader<UnixStream>) -> Reply {
    let mut line = String::new();
    assert!(
        replies.read_line(&mut line).unwrap() > 0,
        "connection closed"
    );
    serde_json::from_str(&line).unwrap()
}

/// `out`, all a connection got, ends in a fatal error saying `why`, and the connection closed
/// `closed_after` its start: not before the 300 ms deadline, nor seconds after it.
fn assert_closed_at_the_deadline(out: &str, why: &str, closed_after: Duration) {
    assert!(
        out.contains(why) && out.contains("\"fatal\":true"),
        "{out:?}"
    );
    assert!(
        closed_after >= Duration::from_millis(300) && closed_after < Duration::from_secs(5),
        "closed after {closed_after:?}"
    );
}

const HELLO_OBSERVE: &[u8] = b"{\"type\":\"hello\",\"version\":1,\"role\":\"observe\"}\n";
const HELLO_CONTROL: &[u8] = b"{\"type\":\"hello\",\"version\":1,\"role\":\"control\"}\n";

/// The golden transcript, and the header it starts with.
const GOLDEN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/golden/app-session.txt");
const GOLDEN_HEADER: &str = "\
# hgcd application protocol v1: a scripted session, run and compared with this file by
# tests/app_socket.rs. A daemon serves the simulated point mass in virtual time with a grid;
# A to E are connections opened one after another. `>>`: client to daemon, `<<`: daemon
# to client, one line each, exactly as on the wire except: values that vary from run to run
# (times, positions, velocities, forces, masses, uptime and servo counters) read \"*\",
# $STATE_DIR is the daemon's state directory, and a `state` line appears only where the script
# waits for one (the samples before it are left out). After a deliberate protocol change,
# regenerate with `HGCD_BLESS=1 cargo test --test app_socket scripted_session` and review the
# diff.
";

/// The length of the JSON value `text` starts with (no whitespace: serde's compact output).
fn value_len(text: &str) -> usize {
    let (mut depth, mut in_string, mut escaped) = (0usize, false, false);
    for (i, c) in text.char_indices() {
        if in_string {
            match c {
                _ if escaped => escaped = false,
                '\\' => escaped = true,
                '"' => in_string = false,
                _ => {}
            }
            continue;
        }
        match c {
            '"' => in_string = true,
            '[' | '{' => depth += 1,
            ']' | '}' if depth > 0 => depth -= 1,
            ',' | '}' if depth == 0 => return i,
            _ => {}
        }
    }
    text.len()
}

/// `line` (one JSON object) with the values of the members `keep` does not name replaced by
/// "*", members in their order on the wire.
fn mask(line: &str, keep: impl Fn(&str) -> bool) -> String {
    let mut rest = line.strip_prefix('{').expect("an object");
    let mut members = Vec::new();
    while let Some(after_quote) = rest.strip_prefix('"') {
        let key_end = after_quote.find("\":").expect("a member");
        let key = &after_quote[..key_end];
        let value = &after_quote[key_end + 2..];
        let len = value_len(value);
        members.push(if keep(key) {
            format!("\"{key}\":{}", &value[..len])
        } else {
            format!("\"{key}\":\"*\"")
        });
        rest = value[len..].strip_prefix(',').unwrap_or(&value[len..]);
    }
    assert_eq!(rest, "}", "unparsed rest of {line}");
    format!("{{{}}}", members.join(","))
}

/// A reply line as the transcript shows it.
fn masked(line: &str, reply: &Reply) -> String {
    match reply {
        Reply::State(_) => mask(line, |k| matches!(k, "type" | "flags" | "offset_seq")),
        Reply::Status(_) => mask(line, |k| {
            matches!(
                k,
                "type"
                    | "device"
                    | "device_id"
                    | "grid"
                    | "mode"
                    | "held_out_pct"
                    | "calibrating"
                    | "clients"
                    | "owner"
                    | "model_stale"
            )
        }),
        // The time left a vertex reports, and where the run's time went, depend on how long the
        // run took.
        Reply::Calibration {
            event: CalibrationStage::VertexDone | CalibrationStage::TimeSpent,
            ..
        } => mask(line, |k| k != "mass_kg" && k != "message"),
        Reply::Calibration { .. } => mask(line, |k| k != "mass_kg"),
        // Measured forces and times: only its shape is the transcript's.
        Reply::Checked(_) => mask(line, |k| k == "type" || k == "verdict"),
        Reply::Reverted(_) => mask(line, |k| k == "type"),
        Reply::Welcome { .. } | Reply::Error { .. } => line.to_string(),
    }
}

/// One connection of the scripted session.
struct Peer {
    name: char,
    stream: UnixStream,
    replies: BufReader<UnixStream>,
}

/// The scripted session and its transcript.
struct Script<'a> {
    daemon: &'a Running,
    state_dir: String,
    transcript: String,
}

impl Script<'_> {
    fn connect(&mut self, name: char) -> Peer {
        let stream = connect(self.daemon);
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        let replies = BufReader::new(stream.try_clone().unwrap());
        Peer {
            name,
            stream,
            replies,
        }
    }

    fn note(&mut self, text: &str) {
        self.transcript += &format!("\n# {text}\n");
    }

    fn send(&mut self, peer: &mut Peer, line: &str) {
        peer.stream
            .write_all(format!("{line}\n").as_bytes())
            .unwrap();
        self.transcript += &format!("{} >> {line}\n", peer.name);
    }

    /// The next reply for which `wanted` holds, state samples before it skipped. Any other
    /// reply in between fails the test.
    fn expect(&mut self, peer: &mut Peer, wanted: impl Fn(&Reply) -> bool) -> Reply {
        loop {
            let mut line = String::new();
            let n = peer.replies.read_line(&mut line).unwrap();
            assert!(
                n > 0,
                "{}: connection closed; so far:\n{}",
                peer.name,
                self.transcript
            );
            let line = line
                .trim_end_matches('\n')
                .replace(&self.state_dir, "$STATE_DIR");
            let reply: Reply = serde_json::from_str(&line)
                .unwrap_or_else(|e| panic!("{}: not a reply ({e}): {line}", peer.name));
            if wanted(&reply) {
                self.transcript += &format!("{} << {}\n", peer.name, masked(&line, &reply));
                return reply;
            }
            assert!(
                matches!(reply, Reply::State(_)),
                "{}: unexpected {line}; so far:\n{}",
                peer.name,
                self.transcript
            );
        }
    }

    /// The welcome, which must grant `role` and number the client `client_id`.
    /// Connect `name` and say hello as the client `client` asking for control; the daemon
    /// welcomes it as `role` with the id `client_id`.
    fn hello_control(&mut self, name: char, client: &str, role: Role, client_id: u64) -> Peer {
        let mut peer = self.connect(name);
        let hello = format!(r#"{{"type":"hello","version":1,"role":"control","name":"{client}"}}"#);
        self.send(&mut peer, &hello);
        self.expect_welcome(&mut peer, role, client_id);
        peer
    }

    fn expect_welcome(&mut self, peer: &mut Peer, role: Role, client_id: u64) {
        let welcome = self.expect(peer, |r| matches!(r, Reply::Welcome { .. }));
        assert!(
            matches!(welcome, Reply::Welcome { role: r, client_id: id, .. } if r == role && id == client_id),
            "{welcome:?}"
        );
    }

    /// Ask for the status and wait for it.
    fn status(&mut self, peer: &mut Peer) -> Box<Status> {
        self.send(peer, r#"{"type":"status"}"#);
        let Reply::Status(status) = self.expect(peer, is_status) else {
            unreachable!()
        };
        status
    }

    /// The fatal error that ends `peer`'s connection, and the end of the stream.
    fn expect_fatal(&mut self, peer: &mut Peer) -> String {
        let Reply::Error { message, fatal } =
            self.expect(peer, |r| matches!(r, Reply::Error { .. }))
        else {
            unreachable!()
        };
        assert!(fatal, "{message}");
        let mut rest = String::new();
        peer.replies.read_to_string(&mut rest).unwrap();
        assert_eq!(rest, "", "after a fatal error");
        self.transcript += &format!("{} << (end of stream)\n", peer.name);
        message
    }
}

fn is_status(r: &Reply) -> bool {
    matches!(r, Reply::Status(_))
}

fn is_error(r: &Reply) -> bool {
    matches!(r, Reply::Error { fatal: false, .. })
}

#[test]
fn the_scripted_session_matches_its_golden_transcript() {
    let _serial = serial();
    let grid = with_device_id(truth_field_27(), "sim-point-mass");
    let daemon = start(Config::default(), Some(&grid));
    let state_dir = daemon.dir.path().join("state");
    let grid_file = state_dir.join("sim-point-mass.toml");
    let mut s = Script {
        daemon: &daemon,
        state_dir: state_dir.display().to_string(),
        transcript: GOLDEN_HEADER.to_string(),
    };

    s.note("A asks for the force and gets it; its status names it as the owner.");
    let mut a = s.hello_control('A', "golden", Role::Control, 1);
    let status = s.status(&mut a);
    assert_eq!(
        (status.mode, status.owner.as_deref()),
        (Compensating::Scalar, Some("golden"))
    );

    s.note(
        "A streams the state at 100 Hz and renders 0.5 N along +z on top of gravity compensation.",
    );
    s.send(&mut a, r#"{"type":"subscribe","rate_hz":100}"#);
    s.send(
        &mut a,
        r#"{"type":"set_force","seq":1,"force":[0.0,0.0,0.5]}"#,
    );
    // Tick 0 is sampled too; its report precedes the first output report, so it shows the
    // motors not yet enabled (flags 0) when the script gets there before the servo loop starts.
    let Reply::State(state) = s.expect(
        &mut a,
        |r| matches!(r, Reply::State(x) if x.offset_seq == 1 && x.tick > 0),
    ) else {
        unreachable!()
    };
    assert_eq!(state.tick % 10, 0, "every 10th tick at 100 Hz");
    // Gravity compensation plus the offset (or, had the hub dropped the first samples that
    // carried it, the offset already ramping down as stale): never more than the offset.
    let beyond_gravity =
        nalgebra::Vector3::from(state.force) - grid.grid.gravity_force(&state.position.into());
    assert!(
        beyond_gravity.xy().norm() < 2e-3 && (-2e-3..0.502).contains(&beyond_gravity.z),
        "force {:?} is gravity + {beyond_gravity}",
        state.force
    );
    // The gravity part alone, as the grid gives it at that position.
    let gravity = nalgebra::Vector3::from(state.gravity.expect("the daemon sends `gravity`"));
    let expected = grid.grid.gravity_force(&state.position.into());
    assert!(
        (gravity - expected).norm() < 1e-9 && expected.norm() > 0.1,
        "gravity {gravity} where the grid gives {expected}"
    );
    s.note("A stops the stream; samples already queued still arrive, up to the status reply.");
    s.send(&mut a, r#"{"type":"subscribe","rate_hz":0}"#);
    s.send(&mut a, r#"{"type":"status"}"#);
    s.expect(&mut a, is_status);

    s.note(
        "The owner calibrates; progress goes to it alone, and the daemon switches to the new grid.",
    );
    s.send(&mut a, r#"{"type":"calibrate"}"#);
    loop {
        let reply = s.expect(&mut a, |r| matches!(r, Reply::Calibration { .. }));
        let Reply::Calibration { event, message, .. } = reply else {
            unreachable!()
        };
        match event {
            CalibrationStage::Finished => {
                assert_eq!(message, "$STATE_DIR/sim-point-mass.toml");
                break;
            }
            CalibrationStage::Failed => panic!("calibration failed: {message}"),
            _ => {}
        }
    }
    let status = s.status(&mut a);
    assert!(!status.calibrating);
    assert!(GridFile::load(&grid_file).is_ok());

    s.note("B asks for the force while A owns it: B may observe, and is refused what only the owner may do.");
    let mut b = s.hello_control('B', "second", Role::Observe, 2);
    s.expect(&mut b, is_error);
    s.send(
        &mut b,
        r#"{"type":"set_force","seq":1,"force":[1.0,0.0,0.0]}"#,
    );
    s.expect(&mut b, is_error);
    s.send(&mut b, r#"{"type":"calibrate"}"#);
    s.expect(&mut b, is_error);
    s.note("A request out of range is fatal, for observers too.");
    s.send(&mut b, r#"{"type":"subscribe","rate_hz":5000}"#);
    s.expect_fatal(&mut b);

    s.note("A malformed line is fatal.");
    let mut c = s.connect('C');
    s.send(
        &mut c,
        r#"{"type":"hello","version":1,"role":"observe","name":"third"}"#,
    );
    s.expect(&mut c, |r| matches!(r, Reply::Welcome { .. }));
    s.send(&mut c, r#"{"type":"set_force","seq":1}"#);
    s.expect_fatal(&mut c);

    s.note("Anything before hello is fatal, and so is another protocol version.");
    let mut d = s.connect('D');
    s.send(&mut d, r#"{"type":"status"}"#);
    s.expect_fatal(&mut d);
    let mut e = s.connect('E');
    s.send(&mut e, r#"{"type":"hello","version":2,"role":"observe"}"#);
    s.expect_fatal(&mut e);

    s.note("set_force sequence numbers must increase: a repeated one is fatal, and the offset goes with the owner.");
    s.send(
        &mut a,
        r#"{"type":"set_force","seq":2,"force":[0.0,0.0,0.0]}"#,
    );
    s.send(
        &mut a,
        r#"{"type":"set_force","seq":2,"force":[0.0,0.0,0.0]}"#,
    );
    s.expect_fatal(&mut a);

    let transcript = s.transcript;
    stop(daemon);
    if std::env::var_os("HGCD_BLESS").is_some() {
        std::fs::write(GOLDEN, &transcript).unwrap();
        return;
    }
    // The example lines of the protocol's documentation come from this session.
    let doc = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/app-protocol.md");
    for line in std::fs::read_to_string(doc).unwrap().lines() {
        let exchange = matches!(line.get(1..5), Some(" >> " | " << "));
        assert!(
            !exchange || transcript.lines().any(|t| t == line),
            "{doc}: this line is not in the session:\n{line}"
        );
    }
    let golden = std::fs::read_to_string(GOLDEN).unwrap_or_default();
    for (n, (got, want)) in transcript.lines().zip(golden.lines()).enumerate() {
        assert_eq!(got, want, "{GOLDEN}:{} differs", n + 1);
    }
    assert_eq!(
        transcript.lines().count(),
        golden.lines().count(),
        "{GOLDEN}: not the same length; the session gave:\n{transcript}"
    );
}

#[test]
fn a_client_trickling_bytes_is_closed_at_the_hello_deadline() {
    let _serial = serial();
    let mut config = Config::default();
    config.app.hello_timeout_ms = 300.0;
    let daemon = start(config, None);

    let stream = connect(&daemon);
    let connected = Instant::now();
    // One byte every 20 ms and never a newline: every read returns long before the 300 ms
    // timeout, so only a deadline counted from the connection can end it.
    let mut trickle = stream.try_clone().unwrap();
    let trickler = thread::spawn(move || {
        let give_up = Instant::now() + Duration::from_secs(15);
        while Instant::now() < give_up {
            if trickle.write_all(b" ").is_err() {
                return;
            }
            thread::sleep(Duration::from_millis(20));
        }
    });
    let out = read_until_closed(stream, Duration::from_secs(30));
    let closed_after = connected.elapsed();
    trickler.join().unwrap();

    // The deadline starts at accept, after connect: never early. A loaded machine may be late,
    // but nowhere near the 15 s the trickle would last.
    assert_closed_at_the_deadline(&out, "no hello within the time limit", closed_after);
    stop(daemon);
}

#[test]
fn status_still_answers_when_max_clients_connections_are_held() {
    let _serial = serial();
    // A hello deadline long enough that the idle connections below are all still open when
    // status is asked.
    let daemon = start_limited(4, 60_000.0);

    // Every place taken: two subscribers that said hello, two connections that never will.
    let mut held = Vec::new();
    for name in ["sub-1", "sub-2"] {
        let mut c = Client::connect(&daemon.socket, Role::Observe, name).unwrap();
        c.subscribe(1.0).unwrap();
        held.push(c);
    }
    let idle: Vec<UnixStream> = (0..2).map(|_| connect(&daemon)).collect();

    let stdout = stdout_of(
        hgcd()
            .arg("--config")
            .arg("/dev/null")
            .arg("--socket")
            .arg(&daemon.socket)
            .arg("status"),
    );
    assert!(stdout.contains("device        sim:point-mass"), "{stdout}");
    // The four held connections and the status query itself.
    assert!(stdout.contains("clients       5 "), "{stdout}");

    // Once that query has gone, the spare place is free again; it takes one connection at a
    // time, which may only ask for status.
    let gone = Instant::now() + Duration::from_secs(10);
    while held[0].status().unwrap().clients != 4 {
        assert!(Instant::now() < gone, "the status query never left");
    }
    let spare = connect(&daemon);
    spare
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let mut replies = BufReader::new(spare.try_clone().unwrap());
    let send = |line: &[u8]| (&spare).write_all(line).unwrap();
    send(HELLO_CONTROL);
    match next_reply(&mut replies) {
        Reply::Welcome { role, .. } => assert_eq!(role, Role::Observe, "no force for a spare"),
        other => panic!("{other:?}"),
    }
    match next_reply(&mut replies) {
        Reply::Error { message, fatal } => {
            assert!(!fatal);
            assert!(message.contains("may only ask for status"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    send(b"{\"type\":\"status\"}\n");
    match next_reply(&mut replies) {
        Reply::Status(s) => assert_eq!(s.clients, 5),
        other => panic!("{other:?}"),
    }
    let refused = read_until_closed(connect(&daemon), Duration::from_secs(30));
    assert!(refused.contains("too many clients"), "{refused:?}");
    send(b"{\"type\":\"subscribe\",\"rate_hz\":10}\n");
    let mut rest = String::new();
    let _ = replies.read_to_string(&mut rest);
    assert!(
        rest.contains("may only ask for status") && rest.contains("\"fatal\":true"),
        "{rest:?}"
    );

    drop(idle);
    drop(held);
    stop(daemon);
}

#[test]
fn a_status_only_connection_is_closed_at_its_deadline() {
    let _serial = serial();
    let daemon = start_limited(1, 300.0);
    // The one place, held by a client that said hello (no deadline for it).
    let mut held = Client::connect(&daemon.socket, Role::Observe, "held").unwrap();

    let spare = connect(&daemon);
    let connected = Instant::now();
    (&spare).write_all(HELLO_OBSERVE).unwrap();
    (&spare).write_all(b"{\"type\":\"status\"}\n").unwrap();
    let out = read_until_closed(spare, Duration::from_secs(30));
    let closed_after = connected.elapsed();
    assert!(out.contains("\"type\":\"status\""), "{out:?}");
    assert_closed_at_the_deadline(&out, "status-only connection: its time limit", closed_after);
    // The client that holds the place is not touched, and the spare place is free again.
    let gone = Instant::now() + Duration::from_secs(10);
    while held.status().unwrap().clients != 1 {
        assert!(
            Instant::now() < gone,
            "the status-only connection never left"
        );
    }
    drop(held);
    stop(daemon);
}
