//! `hgcd run`: the daemon. It owns the device and the servo thread, loads the device's grid and
//! compensates gravity at every tick, serves applications on a Unix socket, calibrates on request
//! and hot-swaps to the new grid, reloads on SIGHUP, and writes zero force before it exits.
//!
//! Threads: the servo thread runs [`controller::DaemonController`]; the hub (the thread that calls
//! [`Daemon::run`]) fans state out to clients, answers status, runs calibrations' bookkeeping and
//! talks to systemd; the application server has a listener and two threads per client.

pub mod controller;
mod watch;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};
use nalgebra::{Rotation3, Vector3};
use thiserror::Error;
use tracing::{error, info, warn};

use crate::app::endpoint;
use crate::app::protocol::{
    CalibrationStage, Compensating, ModelStale, Reply, StaleEvidence, StateSample, Status,
};
use crate::app::server::{self, lock, HubRequest, ServerContext, SharedRegistry};
use crate::calibrate::check::{self, Verdict};
use crate::calibrate::persist::{self, grid_file};
use crate::calibrate::TimeLeft;
use crate::config::{Config, ConfigError, DeviceSpec};
use crate::control::calibration::{
    unreachable_note, Calibration, CalibrationEvent, CalibrationParams, CalibrationResult,
};
use crate::control::compensation::{
    Compensation, ForceOffset, GravityModel, ModelError, StaticEffect,
};
use crate::grid::{
    grid_path, DeviceIdentity, EffectRecord, GridError, GridFile, ModelFile, ModelFileError,
};
use crate::mailbox::{
    mailbox, CommandSender, HubMailbox, OffsetSender, PublishedState, ServoCommand, ServoReturn,
};
use crate::servo::thread::EventLog;
use crate::servo::{self, ServoError, ServoEvent, ServoOptions, ServoReport};
use crate::sim::LiveWorld;
use crate::transport::{self, Pacing, Transport, TransportError};
use controller::DaemonController;
use watch::{ModelWatch, Noticed, HELD_RESTS};

/// What `hgcd run` was asked to do.
#[derive(Clone, Debug)]
pub struct RunRequest {
    pub device: DeviceSpec,
    /// Stop after this many seconds; None runs until a signal.
    pub duration: Option<f64>,
    /// Pacing of simulated devices.
    pub pacing: Pacing,
    /// The config file it was started with: on SIGHUP a simulated device takes its `[sim]`
    /// payload and gravity direction from it again (docs/simulated-devices.md).
    pub config_file: Option<PathBuf>,
}

/// Signals the daemon reacts to (set by handlers in the binary).
#[derive(Clone, Debug, Default)]
pub struct Signals {
    /// SIGINT/SIGTERM: write zero force and exit.
    pub stop: Arc<AtomicBool>,
    /// SIGHUP: reload the grid from disk (and a simulated device's payload and gravity from the
    /// config file).
    pub reload: Arc<AtomicBool>,
}

/// Why the daemon could not start, or why it stopped other than by a signal or its duration.
#[derive(Debug, Error)]
pub enum RunError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The device cannot be opened (the error names it).
    #[error(transparent)]
    Open(TransportError),
    #[error(
        "{}: refusing to run with this grid (recalibrate, remove the file, or set \
         compensation.allow_uncompensated = true)",
        chain(.0)
    )]
    Grid(UnusableGrid),
    #[error(
        "cannot listen on {} (give another path with --socket PATH or app.socket, or let this \
         user create files in {})",
        path.display(),
        path.parent().unwrap_or(Path::new("/")).display()
    )]
    Listen {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("compensation.effect_file")]
    EffectFile(#[source] ModelFileError),
    #[error("starting a daemon thread")]
    Spawn(#[source] std::io::Error),
    #[error("the servo thread panicked")]
    ServoPanicked,
    #[error("servo loop")]
    Servo(#[source] ServoError),
}

/// Why a grid file cannot serve as the gravity model.
#[derive(Debug, Error)]
pub enum UnusableGrid {
    #[error(transparent)]
    File(#[from] GridError),
    #[error(transparent)]
    Model(#[from] ModelError),
}

/// The end of a run: the servo loop has finished (or is told to); stop serving applications,
/// join the servo thread and log what it said last.
fn shut_down(
    server: AppServer,
    servo: JoinHandle<(Result<ServoReport, ServoError>, DaemonController)>,
    events: &Receiver<ServoEvent>,
    log: &mut EventLog,
) -> Result<ServoReport, RunError> {
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    server.stop();
    let (result, _) = servo.join().map_err(|_| RunError::ServoPanicked)?;
    for e in events.try_iter() {
        log.log(&e);
    }
    log.flush();
    let report = result.map_err(RunError::Servo)?;
    info!("servo loop ended: {:?}", report.exit);
    Ok(report)
}

/// `e` and its sources on one line, each after a colon, outermost first.
fn chain(e: &dyn std::error::Error) -> String {
    let mut line = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        line.push_str(": ");
        line.push_str(&s.to_string());
        source = s.source();
    }
    line
}

/// The grid file of `device` and the model built from it, if any. A missing grid (nothing at
/// `path`) runs uncompensated with a warning; any other grid error, a grid made for another
/// device or calibrated on another unit, or one the compensation mode cannot use is refused
/// unless `compensation.allow_uncompensated` is set.
pub fn load_model(
    config: &Config,
    device: &DeviceIdentity,
    path: &Path,
) -> Result<Option<Box<GravityModel>>, RunError> {
    load_model_with(config, device, path, &TakenIn::default())
}

/// What `compensation.auto_update` took into the compensation since the grid was loaded.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct TakenIn {
    payload_kg: f64,
    /// Gravity turned by (the grid's force, with the payload's weight, turned by it).
    tilt: Rotation3<f64>,
}

/// [`load_model`] with what `compensation.auto_update` noticed in use taken in as well.
fn load_model_with(
    config: &Config,
    device: &DeviceIdentity,
    path: &Path,
    taken: &TakenIn,
) -> Result<Option<Box<GravityModel>>, RunError> {
    let built: Result<GravityModel, UnusableGrid> = match GridFile::load_for(path, device) {
        Err(GridError::Missing { .. }) => {
            warn!(
                "no calibration grid at {}: running WITHOUT gravity compensation; {}",
                path.display(),
                how_to_calibrate(device)
            );
            return Ok(None);
        }
        Err(e) => Err(e.into()),
        Ok(file) => {
            if file.device.is_none() {
                warn!(
                    "grid {} names no device ([device] id); using it for {}",
                    path.display(),
                    device.grid_id()
                );
            }
            let c = &config.compensation;
            GravityModel::configured(file, c.mode, c.outside_grid).map_err(UnusableGrid::from)
        }
    };
    match built {
        Ok(model) => {
            let model = with_effect(model, config, taken)?;
            info!(
                "gravity compensation from {} ({:?} mode)",
                path.display(),
                model.mode
            );
            Ok(Some(Box::new(model)))
        }
        Err(e) if config.compensation.allow_uncompensated => {
            warn!(
                "{}; running WITHOUT gravity compensation (compensation.allow_uncompensated)",
                chain(&e)
            );
            Ok(None)
        }
        Err(e) => Err(RunError::Grid(e)),
    }
}

/// What the calibration the servo thread gave back for `what` (a calibration, a check) found,
/// or why it found nothing (its failure, or its requester's disconnecting).
fn result_of(calibration: &Calibration, what: &str) -> Result<CalibrationResult, String> {
    match calibration.outcome() {
        Some(Ok(result)) => Ok(result),
        Some(Err(failure)) => Err(failure.to_string()),
        None => Err(format!(
            "{what} aborted (its requester disconnected); nothing was written"
        )),
    }
}

/// `model` with the effects of `compensation.effect_file` added, those that are forces of the
/// position alone (a warning says why another is left out), and what `auto_update` took in.
fn with_effect(
    model: GravityModel,
    config: &Config,
    taken: &TakenIn,
) -> Result<GravityModel, RunError> {
    let mut records = Vec::new();
    if let Some(path) = &config.compensation.effect_file {
        let file = ModelFile::load(path).map_err(RunError::EffectFile)?;
        records = file.all_effects();
        info!(
            "compensating {:?} from {} as well as the grid",
            records,
            path.display()
        );
    }
    if taken.payload_kg != 0.0 {
        records.push(EffectRecord::Payload {
            mass_kg: taken.payload_kg,
        });
    }
    if let Some((axis, angle)) = taken.tilt.axis_angle() {
        records.push(EffectRecord::GravityTilt {
            angle_rad: angle,
            rotation_axis: axis.into_inner().into(),
        });
    }
    if records.is_empty() {
        return Ok(model);
    }
    let grid = &model.grid;
    let (effect, refused) = StaticEffect::from_records(&records, &model.up, grid.g);
    for (record, why) in refused {
        warn!("{record:?} is not compensated: {why}");
    }
    Ok(model.with_effect(effect))
}

/// What to run to calibrate `device` while a daemon drives it. A simulated device is calibrated
/// by `hgcd calibrate` on its own copy, in virtual time (the same configuration makes the same
/// plant); a real one only by the daemon that holds it, named by its device id.
fn how_to_calibrate(device: &DeviceIdentity) -> String {
    match &device.spec {
        DeviceSpec::Sim { .. } => format!(
            "calibrate with `hgcd calibrate --device {}` (with this daemon's --config and \
             --state-dir, if it was given any), then reload (SIGHUP) or restart",
            device.spec
        ),
        _ => format!(
            "calibrate with `hgcd calibrate --via-daemon --device {}` (the daemon then uses the \
             new grid)",
            device.grid_id()
        ),
    }
}

fn mode_name(model: &Option<Box<GravityModel>>) -> Compensating {
    model.as_ref().map(|m| m.mode).into()
}

/// A running daemon's hub state.
struct Hub {
    config: Config,
    device: DeviceIdentity,
    grid_path: PathBuf,
    registry: SharedRegistry,
    commands: CommandSender,
    status: Status,
    started: Instant,
    /// Client waiting for the calibration in progress, and the events channel of that run.
    calibration: Option<(u64, Receiver<CalibrationEvent>)>,
    abort_sent: bool,
    /// The running calibration is a check's (`hgcd check --via-daemon`), and whether to apply
    /// what it finds.
    checking: Option<(check::Planned, bool)>,
    /// The time the running calibration has left, reported with each vertex.
    calibration_time_left: TimeLeft,
    log: EventLog,
    last_housekeeping: Instant,
    /// Whether the gravity model in use still fits, read from the published states (None
    /// without a model).
    watch: Option<ModelWatch>,
    /// What `compensation.auto_update` took in since the grid was loaded.
    taken_in: TakenIn,
    /// A simulated device's world, and the config file SIGHUP reads it from again.
    world: Option<(Arc<LiveWorld>, PathBuf)>,
}

impl Hub {
    fn new(
        config: Config,
        device: DeviceIdentity,
        grid_path: PathBuf,
        mode: Compensating,
        registry: SharedRegistry,
        commands: CommandSender,
    ) -> Self {
        Hub {
            status: Status {
                device: device.spec.to_string(),
                device_id: device.grid_id(),
                grid: (mode != Compensating::None).then(|| grid_path.display().to_string()),
                mode,
                ..Status::default()
            },
            config,
            device,
            grid_path,
            registry,
            commands,
            started: Instant::now(),
            calibration: None,
            abort_sent: false,
            checking: None,
            calibration_time_left: TimeLeft::default(),
            log: EventLog::new(),
            last_housekeeping: Instant::now(),
            watch: None,
            taken_in: TakenIn::default(),
            world: None,
        }
    }

    /// A watch over `model` (of the grid at `grid_path`), or None without one.
    fn watch_of(grid_path: &Path, model: Option<&GravityModel>) -> Option<ModelWatch> {
        let model = model?;
        match GridFile::load(grid_path) {
            Ok(file) => Some(ModelWatch::new(&file, model)),
            Err(e) => {
                warn!("not watching the gravity model in use: {}", chain(&e));
                None
            }
        }
    }

    /// The model in use no longer fits the device: say so once (journal, status, a
    /// `calibration` event `stale` to every client), and with `compensation.auto_update` take a
    /// payload and a tilt within their bounds, shown by a released handle, into the
    /// compensation.
    fn noticed(&mut self, noticed: Noticed) {
        let grams = noticed.payload_kg * 1e3;
        let degrees = noticed.tilt.norm().to_degrees();
        let c = &self.config.compensation;
        let released = noticed.evidence == StaleEvidence::Released;
        let within = grams.abs() <= c.auto_update_max_g && degrees <= c.auto_update_max_deg;
        let take = c.auto_update && released && within;
        let tilt_axis = noticed.tilt.try_normalize(0.0).unwrap_or_default();
        let tilted = if degrees >= ModelStale::NAMED_TILT_DEG {
            format!(
                " and a tilt of {degrees:.2}° about ({:.3}, {:.3}, {:.3}) explain",
                tilt_axis.x, tilt_axis.y, tilt_axis.z
            )
        } else {
            " explains".into()
        };
        let (shown, by) = if released {
            (
                format!(
                    "a released handle kept {} at {:.1} s",
                    if grams >= 0.0 { "sinking" } else { "rising" },
                    noticed.time
                ),
                "what a released handle did",
            )
        } else {
            (
                format!(
                    "an application's force held the handle still at {HELD_RESTS} places with \
                     the same offset, the last at {:.1} s",
                    noticed.time
                ),
                "what an application held the handle with",
            )
        };
        warn!(
            "the gravity model no longer fits: {shown}; a payload of {grams:+.1} g{tilted} \
             it ({:.1} mN across gravity){}",
            noticed.sideways_n * 1e3,
            if take {
                "; taking it in (compensation.auto_update; SIGHUP goes back to the grid)"
            } else if c.auto_update && !released {
                "; not taken in (compensation.auto_update takes what a released handle shows): \
                 run hgcd check or calibrate"
            } else if c.auto_update {
                "; over compensation.auto_update_max_g or auto_update_max_deg, not taken in: run \
                 hgcd check or calibrate"
            } else {
                "; run hgcd check, or calibrate"
            }
        );
        let stale = ModelStale {
            payload_g: grams,
            sideways_n: noticed.sideways_n,
            tilt_deg: degrees,
            tilt_axis: tilt_axis.into(),
            device_time_s: noticed.time,
            evidence: noticed.evidence,
            auto_updated: false,
        };
        let event = Reply::Calibration {
            event: CalibrationStage::Stale,
            vertex: None,
            of: None,
            mass_kg: Some(noticed.payload_kg),
            message: format!(
                "the gravity model no longer fits: a payload of {grams:+.1} g{tilted} {by}{}",
                if take {
                    "; taken into the compensation"
                } else {
                    ""
                }
            ),
        };
        let outbound = lock(&self.registry).welcomed_outbound();
        for tx in outbound {
            let _ = tx.send_timeout(event.clone(), server::REPLY_WAIT);
        }
        if take {
            let taken = TakenIn {
                payload_kg: self.taken_in.payload_kg + noticed.payload_kg,
                tilt: Rotation3::new(noticed.tilt) * self.taken_in.tilt,
            };
            match load_model_with(&self.config, &self.device, &self.grid_path, &taken) {
                Ok(model) => {
                    self.swap_model(model);
                    self.taken_in = taken;
                }
                Err(e) => error!("auto_update: cannot rebuild the model: {}", chain(&e)),
            }
        }
        self.status.model_stale = Some(ModelStale {
            auto_updated: take,
            ..stale
        });
    }

    /// SIGHUP on a simulated device: its payload and gravity direction from the config file.
    fn reload_world(&self) {
        let Some((world, path)) = &self.world else {
            return;
        };
        match Config::load(path) {
            Ok(config) => {
                let sim = &config.sim;
                info!(
                    "SIGHUP: the simulated device now carries {:.1} g, gravity against ({:.4}, \
                     {:.4}, {:.4}) (from {})",
                    sim.probe_mass_kg * 1e3,
                    sim.gravity_direction[0],
                    sim.gravity_direction[1],
                    sim.gravity_direction[2],
                    path.display()
                );
                world.set(sim.probe_mass_kg, Vector3::from(sim.gravity_direction));
            }
            Err(e) => error!(
                "SIGHUP: the simulated device keeps its world: {}",
                chain(&e)
            ),
        }
    }

    fn reply(&self, client: u64, reply: Reply) {
        let outbound = lock(&self.registry)
            .clients
            .get(&client)
            .map(|c| c.outbound.clone());
        if let Some(tx) = outbound {
            let _ = tx.send_timeout(reply, server::REPLY_WAIT);
        }
    }

    fn calibration_reply(&self, event: CalibrationStage, message: String) -> Reply {
        Reply::Calibration {
            event,
            vertex: None,
            of: None,
            mass_kg: None,
            message,
        }
    }

    /// Hand a command to the servo thread without ever blocking the hub (the servo drains its
    /// commands every tick; a full queue means the device is silent). False if it was dropped.
    fn command(&self, command: ServoCommand) -> bool {
        match self.commands.send(command) {
            Ok(()) => true,
            Err(command) => {
                error!("servo loop not taking commands (device silent?): dropped {command:?}");
                false
            }
        }
    }

    fn fan_out(&self, published: &PublishedState) {
        let reg = lock(&self.registry);
        let sample = StateSample::from(published);
        for c in reg.clients.values() {
            if c.state_divider > 0 && sample.tick % c.state_divider == 0 {
                let _ = c.outbound.try_send(Reply::State(sample));
            }
        }
    }

    fn swap_model(&mut self, model: Option<Box<GravityModel>>) {
        self.taken_in = TakenIn::default();
        self.watch = Self::watch_of(&self.grid_path, model.as_deref());
        self.status.model_stale = None;
        self.status.mode = mode_name(&model);
        self.status.held_out_pct = model.as_ref().and_then(|m| m.held_out_pct);
        self.status.grid = model.as_ref().map(|_| self.grid_path.display().to_string());
        info!("compensation mode now: {}", self.status.mode);
        self.command(ServoCommand::SwapModel(model));
    }

    fn handle_request(&mut self, request: HubRequest) {
        match request {
            HubRequest::Status { client } => {
                let mut status = self.status.clone();
                {
                    let reg = lock(&self.registry);
                    status.clients = reg.clients.len();
                    status.owner = reg.owner_name();
                }
                status.uptime_s = self.started.elapsed().as_secs_f64();
                self.reply(client, Reply::Status(Box::new(status)));
            }
            HubRequest::Calibrate { client } => self.start_calibration(client, None),
            HubRequest::Check { client, apply } => {
                let planned = GridFile::load_for(&self.grid_path, &self.device)
                    .map_err(|e| format!("nothing to check against: {}", chain(&e)))
                    .and_then(|file| {
                        check::plan(
                            &self.config,
                            &self.device.spec,
                            file,
                            self.grid_path.clone(),
                        )
                        .map_err(|e| chain(&e))
                    });
                match planned {
                    Ok(planned) => self.start_calibration(client, Some((planned, apply))),
                    Err(message) => self.reply(
                        client,
                        self.calibration_reply(CalibrationStage::Failed, message),
                    ),
                }
            }
            HubRequest::Revert { client } => {
                let reply = match self.revert() {
                    Ok(reverted) => Reply::Reverted(Box::new(reverted)),
                    Err(message) => Reply::Error {
                        message,
                        fatal: false,
                    },
                };
                self.reply(client, reply);
            }
        }
    }

    /// `hgcd check --revert --via-daemon`: the model kept beside the grid put back and
    /// compensated at once. Refused while a calibration or check runs (it would replace the
    /// grid under it); a grid put back that will not load leaves the model in use, and says so.
    fn revert(&mut self) -> Result<check::Reverted, String> {
        if self.calibration.is_some() {
            return Err("a calibration or a check is running: put the model back after it".into());
        }
        let reverted = check::revert_at(&self.grid_path, &self.device).map_err(|e| chain(&e))?;
        let model = load_model(&self.config, &self.device, &self.grid_path).map_err(|e| {
            error!("the model put back cannot be loaded; the model in use stays: {e:#}");
            format!("the model put back cannot be loaded ({e:#}); the model in use stays")
        })?;
        info!(
            "put back the model kept as {}.bak; compensating with it",
            self.grid_path.display()
        );
        self.swap_model(model);
        Ok(reverted)
    }

    /// Start a calibration on the servo thread for `client`: the daemon's own, or a check's
    /// two holds.
    fn start_calibration(&mut self, client: u64, checking: Option<(check::Planned, bool)>) {
        if self.calibration.is_some() {
            self.reply(
                client,
                self.calibration_reply(
                    CalibrationStage::Failed,
                    "a calibration or a check is already running".into(),
                ),
            );
            return;
        }
        let params = match &checking {
            Some((planned, _)) => planned.params.clone(),
            None => CalibrationParams::for_device(&self.config, &self.device.spec),
        };
        let (tx, rx) = crossbeam_channel::bounded(4096);
        let calibration = match Calibration::new(params, Some(tx)) {
            Ok(calibration) => calibration,
            Err(e) => {
                let reply = self.calibration_reply(CalibrationStage::Failed, e.to_string());
                self.reply(client, reply);
                return;
            }
        };
        if checking.is_none() {
            // Fail now rather than after minutes of calibration.
            let room = persist::check_room(&self.grid_path, calibration.plan(), &self.device.spec);
            if let Err(e) = room {
                let reply = self.calibration_reply(CalibrationStage::Failed, chain(&e));
                self.reply(client, reply);
                return;
            }
        }
        let what = if checking.is_some() {
            "check"
        } else {
            "calibration"
        };
        if self.command(ServoCommand::StartCalibration(Box::new(calibration))) {
            info!("{what} requested by application client {client}");
            self.calibration_time_left = TimeLeft::default();
            self.calibration = Some((client, rx));
            self.checking = checking;
            self.status.calibrating = true;
            self.reply(
                client,
                self.calibration_reply(CalibrationStage::Started, String::new()),
            );
        } else {
            self.reply(
                client,
                self.calibration_reply(
                    CalibrationStage::Failed,
                    "the servo loop is not taking commands (device silent?)".into(),
                ),
            );
        }
    }

    /// A calibration whose requester went away (Ctrl-C on `hgcd calibrate --via-daemon`) is
    /// abandoned, as a direct `hgcd calibrate` would be.
    fn abort_orphaned_calibration(&mut self) {
        if let Some((client, _)) = &self.calibration {
            if !lock(&self.registry).clients.contains_key(client) && !self.abort_sent {
                info!("calibration requester {client} disconnected: aborting the calibration");
                self.command(ServoCommand::AbortCalibration);
                self.abort_sent = true;
            }
        }
    }

    fn forward_calibration_events(&mut self) {
        let Some((client, rx)) = &self.calibration else {
            return;
        };
        let client = *client;
        let events: Vec<CalibrationEvent> = rx.try_iter().collect();
        for event in events {
            let left = self.calibration_time_left.update(&event);
            let reply = match event {
                CalibrationEvent::InitDone { initial_mass, .. } => Reply::Calibration {
                    event: CalibrationStage::InitDone,
                    vertex: None,
                    of: None,
                    mass_kg: Some(initial_mass),
                    message: String::new(),
                },
                CalibrationEvent::VertexDone {
                    vertex, of, mass, ..
                } => Reply::Calibration {
                    event: CalibrationStage::VertexDone,
                    vertex: Some(vertex),
                    of: Some(of),
                    mass_kg: Some(mass),
                    message: left.unwrap_or_default(),
                },
                CalibrationEvent::VertexUnreachable {
                    vertex,
                    of,
                    at,
                    distance,
                    failure,
                    retried,
                    ..
                } => Reply::Calibration {
                    event: CalibrationStage::VertexUnreachable,
                    vertex: Some(vertex),
                    of: Some(of),
                    mass_kg: None,
                    message: {
                        let note = unreachable_note(&at, distance, failure.as_ref(), retried);
                        match left {
                            Some(left) => format!("{note}; {left}"),
                            None => note,
                        }
                    },
                },
                _ => continue,
            };
            self.reply(client, reply);
        }
    }

    fn handle_return(&mut self, item: ServoReturn) {
        match item {
            ServoReturn::OldModel(_) => {} // dropped here, off the servo thread
            ServoReturn::CalibrationRefused(_) => warn!("a calibration was already running"),
            ServoReturn::CalibrationDone(calibration) => {
                self.forward_calibration_events();
                let client = self.calibration.take().map(|(c, _)| c);
                self.status.calibrating = false;
                self.abort_sent = false;
                if let Some((planned, apply)) = self.checking.take() {
                    self.finish_check(client, &calibration, &planned, apply);
                    return;
                }
                let outcome = result_of(&calibration, "calibration").and_then(|result| {
                    if let Some(c) = client {
                        let time = format!("{}", result.time_spent);
                        self.reply(c, self.calibration_reply(CalibrationStage::TimeSpent, time));
                    }
                    let mut file = grid_file(&result, &self.config, &self.device.spec);
                    self.device.stamp(&mut file);
                    let c = &self.config.compensation;
                    file.save_atomic(&self.grid_path)
                        .map_err(|e| chain(&e))
                        .and_then(|_| {
                            GravityModel::configured(file, c.mode, c.outside_grid)
                                .map_err(|e| chain(&e))
                        })
                });
                match outcome {
                    Ok(model) => {
                        info!(
                            "calibration finished; grid saved to {}",
                            self.grid_path.display()
                        );
                        self.swap_model(Some(Box::new(model)));
                        if let Some(c) = client {
                            self.reply(
                                c,
                                self.calibration_reply(
                                    CalibrationStage::Finished,
                                    self.grid_path.display().to_string(),
                                ),
                            );
                        }
                    }
                    Err(e) => self.ended_without_result(
                        client,
                        &format!("calibration failed: {e}; the previous grid stays in use"),
                        e,
                    ),
                }
            }
        }
    }

    /// A calibration or check that ended without a result: the hold after it released
    /// (compensation resumes with the model in use), `log` logged, the requester told `why`.
    fn ended_without_result(&mut self, client: Option<u64>, log: &str, why: String) {
        self.command(ServoCommand::ReleaseHold);
        error!("{log}");
        if let Some(c) = client {
            self.reply(c, self.calibration_reply(CalibrationStage::Failed, why));
        }
    }

    /// A check's holds are done: its answer to the client; with `apply`, a change found taken
    /// into the grid and the model rebuilt from it. Compensation resumes either way.
    fn finish_check(
        &mut self,
        client: Option<u64>,
        calibration: &Calibration,
        planned: &check::Planned,
        apply: bool,
    ) {
        let outcome = result_of(calibration, "check")
            .and_then(|result| planned.conclude(&result).map_err(|e| chain(&e)))
            .and_then(|mut found| {
                if apply && found.verdict == Verdict::Apply {
                    check::apply(&mut found).map_err(|e| chain(&e))?;
                }
                Ok(found)
            });
        let found = match outcome {
            Ok(found) => found,
            Err(e) => {
                let log = format!("check failed: {e}; the model in use stays");
                self.ended_without_result(client, &log, e);
                return;
            }
        };
        info!(
            "check: {:?}: payload {:+.1} g, tilt {:.2}°{}",
            found.verdict,
            found.payload_g,
            found.tilt_deg,
            if found.applied.is_some() {
                "; applied to the grid"
            } else {
                ""
            }
        );
        if found.applied.is_some() {
            match load_model(&self.config, &self.device, &self.grid_path) {
                Ok(model) => self.swap_model(model),
                Err(e) => {
                    self.command(ServoCommand::ReleaseHold);
                    error!("the applied grid cannot be loaded; the model in use stays: {e:#}");
                }
            }
        } else {
            self.command(ServoCommand::ReleaseHold);
        }
        if let Some(c) = client {
            self.reply(c, Reply::Checked(Box::new(found)));
        }
    }

    /// Everything the servo thread sent since the last call: states to fan out, events to log,
    /// returns to deal with. Polled, never waited on (see [`servo::thread::POLL`]).
    fn take_from_servo(&mut self, mailbox: &mut HubMailbox, events: &Receiver<ServoEvent>) {
        // Only what is there now: a servo thread in virtual time may publish faster than the
        // hub fans out, and the hub must still get to its requests.
        for _ in 0..mailbox.states.slots() {
            let Ok(published) = mailbox.states.pop() else {
                break;
            };
            self.fan_out(&published);
            if let Some(noticed) = self.watch.as_mut().and_then(|w| w.observe(&published)) {
                self.noticed(noticed);
            }
        }
        for e in events.try_iter() {
            if let ServoEvent::Stats(s) = &e {
                self.status.servo = *s;
            }
            self.log.log(&e);
        }
        while let Ok(item) = mailbox.returns.pop() {
            self.handle_return(item);
        }
    }

    /// One turn of the hub's loop: what the servo thread sent, at most a millisecond's wait for a
    /// client request, and every 50 ms the housekeeping (calibration events, orphaned
    /// calibrations, log summaries, SIGHUP, systemd's watchdog).
    fn turn(
        &mut self,
        mailbox: &mut HubMailbox,
        events: &Receiver<ServoEvent>,
        requests: &Receiver<HubRequest>,
        signals: &Signals,
        systemd: &mut SystemdWatchdog,
    ) {
        // Channels fed by the servo thread are polled, never waited on (see servo::thread::POLL);
        // the hub waits on its client requests instead, at most a millisecond.
        self.take_from_servo(mailbox, events);
        if let Ok(r) = requests.recv_timeout(Duration::from_millis(1)) {
            self.handle_request(r);
        }
        if self.last_housekeeping.elapsed() >= Duration::from_millis(50) {
            self.last_housekeeping = Instant::now();
            self.forward_calibration_events();
            self.abort_orphaned_calibration();
            self.log.flush();
            if signals.reload.swap(false, Ordering::SeqCst) {
                self.reload();
            }
            systemd.pet_if_turning();
        }
    }

    fn reload(&mut self) {
        self.reload_world();
        info!("SIGHUP: reloading {}", self.grid_path.display());
        match load_model(&self.config, &self.device, &self.grid_path) {
            Ok(model) => self.swap_model(model),
            Err(e) => error!("reload failed, keeping the current grid: {e:#}"),
        }
    }
}

/// The daemon, ready to run on a transport.
pub struct Daemon {
    pub config: Config,
    pub device: DeviceSpec,
    /// How a simulated device keeps time.
    pub pacing: Pacing,
    pub duration: Option<f64>,
    /// Where SIGHUP reads a simulated device's world again.
    pub config_file: Option<PathBuf>,
}

impl Daemon {
    pub fn new(config: Config, request: &RunRequest) -> Self {
        Self {
            config,
            device: request.device.clone(),
            pacing: request.pacing,
            duration: request.duration,
            config_file: request.config_file.clone(),
        }
    }

    /// Run until a stop signal, the duration, or the end of the servo loop. `ready` is called
    /// with the socket's path once it listens and the servo thread runs (systemd readiness); the
    /// socket is `app.socket`, else the device's own ([`endpoint::socket_path`]). What the device
    /// says about itself (its device-info report) names its grid and stands in for the workspace
    /// and calibration-cube keys the config file does not give ([`Config::for_device`]).
    ///
    /// Errors: [`RunError::Grid`] or `File`/`Model` for a stored grid it must not use, `Listen`
    /// when the socket cannot be served, `Spawn` or `ServoPanicked` for the servo thread, `Servo`
    /// when the device fails under it.
    pub fn run(
        mut self,
        transport: Box<dyn Transport>,
        signals: Signals,
        ready: &mut dyn FnMut(&Path),
    ) -> Result<ServoReport, RunError> {
        self.config.validate()?;
        let device = transport::identify(transport.as_ref(), &self.device, &self.config)
            .map_err(RunError::Open)?;
        self.config = self.config.for_device(device.info.as_ref());
        if self.pacing.set_by_device(&device) {
            // A loop the device paces runs flat out: never let it take a core at real-time
            // priority.
            self.config.servo.realtime_priority = 0;
        }
        let config = &self.config;
        let grid_path = grid_path(&config.state_dir(), &device.grid_id());
        if let Err(e) = std::fs::create_dir_all(config.state_dir()) {
            warn!(
                "state directory {} is not usable ({e}); calibrations will fail to save",
                config.state_dir().display()
            );
        }
        let model = load_model(config, &device, &grid_path)?;
        let watch = Hub::watch_of(&grid_path, model.as_deref());
        let world = transport.sim_world().zip(self.config_file.clone());
        let mode = mode_name(&model);
        let held_out_pct = model.as_ref().and_then(|m| m.held_out_pct);
        let offset = ForceOffset::new(config.app.stale_offset(), config.app.stale_ramp());
        let compensation = Compensation::new(model, offset);

        let (commands, offsets, servo_mailbox, mut hub_mailbox) = mailbox();
        let (events_tx, events) = crossbeam_channel::bounded(1024);
        let (hub_tx, requests) = crossbeam_channel::bounded(256);
        let socket = match &config.app.socket {
            Some(path) => path.clone(),
            None => endpoint::socket_path(&endpoint::runtime_dir(), &device.grid_id()),
        };
        let server =
            self.serve_applications(&socket, &device, commands.clone(), offsets, hub_tx)?;

        let mut options = ServoOptions::from_config(config);
        options.duration = self.duration;
        let heartbeat = Arc::new(AtomicU64::new(0));
        options.heartbeat = Some(heartbeat.clone());
        let servo = servo::thread::spawn(
            transport,
            DaemonController::new(compensation, servo_mailbox),
            options,
            config.servo.clone(),
            signals.stop.clone(),
            Some(events_tx),
        )
        .map_err(RunError::Spawn)?;
        info!(
            "hgcd running on {device} (grid id {}), compensation: {mode} ({}), socket {}",
            device.grid_id(),
            mode.meaning(),
            socket.display()
        );
        ready(&socket);

        let mut hub = Hub::new(
            self.config.clone(),
            device,
            grid_path,
            mode,
            server.registry.clone(),
            commands,
        );
        hub.status.held_out_pct = held_out_pct;
        hub.watch = watch;
        hub.world = world;
        let mut systemd = SystemdWatchdog::new(heartbeat);
        while !servo.is_finished() {
            hub.turn(&mut hub_mailbox, &events, &requests, &signals, &mut systemd);
        }

        shut_down(server, servo, &events, &mut hub.log)
    }

    /// Listen on the application socket; client threads reach the servo thread through
    /// `commands` and `offsets` and the hub through `hub`.
    fn serve_applications(
        &self,
        socket: &Path,
        device: &DeviceIdentity,
        commands: CommandSender,
        offsets: OffsetSender,
        hub: Sender<HubRequest>,
    ) -> Result<AppServer, RunError> {
        let config = &self.config;
        let listener =
            server::bind(socket, config.socket_mode()?).map_err(|source| RunError::Listen {
                path: socket.to_path_buf(),
                source,
            })?;
        let registry = SharedRegistry::default();
        let ctx = Arc::new(ServerContext {
            registry: registry.clone(),
            commands,
            offsets,
            hub,
            device: device.spec.to_string(),
            device_id: device.grid_id(),
            rate_hz: config.servo.rate_hz,
            max_force: config.safety.max_force_n,
            max_clients: config.app.max_clients,
            hello_timeout: config.app.hello_timeout(),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let listener = server::spawn_listener(listener, socket.to_path_buf(), ctx, stop.clone())
            .map_err(RunError::Spawn)?;
        Ok(AppServer {
            registry,
            stop,
            listener,
        })
    }
}

/// The running application server.
struct AppServer {
    registry: SharedRegistry,
    stop: Arc<AtomicBool>,
    listener: JoinHandle<()>,
}

impl AppServer {
    /// Close every connection, remove the socket and wait for the listener.
    fn stop(self) {
        self.stop.store(true, Ordering::SeqCst);
        let _ = self.listener.join();
    }
}

/// systemd's watchdog (`WatchdogSec=`), petted only while the servo loop is turning.
struct SystemdWatchdog {
    enabled: bool,
    interval: Duration,
    heartbeat: Arc<AtomicU64>,
    last_beat: u64,
    last_pet: Instant,
}

impl SystemdWatchdog {
    fn new(heartbeat: Arc<AtomicU64>) -> Self {
        let mut usec = 0u64;
        let enabled = sd_notify::watchdog_enabled(false, &mut usec);
        Self {
            enabled,
            interval: Duration::from_micros(usec / 2),
            heartbeat,
            last_beat: 0,
            last_pet: Instant::now(),
        }
    }

    fn pet_if_turning(&mut self) {
        let beat = self.heartbeat.load(Ordering::Relaxed);
        if self.enabled && beat != self.last_beat && self.last_pet.elapsed() >= self.interval {
            let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
            self.last_pet = Instant::now();
            self.last_beat = beat;
        }
    }
}

/// `hgcd run`: open the device and run the daemon.
///
/// Errors: [`RunError::Config`] for an invalid config, [`RunError::Open`] when the device cannot
/// be opened, then as [`Daemon::run`].
pub fn run(
    config: &Config,
    request: &RunRequest,
    signals: Signals,
) -> Result<ServoReport, RunError> {
    let transport =
        transport::open(&request.device, config, request.pacing).map_err(RunError::Open)?;
    Daemon::new(config.clone(), request).run(transport, signals, &mut |_| {
        let _ = sd_notify::notify(
            false,
            &[
                sd_notify::NotifyState::Ready,
                sd_notify::NotifyState::Status("servo loop running"),
            ],
        );
    })
}
