//! The application socket under slow and idle clients: the hello deadline, the status slot.
//! Daemons here run the simulated device in virtual time; only the clients keep wall-clock time.

use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use hgcd::client::{Client, Reply, Role};
use hgcd::config::Config;
use hgcd::daemon::{Daemon, RunRequest, Signals};
use hgcd::servo::ServoReport;
use hgcd::transport::sim::{SimDevice, SimTransport};
use hgcd::transport::Pacing;

mod common;
use common::{hgcd, serial, truth_field_27};

/// A daemon serving the simulated point mass in virtual time, with its own socket and state dir.
struct Running {
    dir: tempfile::TempDir,
    socket: PathBuf,
    signals: Signals,
    handle: JoinHandle<anyhow::Result<ServoReport>>,
}

impl Running {
    fn start(mut config: Config) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let truth = dir.path().join("truth.toml");
        truth_field_27().save_atomic(&truth).unwrap();
        config.sim.mass_grid = Some(truth);
        config.sim.damping_n_s_per_m = 1.0;
        config.paths.state_dir = Some(dir.path().join("state"));
        let socket = dir.path().join("hgcd.sock");
        config.app.socket = Some(socket.clone());
        config.servo.lock_memory = false;
        let transport = Box::new(SimTransport::new(
            SimDevice::from_config("point-mass", &config).unwrap(),
            Pacing::Virtual,
        ));
        let request = RunRequest {
            device: "sim:point-mass".parse().unwrap(),
            duration: None,
            pacing: Pacing::Virtual,
        };
        let signals = Signals::default();
        let s2 = signals.clone();
        let (ready_tx, ready_rx) = crossbeam_channel::bounded(1);
        let handle = thread::spawn(move || {
            Daemon::new(config, &request).run(transport, s2, &mut |_| {
                let _ = ready_tx.send(());
            })
        });
        ready_rx
            .recv()
            .expect("the daemon failed before it was ready");
        Self {
            dir,
            socket,
            signals,
            handle,
        }
    }

    fn connect(&self) -> UnixStream {
        UnixStream::connect(&self.socket).unwrap()
    }

    fn stop(self) {
        self.signals.stop.store(true, Ordering::SeqCst);
        self.handle.join().unwrap().unwrap();
        drop(self.dir);
    }
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

const HELLO_OBSERVE: &[u8] = b"{\"type\":\"hello\",\"version\":1,\"role\":\"observe\"}\n";
const HELLO_CONTROL: &[u8] = b"{\"type\":\"hello\",\"version\":1,\"role\":\"control\"}\n";

#[test]
fn a_client_trickling_bytes_is_closed_at_the_hello_deadline() {
    let _serial = serial();
    let mut config = Config::default();
    config.app.hello_timeout_ms = 300.0;
    let daemon = Running::start(config);

    let stream = daemon.connect();
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

    assert!(
        out.contains("no hello within the time limit") && out.contains("\"fatal\":true"),
        "{out:?}"
    );
    // The deadline starts at accept, after connect: never early. A loaded machine may be late,
    // but nowhere near the 15 s the trickle would last.
    assert!(
        closed_after >= Duration::from_millis(300),
        "closed after {closed_after:?}"
    );
    assert!(
        closed_after < Duration::from_secs(5),
        "closed after {closed_after:?}"
    );
    daemon.stop();
}

#[test]
fn status_still_answers_when_max_clients_connections_are_held() {
    let _serial = serial();
    let mut config = Config::default();
    config.app.max_clients = 4;
    // Long enough that the idle connections below are all still open when status is asked.
    config.app.hello_timeout_ms = 60_000.0;
    let daemon = Running::start(config);

    // Every place taken: two subscribers that said hello, two connections that never will.
    let mut held = Vec::new();
    for name in ["sub-1", "sub-2"] {
        let mut c = Client::connect(&daemon.socket, Role::Observe, name).unwrap();
        c.subscribe(1.0).unwrap();
        held.push(c);
    }
    let idle: Vec<UnixStream> = (0..2).map(|_| daemon.connect()).collect();

    let out = hgcd()
        .arg("--config")
        .arg("/dev/null")
        .arg("--socket")
        .arg(&daemon.socket)
        .arg("status")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "hgcd status failed: {}",
        String::from_utf8_lossy(&out.stderr)
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
    let spare = daemon.connect();
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
    let refused = read_until_closed(daemon.connect(), Duration::from_secs(30));
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
    daemon.stop();
}

#[test]
fn a_status_only_connection_is_closed_at_its_deadline() {
    let _serial = serial();
    let mut config = Config::default();
    config.app.max_clients = 1;
    config.app.hello_timeout_ms = 300.0;
    let daemon = Running::start(config);
    // The one place, held by a client that said hello (no deadline for it).
    let mut held = Client::connect(&daemon.socket, Role::Observe, "held").unwrap();

    let spare = daemon.connect();
    let connected = Instant::now();
    (&spare).write_all(HELLO_OBSERVE).unwrap();
    (&spare).write_all(b"{\"type\":\"status\"}\n").unwrap();
    let out = read_until_closed(spare, Duration::from_secs(30));
    let closed_after = connected.elapsed();
    assert!(out.contains("\"type\":\"status\""), "{out:?}");
    assert!(
        out.contains("status-only connection: its time limit") && out.contains("\"fatal\":true"),
        "{out:?}"
    );
    assert!(
        closed_after >= Duration::from_millis(300),
        "closed after {closed_after:?}"
    );
    assert!(
        closed_after < Duration::from_secs(5),
        "closed after {closed_after:?}"
    );
    // The client that holds the place is not touched.
    assert_eq!(held.status().unwrap().clients, 1);
    drop(held);
    daemon.stop();
}
