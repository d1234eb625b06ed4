//! A model gone stale, noticed while the daemon runs (issue 36, item 3): the simulated handle's
//! payload grows by 30 g under a running daemon (`LiveWorld`, as SIGHUP with a changed config
//! does it); the released handle sinks; the daemon reports it in `hgcd status` and as a
//! `calibration` event `stale` on the socket, with its estimate, and with
//! `compensation.auto_update` it takes the payload in and the sinking stops. The device runs in
//! virtual time behind a gate: everything is counted in ticks, whatever the machine's load.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use nalgebra::Vector3;

use hgcd::calibrate::{calibrate, CalibrateRequest};
use hgcd::client::{CalibrationStage, Client, Reply, Role, StateSample};
use hgcd::config::{Config, OutsideGrid};
use hgcd::control::compensation::GravityModel;
use hgcd::grid::{GridFile, MassGrid};
use hgcd::sim::LiveWorld;
use hgcd::transport::Pacing;

mod common;
use common::daemon::{Running, TestDaemon};
use common::tap::{Gate, Tap};
use common::{env_list, tilted_v_g, WAIT};

const PAYLOAD: f64 = 0.03;

/// A reading of the [`PAYLOAD`] within 20 % (the Must show), g.
fn within_a_fifth(grams: f64) -> bool {
    (grams - 30.0).abs() <= 0.2 * 30.0
}
/// Ticks at 1 kHz.
const TEN_SECONDS: u64 = 10_000;
const BATCH: u64 = 50;
/// Ticks between two looks at the status while waiting for the watch: the model is swapped
/// (with `auto_update`) within this many ticks of the watch noticing.
const NOTICE_BATCH: u64 = 10;

/// A uniform 120 g handle, gravity tilted, on a ±80 mm lattice: the plant's field and, exactly,
/// the daemon's grid (without a calibration record: the watch takes its moving mass from it).
fn field() -> MassGrid {
    MassGrid::uniform(
        0.12,
        9.81,
        tilted_v_g(),
        Vector3::repeat(-0.08),
        0.08,
        [3, 3, 3],
    )
}

struct Rig {
    daemon: Running,
    gate: Arc<Gate>,
    world: Arc<LiveWorld>,
}

fn start(auto_update: bool) -> Rig {
    start_with_file(auto_update, None)
}

/// [`start`], the daemon told its config came from `file` (read again on SIGHUP). The point
/// mass's stops are 250 mm from where it starts: a handle that sinks until it is noticed and
/// coasts on stops well short of them when the payload is taken in.
fn start_with_file(auto_update: bool, file: Option<&std::path::Path>) -> Rig {
    let mut config = Config::default();
    config.compensation.auto_update = auto_update;
    config.sim.workspace_min_mm = [-250.0; 3];
    config.sim.workspace_max_mm = [250.0; 3];
    let grid = GridFile::from(field());
    let mut daemon = TestDaemon::new(config);
    if let Some(file) = file {
        daemon = daemon.config_file(file);
    }
    rig(daemon.truth(&field()).grid(Some(&grid)))
}

/// `sim:MODEL` with 0.04 N of Coulomb friction at its handle, calibrated by `hgcd calibrate`
/// in virtual time (its built-in profile: the arm model), then run by the daemon with that model.
fn start_linkage(model: &'static str, auto_update: bool) -> Rig {
    start_unit(model, auto_update, "").0
}

/// [`start_linkage`] with more of the `[sim]` section (`unit_seed = 2\nseed = 3`, say); also
/// the moving mass along each axis its calibration recorded, kg.
fn start_unit(model: &'static str, auto_update: bool, sim: &str) -> (Rig, [f64; 3]) {
    let mut config = Config::from_toml_str(
        &format!("[sim]\ncoulomb_friction_n = 0.04\n{sim}\n"),
        Path::new("test"),
    )
    .unwrap();
    let state = tempfile::tempdir().unwrap();
    let request = CalibrateRequest {
        device: format!("sim:{model}").parse().unwrap(),
        pacing: Pacing::Virtual,
        output: None,
        state_dir: state.path().to_path_buf(),
    };
    let run = calibrate(
        &config,
        &request,
        Arc::new(AtomicBool::new(false)),
        &mut |_| {},
    )
    .expect("the linkage calibrates");
    config.compensation.auto_update = auto_update;
    let inertia = run
        .grid
        .calibration
        .as_ref()
        .and_then(|c| c.inertia_kg)
        .expect("a calibration records the moving mass");
    let rig = rig(TestDaemon::new(config).model(model).grid(Some(&run.grid)));
    (rig, inertia)
}

/// Start `daemon` behind a gate, keeping its simulated device's world.
fn rig(daemon: TestDaemon) -> Rig {
    let gate = Gate::new();
    let mut world = None;
    let daemon = daemon.start_with(|sim| {
        world = Some(hgcd::transport::Transport::sim_world(&sim).expect("a simulated device"));
        Tap::new(sim).gated(gate.clone())
    });
    Rig {
        daemon,
        gate,
        world: world.expect("the transport was made"),
    }
}

impl Rig {
    /// A client subscribed to every state (the subscription in place before the next tick).
    fn client(&self) -> Client {
        let mut c = Client::connect(&self.daemon.socket, Role::Observe, "watcher").unwrap();
        c.set_read_timeout(Some(WAIT)).unwrap();
        c.subscribe(1000.0).unwrap();
        c.status().unwrap();
        c
    }

    /// The state of the last tick run after `ticks` more, as a subscribed `client` sees it
    /// (run [`BATCH`] at a time: the client's queue holds 256 states).
    fn run(&self, client: &mut Client, ticks: u64) -> StateSample {
        let end = self.gate.passed() + ticks;
        loop {
            self.gate.advance(BATCH.min(end - self.gate.passed()));
            let last = self.gate.passed() - 1;
            let s = loop {
                let s = client.next_state().unwrap();
                if s.tick == last {
                    break s;
                }
            };
            if self.gate.passed() == end {
                return s;
            }
        }
    }
}

impl Drop for Rig {
    fn drop(&mut self) {
        self.gate.open();
    }
}

/// The payload grown by [`PAYLOAD`], then [`noticed`].
fn until_noticed(rig: &Rig, client: &mut Client) -> (u64, hgcd::client::ModelStale, f64) {
    rig.world.set(PAYLOAD, tilted_v_g());
    noticed(rig, client)
}

/// Until the daemon's status reports a stale model: the ticks it took, what it says, and the
/// `stale` event the client received on the way (state samples in between are read past).
fn noticed(rig: &Rig, client: &mut Client) -> (u64, hgcd::client::ModelStale, f64) {
    noticed_within(rig, client, TEN_SECONDS).expect("not noticed within 10 s of device time")
}

/// [`noticed`], or None once `ticks` have passed without.
fn noticed_within(
    rig: &Rig,
    client: &mut Client,
    ticks: u64,
) -> Option<(u64, hgcd::client::ModelStale, f64)> {
    let start = rig.gate.passed();
    let mut event = None;
    loop {
        rig.gate.advance(NOTICE_BATCH);
        // The hub reads the published states on its own thread, one after the other as it fans
        // them out: once the client has the last tick's, a status asked for now is answered
        // after the watch has read them all, whatever the machine's load.
        let last = rig.gate.passed() - 1;
        read_until(
            client,
            &mut event,
            |r| matches!(r, Reply::State(s) if s.tick == last),
        );
        client.request_status().unwrap();
        let Reply::Status(status) =
            read_until(client, &mut event, |r| matches!(r, Reply::Status(_)))
        else {
            unreachable!("read_until stops at a status")
        };
        if let Some(stale) = status.model_stale {
            // The event goes out before the status changes.
            let passed = rig.gate.passed() - start;
            return Some((passed, stale, event.expect("a `stale` event")));
        }
        if rig.gate.passed() - start >= ticks {
            return None;
        }
    }
}

/// Replies until one `stop` accepts (returned), the mass of a `stale` event on the way kept.
fn read_until(
    client: &mut Client,
    event: &mut Option<f64>,
    stop: impl Fn(&Reply) -> bool,
) -> Reply {
    loop {
        let reply = client.next_reply().unwrap();
        if let Reply::Calibration {
            event: CalibrationStage::Stale,
            mass_kg,
            ..
        } = reply
        {
            *event = mass_kg;
        } else if stop(&reply) {
            return reply;
        }
    }
}

fn assert_estimate(stale: &hgcd::client::ModelStale, event_kg: f64) {
    assert!(
        within_a_fifth(stale.payload_g),
        "status: {} g",
        stale.payload_g
    );
    assert!(
        (event_kg * 1e3 - stale.payload_g).abs() < 1e-9,
        "event {event_kg} kg, status {} g",
        stale.payload_g
    );
}

#[test]
fn a_grown_payload_is_reported_and_the_force_left_as_it_was() {
    let rig = start(false);
    let mut client = rig.client();
    // Compensated exactly, the released handle stays put: nothing to report.
    let before = rig.run(&mut client, 1000);
    let status = client.status().unwrap();
    assert_eq!(status.model_stale, None);
    let (ticks, stale, event) = until_noticed(&rig, &mut client);
    println!(
        "noticed after {ticks} ticks: {:+.2} g, {:.2} mN sideways",
        stale.payload_g,
        stale.sideways_n * 1e3
    );
    assert_estimate(&stale, event);
    assert!(!stale.auto_updated);
    // The force stays the grid's: the handle sinks on to the bottom stop.
    let after = rig.run(&mut client, 2000);
    let model =
        GravityModel::configured(GridFile::from(field()), None, OutsideGrid::HoldNearest).unwrap();
    let expected = model.force(&Vector3::from(after.position));
    assert!(
        (Vector3::from(after.force) - expected).norm() < 1e-6,
        "force {:?}, the grid's {expected:?}",
        after.force
    );
    let sunk = (Vector3::from(before.position) - Vector3::from(after.position)).dot(&tilted_v_g());
    println!("sank {:.1} mm", sunk * 1e3);
    assert!(sunk > 0.07, "sank {:.1} mm", sunk * 1e3);
}

#[test]
fn with_auto_update_the_payload_is_taken_in_and_the_sinking_stops() {
    let rig = start(true);
    let mut client = rig.client();
    let before = rig.run(&mut client, 1000);
    let (ticks, stale, event) = until_noticed(&rig, &mut client);
    println!(
        "noticed after {ticks} ticks: {:+.2} g, taken in",
        stale.payload_g
    );
    assert_estimate(&stale, event);
    assert!(stale.auto_updated);
    // Taken in, the sinking stops, far short of the stop the handle falls to without (250 mm
    // down, at 294 mm/s): it sank while the watch read it (about 35 mm in 240 ms), coasts on
    // for the 0.15 s the plant's damping (1 N·s/m) takes to stop 0.15 kg (as far again), and
    // what the estimate leaves (a fraction of a gram here; 20 % would be 6 g) sinks it at that
    // weight over the damping.
    let settled = rig.run(&mut client, 2000);
    let after = rig.run(&mut client, 1000);
    let sunk = (Vector3::from(before.position) - Vector3::from(after.position)).dot(&tilted_v_g());
    let drift = (Vector3::from(after.position) - Vector3::from(settled.position)).norm();
    let left = (stale.payload_g * 1e-3 - PAYLOAD).abs() * 9.81 / 1.0;
    println!(
        "sank {:.1} mm in all, {:.3} mm in the last second ({:.3} mm/s from the estimate's error)",
        sunk * 1e3,
        drift * 1e3,
        left * 1e3
    );
    assert!(
        drift <= left * 1.2 + 1e-4,
        "drifted {:.3} mm in a second",
        drift * 1e3
    );
    assert!(sunk < 0.1, "sank {:.1} mm", sunk * 1e3);
}

/// `hgcd run` on SIGHUP: a simulated device takes the payload and gravity of its config file
/// again, as an edited file gives them (`[sim] probe_mass_kg`, `gravity_direction`).
#[test]
fn sighup_gives_the_simulated_device_the_payload_of_its_edited_config() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("hgcd.toml");
    let v = tilted_v_g();
    std::fs::write(&file, "").unwrap();
    let rig = start_with_file(false, Some(&file));
    let mut client = rig.client();
    rig.run(&mut client, 500);
    std::fs::write(
        &file,
        format!(
            "[sim]\nprobe_mass_kg = {PAYLOAD}\ngravity_direction = [{}, {}, {}]\n",
            v.x, v.y, v.z
        ),
    )
    .unwrap();
    let reload = &rig.daemon.signals.reload;
    reload.store(true, std::sync::atomic::Ordering::SeqCst);
    // The hub takes the signal at its housekeeping, on the wall clock.
    let deadline = std::time::Instant::now() + WAIT;
    while reload.load(std::sync::atomic::Ordering::SeqCst) {
        assert!(std::time::Instant::now() < deadline, "SIGHUP not taken");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let (_, stale, event) = noticed(&rig, &mut client);
    assert_estimate(&stale, event);
}

/// An application's spring holds the handle still at three places in turn while the payload has
/// grown by 30 g: the offsets that hold it are the same wherever it rests, and read as the
/// payload, reported with its estimate; with `auto_update` on it is not taken in (only what a
/// released handle shows is). The application's force reaches the servo before the next ticks
/// run: each `set_force` is followed by a status round trip on the same connection.
#[test]
fn an_application_holding_the_heavier_handle_still_shows_the_payload() {
    let stale = held_still_after_the_payload(&start(true), tilted_v_g());
    assert!(within_a_fifth(stale.payload_g), "{} g", stale.payload_g);
}

/// An application's spring holds the handle of a running daemon still at three places 20 mm
/// apart along x, two seconds each, while the payload has grown by [`PAYLOAD`] (gravity `up`):
/// the daemon's report, which must not have been taken in.
fn held_still_after_the_payload(rig: &Rig, up: Vector3<f64>) -> hgcd::client::ModelStale {
    let mut observer = rig.client();
    let mut app = Client::connect(&rig.daemon.socket, Role::Control, "spring").unwrap();
    app.set_read_timeout(Some(WAIT)).unwrap();
    let mut s = rig.run(&mut observer, 100);
    let start = Vector3::from(s.position);
    let (stiffness, damping) = (200.0, 4.0);
    let mut spring = |s: &StateSample, anchor: Vector3<f64>| {
        let x = Vector3::from(s.position);
        let v = Vector3::from(s.velocity);
        app.set_force(stiffness * (anchor - x) - damping * v)
            .unwrap();
        app.status().unwrap();
    };
    spring(&s, start);
    rig.world.set(PAYLOAD, up);
    let mut found = None;
    'places: for dx in [0.0, 0.02, 0.04] {
        let anchor = start + Vector3::x() * dx;
        // Two seconds at each place: the spring settles the handle in about one, and a rest
        // takes 0.2 s.
        for _ in 0..200 {
            s = rig.run(&mut observer, 10);
            spring(&s, anchor);
            let status = observer.status().unwrap();
            if let Some(stale) = status.model_stale {
                found = Some(stale);
                break 'places;
            }
        }
    }
    let stale = found.expect("the payload is noticed at the third place");
    println!(
        "held still: {:+.2} g, {:.2} mN sideways, {:.2}° tilt, at {:.2} s",
        stale.payload_g,
        stale.sideways_n * 1e3,
        stale.tilt_deg,
        stale.device_time_s
    );
    assert!(
        !stale.auto_updated,
        "a held handle's evidence is not taken in"
    );
    stale
}

/// The table tilted 3° under a running daemon: the released handle slides sideways; the daemon
/// reads the tilt, and with `auto_update` takes it in and the sliding stops. A tilt over
/// `compensation.auto_update_max_deg` (10° against its 5°) is reported and not taken in.
#[test]
fn with_auto_update_a_tilt_is_taken_in_within_its_bound() {
    let rig = start(true);
    let mut client = rig.client();
    rig.run(&mut client, 1000);
    let axis = Vector3::x();
    let turned = nalgebra::Rotation3::new(axis * 3f64.to_radians()) * tilted_v_g();
    rig.world.set(0.0, turned);
    let (ticks, stale, _) = noticed(&rig, &mut client);
    println!(
        "noticed after {ticks} ticks: {:.3}° about {:?}, {:+.2} g, taken in: {}",
        stale.tilt_deg, stale.tilt_axis, stale.payload_g, stale.auto_updated
    );
    assert!((stale.tilt_deg - 3.0).abs() <= 0.3, "{stale:?}");
    // The axis lies across gravity, about x turned with it.
    let found = Vector3::from(stale.tilt_axis);
    assert!(found.dot(&axis) > 0.99, "{stale:?}");
    assert!(stale.payload_g.abs() <= 2.0, "{stale:?}");
    assert!(stale.auto_updated, "{stale:?}");
    let settled = rig.run(&mut client, 2000);
    let after = rig.run(&mut client, 1000);
    let drift = (Vector3::from(after.position) - Vector3::from(settled.position)).norm();
    println!("drifted {:.3} mm in the last second", drift * 1e3);
    // Uncompensated, 62 mN across gravity over the plant's 1 N·s/m slides it at 62 mm/s.
    assert!(drift < 0.003, "drifted {:.3} mm in a second", drift * 1e3);

    let rig = start(true);
    let mut client = rig.client();
    rig.run(&mut client, 1000);
    rig.world.set(
        0.0,
        nalgebra::Rotation3::new(axis * 10f64.to_radians()) * tilted_v_g(),
    );
    let (_, stale, _) = noticed(&rig, &mut client);
    assert!((stale.tilt_deg - 10.0).abs() <= 1.0, "{stale:?}");
    assert!(!stale.auto_updated, "{stale:?}");
}

/// The released handle of a calibrated linkage (its arm model, 0.04 N of friction at the
/// handle) stays where it is for three seconds, no alarm raised; under 30 g more it sinks:
/// noticed within 10 s of device time, its estimate within 20 %, taken in with `auto_update`,
/// and the handle then stays where it is (over units and seeds:
/// [`released_payload_over_units_and_seeds`]).
#[test]
fn on_a_linkage_a_grown_payload_is_noticed_and_taken_in() {
    for model in ["phantom", "delta", "woodenhaptics"] {
        let rig = start_linkage(model, true);
        let mut client = rig.client();
        rig.run(&mut client, 3000);
        let unchanged = client.status().unwrap();
        assert_eq!(unchanged.model_stale, None, "{model}: a false alarm");
        rig.world.set(PAYLOAD, Vector3::z());
        let (ticks, stale, event_kg) = noticed(&rig, &mut client);
        println!(
            "{model}: noticed after {ticks} ticks: {:+.2} g, {:.2}° tilt, taken in: {}",
            stale.payload_g, stale.tilt_deg, stale.auto_updated
        );
        assert_estimate(&stale, event_kg);
        assert!(stale.auto_updated, "{model}: {stale:?}");
        let settled = rig.run(&mut client, 2000);
        let after = rig.run(&mut client, 1000);
        let drift = (Vector3::from(after.position) - Vector3::from(settled.position)).norm();
        println!("{model}: drifted {:.3} mm in the last second", drift * 1e3);
        assert!(
            drift < 0.001,
            "{model}: drifted {:.3} mm in a second",
            drift * 1e3
        );
    }
}

/// A delta left alone raises no alarm: at rest its velocity reads a few mm/s of its encoders'
/// noise for windows on end, and the watch took the friction term of that "motion" for a
/// payload of about 20 g (units 1 and 3, 8 of their 10 noise seeds; with `auto_update` it would
/// have taken it in).
#[test]
fn a_delta_left_alone_raises_no_alarm() {
    for sim in ["unit_seed = 1\nseed = 1", "unit_seed = 3\nseed = 2"] {
        let (rig, _) = start_unit("delta", true, sim);
        let mut client = rig.client();
        let before = rig.run(&mut client, 1);
        let after = rig.run(&mut client, 5000);
        let status = client.status().unwrap();
        assert_eq!(status.model_stale, None, "{sim}: a false alarm");
        let moved = (Vector3::from(after.position) - Vector3::from(before.position)).norm();
        assert!(
            moved < 0.001,
            "{sim}: the handle moved {:.3} mm",
            moved * 1e3
        );
    }
}

/// What went wrong with a released handle's reading.
#[derive(Debug)]
enum Unread {
    /// Reported before anything changed, g.
    FalseAlarm(f64),
    NotNoticed,
}

impl std::fmt::Display for Unread {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::FalseAlarm(grams) => write!(f, "a false alarm ({grams:+.1} g)"),
            Self::NotNoticed => write!(f, "not noticed in 10 s"),
        }
    }
}

/// What a released handle of `model` (`unit`, noise `seed`, 0.04 N at the handle) says once
/// calibrated, left alone for 3 s, then given 30 g more: the reading (g) and the ticks it took,
/// with the moving mass its calibration timed along z (kg), or what went wrong.
fn released_reading(
    model: &'static str,
    unit: u64,
    seed: u64,
    sim: &str,
) -> Result<(f64, u64, f64), Unread> {
    let (rig, inertia) = start_unit(
        model,
        false,
        &format!("unit_seed = {unit}\nseed = {seed}\n{sim}"),
    );
    let mut client = rig.client();
    rig.run(&mut client, 3000);
    if let Some(stale) = client.status().unwrap().model_stale {
        return Err(Unread::FalseAlarm(stale.payload_g));
    }
    rig.world.set(PAYLOAD, Vector3::z());
    let (ticks, stale, _) =
        noticed_within(&rig, &mut client, TEN_SECONDS).ok_or(Unread::NotNoticed)?;
    Ok((stale.payload_g, ticks, inertia[2]))
}

/// The released handles that the windows' own velocity slopes misread: the delta unit 2,
/// seed 2 (+44.5 g, a damping of 0.9 N·s/m taken from their scatter) and WoodenHaptics unit 1,
/// seed 1 (+36.0 g, its arc's velocity product taken for a damping), now within 20 %.
#[test]
fn released_handles_once_misread_are_read_within_a_fifth() {
    for (model, unit, seed) in [("delta", 2, 2), ("woodenhaptics", 1, 1)] {
        let (grams, ticks, _) = released_reading(model, unit, seed, "").unwrap();
        println!("{model} unit {unit} seed {seed}: {grams:+.1} g after {ticks} ticks");
        assert!(
            within_a_fifth(grams),
            "{model} unit {unit} seed {seed}: {grams:+.1} g"
        );
    }
}

/// The released handle's reading over units and noise seeds (issue 36's Must show asks within
/// 20 % and no false alarm): each linkage (`RELEASED_MODELS`, default all three), units 1–3
/// (`RELEASED_UNITS`), noise seeds 1–5 (`RELEASED_SEEDS`), more `[sim]` lines from `RELEASED_SIM`,
/// [`released_reading`]. Prints each
/// run with the moving mass its calibration timed along z, and a summary; fails while any run
/// misses. About 30 s: `cargo test --release --test in_use -- --ignored --nocapture
/// released_payload_over_units_and_seeds` (docs/calibration.md §2.3).
#[test]
#[ignore = "about 30 s: 45 calibrations and runs"]
fn released_payload_over_units_and_seeds() {
    let models: Vec<String> = env_list(
        "RELEASED_MODELS",
        &["phantom", "delta", "woodenhaptics"].map(String::from),
    );
    let units: Vec<u64> = env_list("RELEASED_UNITS", &[1, 2, 3]);
    let seeds: u64 = env_list("RELEASED_SEEDS", &[5])[0];
    // More `[sim]` lines for every run (a handle damper: `damping_n_s_per_m = 0.5`).
    let sim = std::env::var("RELEASED_SIM").unwrap_or_default();
    let mut misses = Vec::new();
    for model in &models {
        let model: &'static str = Box::leak(model.clone().into_boxed_str());
        let (mut within, mut runs, mut alarms) = (0, 0, 0);
        let (mut low, mut high) = (f64::INFINITY, f64::NEG_INFINITY);
        for unit in &units {
            for seed in 1..=seeds {
                runs += 1;
                let case = format!("{model} unit {unit} seed {seed}");
                let (grams, ticks, mass) = match released_reading(model, *unit, seed, &sim) {
                    Ok(reading) => reading,
                    Err(e) => {
                        alarms += usize::from(matches!(e, Unread::FalseAlarm(_)));
                        println!("{case}: {e}");
                        misses.push(format!("{case}: {e}"));
                        continue;
                    }
                };
                low = low.min(grams);
                high = high.max(grams);
                let ok = within_a_fifth(grams);
                within += usize::from(ok);
                println!(
                    "{case}: {grams:+.1} g after {ticks} ticks (moving mass along z {mass:.3} kg){}",
                    if ok { "" } else { "  MISSED" }
                );
                if !ok {
                    misses.push(format!("{case}: {grams:+.1} g"));
                }
            }
        }
        println!(
            "SUMMARY {model}: {within} of {runs} within 20 %, {alarms} false alarms, \
             estimates {low:+.1} to {high:+.1} g"
        );
    }
    assert!(misses.is_empty(), "{misses:#?}");
}

/// [`an_application_holding_the_heavier_handle_still_shows_the_payload`] on each calibrated
/// linkage: their friction (0.15–0.18 N along an axis on the delta) scatters the offsets that
/// hold the handle still.
#[test]
fn on_a_linkage_an_application_holding_the_heavier_handle_still_shows_the_payload() {
    for model in ["phantom", "delta", "woodenhaptics"] {
        let stale = held_still_after_the_payload(&start_linkage(model, true), Vector3::z());
        assert!(
            within_a_fifth(stale.payload_g),
            "{model}: {} g",
            stale.payload_g
        );
        assert!(stale.tilt_deg < 0.5, "{model}: {stale:?}");
    }
}
